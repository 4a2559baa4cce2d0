"""Compiled CPU ray march through an :class:`~nimbus.methods.nimbusgs.scattering.ExtinctionGrid` (forward and backward).

NimbusGS's kernels (``csrc/march.cpp``, ``csrc/airlight.cpp`` for
:mod:`nimbus.kernels.airlight` and ``csrc/consistency.cpp`` for :mod:`nimbus.kernels.consistency`) are their own library (:data:`EXTENSION`, built and
cached by :class:`nimbus.kernels.extension.Extension`, apart from the rasterizer's).  The march
computes, per ray, the softplus feature integral ``S = ds * sum_i softplus(f(x_i))`` over
the K uniform samples of
:func:`nimbus.methods.nimbusgs.scattering.march`, without materialising the ``[P, K, 3]``
sample points; the optical depth is ``tau = S * exp(log_scale)``.  Gradients flow to
the grid features (and, through the product, to ``log_scale``), not to the rays or
their intervals: :func:`usable` says when the kernel applies.  A march that will be
differentiated keeps each sample's softplus' from its forward ([P, K], 4 bytes a sample), so its
backward only locates the samples and scatters into the grid.  The same library holds
:func:`grid_tv`, the extinction grid's L_TV in one pass.
"""

from __future__ import annotations

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from nimbus.kernels.extension import Extension

__all__ = ["available", "usable", "grid_optical_depth", "grid_tv", "EXTENSION"]

#: march.cpp (torch.ops.nimbus_march), airlight.cpp (torch.ops.nimbus_airlight), consistency.cpp
#: (torch.ops.nimbus_consistency) and sample.cpp (torch.ops.nimbus_sample): one library, one build.
EXTENSION = Extension("nimbus_march", ("march.cpp", "airlight.cpp", "consistency.cpp", "sample.cpp"),
                      kernel="ray-march kernel",
                      fallback="the torch ray march, airlight, consistency check and GGS sampling")


def available() -> bool:
    """Whether the compiled march kernel can be used; never raises, warns once on failure."""
    return EXTENSION.available()


def usable(features: Tensor, *rays: Tensor) -> bool:
    """Whether the kernel can march these inputs: CPU float32/float64 features, and no gradient wanted for
    ``rays`` (origin, directions, interval: the kernel differentiates the features only)."""
    return (features.device.type == "cpu" and features.dtype in (torch.float32, torch.float64)
            and not any(t.requires_grad for t in rays))


class _GridMarch(torch.autograd.Function):
    # A march that will be differentiated keeps each sample's softplus' [P, K] from its forward
    # (march_forward_keep), so that the backward only locates the samples and scatters: the same
    # gradient, bit for bit, as march_backward's, which evaluates every sample again.
    @staticmethod
    def forward(ctx, features, origin, dirs, t_start, t_end, lo, hi, samples):
        ops = torch.ops.nimbus_march
        if ctx.needs_input_grad[0]:
            S, kept = ops.march_forward_keep(features, origin, dirs, t_start, t_end, lo, hi, samples)
            ctx.save_for_backward(features, origin, dirs, t_start, t_end, lo, hi, kept)
        else:
            S = ops.march_forward(features, origin, dirs, t_start, t_end, lo, hi, samples)
        ctx.samples = samples
        return S

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_s):
        features, origin, dirs, t_start, t_end, lo, hi, kept = ctx.saved_tensors
        g = torch.ops.nimbus_march.march_backward_kept(features, origin, dirs, t_start, t_end, lo, hi, ctx.samples,
                                                       kept, grad_s.contiguous())
        return (g,) + (None,) * 7


def grid_optical_depth(features: Tensor, lo: Tensor, hi: Tensor, origin: Tensor, dirs: Tensor, t_start: Tensor,
                       t_end: Tensor, samples: int) -> Tensor:
    """``S`` ``[P]``: ``ds * sum_i softplus(trilinear(features, x_i))`` over each ray's K samples (module docstring).

    Parameters
    ----------
    features : Tensor [1, 1, Z, Y, X] or [Z, Y, X]
        The grid's raw features (voxel centres span ``lo`` .. ``hi`` corner to corner);
        gradients flow to it.
    lo, hi : Tensor [3]
        The box, world units.
    origin : Tensor [3]
    dirs : Tensor [P, 3], unit
    t_start, t_end : Tensor [P]
        Interval along each ray (an empty or reversed one gives 0); no gradient.
    samples : int
        K >= 1.

    All tensors on the CPU and of one dtype (float32 or float64).  Samples outside the
    box contribute 0.  Raises RuntimeError when the compiled library is unavailable.
    """
    EXTENSION.require("nimbus.kernels.march")
    dtype = features.dtype
    grid = features.reshape(features.shape[-3:])
    args = [t.detach().to(dtype).contiguous() for t in (origin.reshape(3), dirs, t_start.reshape(-1),
                                                         t_end.reshape(-1), lo.reshape(3), hi.reshape(3))]
    return _GridMarch.apply(grid.contiguous(), *args, int(samples))


class _GridTV(torch.autograd.Function):
    @staticmethod
    def forward(ctx, features):
        value, softplus, derivative = torch.ops.nimbus_march.grid_tv(features)
        ctx.save_for_backward(softplus, derivative)
        return value

    @staticmethod
    @once_differentiable
    def backward(ctx, grad):
        softplus, derivative = ctx.saved_tensors
        return torch.ops.nimbus_march.grid_tv_backward(softplus, derivative, grad.detach())


def grid_tv(features: Tensor) -> Tensor:
    """``sum over the three axes of mean |forward difference of softplus(features)|`` (0-d), differentiable.

    :meth:`~nimbus.methods.nimbusgs.scattering.ExtinctionGrid.tv` without the density scale, in one
    compiled pass (``csrc/march.cpp``: 5.2 ms instead of torch's 10.8 at 64^3 with its backward, one
    idle thread); equal to the torch expression up to float rounding (softplus by the march's polynomial,
    the sums in slice order: the same bits at any thread count).

    ``features`` [Z, Y, X] or [1, 1, Z, Y, X], every side >= 2, CPU float32/float64.  Raises RuntimeError
    when the compiled library is unavailable.
    """
    EXTENSION.require("nimbus.kernels.march")
    return _GridTV.apply(features.reshape(features.shape[-3:]).contiguous())
