"""2D restoration of single views, before a reconstruction (the ``restore-3dgs`` baseline).

A restorer is named by a string (``restorer=...``, :func:`parse_restorer`):

``dcp``
    dark-channel-prior dehazing with a guided-filter refinement (:func:`nimbus.restore.classical.dehaze`).
``particles``
    bright-particle (rain streak, snow flake) removal by top-hat detection and inpainting
    (:func:`nimbus.restore.classical.remove_particles`).
``dcp+particles``
    both: particles first (a white flake is the brightest thing in the view and would pull
    the airlight estimate towards white), then dehazing.
``none``
    the views as they are (the baseline is then plain 3DGS).
``auto`` (default)
    per view, from what the view shows (:func:`image_evidence`): ``dcp`` when its mean dark
    channel is at least :data:`HAZE_DARK_MEAN`, ``particles`` when its top-hat energy is at
    least :data:`PARTICLE_ENERGY`, both, or none.
``onnx:PATH``
    a user-supplied image-to-image ONNX model (:class:`nimbus.restore.onnx_model.OnnxRestorer`).

Sizes in pixels scale with the image's short side (:func:`pixel_sizes`): the dark-channel
patch is He et al.'s 15 px at 400 px (at least 3), the guided filter's window 4 patches, and
the particle element's half-width 2 px up to 200 px, 1 % of the side above.

Thresholds of ``auto`` (chosen on validation data, never on test views)
------------------------------------------------------------------------
The built-in scenes (garden, street, tabletop) at sizes ``tiny`` and ``small`` rendered with
scene seed 1 and degraded with synthesis seed 1 (the benchmark uses seed 0 for both), the
``onerestore`` protocol, all seven settings plus the clean views; training views only.
Reproduce with ``python -m benchmark.restore_thresholds``, which prints the ranges below.

* dark-channel mean: hazy views 0.328..0.685, haze-free views 0.084..0.306 (1176 views);
  :data:`HAZE_DARK_MEAN` = 0.32 separates them with no view wrong.
* top-hat energy: views with rain or snow 0.0064..0.077, without 0.0018..0.056.  The classes
  overlap (fine bright texture of the tiny scenes -- flowers, specular edges -- looks like
  flakes, and haze dims the particles' contrast); :data:`PARTICLE_ENERGY` = 0.009 is the
  value with the fewest wrong views there (214 of 1176, mostly haze-free views taken for
  particles).  A wrong ``particles`` costs little (the remover only inpaints what it finds).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import torch

from nimbus.errors import NimbusError
from nimbus.nimbusgs.airlight import dark_channel_hard
from nimbus.restore.classical import ParticleConfig, RestoreConfig, dehaze, remove_particles, white_tophat

#: The named restorers (besides ``onnx:PATH``).
RESTORERS = ("auto", "dcp", "particles", "dcp+particles", "none")
#: ``auto``: a view is hazy when the mean of its dark channel is at least this (module docstring).
HAZE_DARK_MEAN = 0.32
#: ``auto``: a view holds particles when its top-hat energy (mean over pixels of the top-hat above
#: :attr:`ParticleConfig.tophat_floor`) is at least this.
PARTICLE_ENERGY = 0.009
#: A bright structure counts as a particle when its top-hat in the darkest channel is at least this
#: fraction of its top-hat in the brightest (white: 1).
ACHROMATIC = 0.8
#: He et al.'s dark-channel patch (15 px) for a 400-px short side.
_PATCH_PER_PX = 15 / 400
_MIN_PATCH = 3


def parse_restorer(spec: str) -> str:
    """``spec`` in canonical form (``"particles+dcp"`` -> ``"dcp+particles"``, ``"onnx:PATH"`` kept).

    Raises NimbusError naming the accepted values.
    """
    text = str(spec).strip()
    if text.lower().startswith("onnx:"):
        if not text[5:].strip():
            raise NimbusError(f"restorer={spec!r}: onnx: needs a model path, e.g. restorer=onnx:model.onnx")
        return "onnx:" + text[5:].strip()
    parts = {p.strip() for p in text.lower().split("+")}
    canonical = "+".join(p for p in ("dcp", "particles") if p in parts)
    if parts <= {"dcp", "particles"} and canonical:
        return canonical
    if text.lower() in RESTORERS:
        return text.lower()
    raise NimbusError(f"restorer={spec!r}: unknown; use one of {', '.join(RESTORERS)} or onnx:PATH/TO/MODEL.onnx")


def _odd(x: float) -> int:
    return int(round(x)) // 2 * 2 + 1


def pixel_sizes(height: int, width: int) -> tuple[RestoreConfig, ParticleConfig]:
    """The dehazing and particle settings for an image of ``height`` x ``width`` (module docstring)."""
    side = min(height, width)
    patch = max(_MIN_PATCH, _odd(side * _PATCH_PER_PX))
    dcp = RestoreConfig(median=1, patch=patch, smooth=4 * patch, refine="guided")
    return dcp, ParticleConfig(size=max(2, int(round(side / 100))))


@dataclass(frozen=True)
class ImageEvidence:
    """What ``auto`` sees in one view: ``dark_mean`` (mean dark channel, [0, 1]), ``tophat_energy``
    (mean over pixels of the channel minimum's white top-hat above the floor, counted where it is
    achromatic, [0, 1]), and the decisions."""

    dark_mean: float
    tophat_energy: float
    haze: bool
    particles: bool

    def to_dict(self) -> dict:
        return asdict(self)


def image_evidence(image: np.ndarray) -> ImageEvidence:
    """The haze and particle statistics of ``image`` (H, W, 3) float32 in [0, 1] and ``auto``'s decisions."""
    dcp, particles = pixel_sizes(*image.shape[:2])
    dark = float(dark_channel_hard(torch.from_numpy(np.ascontiguousarray(image, np.float32)), dcp.patch).mean())
    th = white_tophat(image.min(axis=-1), particles.size)
    # Only achromatic structures count: a bright flower or a red light has a much larger top-hat in
    # its brightest channel than in its darkest; a white streak or flake has about the same in all.
    white = th >= ACHROMATIC * white_tophat(image.max(axis=-1), particles.size)
    energy = float((np.maximum(th - particles.tophat_floor, 0.0) * white).mean())
    return ImageEvidence(dark, energy, dark >= HAZE_DARK_MEAN, energy >= PARTICLE_ENERGY)


class Restorer:
    """The restorer named ``spec`` (:func:`parse_restorer`), called on one view at a time.

    ``restorer(image) -> (restored, info)``: ``image`` and ``restored`` (H, W, 3) float32 in [0, 1];
    ``info`` says what ran (``steps``) and, for ``auto``, the evidence.  Loading an ONNX model that
    is missing or broken raises NimbusError here, at construction.
    """

    def __init__(self, spec: str) -> None:
        self.spec = parse_restorer(spec)
        self.model = None
        if self.spec.startswith("onnx:"):
            from nimbus.restore.onnx_model import OnnxRestorer

            self.model = OnnxRestorer(self.spec[5:])

    def describe(self) -> dict:
        """JSON-able: the restorer, and the model's hash for ``onnx``."""
        return {"restorer": self.spec, **({"model_sha256": self.model.sha256} if self.model is not None else {})}

    def __call__(self, image: np.ndarray) -> tuple[np.ndarray, dict]:
        image = np.ascontiguousarray(image, np.float32)
        if self.model is not None:
            return self.model(image), {"steps": ["onnx"]}
        info: dict = {}
        if self.spec == "auto":
            evidence = image_evidence(image)
            steps = [s for s, on in (("particles", evidence.particles), ("dcp", evidence.haze)) if on]
            info["evidence"] = evidence.to_dict()
        else:
            steps = [s for s in ("particles", "dcp") if s in self.spec.split("+")]
        dcp, particles = pixel_sizes(*image.shape[:2])
        out = image
        if "particles" in steps:
            out = remove_particles(out, particles)
        if "dcp" in steps:
            out = dehaze(torch.from_numpy(out), dcp)[0].numpy()
        return np.ascontiguousarray(out, np.float32), {"steps": steps, **info}
