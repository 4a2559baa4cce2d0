"""The training step's compiled CPU kernels: the loss with its gradient, and the gradients' finiteness check.

:func:`photometric_loss` computes what :func:`nimbus.losses.photometric_loss` computes with
torch ops (the 3dgs SSIM protocol of :mod:`nimbus.metrics.image`: Gaussian window, zero
'same' padding, mean over the map) for one ``[H, W, C]`` pair (with its validity mask), with
separable filters instead of five 11x11 depthwise convolutions and their transposes; the
forward also forms the gradient w.r.t. the prediction, which the backward only scales.
Equal to the torch loss up to float rounding (not bit for bit).  :func:`all_finite` is
``all(torch.isfinite(t).all() for t in tensors)``, in one read pass without temporaries
where it can, and :func:`scale_rows_all_finite` the same check fused with GGS's per-row scaling
of the gradients.  Every result is bitwise the same for any thread count.

The kernels (``csrc/train_step.cpp``) are their own library (:data:`EXTENSION`, built and
cached by :class:`nimbus.kernels.extension.Extension`, apart from the rasterizer's);
:func:`loss_usable` says when the loss applies, and :mod:`nimbus.losses` takes the torch
ops otherwise.
"""

from __future__ import annotations

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from nimbus.kernels.extension import Extension

__all__ = ["loss_usable", "photometric_loss", "target_moments", "all_finite", "scale_rows_all_finite", "EXTENSION"]

#: train_step.cpp (torch.ops.nimbus_train_step).
EXTENSION = Extension("nimbus_train_step", ("train_step.cpp",), kernel="training-step kernels (loss, gradient check)",
                      fallback="the torch loss and isfinite")


def loss_usable(pred: Tensor, gt: Tensor, mask: Tensor | None) -> bool:
    """Whether the kernel can compute this loss: one CPU float32/float64 ``[H, W, C]`` pair, a mask (if any) of
    their ``[H, W]``, no gradient wanted for ``gt`` or the mask, and the library builds (no warning when it does
    not: the torch loss is the same)."""
    return (pred.dim() == 3 and pred.shape == gt.shape and pred.device.type == "cpu" and gt.device.type == "cpu"
            and pred.dtype in (torch.float32, torch.float64) and gt.dtype == pred.dtype and not gt.requires_grad
            and (mask is None or (mask.shape == pred.shape[:2] and mask.device.type == "cpu"
                                  and not mask.requires_grad))
            and EXTENSION.available(warn=False))


class _PhotometricLoss(torch.autograd.Function):
    @staticmethod
    def forward(ctx, pred, gt, mask, taps, lambda_dssim, c1, c2, gt_moments):
        loss, grad = torch.ops.nimbus_train_step.photometric_loss(pred, gt, mask, taps, lambda_dssim, c1, c2,
                                                                  ctx.needs_input_grad[0], gt_moments)
        ctx.save_for_backward(grad)
        return loss

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_loss):
        (grad,) = ctx.saved_tensors
        return grad_loss * grad, None, None, None, None, None, None, None


def target_moments(gt: Tensor, taps: Tensor, mask: Tensor | None = None) -> Tensor:
    """The SSIM's filtered moments of a target alone, ``[2, C, H, W]`` (``F(y)``, ``F(y^2)``), for
    :func:`photometric_loss`'s ``gt_moments``: a constant target (a training view) need not be filtered again
    at every step.  Same arguments as there; :func:`loss_usable` must hold for ``(gt, gt, mask)``."""
    EXTENSION.require("nimbus.kernels.train_step")
    weight = gt.new_empty(0) if mask is None else mask.detach().to(gt.dtype).contiguous()
    return torch.ops.nimbus_train_step.target_moments(gt.detach().contiguous(), weight, taps.detach().contiguous())


def photometric_loss(pred: Tensor, gt: Tensor, lambda_dssim: float, taps: Tensor, c1: float, c2: float,
                     mask: Tensor | None = None, gt_moments: Tensor | None = None) -> Tensor:
    """``(1 - lambda_dssim) mean|pred - gt| + lambda_dssim (1 - mean SSIM(pred, gt))`` (0-d, pred's dtype).

    Parameters
    ----------
    pred, gt : Tensor [H, W, C]
        CPU, one dtype (float32 or float64); the gradient flows to ``pred`` only (:func:`loss_usable`).
    lambda_dssim : float
    taps : Tensor [K] float64
        The 1-D SSIM window (odd K, summing to 1); the 2-D window is its outer product.
    c1, c2 : float
        SSIM's stabilising constants.
    mask : bool Tensor [H, W], optional
        Validity mask, as :func:`nimbus.metrics.masked_pair` applies it: both images zeroed outside it,
        both means over its pixels (at least one).
    gt_moments : Tensor [2, C, H, W], optional
        :func:`target_moments` of this ``gt``, ``taps`` and ``mask`` (the caller's promise, not checked):
        the same loss and gradient, bit for bit, filtering three of the SSIM's five moments instead of five.
    """
    EXTENSION.require("nimbus.kernels.train_step")
    weight = pred.new_empty(0) if mask is None else mask.detach().to(pred.dtype).contiguous()
    cached = pred.new_empty(0) if gt_moments is None else gt_moments.detach().contiguous()
    return _PhotometricLoss.apply(pred.contiguous(), gt.detach().contiguous(), weight, taps.detach().contiguous(),
                                  float(lambda_dssim), float(c1), float(c2), cached)


def _cpu_float(t: Tensor) -> bool:
    return t.device.type == "cpu" and t.dtype in (torch.float32, torch.float64) and t.is_contiguous()


def scale_rows_all_finite(tensors: list[Tensor], weights: Tensor) -> bool:
    """Multiply row ``i`` of every tensor (first dimension ``N``) by ``weights[i]`` in place, and return whether
    every product is finite: ``t.mul_(w.reshape(N, 1, ...))`` for each, then :func:`all_finite`, in one pass
    where the library loads and every tensor is a contiguous CPU float tensor of the weights' dtype (the same
    products, bit for bit), else with those torch ops."""
    n = weights.shape[0]
    if (tensors and _cpu_float(weights) and all(_cpu_float(t) and t.dtype == weights.dtype and t.dim() >= 1
                                                and t.shape[0] == n for t in tensors)
            and EXTENSION.available(warn=False)):
        return bool(torch.ops.nimbus_train_step.scale_rows_all_finite(tensors, weights))
    for t in tensors:
        t.mul_(weights.to(t.dtype).reshape((n,) + (1,) * (t.dim() - 1)))
    return all_finite(tensors)


def all_finite(tensors: list[Tensor]) -> bool:
    """Whether every element of every tensor is finite: one read pass without temporaries for contiguous CPU
    float tensors when the library loads, ``torch.isfinite`` for the others, read back once per device (on
    CUDA one synchronisation a call, not one a tensor; and no CPU library is loaded for CUDA tensors)."""
    cpu = [t for t in tensors if _cpu_float(t)]
    kernel = cpu if cpu and EXTENSION.available(warn=False) else []
    if kernel and not torch.ops.nimbus_train_step.all_finite(kernel):
        return False
    flags: dict[torch.device, list[Tensor]] = {}
    for t in tensors:
        if not any(t is k for k in kernel):
            flags.setdefault(t.device, []).append(torch.isfinite(t).all())
    return all(bool(torch.stack(f).all()) for f in flags.values())
