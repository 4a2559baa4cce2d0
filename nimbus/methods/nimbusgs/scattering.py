"""Continuous Scattering Modelling (CSM): an extinction field beta(x) and the ray march that turns it into T and P.

Model (paper, Eqs. 4-7): along each pixel's ray ``r(s) = o + s d`` (``d`` a unit world
direction, ``s`` the Euclidean distance from the camera centre), take K samples
uniformly in ``[t_n, t_0]`` (the near bound and the rendered surface), then

    T   = exp(-sum_j beta(r(s_j)) ds)                      transmission to the surface
    T_i = exp(-sum_{j<i} beta(r(s_j)) ds)                  transmission to sample i
    P   = sum_i T_i (1 - exp(-beta(r(s_i)) ds)) A          in-scattered airlight

Samples sit at the centres of K equal segments, so a homogeneous field gives
``T = exp(-beta L)``.  With one airlight per ray the weights telescope for any field,
``sum_i T_i (1 - exp(-tau_i)) = 1 - T``, so :func:`march` only accumulates the optical
depth (on the CPU in a compiled kernel, :mod:`nimbus.kernels.march`);
:func:`march_reference` evaluates the equations term by term.

Conventions: rays follow the camera convention of :mod:`nimbus.data.camera` (OpenCV,
+z forward): the camera-frame direction of pixel (u, v) is ``((u + 0.5 - cx) / fx,
(v + 0.5 - cy) / fy, 1)`` rotated to the world by ``R^T``.  (The authors' released code
builds ``-z``-forward directions for ``+z``-forward cameras, so it samples the grid
behind the camera; ``test_rays_point_into_the_scene`` guards against that.)

Fields share one interface: ``field(points [..., 3]) -> beta [...] >= 0`` (zero outside
the box) and ``field.tv()`` (the TV regulariser).  :class:`ExtinctionGrid` is the
paper's voxel field; :class:`UniformExtinction` the "uniform extinction" ablation.  The
"Gaussian-driven" ablation has no field: its per-pixel extinction is rendered from a
per-Gaussian attribute (:func:`gaussian_extinction_map`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from dataclasses import field as dataclass_field

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from nimbus.data.camera import Camera
from nimbus.errors import NimbusError

#: softplus(0): the extinction of a zero feature before the density scale.
SOFTPLUS_ZERO = math.log(2.0)
#: About how many bytes one ray sample takes in the torch march (:func:`march`, float32, forward and backward:
#: the ``[P, K, 3]`` points and what grid_sample keeps).  Measured on the CPU at 4096 rays and 256 or 1024
#: samples: 63 to 64 (28 to 60 without gradients).  The compiled CPU march allocates nothing per sample, but
#: the torch march is its fallback and the GPU's path, so sizes are checked against this figure.
MARCH_BYTES_PER_SAMPLE = 64
#: About how many bytes one voxel of an :class:`ExtinctionGrid` takes while training: the feature, its gradient,
#: two Adam moments and L_TV's differences.  Measured on the CPU at 200^3: 119 (176 at 100^3, with overheads).
GRID_BYTES_PER_VOXEL = 128


def softplus_inverse(y: float) -> float:
    """x with softplus(x) = y (y > 0)."""
    return y + math.log(-math.expm1(-y))


@dataclass(frozen=True)
class Box:
    """An axis-aligned box ``[lo, hi]`` in world coordinates (each a length-3 tuple)."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]

    @classmethod
    def around(cls, points: np.ndarray | Tensor, scale: float = 2.0, min_size: float = 1e-3) -> "Box":
        """The points' AABB enlarged ``scale`` times about its centre (paper: 2x); never thinner than ``min_size``."""
        p = torch.as_tensor(points, dtype=torch.float64).reshape(-1, 3)
        if p.shape[0] == 0:
            return cls((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
        lo, hi = p.min(0).values, p.max(0).values
        center, half = (lo + hi) / 2, ((hi - lo) / 2 * scale).clamp_min(min_size / 2)
        return cls(tuple((center - half).tolist()), tuple((center + half).tolist()))

    @classmethod
    def around_content(cls, points: np.ndarray | Tensor, cameras: np.ndarray, scale: float = 2.0,
                       content_factor: float = 0.0) -> "Box":
        """:meth:`around` the points that are not backdrop.

        A point is backdrop when its distance from the mean of ``cameras`` (``[C, 3]``
        centres) exceeds ``content_factor`` times the points' median distance;
        ``content_factor`` 0 keeps every point (the plain AABB).
        """
        p = torch.as_tensor(points, dtype=torch.float64).reshape(-1, 3)
        if content_factor > 0 and p.shape[0] > 0:
            centre = torch.as_tensor(np.asarray(cameras, dtype=np.float64).reshape(-1, 3).mean(0))
            d = torch.linalg.norm(p - centre, dim=1)
            p = p[d <= content_factor * d.median()]
        return cls.around(p, scale)

    def tensors(self, device=None, dtype=torch.float32) -> tuple[Tensor, Tensor]:
        return (torch.tensor(self.lo, device=device, dtype=dtype), torch.tensor(self.hi, device=device, dtype=dtype))


def normalized_coords(points: Tensor, lo: Tensor, hi: Tensor) -> tuple[Tensor, Tensor]:
    """Points mapped to [-1, 1]^3 over the box (grid_sample's ``align_corners=True`` frame) and an inside mask."""
    n = (points - lo) / (hi - lo) * 2 - 1
    inside = (n.abs() <= 1).all(dim=-1)
    return n, inside


class ExtinctionGrid(nn.Module):
    """The paper's extinction field: ``beta(x) = softplus(f(x)) * exp(log_scale)`` inside the box, 0 outside.

    ``f`` is a scalar voxel grid (``resolution^3``, features ~ N(0, init_std)) sampled
    trilinearly; voxel centres span the box corners to corners.

    Parameters
    ----------
    box : Box
    resolution : int
    init_std : float
    density_scale : float
        Initial ``exp(log_scale)``, 1/m: a zero feature gives ``beta = ln 2 * density_scale``.
    generator : torch.Generator, optional
        Seeds the feature initialisation.
    """

    def __init__(self, box: Box, resolution: int, init_std: float, density_scale: float,
                 generator: torch.Generator | None = None) -> None:
        super().__init__()
        self.box = box
        self.resolution = int(resolution)
        feats = torch.randn((1, 1, resolution, resolution, resolution), generator=generator) * init_std
        self.features = nn.Parameter(feats)  # [1, 1, Z, Y, X]
        self.log_scale = nn.Parameter(torch.tensor(math.log(max(density_scale, 1e-12))))
        lo, hi = box.tensors()
        self.register_buffer("lo", lo)
        self.register_buffer("hi", hi)

    def forward(self, points: Tensor) -> Tensor:
        """Extinction at world points ``[..., 3]`` -> ``[...]`` (1/m, >= 0; 0 outside the box)."""
        shape = points.shape[:-1]
        n, inside = normalized_coords(points.reshape(-1, 3), self.lo, self.hi)
        # grid_sample reads (x, y, z) against the feature layout [Z, Y, X].
        f = F.grid_sample(self.features, n.reshape(1, 1, 1, -1, 3), mode="bilinear", padding_mode="border",
                          align_corners=True).reshape(-1)
        beta = F.softplus(f) * torch.exp(self.log_scale) * inside
        return beta.reshape(shape)

    def values(self) -> Tensor:
        """beta at the voxel centres, ``[Z, Y, X]``."""
        return F.softplus(self.features[0, 0]) * torch.exp(self.log_scale)

    def tv(self) -> Tensor:
        """L_TV = mean |grad beta| over the grid (forward differences, summed over the three axes).

        On the CPU with the compiled kernels, in one pass (:func:`nimbus.kernels.march.grid_tv`: the
        same value up to float rounding), else in torch.
        """
        from nimbus.kernels import march as march_kernel

        if march_kernel.usable(self.features) and march_kernel.available():
            return march_kernel.grid_tv(self.features) * torch.exp(self.log_scale)
        b = self.values()
        return sum((torch.diff(b, dim=d).abs().mean() for d in range(3)), torch.zeros((), device=b.device))


class UniformExtinction(nn.Module):
    """One extinction coefficient everywhere inside the box (the paper's "uniform extinction" ablation)."""

    def __init__(self, box: Box, density_scale: float) -> None:
        super().__init__()
        self.box = box
        self.feature = nn.Parameter(torch.zeros(()))
        self.log_scale = nn.Parameter(torch.tensor(math.log(max(density_scale, 1e-12))))
        lo, hi = box.tensors()
        self.register_buffer("lo", lo)
        self.register_buffer("hi", hi)

    def forward(self, points: Tensor) -> Tensor:
        _, inside = normalized_coords(points.reshape(-1, 3), self.lo, self.hi)
        beta = F.softplus(self.feature) * torch.exp(self.log_scale) * inside
        return beta.reshape(points.shape[:-1])

    def values(self) -> Tensor:
        return (F.softplus(self.feature) * torch.exp(self.log_scale)).reshape(1, 1, 1)

    def tv(self) -> Tensor:
        return torch.zeros((), device=self.feature.device)


# --------------------------------------------------------------------------------------
# Rays
# --------------------------------------------------------------------------------------
@dataclass
class ViewRays:
    """Per-pixel rays of one camera, flattened row-major (P = H * W).

    Attributes
    ----------
    origin : Tensor [3]
        Camera centre, world frame.
    dirs : Tensor [P, 3]
        Unit world directions pointing into the scene (+z of the OpenCV camera).
    z_to_distance : Tensor [P]
        ``|(x', y', 1)|``: multiply a z-depth by it to get the distance along the ray.
    """

    origin: Tensor
    dirs: Tensor
    z_to_distance: Tensor
    height: int
    width: int
    _derived: dict = dataclass_field(default_factory=dict, repr=False, compare=False)

    def derived(self, key, compute):
        """``compute()``, computed once per ``key`` for these rays: a value that depends on the rays alone
        (a training view's rays do not change during training)."""
        if key not in self._derived:
            self._derived[key] = compute()
        return self._derived[key]

    def box_interval(self, lo: Tensor, hi: Tensor) -> tuple[Tensor, Tensor]:
        """:func:`ray_box_interval` of these rays through the box ``[lo, hi]``, computed once per box (a
        training view's rays and the medium's box do not change during training)."""
        key = ("box", *lo.tolist(), *hi.tolist())
        return self.derived(key, lambda: ray_box_interval(self.origin, self.dirs, lo.detach(), hi.detach()))


def camera_rays(camera: Camera, device=None) -> ViewRays:
    """The :class:`ViewRays` of ``camera`` (directions from :meth:`Camera.world_rays`: +z forward)."""
    dirs, origin = camera.world_rays(np.float64)
    norm = np.linalg.norm(camera.pixel_rays(np.float64), axis=-1)
    return ViewRays(torch.as_tensor(origin, dtype=torch.float32, device=device),
                    torch.as_tensor(dirs.reshape(-1, 3), dtype=torch.float32, device=device),
                    torch.as_tensor(norm.reshape(-1), dtype=torch.float32, device=device),
                    camera.height, camera.width)


def ray_box_interval(origin: Tensor, dirs: Tensor, lo: Tensor, hi: Tensor) -> tuple[Tensor, Tensor]:
    """Entry and exit distances ``[P]`` of rays through a box (slab method).

    A ray that misses the box, or meets it only behind the camera, gets ``exit < entry``
    or ``exit < 0``; callers clamp the interval to a non-negative length.
    """
    # Replace zero components by a tiny value of the same sign, so 1/d stays finite.
    tiny = 1e-12
    d = torch.where(dirs.abs() < tiny, torch.where(dirs < 0, -tiny, tiny), dirs)
    inv = 1.0 / d
    t1, t2 = (lo - origin) * inv, (hi - origin) * inv
    entry = torch.minimum(t1, t2).amax(dim=-1)
    exit_ = torch.maximum(t1, t2).amin(dim=-1)
    return entry, exit_


def march_interval(rays: ViewRays, lo: Tensor, hi: Tensor, depth: Tensor, alpha: Tensor, near: float,
                   alpha_min: float) -> tuple[Tensor, Tensor]:
    """``(t_start, t_end)`` ``[P]`` of each pixel's march: from the near bound to the surface, inside the box.

    Parameters
    ----------
    depth, alpha : Tensor [H, W]
        The rasterizer's accumulated z (``sum z_i alpha_i T_i``) and accumulated alpha.
    near : float
        Near bound (the rasterizer's near plane), along the ray.
    alpha_min : float
        Below this accumulated alpha the rendered depth is not a surface: march to the box exit.
    """
    entry, exit_ = rays.box_interval(lo, hi)
    surface = _surface_distance(rays, depth, alpha, alpha_min, exit_)
    t_start = entry.clamp_min(near)
    t_end = torch.minimum(surface, exit_)
    t_end = torch.maximum(t_end, t_start)  # misses and surfaces before the box: empty interval
    return t_start, t_end


def _surface_distance(rays: ViewRays, depth: Tensor, alpha: Tensor, alpha_min: float, exit_: Tensor) -> Tensor:
    a = alpha.reshape(-1)
    z = depth.reshape(-1) / a.clamp_min(1e-6)
    return torch.where(a >= alpha_min, z * rays.z_to_distance, exit_)


def surface_in_box(rays: ViewRays, lo: Tensor, hi: Tensor, depth: Tensor, alpha: Tensor, alpha_min: float) -> Tensor:
    """Bool ``[P]``: the pixel's march ends at a rendered surface inside the box.

    False for rays with accumulated alpha below ``alpha_min`` (sky), for surfaces beyond
    the box exit (a backdrop outside the medium's box) and for rays that miss the box.
    """
    entry, exit_ = rays.box_interval(lo, hi)
    a = alpha.reshape(-1)
    surface = _surface_distance(rays, depth, alpha, alpha_min, exit_)
    return (a >= alpha_min) & (surface <= exit_) & (exit_ > entry.clamp_min(0.0))


@dataclass
class MarchResult:
    """Transmission ``[P]`` to the end of each ray and the scattering weight ``[P]`` = sum_i T_i (1 - exp(-tau_i))."""

    transmission: Tensor
    scatter: Tensor


#: ``march`` backends: ``auto`` (compiled for an :class:`ExtinctionGrid` on the CPU when it
#: can be used, else ``torch``), ``cpp`` (compiled; NimbusError if it cannot be used),
#: ``torch`` (any field, any device).
MARCH_BACKENDS = ("auto", "cpp", "torch")


def march(field: nn.Module, origin: Tensor, dirs: Tensor, t_start: Tensor, t_end: Tensor, samples: int,
          backend: str = "auto") -> MarchResult:
    """Integrate ``field`` along rays with ``samples`` uniform samples per ray (module docstring).

    The scattering weights telescope for any field, ``sum_i T_i (1 - e^-tau_i) = 1 - T``,
    so only the optical depth ``tau = sum_i beta_i ds`` is accumulated: ``T = exp(-tau)``
    and ``scatter = -expm1(-tau)``.  :func:`march_reference` evaluates the equations term
    by term; the two agree to rounding.

    Parameters
    ----------
    field : callable ``[..., 3] -> [...]``
    origin : Tensor [3]
    dirs : Tensor [P, 3], unit
    t_start, t_end : Tensor [P]
        ``t_end >= t_start`` (empty intervals give T = 1, scatter = 0).
    samples : int
        K.
    backend : str
        One of :data:`MARCH_BACKENDS`.  The compiled kernel (:mod:`nimbus.kernels.march`)
        marches an :class:`ExtinctionGrid` on the CPU when the rays and intervals need no gradient.
    """
    if backend not in MARCH_BACKENDS:
        raise NimbusError(f"unknown march backend {backend!r}; choose one of {', '.join(MARCH_BACKENDS)}")
    compiled = (backend != "torch" and isinstance(field, ExtinctionGrid)
                and _compiled_usable(field, origin, dirs, t_start, t_end))
    if backend == "cpp" and not compiled:
        raise NimbusError("march backend 'cpp' needs an extinction grid on the CPU, rays and intervals without "
                          "gradient and a working C++ kernel; use backend 'torch' or 'auto'")
    if compiled:
        from nimbus.kernels import march as march_kernel

        s = march_kernel.grid_optical_depth(field.features, field.lo, field.hi, origin, dirs, t_start, t_end,
                                            samples)
        tau = s * torch.exp(field.log_scale)
    else:
        length = (t_end - t_start).clamp_min(0.0)
        ds = length / samples                                                   # [P]
        steps = torch.arange(samples, device=dirs.device, dtype=dirs.dtype) + 0.5
        s = t_start[:, None] + steps[None] * ds[:, None]                        # [P, K]
        points = origin + s[..., None] * dirs[:, None, :]                       # [P, K, 3]
        tau = field(points).sum(dim=1) * ds
    return MarchResult(torch.exp(-tau), -torch.expm1(-tau))


def _compiled_usable(field: "ExtinctionGrid", *rays: Tensor) -> bool:
    from nimbus.kernels import march as march_kernel

    return march_kernel.usable(field.features, *rays) and march_kernel.available()


def march_reference(field: nn.Module, origin: Tensor, dirs: Tensor, t_start: Tensor, t_end: Tensor,
                    samples: int) -> MarchResult:
    """:func:`march` written as the paper's equations (per-sample T_i, cumulative sums): the slow reference."""
    length = (t_end - t_start).clamp_min(0.0)
    ds = length / samples                                                   # [P]
    steps = torch.arange(samples, device=dirs.device, dtype=dirs.dtype) + 0.5
    s = t_start[:, None] + steps[None] * ds[:, None]                        # [P, K]
    points = origin + s[..., None] * dirs[:, None, :]                       # [P, K, 3]
    tau = field(points) * ds[:, None]                                       # [P, K]
    cum = torch.cumsum(tau, dim=1)
    transmission = torch.exp(-cum[:, -1])
    t_before = torch.exp(-(cum - tau))                                      # T_i, exclusive
    scatter = (t_before * -torch.expm1(-tau)).sum(dim=1)
    return MarchResult(transmission, scatter)


def gaussian_extinction_map(beta_image: Tensor, alpha: Tensor, t_start: Tensor, t_end: Tensor) -> MarchResult:
    """T and the scattering weight of the Gaussian-driven ablation.

    ``beta_image`` [H, W] is the alpha-blended per-Gaussian extinction (``sum beta_i
    alpha_i T_i``); normalised by the accumulated alpha it is the mean extinction along
    the ray, applied over the march interval: ``T = exp(-beta_bar L)``, scatter ``1 - T``.
    """
    a = alpha.reshape(-1)
    beta_bar = beta_image.reshape(-1) / a.clamp_min(1e-6) * (a > 1e-6)
    tau = beta_bar * (t_end - t_start).clamp_min(0.0)
    transmission = torch.exp(-tau)
    return MarchResult(transmission, -torch.expm1(-tau))


def density_scale_for(transmission: float, mean_distance: float) -> float:
    """Density scale giving ``transmission`` over ``mean_distance`` with zero features: ``-ln T / (ln 2 * d)``."""
    t = min(max(transmission, 1e-3), 0.999)
    return -math.log(t) / (SOFTPLUS_ZERO * max(mean_distance, 1e-6))
