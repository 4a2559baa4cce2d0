"""Compiled CPU forward and backward of NimbusGS's network airlight (its MLP, fused).

:class:`~nimbus.methods.nimbusgs.airlight.NetworkAirlight` evaluates ``A = sigmoid(base + MLP(x))``
for every pixel of a view, every step: with torch that is ten passes over ``[P, hidden]``
tensors (two products, two SiLUs and their backward).  ``csrc/airlight.cpp`` runs a
block of rows through every layer while it is in cache, forward and backward, and
differentiates the weights and biases only (the features ``x`` and ``base`` are
constants; :func:`usable` says when the kernel applies).  It is built into NimbusGS's
library with the ray march (:data:`nimbus.kernels.march.EXTENSION`).  Equal to the torch
MLP up to float rounding (sums in another order, sigmoid's exp by a polynomial).
"""

from __future__ import annotations

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from nimbus.kernels.march import EXTENSION

__all__ = ["usable", "network_airlight"]


def usable(x: Tensor, base: Tensor, *weights: Tensor) -> bool:
    """Whether the kernel can evaluate this MLP: CPU float32/float64 tensors of one dtype, no gradient wanted
    for ``x`` or ``base``, and the library builds (no warning when it does not: the torch MLP is the same)."""
    tensors = (x, base) + weights
    return (all(t.device.type == "cpu" and t.dtype == x.dtype for t in tensors)
            and x.dtype in (torch.float32, torch.float64) and not x.requires_grad and not base.requires_grad
            and EXTENSION.available(warn=False))


class _NetworkAirlight(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, base, w1, b1, w2, b2, w3, b3):
        a, z1, z2 = torch.ops.nimbus_airlight.airlight_forward(x, w1, b1, w2, b2, w3, b3, base)
        ctx.save_for_backward(x, base, w1, b1, w2, b2, w3, b3, z1, z2, a)
        return a

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_a):
        x, base, w1, b1, w2, b2, w3, b3, z1, z2, a = ctx.saved_tensors
        grads = torch.ops.nimbus_airlight.airlight_backward(x, w1, b1, w2, b2, w3, b3, base, z1, z2, a,
                                                            grad_a.contiguous())
        return (None, None, *grads)


def network_airlight(x: Tensor, base: Tensor, w1: Tensor, b1: Tensor, w2: Tensor, b2: Tensor, w3: Tensor,
                     b3: Tensor) -> Tensor:
    """``A = sigmoid(base + silu(silu(x W1^T + b1) W2^T + b2) W3^T + b3)`` ``[P, O]``.

    Parameters
    ----------
    x : Tensor [P, I]
        The features of each row (no gradient).
    base : Tensor [O]
        The output's logit offset (no gradient).
    w1, b1, w2, b2, w3, b3 : Tensor
        ``[H, I]``, ``[H]``, ``[H, H]``, ``[H]``, ``[O, H]``, ``[O]``: the three ``nn.Linear`` layers; gradients
        flow to them.

    All on the CPU and of one dtype (float32 or float64).  Raises RuntimeError when the
    compiled library is unavailable.
    """
    EXTENSION.require("nimbus.kernels.airlight")
    return _NetworkAirlight.apply(x.contiguous(), base.contiguous(), w1.contiguous(), b1.contiguous(),
                                  w2.contiguous(), b2.contiguous(), w3.contiguous(), b3.contiguous())
