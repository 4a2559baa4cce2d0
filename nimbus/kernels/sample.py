"""Compiled CPU bilinear sampling of a map at pixel positions: GGS's per-Gaussian error.

:func:`nimbus.methods.nimbusgs.ggs.sample_error` samples the per-pixel error of a view at the
projected centres of the visible Gaussians: in torch an ``index_select`` of the centres, a
normalisation into a grid and a ``grid_sample`` (align_corners=False, border padding), about 1.3 ms
for 165k Gaussians on one loaded core, every stage-2 step.  ``csrc/sample.cpp`` takes each index
through all of it at once, with grid_sample's float32 arithmetic (``csrc/grid_sample.h``), so the
result is the same bit for bit where torch runs its vectorised kernel (``tests/test_sample_kernel.py``).
It is built into NimbusGS's library with the ray march (:data:`nimbus.kernels.march.EXTENSION`).
"""

from __future__ import annotations

import torch
from torch import Tensor

from nimbus.kernels.march import EXTENSION

__all__ = ["usable", "bilinear_border"]


def usable(*tensors: Tensor) -> bool:
    """Whether the kernel can sample these: CPU float32 tensors, and the library builds (no warning when it
    does not: the torch path gives the same numbers)."""
    return (all(t.device.type == "cpu" and t.dtype == torch.float32 for t in tensors)
            and EXTENSION.available(warn=False))


def bilinear_border(image: Tensor, xy: Tensor, index: Tensor) -> Tensor:
    """``grid_sample`` of ``image`` [H, W] (align_corners=False, border padding, bilinear) at the pixel positions
    ``xy[index]`` (``xy`` [N, 2], x then y, pixel (u, v) spanning [u, u + 1) x [v, v + 1)): ``[len(index)]``.

    Raises RuntimeError when the compiled library is unavailable.
    """
    EXTENSION.require("nimbus.kernels.sample")
    return torch.ops.nimbus_sample.bilinear_border(image.contiguous(), xy.contiguous(),
                                                   index.to(torch.int64).contiguous())
