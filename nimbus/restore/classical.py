"""Classical, training-free single-image restoration: dark-channel dehazing and bright-particle removal.

Dehazing (He et al., "Single image haze removal using dark channel prior", 2009/2011)
    The haze model is ``I = J t + A (1 - t)``.  The airlight ``A`` is the mean colour of
    the input at the brightest 0.1 % of its dark channel (min over RGB and a ``patch``
    window); the transmission is ``t = 1 - omega dark(I / A)`` (``omega`` keeps a little
    haze for depth perception, He: 0.95), refined edge-aware with a guided filter on the
    input (He et al. 2013; :mod:`nimbus.utils.guided`, in float64: OpenCV contrib's float32 one drifts
    on hazy images) or smoothed by a box filter,
    floored at ``t_min``; then ``J = (I - A) / t + A``.  The dark-channel prior is false on a
    bright sky (every channel is high, so it reads as thick haze and ``J`` is pushed dark); a pixel
    within ``sky_tolerance`` of the airlight in every channel has its ``t`` raised by
    ``sky_tolerance / max|I - A|`` (at most to 1): the tolerance used by dark-channel follow-ups
    for sky regions.  0 turns it off.

Particle removal (rain streaks, snow flakes)
    Per image, with no geometry: particles are bright, thin structures, brighter in all
    three channels than their surroundings.  The white top-hat of the channel minimum
    (``min_rgb - opening(min_rgb)``, a square element of ``2 size + 1`` px) responds to
    bright structures narrower than the element and not to flat or dark texture; pixels
    whose top-hat exceeds ``max(tophat_floor, median + tophat_sigmas robust sigma)`` (a
    robust level, so the image's own texture sets its bar) are dilated by one pixel and
    filled by inpainting from their surroundings (Telea's method, ``cv2.inpaint``).

:func:`classical_restore` (median filter, then dark-channel dehazing with a box-filtered
transmission) is the stand-in for OneRestore in NimbusGS's "restored-derived residuals"
ablation; the ``restore-3dgs`` baseline (:mod:`nimbus.restore`) uses :func:`dehaze` with the
guided-filter refinement and :func:`remove_particles`.  Both work one view at a time, so
they are not view-consistent -- which is what the ablation and the baseline measure.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from nimbus.methods.nimbusgs.airlight import dark_channel_hard, estimate_airlight
from nimbus.utils.guided import guided_filter as _guided

#: Transmission refinements of :func:`dehaze`.
REFINEMENTS = ("box", "guided")
_MAD_TO_STD = 1.4826


@dataclass(frozen=True)
class RestoreConfig:
    """median: median-filter window (px); patch: dark-channel patch (px); omega: haze kept (He: 0.95);
    t_min: lower bound of the transmission; smooth: window of the transmission's refinement (px; the
    guided filter's radius is ``smooth // 2``); refine: ``box`` or ``guided`` (:data:`REFINEMENTS`);
    guided_eps: the guided filter's regulariser (He et al. 2013: 1e-3 for a [0, 1] guide);
    dehaze: run the dark-channel dehazing step; sky_tolerance: the sky tolerance ``K`` (module
    docstring; 0: off).  0.2 was chosen on the validation views (scene seeds 1 and 2, tiny and small,
    the H folders: the single-image dehaze's PSNR against ``clean/``, ``docs/methods/baselines.md``)."""

    median: int = 3
    patch: int = 15
    omega: float = 0.95
    t_min: float = 0.1
    smooth: int = 15
    refine: str = "box"
    guided_eps: float = 1e-3
    dehaze: bool = True
    sky_tolerance: float = 0.2


def median_filter(image: Tensor, window: int) -> Tensor:
    """Per-channel median filter of ``[H, W, 3]`` (reflect padding)."""
    if window <= 1:
        return image
    pad = window // 2
    x = F.pad(image.permute(2, 0, 1)[None], (pad, pad, pad, pad), mode="reflect")
    patches = F.unfold(x, window)  # [1, 3 * k * k, H * W]
    h, w = image.shape[:2]
    return patches.reshape(3, window * window, h * w).median(dim=1).values.reshape(3, h, w).permute(1, 2, 0)


def box_filter(x: Tensor, window: int) -> Tensor:
    pad = window // 2
    return F.avg_pool2d(F.pad(x[None, None], (pad, pad, pad, pad), mode="replicate"), window, stride=1)[0, 0]


def guided_filter(guide: Tensor, x: Tensor, radius: int, eps: float) -> Tensor:
    """``x`` [H, W] filtered edge-aware by the colour ``guide`` [H, W, 3] (He et al. 2013; :mod:`nimbus.utils.guided`)."""
    out = _guided(guide.detach().cpu().numpy(), x.detach().cpu().numpy(), radius, eps)
    return torch.from_numpy(out).to(x.device)


@torch.no_grad()
def dehaze(image: Tensor, config: RestoreConfig = RestoreConfig()) -> tuple[Tensor, Tensor, Tensor]:
    """Dark-channel dehazing of one view ``[H, W, 3]`` in [0, 1] (module docstring).

    Returns
    -------
    restored : Tensor [H, W, 3] in [0, 1]
    transmission : Tensor [H, W] in [t_min, 1]
        The refined, floored ``t``.
    airlight : Tensor [3]
    """
    if config.refine not in REFINEMENTS:
        raise ValueError(f"unknown transmission refinement {config.refine!r}")
    a = estimate_airlight(image, config.patch)
    t = 1 - config.omega * dark_channel_hard(image / a, config.patch)
    if config.refine == "guided":
        t = guided_filter(image, t, config.smooth // 2, config.guided_eps)
    else:
        t = box_filter(t, config.smooth)
    t = t.clamp_min(config.t_min)
    if config.sky_tolerance > 0:
        gap = (image - a).abs().amax(dim=-1).clamp_min(1e-6)
        t = t * (config.sky_tolerance / gap).clamp_min(1.0)
    t = t.clamp_max(1)
    return ((image - a) / t[..., None] + a).clamp(0, 1), t, a


@torch.no_grad()
def classical_restore(image: Tensor, config: RestoreConfig = RestoreConfig()) -> Tensor:
    """Restore one degraded view ``[H, W, 3]`` in [0, 1] -> ``[H, W, 3]`` in [0, 1]: median filter, then
    :func:`dehaze` (module docstring)."""
    x = median_filter(image.float(), config.median)
    if not config.dehaze:
        return x.clamp(0, 1)
    return dehaze(x, config)[0]


# --- particles ---------------------------------------------------------------------------
@dataclass(frozen=True)
class ParticleConfig:
    """size: half-width of the top-hat's square element (px; particles narrower than ``2 size + 1`` are
    found); tophat_sigmas: the detection level in robust standard deviations of the image's top-hat above
    its median; tophat_floor: the least top-hat that counts as a particle (brightness in [0, 1]);
    inpaint_radius: Telea's neighbourhood (px)."""

    size: int = 2
    tophat_sigmas: float = 4.0
    tophat_floor: float = 0.04
    inpaint_radius: int = 3


def white_tophat(x: np.ndarray, size: int) -> np.ndarray:
    """The white top-hat of ``x`` (H, W) with a ``2 size + 1`` square element -> (H, W) >= 0: what is brighter
    than its surroundings and narrower than the element."""
    m = np.ascontiguousarray(x, np.float32)
    kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * size + 1, 2 * size + 1))
    return np.maximum(m - cv2.morphologyEx(m, cv2.MORPH_OPEN, kernel, borderType=cv2.BORDER_REFLECT), 0.0)


def particle_mask(image: np.ndarray, config: ParticleConfig = ParticleConfig()) -> np.ndarray:
    """Bool (H, W): the pixels :func:`remove_particles` replaces (module docstring)."""
    th = white_tophat(image.min(axis=-1), config.size)
    med = float(np.median(th))
    sigma = _MAD_TO_STD * float(np.median(np.abs(th - med)))
    mask = th > max(config.tophat_floor, med + config.tophat_sigmas * sigma)
    # The dilation takes the anti-aliased rims of a streak, which sit below the level.
    return cv2.dilate(mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)


def remove_particles(image: np.ndarray, config: ParticleConfig = ParticleConfig()) -> np.ndarray:
    """``image`` (H, W, 3) float32 in [0, 1] with bright thin particles inpainted from their surroundings."""
    image = np.ascontiguousarray(image, np.float32)
    mask = particle_mask(image, config)
    if not mask.any():
        return image.copy()
    # cv2.inpaint fills colour images only in 8 bits; the pixels outside the mask keep their float values.
    rgb8 = np.rint(np.clip(image, 0.0, 1.0) * 255).astype(np.uint8)
    filled = cv2.inpaint(rgb8, mask.astype(np.uint8), config.inpaint_radius, cv2.INPAINT_TELEA)
    return np.where(mask[..., None], filled.astype(np.float32) / 255, image).astype(np.float32)
