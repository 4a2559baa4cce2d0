"""Particulate Layer Modelling (PLM): per-view residuals R = ReLU(I_in - I_con), stored compactly.

After stage 1 the continuous-medium render I_con holds the view-consistent scene; what
the input has in excess of it (rain streaks, snow flakes) is the view's particulate layer
R.  Stage 2 renders ``I_deg = I_con + R`` and re-extracts R every Z_ref iterations
(:func:`is_refresh_step`).  R has no learnable parameters.

Storage: one ``uint8`` ``[H, W, 3]`` tensor per training view (R is in [0, 1]; 8-bit
steps of 1/255 are below what a PNG input resolves), replaced in place at each refresh,
so memory is ``3 H W`` bytes per view whatever the run length.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

_LEVELS = 255.0
_MAD_TO_STD = 1.4826
#: Window of the local mean removed before outliers are looked for (pixels).
HIGHPASS_WINDOW = 5
#: Floor of the robust noise level (intensity units), so a perfect fit does not flag everything.
MIN_SIGMA = 1e-3


def highpass(x: Tensor, window: int = HIGHPASS_WINDOW) -> Tensor:
    """``x - box_mean(x)`` for a map ``[H, W]`` (replicate padding)."""
    pad = window // 2
    m = F.avg_pool2d(F.pad(x[None, None], (pad, pad, pad, pad), mode="replicate"), window, stride=1)[0, 0]
    return x - m


def outlier_mask(image: Tensor, composite: Tensor, sigmas: float) -> Tensor:
    """Pixels ``[H, W]`` whose high-passed residual exceeds ``sigmas`` robust standard deviations, grown by 1 px."""
    d = highpass((image - composite).float().mean(dim=-1))
    sigma = max(_MAD_TO_STD * float((d - d.median()).abs().median()), MIN_SIGMA)
    mask = (d > sigmas * sigma).float()
    return F.max_pool2d(mask[None, None], 3, stride=1, padding=1)[0, 0] > 0


def extract_residual(image: Tensor, composite: Tensor, outlier_sigmas: float = 0.0) -> Tensor:
    """R = ReLU(I_in - I_con), clipped to [0, 1]; ``[H, W, 3]`` float.

    ``outlier_sigmas > 0`` keeps R only where the residual stands out of the view's
    residual distribution (:func:`outlier_mask`), so a stage-1 model that is still
    under-fitted everywhere does not have its whole misfit frozen into R (ours; the
    paper's R is ``outlier_sigmas = 0``).
    """
    r = (image - composite).clamp(0.0, 1.0)
    if outlier_sigmas > 0:
        r = r * outlier_mask(image, composite, outlier_sigmas)[..., None]
    return r


def is_refresh_step(iteration: int, m_init: int, interval: int) -> bool:
    """Whether ``iteration`` (1-based) ends a refresh period of stage 2 (``j mod Z_ref = 0``, j the stage-2 count)."""
    j = iteration - m_init
    return j > 0 and j % interval == 0


class ResidualStore:
    """One quantised residual per training view.

    Parameters
    ----------
    shapes : list of (H, W)
        Image size of each view.
    device : torch.device
    """

    def __init__(self, shapes: list[tuple[int, int]], device=None) -> None:
        self.shapes = [tuple(s) for s in shapes]
        self.device = device
        self.data: list[Tensor] = [torch.zeros((h, w, 3), dtype=torch.uint8, device=device) for h, w in self.shapes]
        #: Iteration at which each view's residual was last written (-1: never).
        self.stamps: list[int] = [-1] * len(self.shapes)
        self.refreshes = 0

    def __len__(self) -> int:
        return len(self.data)

    def set(self, index: int, residual: Tensor, iteration: int) -> None:
        """Store ``residual`` [H, W, 3] (values in [0, 1]) for view ``index``."""
        r = residual.detach().clamp(0.0, 1.0)
        self.data[index] = torch.round(r * _LEVELS).to(torch.uint8)
        self.stamps[index] = int(iteration)

    def get(self, index: int, dtype=torch.float32) -> Tensor:
        """The residual of view ``index`` as float ``[H, W, 3]`` in [0, 1] (zeros if never set)."""
        return self.data[index].to(dtype) / _LEVELS

    def is_stale(self, index: int, last_refresh_point: int) -> bool:
        """Whether view ``index`` was last written before ``last_refresh_point``."""
        return self.stamps[index] < last_refresh_point

    @property
    def nbytes(self) -> int:
        return sum(t.numel() * t.element_size() for t in self.data)

    def state_dict(self) -> dict:
        return {"data": [t.clone() for t in self.data], "stamps": list(self.stamps), "refreshes": self.refreshes}

    def load_state_dict(self, state: dict) -> None:
        self.data = [t.to(self.device) for t in state["data"]]
        self.stamps = list(state["stamps"])
        self.refreshes = int(state["refreshes"])
