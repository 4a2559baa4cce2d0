"""Compiled CPU view-consistency excess of NimbusGS's particulate layer.

:class:`~nimbus.methods.nimbusgs.particulate.ViewConsistency` asks, for every pixel of a
training view, how much brighter it is than its neighbouring views see the same surface
point.  torch computes that with about thirty passes over ``[K, H W]`` tensors (three
``grid_sample`` calls per neighbour, a ``nanmedian`` over the stacked samples): about 13 ms a
view at 240 x 180 with four neighbours on one core, paid at every lazy refresh of R.
``csrc/consistency.cpp`` takes each pixel through every neighbour at once, with the same
float32 operations in the same order, so the result is the same bit for bit
(``tests/test_consistency_kernel.py`` checks it against the torch path).  It is built into
NimbusGS's library with the ray march (:data:`nimbus.kernels.march.EXTENSION`).
"""

from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor

from nimbus.kernels.march import EXTENSION

__all__ = ["usable", "consistency_excess"]

#: Most neighbours the kernel takes (its median's buffer).
MAX_NEIGHBOURS = 64


def usable(*tensors: Tensor, neighbours: int = 0) -> bool:
    """Whether the kernel can compute this excess: CPU tensors, at most :data:`MAX_NEIGHBOURS` neighbours, and
    the library builds (no warning when it does not: the torch path gives the same numbers)."""
    return (all(t.device.type == "cpu" for t in tensors) and neighbours <= MAX_NEIGHBOURS
            and EXTENSION.available(warn=False))


def _f32(t: Tensor) -> Tensor:
    return t.to(torch.float32).contiguous()


def consistency_excess(lum: Tensor, rays: Tensor, depth: Tensor, valid: Tensor, pose: Tensor,
                       neighbours: Sequence[tuple[Tensor, Tensor, Tensor, Tensor, Tensor, tuple[int, int]]]) -> Tensor:
    """The view's intensity minus the median of what its neighbours see at its surface points, ``[P]``.

    Parameters
    ----------
    lum : Tensor [P]
        The view's intensity (mean over RGB) per pixel.
    rays : Tensor [P, 3]
        Its camera-frame pixel rays (z = 1).
    depth, valid : Tensor [P]
        Its rendered camera z and where that surface is valid (bool or float, > 0).
    pose : Tensor [12]
        Its world-to-camera rotation (row-major) and translation.
    neighbours : sequence of (pose [12], intrinsics [4], depth [H, W], valid [H, W], bright [H, W], (width, height))
        Each neighbour's pose, ``(fx, fy, cx, cy)``, rendered surface, maximum-filtered intensity and camera size.

    NaN where no neighbour counts.  Raises RuntimeError when the compiled library is unavailable.
    """
    EXTENSION.require("nimbus.kernels.consistency")
    poses = torch.stack([_f32(n[0]).reshape(12) for n in neighbours]) if neighbours else torch.zeros((0, 12))
    intrinsics = torch.stack([_f32(n[1]).reshape(4) for n in neighbours]) if neighbours else torch.zeros((0, 4))
    sizes = torch.tensor([list(n[5]) for n in neighbours], dtype=torch.int64).reshape(-1, 2)
    return torch.ops.nimbus_consistency.excess(
        _f32(lum).reshape(-1), _f32(rays).reshape(-1, 3), _f32(depth).reshape(-1), _f32(valid).reshape(-1),
        _f32(pose).reshape(12), poses, intrinsics, sizes,
        [_f32(n[2]) for n in neighbours], [_f32(n[3]) for n in neighbours], [_f32(n[4]) for n in neighbours])
