"""3DGS inside a homogeneous scattering medium (the SeaThru-NeRF / WaterSplatting / SeaSplat model).

The Gaussians render the clean scene J; one medium per scene, with per-channel attenuation
``sigma_attn``, backscatter coefficient ``sigma_bs`` and backscatter (veiling light) colour ``B``,
degrades it along each pixel's ray::

    I = J exp(-sigma_attn z) + B (1 - exp(-sigma_bs z))

and the 3DGS loss compares the degraded ``I`` with the input views.  ``J`` (``render(camera)["rgb"]``)
is what is scored.  ``sigma_attn, sigma_bs = softplus(raw) >= 0`` and ``B = sigmoid(logit)`` in (0, 1)
are learned with their own Adam (``lr_medium``), after an optional warm-up (``medium_from``) in which
the medium stays at its initial values while the Gaussians settle.

Initial medium (``medium_init``)
--------------------------------
``data`` (the default) starts the medium where the training views put it, by the dark-channel prior
NimbusGS's CSM is seeded with (:func:`estimate_medium`): a transmission ``T`` (the median over views
of the median of He et al.'s ``1 - dark / A``) over a typical depth ``z`` (the median over views of
the sparse points' median z-depth) gives ``sigma_attn = sigma_bs = -ln T / z`` (grey); ``B`` and the
``A`` of ``1 - dark / A`` are He et al.'s airlight over the whole capture (the colour where the dark channel
is brightest in any view).  ``fixed`` starts at ``init_sigma_attn``,
``init_sigma_bs`` and ``init_backscatter``.  From a fixed small medium the Gaussians bake the haze
into their colours during the warm-up and the medium never recovers it (validation, seed-1 tiny
garden under physical haze: sigma 0.11 learned per extent unit for about 0.8 in the data).

Depth convention
----------------
``z`` is the expected camera z-depth of the Gaussians, ``depth / alpha``, in units of the training
frame (:class:`~nimbus.train.frame.SceneFrame`: extent 1), so the learned sigma is per extent unit;
:meth:`Medium3DGS.get_info` reports it per world unit (divided by the frame scale).  The part of a
pixel no Gaussian covers (``1 - alpha``) is taken to lie at infinite depth: it is fully attenuated
and shows ``B`` (a sky or a far backdrop seen through fog).  With ``F = sum_i c_i w_i`` the
Gaussians' colour composited on black (``F = alpha J_surface``), the composite is therefore::

    I = F exp(-sigma_attn z) + B (1 - alpha exp(-sigma_bs z))
      = alpha [J_surface e^(-sigma_attn z) + B (1 - e^(-sigma_bs z))] + (1 - alpha) B

which is the model above for a covered pixel and ``B`` for an empty one, continuous in between.
The clean render shows ``F + (1 - alpha) B`` too (``far_from_medium``, the default): the medium's far
light where no Gaussian covers; with ``far_from_medium=false`` the background colour (``background``,
``random_background``) is there instead, as in 3DGS.  The degraded render never uses the background.

Extras of :meth:`Medium3DGS.render` (any camera; ``view_index`` changes nothing, the medium is the
scene's): ``transmission`` (``alpha exp(-sigma_attn z)``, [H, W, 3]: the share of the surface's light
that arrives, 0 where nothing is covered), ``backscatter`` (``B (1 - alpha exp(-sigma_bs z))``,
[H, W, 3]) and ``degraded`` (``I``, [H, W, 3], what the loss compares with the input).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from nimbus.config_validation import Limit, at_least, between, one_of, positive
from nimbus.data import Camera
from nimbus.losses import photometric_loss
from nimbus.methods.gs3d import GaussianSplatting
from nimbus.methods.nimbusgs.airlight import dark_channel_hard, estimate_airlight
from nimbus.restore import pixel_sizes
from nimbus.train.config import PRESETS as GS_PRESETS
from nimbus.train.adam import Adam
from nimbus.train.config import TrainConfig, lookup_preset, rescale_step

#: Smallest alpha the expected depth ``depth / alpha`` divides by.  ``depth <= alpha * z_max``, so
#: the quotient stays bounded; where alpha is below it the pixel's terms are weighted by alpha anyway.
ALPHA_EPS = 1e-6
#: The medium's parameters, in their (and the optimiser's, and the checkpoint's) order.
MEDIUM_PARAMS = ("sigma_attn", "sigma_bs", "backscatter")
#: ``medium_init`` choices (module docstring).
MEDIUM_INITS = ("data", "fixed")
#: Bounds of the data-driven transmission estimate (as NimbusGS's): a clear view never claims
#: ``T = 1`` (a zero sigma, softplus's -inf), a dark one never claims an opaque medium.
INIT_TRANSMISSION_RANGE = (0.2, 0.99)


@dataclass(frozen=True)
class MediumConfig(TrainConfig):
    """medium-3dgs training configuration: every 3DGS field, plus the medium's.

    Attributes
    ----------
    lr_medium : float
        Adam learning rate of the medium's raw parameters (softplus inputs of the sigmas, logit of B).
    medium_init : str
        ``data``: the initial medium estimated from the training views (:func:`estimate_medium`; the
        ``init_*`` fields are then used only where the views give no estimate: no sparse point in front of
        any camera); ``fixed``: the ``init_*`` fields.  See the module docstring.  Chosen on the seed-1
        validation scenes at tiny size (street and garden; physical H, R, S, H+R and onerestore H; 10 cells),
        against ``fixed``: PSNR better on all ten (+0.08 to +2.17 dB, mean +1.06), SSIM on seven (the other
        three -0.002 to -0.017).
    init_sigma_attn, init_sigma_bs : tuple of 3 float
        Initial attenuation / backscatter coefficients (R, G, B; > 0: softplus never reaches 0), per
        unit of the training frame (extent 1: the radius of the camera centres), with ``medium_init=fixed``.
    init_backscatter : tuple of 3 float
        Initial backscatter colour B (R, G, B in (0, 1)), with ``medium_init=fixed``.
    medium_from : int
        Warm-up: the medium is held at its initial values for the first ``medium_from`` iterations
        (0: learned from the start; the presets hold it for the first third of the run).  Stretched with the
        schedule when ``iterations`` changes.
    far_from_medium : bool
        What the clean render shows where no Gaussian covers a pixel: the medium's far light ``B`` (true: the
        ``background`` colour is then not used), as the degraded render does, or the ``background`` colour
        (false, as 3DGS).  The loss sees only the degraded render, which explains an uncovered sky by ``B``, so
        the Gaussians need not cover it; with the background there, a clear sky scored as black.  Chosen on
        the seed-1 validation scenes at tiny size (street and garden; physical H, R, S, H+R and onerestore H;
        training is the same either way): PSNR +0.79 dB on average (street R +6.0, S +5.9; the other eight
        -1.38 to +0.54), SSIM better on all ten.
    """

    lr_medium: float = 0.05
    medium_init: str = "data"
    init_sigma_attn: tuple[float, float, float] = (0.1, 0.1, 0.1)
    init_sigma_bs: tuple[float, float, float] = (0.1, 0.1, 0.1)
    init_backscatter: tuple[float, float, float] = (0.5, 0.5, 0.5)
    medium_from: int = 0
    far_from_medium: bool = True

    LIMITS: ClassVar[dict[str, Limit]] = {
        **TrainConfig.LIMITS,
        "lr_medium": at_least(0, note="0 freezes the medium"),
        "medium_init": one_of(*MEDIUM_INITS),
        "init_sigma_attn": positive(scalar=True, note="R, G, B per extent unit"),
        "init_sigma_bs": positive(scalar=True, note="R, G, B per extent unit"),
        "init_backscatter": between(0, 1, lo_open=True, hi_open=True, scalar=True, note="R, G, B"),
        "medium_from": at_least(0, note="0: no warm-up"),
    }

    def rescaled(self, iterations: int) -> "MediumConfig":
        """As :meth:`TrainConfig.rescaled`, also stretching the warm-up (0 stays 0)."""
        ratio = iterations / self.iterations
        warmup = rescale_step(self.medium_from, ratio) if self.medium_from else 0
        return dataclasses.replace(super().rescaled(iterations), medium_from=warmup)


# The 3DGS presets of the same name (a comparison with 3dgs differs only by the medium), with the medium held
# for the first third of the run: learned from the first step, it followed the grey initial Gaussians and
# settled on a wrong B on one of three seeds of the foggy-wall test scene (tests/test_medium_3dgs.py); after
# the warm-up B came within 0.022 of the truth on all three.
PRESETS: dict[str, MediumConfig] = {
    name: MediumConfig(**{**dataclasses.asdict(GS_PRESETS[name]), "medium_from": GS_PRESETS[name].iterations // 3})
    for name in ("tiny", "fast", "paper")
}


def preset(name: str) -> MediumConfig:
    """A named preset (``tiny``, ``fast``, ``paper``); NimbusError lists them for an unknown name."""
    return lookup_preset(PRESETS, name)


def compose_medium(foreground: Tensor, depth: Tensor, alpha: Tensor, sigma_attn: Tensor, sigma_bs: Tensor,
                   backscatter: Tensor) -> dict[str, Tensor]:
    """The homogeneous-medium composite of one render (see the module docstring).

    Parameters
    ----------
    foreground : Tensor [H, W, 3]
        The Gaussians' colour composited on black, ``sum c_i w_i``.
    depth : Tensor [H, W]
        Accumulated z-depth ``sum z_i w_i`` (lengths in the units the sigmas are per).
    alpha : Tensor [H, W]
        Accumulated opacity; ``1 - alpha`` of the pixel is at infinite depth.
    sigma_attn, sigma_bs : Tensor [3]
        Attenuation and backscatter coefficients (>= 0, per unit of ``depth``).
    backscatter : Tensor [3]
        Backscatter colour B in [0, 1].

    Returns
    -------
    dict
        ``degraded`` [H, W, 3] ``foreground e^(-sigma_attn z) + B (1 - alpha e^(-sigma_bs z))``,
        ``transmission`` [H, W, 3] ``alpha e^(-sigma_attn z)`` and ``backscatter`` [H, W, 3]
        ``B (1 - alpha e^(-sigma_bs z))``, with ``z = depth / alpha``.
    """
    z = (depth / alpha.clamp_min(ALPHA_EPS))[..., None]
    a = alpha[..., None]
    attenuation = torch.exp(-sigma_attn * z)
    scattered = backscatter * (1.0 - a * torch.exp(-sigma_bs * z))
    return {"degraded": foreground * attenuation + scattered, "transmission": a * attenuation,
            "backscatter": scattered}


def _inverse_softplus(x: Tensor) -> Tensor:
    return x + torch.log(-torch.expm1(-x))  # log(exp(x) - 1), without overflow for large x


@dataclass(frozen=True)
class MediumEstimate:
    """The data-driven initial medium (:func:`estimate_medium`): ``transmission`` (median T of the views),
    ``depth`` (typical z-depth of the sparse points, frame units), ``sigma`` (``-ln T / depth``, per frame unit),
    ``backscatter`` (R, G, B) and ``points_used``."""

    transmission: float
    depth: float
    sigma: float
    backscatter: tuple[float, float, float]
    points_used: int

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


@torch.no_grad()
def estimate_medium(images: list[Tensor], cameras: list[Camera], points) -> MediumEstimate | None:
    """The medium the views imply (module docstring), or None when no sparse point lies in front of a camera.

    Parameters
    ----------
    images : list of Tensor [H, W, 3] in [0, 1]
        The training views (the dark channel's patch follows their size, as ``restore-3dgs``'s).
    cameras : list of Camera
        One per image, in the frame the sigma is to be per unit of.
    points : array (N, 3)
        The sparse points, in that frame.
    """
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    darks, airlights, depths, used = [], [], [], 0
    for img, cam in zip(images, cameras):
        x = img.float()
        patch = pixel_sizes(*x.shape[:2])[0].patch
        darks.append(dark_channel_hard(x, patch))
        airlights.append(estimate_airlight(x, patch).cpu())
        if len(pts):
            _, z, seen = cam.project_seen(pts)
            if seen.any():
                depths.append(float(np.median(z[seen])))
                used += int(seen.sum())
    if not depths:
        return None
    # He et al.'s airlight over the whole capture: the colour where the dark channel is brightest in any view (a
    # view that sees no far light would put B at its own brightest surface).
    b = max(airlights, key=lambda a: float(a.min()))  # estimate_airlight bounds it to [0.02, 0.98]
    floor = b.min().to(darks[0].device)
    t = float(np.clip(np.median([float((1 - d / floor).clamp(0, 1).median()) for d in darks]),
                      *INIT_TRANSMISSION_RANGE))
    depth = float(np.median(depths))
    return MediumEstimate(t, depth, float(-np.log(t) / depth), tuple(float(v) for v in b), used)


class HomogeneousMedium:
    """The scene's medium: raw parameters (``softplus`` -> sigmas, ``sigmoid`` -> B) and their Adam.

    Parameters
    ----------
    config : MediumConfig
        The learning rate (and, without ``initial``, the initial values).
    device : torch.device
    initial : dict or None
        Initial ``sigma_attn``, ``sigma_bs`` (> 0) and ``backscatter`` (in (0, 1)), each a float or R, G, B;
        None: the config's ``init_*`` fields.
    """

    def __init__(self, config: MediumConfig, device: torch.device, initial: dict | None = None) -> None:
        def rgb(value) -> Tensor:
            return torch.as_tensor(value, dtype=torch.float32, device=device).expand(3).clone()

        init = initial or {"sigma_attn": config.init_sigma_attn, "sigma_bs": config.init_sigma_bs,
                           "backscatter": config.init_backscatter}
        raw = {"sigma_attn": _inverse_softplus(rgb(init["sigma_attn"])),
               "sigma_bs": _inverse_softplus(rgb(init["sigma_bs"])),
               "backscatter": torch.logit(rgb(init["backscatter"]))}
        self.raw = {k: raw[k].requires_grad_(True) for k in MEDIUM_PARAMS}
        self.optimizer = Adam(
            [{"params": [self.raw[k]], "lr": config.lr_medium, "name": k} for k in MEDIUM_PARAMS])

    def values(self, frozen: bool = False) -> dict[str, Tensor]:
        """``sigma_attn``, ``sigma_bs`` [3] (>= 0) and ``backscatter`` [3] (in (0, 1)); detached if ``frozen``."""
        raw = {k: v.detach() if frozen else v for k, v in self.raw.items()}
        return {"sigma_attn": F.softplus(raw["sigma_attn"]), "sigma_bs": F.softplus(raw["sigma_bs"]),
                "backscatter": torch.sigmoid(raw["backscatter"])}

    def step(self) -> None:
        """Step and clear the medium's Adam (a parameter without a gradient, e.g. in the warm-up, is left alone)."""
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)

    def param_groups(self) -> list[dict]:
        return list(self.optimizer.param_groups)

    def state_dict(self) -> dict:
        return {"raw": {k: v.detach().clone() for k, v in self.raw.items()}, "optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        with torch.no_grad():
            for k in MEDIUM_PARAMS:
                self.raw[k].copy_(state["raw"][k])
        self.optimizer.load_state_dict(state["optimizer"])


class Medium3DGS(GaussianSplatting):
    """3DGS with a learned homogeneous medium in front of the loss (same constructor as
    :class:`~nimbus.methods.gs3d.GaussianSplatting`; ``config`` is a :class:`MediumConfig`)."""

    cfg: MediumConfig

    def __init__(self, scene, config: MediumConfig, **kwargs) -> None:
        super().__init__(scene, config, **kwargs)
        initial, self._pending = None, []
        if config.medium_init == "data":
            est = estimate_medium(self.train_images, [v.camera for v in self.train_views], scene.points)
            if est is None:
                self._pending.append(("medium_init", {"source": "fixed", "why": "no sparse point in front of a "
                                                      "training camera: the init_* fields are used"}))
            else:
                initial = {"sigma_attn": est.sigma, "sigma_bs": est.sigma, "backscatter": est.backscatter}
                self._pending.append(("medium_init", {"source": "data", **est.to_dict()}))
        self.medium = HomogeneousMedium(config, self.device, initial)
        self._learning_medium = config.medium_from == 0

    def setup_events(self) -> list[tuple[str, dict]]:
        events, self._pending = self._pending, []
        return events

    def render(self, camera: Camera, sh_degree: int | None = None, background: Tensor | None = None,
               view_index: int | None = None) -> dict:
        """The clean render of ``camera`` (``rgb``, ``depth``, ``alpha``, ``meta``) and the medium's extras
        ``transmission``, ``backscatter`` and ``degraded`` (see the module docstring); ``background`` is used
        only with ``far_from_medium=false``."""
        bg = self.background if background is None else background
        out = super().render(camera, sh_degree, torch.zeros(3, device=self.device))
        foreground = out["rgb"]
        medium = self.medium.values(frozen=not self._learning_medium)
        parts = compose_medium(foreground, out["depth"], out["alpha"], **medium)
        far = medium["backscatter"].detach() if self.cfg.far_from_medium else bg
        return {**out, "rgb": foreground + (1.0 - out["alpha"])[..., None] * far, **parts}

    def loss(self, step: int, view_index: int, render: dict, gt: Tensor) -> tuple[Tensor, Tensor]:
        """The 3DGS loss between the degraded render and the input view."""
        pred = render["degraded"]
        return photometric_loss(pred, gt, self.cfg.lambda_dssim, self.train_masks[view_index]), pred.detach()

    def after_step(self, step: int) -> list[tuple[str, dict]]:
        if step == self.cfg.medium_from and not self._learning_medium:
            self._learning_medium = True
            return [("medium_unfrozen", {"iteration": step})]
        return []

    def optimizer_step(self) -> None:
        super().optimizer_step()
        self.medium.step()

    def param_groups(self) -> list[dict]:
        return super().param_groups() + self.medium.param_groups()

    # --- records and state --------------------------------------------------------------
    def medium_values(self) -> dict[str, list[float]]:
        """The learned medium: sigmas per world unit and per extent unit (the training frame), and B."""
        with torch.no_grad():
            v = {k: [float(x) for x in t.cpu()] for k, t in self.medium.values().items()}
        scale = self.frame.scale
        return {"sigma_attn": [s / scale for s in v["sigma_attn"]], "sigma_bs": [s / scale for s in v["sigma_bs"]],
                "backscatter": v["backscatter"], "sigma_attn_per_extent": v["sigma_attn"],
                "sigma_bs_per_extent": v["sigma_bs"]}

    def get_info(self) -> dict:
        """``medium``: the learned medium (:meth:`medium_values`; ``sigma_*`` per world unit, ``frame_scale`` the
        world length of one extent unit) and ``medium_from``."""
        return {"medium": {**self.medium_values(), "frame_scale": self.frame.scale,
                           "medium_from": self.cfg.medium_from}}

    def state_dict(self) -> dict:
        return {**super().state_dict(), "extra": {"medium": self.medium.state_dict()}}

    def load_state_dict(self, state: dict) -> None:
        super().load_state_dict(state)
        self.medium.load_state_dict(state["extra"]["medium"])
        self._pending = []  # the initial medium was logged by the interrupted run
        self._learning_medium = self.iteration >= self.cfg.medium_from
