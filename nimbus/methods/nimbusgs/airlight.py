"""Airlight A: the colour that the medium scatters into each ray (CSM's P = sum_i T_i (1 - e^-tau_i) A).

Three variants share ``module(dirs [P, 3], transmission [P], descriptor [D], pixels [P, 3] | None)
-> A [P, 3]`` (values in (0, 1); ``pixels`` is the degraded input at the rays' pixels):

* :class:`NetworkAirlight` (paper default): a small MLP conditioned on the degraded input
  and on T.  T enters per pixel (detached: it conditions the colour, it is not a path for
  the extinction's gradient).  How the input enters is ``airlight_input``:

  - ``view`` (ours): through a per-view *global* descriptor (the dark-channel airlight
    estimate of He et al. and the mean colour, :func:`view_descriptor`) and the ray
    direction, not its pixels: a per-pixel copy of I_in would let ``P`` reproduce the
    input with T -> 0 and leave the clean render unconstrained.
  - ``pixel`` (the paper's words): the input's colour at the pixel, and T.

  Either way the output starts at the view's dark-channel estimate (zero-initialised
  last layer around its logit).
* :class:`ConstantAirlight`: one RGB colour for the scene.
* :class:`SHAirlight`: SH of the ray direction (the authors' released code).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from nimbus.kernels import airlight as airlight_kernel
from nimbus.render.sh import num_sh_bases, sh_basis

#: Length of :func:`view_descriptor`.
DESCRIPTOR_SIZE = 6
#: Input features of the network airlight per ``airlight_input``: (d, T, descriptor) or (I_in pixel, T).
_NETWORK_INPUTS = {"view": 3 + 1 + DESCRIPTOR_SIZE, "pixel": 3 + 1}
#: About how many bytes the network airlight takes per weight (its ``hidden x hidden`` layer dominates): the
#: weight, its gradient, two Adam moments and the compiled kernel's copies.  Measured on the CPU (one forward,
#: backward and Adam step, widths 4096 and 8192): 25 to 29 with the compiled kernel, 9 to 10 without.
AIRLIGHT_BYTES_PER_WEIGHT = 32
#: About how many bytes per hidden unit per evaluated pixel (the activations kept for the backward pass).
#: Measured as above at 65,536 pixels, widths 256 and 1024: 10 to 13 compiled, 20 with torch ops.
AIRLIGHT_BYTES_PER_ACTIVATION = 24
#: Fraction of the brightest dark-channel pixels whose colour estimates the airlight (He et al.: 0.1 %).
AIRLIGHT_TOP_FRACTION = 0.001
#: Bounds of the initial airlight estimate, so its logit is finite.
_A_MIN, _A_MAX = 0.02, 0.98


def dark_channel_window(patch: int, height: int, width: int) -> int:
    """The window a ``patch`` x ``patch`` minimum filter of an ``height`` x ``width`` image needs: ``patch``, or
    ``2 * max(height, width) - 1`` if that is smaller, since that window already spans the whole image from every
    pixel (the same minimum, and the same pixel chosen).  A wider one only costs time: torch's filter walks its
    padding pixel by pixel, so ``dcp_patch=2**31`` ran for hours."""
    return min(int(patch), 2 * max(height, width) - 1)


def window_min(x: Tensor, patch: int) -> Tensor:
    """The minimum over each ``patch`` x ``patch`` window (centred; padding ignored) of ``x`` ``[H, W]``.

    As two one-axis passes, columns then rows: the same values as one square window (a minimum of
    minima), in about half the time of ``max_pool2d`` over the square (16 -> 8.5 ms with its backward
    at 240 x 180 and 11 x 11, one thread).  The gradient reaches the window's minimum as the square
    pool's does; only where a window holds the minimum twice may the two pick different copies.
    """
    h, w = x.shape
    patch = dark_channel_window(patch, h, w)
    pad = patch // 2
    y = F.max_pool2d(-x[None, None], (patch, 1), stride=1, padding=(pad, 0))
    return -F.max_pool2d(y, (1, patch), stride=1, padding=(0, pad))[0, 0, :h, :w]


def dark_channel_hard(image: Tensor, patch: int) -> Tensor:
    """min over colour and over a ``patch`` x ``patch`` window: ``[H, W, 3] -> [H, W]``."""
    return window_min(image.min(dim=-1).values, patch)


def estimate_airlight(image: Tensor, patch: int) -> Tensor:
    """He et al.'s airlight: the mean colour of the input at the brightest 0.1 % of its dark channel ``[3]``."""
    dark = dark_channel_hard(image, patch).reshape(-1)
    k = max(1, int(round(dark.numel() * AIRLIGHT_TOP_FRACTION)))
    idx = torch.topk(dark, k).indices
    return image.reshape(-1, 3)[idx].mean(0).clamp(_A_MIN, _A_MAX)


def view_descriptor(image: Tensor, patch: int) -> Tensor:
    """Global descriptor of a degraded view ``[6]``: dark-channel airlight estimate (RGB) and mean colour (RGB)."""
    return torch.cat([estimate_airlight(image, patch), image.reshape(-1, 3).mean(0)])


def _logit(p: Tensor) -> Tensor:
    p = p.clamp(_A_MIN, _A_MAX)
    return torch.log(p) - torch.log1p(-p)


class ConstantAirlight(nn.Module):
    """A = sigmoid(c), one colour; ``init`` [3] in (0, 1)."""

    def __init__(self, init: Tensor) -> None:
        super().__init__()
        self.logit = nn.Parameter(_logit(init.detach().float()))

    def forward(self, dirs: Tensor, transmission: Tensor, descriptor: Tensor, pixels: Tensor | None = None) -> Tensor:
        return torch.sigmoid(self.logit).expand(dirs.shape[0], 3)


class SHAirlight(nn.Module):
    """A = sigmoid(logit(init) + SH_degree(d) . c), c zero-initialised."""

    def __init__(self, init: Tensor, degree: int) -> None:
        super().__init__()
        self.degree = int(degree)
        self.base = nn.Parameter(_logit(init.detach().float()))
        self.coeffs = nn.Parameter(torch.zeros(num_sh_bases(degree), 3))

    def forward(self, dirs: Tensor, transmission: Tensor, descriptor: Tensor, pixels: Tensor | None = None) -> Tensor:
        return torch.sigmoid(self.base + sh_basis(self.degree, dirs) @ self.coeffs)


class _WideInputLinear(torch.autograd.Function):
    """``F.linear(x, weight, bias)`` for an input ``x`` [P, I] of many rows, few columns and no gradient.

    Autograd's weight gradient for it, ``grad.T @ x``, takes a slow matrix-product path for
    this shape ([64, P] by [P, 10]: ~5x slower than the product below with MKL at P = 43200,
    the largest single cost of a NimbusGS step); ``(x.T @ grad).T`` is the same sum, rounded
    differently (float tolerance).  The forward is ``nn.Linear``'s.
    """

    @staticmethod
    def forward(ctx, x: Tensor, weight: Tensor, bias: Tensor) -> Tensor:
        ctx.save_for_backward(x, weight)
        return F.linear(x, weight, bias)

    @staticmethod
    def backward(ctx, grad: Tensor):
        x, weight = ctx.saved_tensors
        grad_x = grad @ weight if ctx.needs_input_grad[0] else None
        return grad_x, (x.t() @ grad).t(), grad.sum(0)


class NetworkAirlight(nn.Module):
    """A = sigmoid(logit(A_dark(view)) + MLP(inputs)); see the module docstring.

    ``inputs`` (``airlight_input``): ``view`` -> (d, T, descriptor), 10 features;
    ``pixel`` -> (I_in at the pixel, T), 4 features.  Two hidden layers of ``hidden``.
    ``compiled``: evaluate the MLP, forward and backward, with the fused CPU kernel
    (:mod:`nimbus.kernels.airlight`; equal to the torch layers up to float rounding) where it
    applies; False always takes the torch layers.
    """

    def __init__(self, hidden: int, inputs: str = "view", compiled: bool = True) -> None:
        super().__init__()
        if inputs not in _NETWORK_INPUTS:
            raise ValueError(f"unknown airlight input {inputs!r}")
        self.inputs = inputs
        self.compiled = compiled
        self.mlp = nn.Sequential(nn.Linear(_NETWORK_INPUTS[inputs], hidden), nn.SiLU(), nn.Linear(hidden, hidden),
                                 nn.SiLU(), nn.Linear(hidden, 3))
        nn.init.zeros_(self.mlp[-1].weight)
        nn.init.zeros_(self.mlp[-1].bias)

    def forward(self, dirs: Tensor, transmission: Tensor, descriptor: Tensor, pixels: Tensor | None = None) -> Tensor:
        n = dirs.shape[0]
        if self.inputs == "pixel":
            if pixels is None:
                raise ValueError("airlight_input='pixel' needs the input's pixels [P, 3]")
            x = torch.cat([pixels.detach().to(transmission.dtype), transmission.detach()[:, None]], dim=1)
        else:
            x = torch.cat([dirs, transmission.detach()[:, None], descriptor.expand(n, DESCRIPTOR_SIZE)], dim=1)
        base = _logit(descriptor[:3])
        layers = (self.mlp[0], self.mlp[2], self.mlp[4])
        weights = [t for layer in layers for t in (layer.weight, layer.bias)]
        if self.compiled and airlight_kernel.usable(x, base, *weights):
            return airlight_kernel.network_airlight(x, base, *weights)
        h = _WideInputLinear.apply(x, layers[0].weight, layers[0].bias)
        for layer in self.mlp[1:]:
            h = layer(h)
        return torch.sigmoid(base + h)


def network_airlight_bytes(hidden: int, points: int) -> float:
    """About how many bytes the network airlight of width ``hidden`` takes to train on ``points`` pixels (or blocks)."""
    return float(hidden) * hidden * AIRLIGHT_BYTES_PER_WEIGHT + float(hidden) * points * AIRLIGHT_BYTES_PER_ACTIVATION


def make_airlight(kind: str, init: Tensor, hidden: int, sh_degree: int, inputs: str = "view",
                  compiled: bool = True) -> nn.Module:
    """The airlight module named ``kind`` (``network``, ``constant``, ``sh``); ``init`` [3] seeds the fixed ones,
    ``inputs`` is the network's conditioning (``view`` or ``pixel``), ``compiled`` lets it use the CPU kernel
    (:class:`NetworkAirlight`)."""
    if kind == "network":
        return NetworkAirlight(hidden, inputs, compiled)
    if kind == "constant":
        return ConstantAirlight(init)
    if kind == "sh":
        return SHAirlight(init, sh_degree)
    raise ValueError(f"unknown airlight {kind!r}")
