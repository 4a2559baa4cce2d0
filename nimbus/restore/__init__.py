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
    channel is at least :data:`HAZE_DARK_MEAN`, ``particles`` when the white share of its
    bright thin structures is at least :data:`PARTICLE_SHARE`, both, or none.
``onnx:PATH``
    a user-supplied image-to-image ONNX model (:class:`nimbus.restore.onnx_model.OnnxRestorer`).

Sizes in pixels scale with the image's short side (:func:`pixel_sizes`): the dark-channel
patch is He et al.'s 15 px at 400 px (at least 3), the guided filter's window 4 patches, and
the particle element's half-width 2 px up to 200 px, 1 % of the side above (the statistic's
element is smaller: 1 px up to 300 px, 0.5 % above, to single out the thinnest structures).

Thresholds of ``auto`` (chosen on validation data, never on test views)
------------------------------------------------------------------------
The built-in scenes (garden, street, tabletop) at sizes ``tiny`` and ``small`` rendered with
scene seed 1 and degraded with synthesis seed 1 (the benchmark uses seed 0 for both), the
``onerestore`` protocol, all seven settings plus the clean views; training views only.
Reproduce with ``python -m tools.restore_thresholds``, which prints the ranges and gains below.

* dark-channel mean: hazy views 0.328..0.685, haze-free views 0.084..0.306 (1176 views);
  :data:`HAZE_DARK_MEAN` = 0.32 separates them with no view wrong.
* white share: views with rain or snow 0.61..1.08, without 0.44..0.94.  0.76 tells them apart
  best (88 of 1176 views wrong), and was the threshold until 2026-12-01; but the remover run on
  those views made them worse: -0.78 dB PSNR against the clean view per degraded training view
  on average, -1.5 to -3.0 dB on the R, S, H+R and H+S views, gains only where rain and snow
  fall together (its top-hat takes the scene's own thin bright texture with the particles, and
  at 64 x 48 the particles are thinner than a pixel).  The step is there to improve a view, so
  :data:`PARTICLE_SHARE` = 0.96 is the cut with the largest mean gain, +0.17 dB (0.92 to 1.00
  are all within 0.13 dB of it; never running the step gives 0): in practice the remover runs
  on the densest, whitest views, mostly R+S and H+R+S.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import torch

from nimbus.errors import NimbusError
from nimbus.methods.nimbusgs.airlight import dark_channel_hard
from nimbus.restore.classical import ParticleConfig, RestoreConfig, dehaze, remove_particles, white_tophat

#: The named restorers (besides ``onnx:PATH``).
RESTORERS = ("auto", "dcp", "particles", "dcp+particles", "none")
#: ``auto``: a view is hazy when the mean of its dark channel is at least this (module docstring).
HAZE_DARK_MEAN = 0.32
#: ``auto``: the particle remover runs on a view when the white share of its bright thin structures
#: (:func:`image_evidence`) is at least this (the cut where the step gains most: module docstring).
PARTICLE_SHARE = 0.96
#: A bright structure counts as white when its top-hat in the darkest channel is at least this
#: fraction of its top-hat in the brightest (white: 1).
ACHROMATIC = 0.7
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
    """What ``auto`` sees in one view: ``dark_mean`` (mean dark channel, [0, 1]), ``white_share`` (the
    white share of the bright thin structures, about [0, 1]: :func:`image_evidence`), and the decisions."""

    dark_mean: float
    white_share: float
    haze: bool
    particles: bool

    def to_dict(self) -> dict:
        return asdict(self)


def image_evidence(image: np.ndarray) -> ImageEvidence:
    """The haze and particle statistics of ``image`` (H, W, 3) float32 in [0, 1] and ``auto``'s decisions.

    ``white_share``: of the bright thin structures' top-hat in the brightest channel (everything
    brighter than its surroundings and narrower than the element), the share that white pixels
    carry in the darkest channel.  Rain and snow are white and add to every channel alike; a
    flower, a leaf or a red light is bright in one or two.  A share, not an energy, so the
    texture's own contrast and haze's loss of contrast cancel out.
    """
    dcp, _ = pixel_sizes(*image.shape[:2])
    dark = float(dark_channel_hard(torch.from_numpy(np.ascontiguousarray(image, np.float32)), dcp.patch).mean())
    size = max(1, int(round(min(image.shape[:2]) / 200)))
    th_min, th_max = white_tophat(image.min(axis=-1), size), white_tophat(image.max(axis=-1), size)
    total = float(th_max.sum())
    share = float((th_min * (th_min >= ACHROMATIC * th_max)).sum()) / total if total > 0 else 0.0
    return ImageEvidence(dark, share, dark >= HAZE_DARK_MEAN, share >= PARTICLE_SHARE)


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
