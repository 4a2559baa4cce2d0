"""A classical single-image restoration, for the "restored-derived residuals" ablation.

The paper's variant takes I_restore from OneRestore (an all-in-one 2D network) and uses
``R = ReLU(I_in - I_restore)`` instead of rendering I_con.  No such network ships here;
the stand-in is the classical pipeline: a median filter (removes thin bright streaks and
flakes) followed by dark-channel dehazing (He et al.): ``A`` from the brightest dark
channel, ``t = max(1 - omega dark(I / A), t_min)`` smoothed by a box filter, and
``J = (I - A) / t + A``.  Like the network it works one view at a time, so it is not
view-consistent -- which is what the ablation measures.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from nimbus.nimbusgs.airlight import dark_channel_hard, estimate_airlight


@dataclass(frozen=True)
class RestoreConfig:
    """median: median-filter window (px); patch: dark-channel patch (px); omega: haze kept (He: 0.95);
    t_min: lower bound of the transmission; smooth: box-filter window of the transmission (px);
    dehaze: run the dark-channel dehazing step."""

    median: int = 3
    patch: int = 15
    omega: float = 0.95
    t_min: float = 0.1
    smooth: int = 15
    dehaze: bool = True


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


@torch.no_grad()
def classical_restore(image: Tensor, config: RestoreConfig = RestoreConfig()) -> Tensor:
    """Restore one degraded view ``[H, W, 3]`` in [0, 1] -> ``[H, W, 3]`` in [0, 1] (module docstring)."""
    x = median_filter(image.float(), config.median)
    if not config.dehaze:
        return x.clamp(0, 1)
    a = estimate_airlight(x, config.patch)
    t = 1 - config.omega * dark_channel_hard(x / a, config.patch)
    t = box_filter(t, config.smooth).clamp_min(config.t_min)
    return ((x - a) / t[..., None] + a).clamp(0, 1)
