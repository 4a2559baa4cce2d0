"""The Gaussian scene representation and its initialisation from a scene.

Parameterisation (the optimiser works on these raw tensors; activations are applied
by the renderer):

* ``means``      [N, 3]  centres, world frame.
* ``log_scales`` [N, 3]  log of the standard deviations along the Gaussian's own axes.
* ``quats``      [N, 4]  rotation as a quaternion (w, x, y, z); normalised by the renderer.
* ``opacity_logits`` [N] ``sigmoid`` gives the opacity in (0, 1).
* ``sh_dc``      [N, 1, 3] degree-0 SH coefficients.
* ``sh_rest``    [N, (D+1)^2 - 1, 3] higher-degree SH coefficients (D = 0..3; zero-width for D = 0).

The tensors are kept separate (rather than one packed array) because 3DGS gives each
its own learning rate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np
import torch
from torch import Tensor

from nimbus.data.camera_focus import RandomInitConfig, RandomInitPlan, plan_random_points, sample_random_points
from nimbus.errors import NimbusError
from nimbus.render.sh import MAX_SH_DEGREE, num_sh_bases, rgb_to_sh


@dataclass
class Gaussians:
    """A set of N 3D Gaussians (see the module docstring for shapes and meaning).

    A plain container: no autograd or device logic beyond :meth:`to`,
    :meth:`requires_grad_` and :meth:`detach`.
    """

    means: Tensor
    log_scales: Tensor
    quats: Tensor
    opacity_logits: Tensor
    sh_dc: Tensor
    sh_rest: Tensor

    def __post_init__(self) -> None:
        n = self.means.shape[0]
        expected = {
            "means": (n, 3),
            "log_scales": (n, 3),
            "quats": (n, 4),
            "opacity_logits": (n,),
            "sh_dc": (n, 1, 3),
        }
        for name, shape in expected.items():
            got = tuple(getattr(self, name).shape)
            if got != shape:
                raise ValueError(f"Gaussians.{name} must have shape {shape}, got {got}")
        rest = tuple(self.sh_rest.shape)
        if len(rest) != 3 or rest[0] != n or rest[2] != 3 or (rest[1] + 1) not in (1, 4, 9, 16):
            raise ValueError(f"Gaussians.sh_rest must have shape [N, (D+1)^2 - 1, 3], got {rest}")

    # --- views ---------------------------------------------------------------------
    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def sh(self) -> Tensor:
        """All SH coefficients, shape [N, (D+1)^2, 3]."""
        return torch.cat([self.sh_dc, self.sh_rest], dim=1)

    @property
    def sh_degree(self) -> int:
        """Largest SH degree the stored coefficients allow."""
        return math.isqrt(self.sh_rest.shape[1] + 1) - 1

    @property
    def scales(self) -> Tensor:
        return torch.exp(self.log_scales)

    @property
    def opacities(self) -> Tensor:
        return torch.sigmoid(self.opacity_logits)

    @property
    def device(self) -> torch.device:
        return self.means.device

    def tensors(self) -> dict[str, Tensor]:
        """The parameter tensors by name (e.g. to build optimiser parameter groups)."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    # --- conversions -----------------------------------------------------------------
    def to(self, device=None, dtype=None) -> "Gaussians":
        return Gaussians(**{k: v.to(device=device, dtype=dtype) for k, v in self.tensors().items()})

    def detach(self) -> "Gaussians":
        return Gaussians(**{k: v.detach() for k, v in self.tensors().items()})

    def requires_grad_(self, flag: bool = True) -> "Gaussians":
        for v in self.tensors().values():
            v.requires_grad_(flag)
        return self


@dataclass(frozen=True)
class GaussianInitConfig:
    """How :func:`init_from_scene` seeds the Gaussians.

    Attributes
    ----------
    sh_degree : int
        Degree of the SH coefficients allocated (0..3; 3DGS uses 3). Higher bands start at 0.
    init_opacity : float
        Initial opacity in (0, 1) (3DGS: 0.1).
    knn : int
        Neighbours averaged for the initial scale (3DGS: 3).
    min_scale : float
        Lower bound on the initial scale (world units), so duplicated points do not get log(0).
    random_points : int
        Number of random points used when the scene has no sparse points. 3DGS uses
        100 000 for its synthetic scenes; 10 000 keeps CPU training affordable.
    random : RandomInitConfig
        Where those random points go: about the training cameras' focus, or in their view
        frusta for a forward-facing capture (:mod:`nimbus.data.camera_focus`).
    seed : int
        Seed of the random points and colours.
    """

    sh_degree: int = 3
    init_opacity: float = 0.1
    knn: int = 3
    min_scale: float = 1e-7
    random_points: int = 10_000
    random: RandomInitConfig = RandomInitConfig()
    seed: int = 0

    def __post_init__(self) -> None:
        if not 0 <= self.sh_degree <= MAX_SH_DEGREE:
            raise NimbusError(f"sh_degree must be in 0..{MAX_SH_DEGREE}, got {self.sh_degree}")
        if not 0.0 < self.init_opacity < 1.0:
            raise NimbusError(f"init_opacity must be in (0, 1), got {self.init_opacity}")
        if self.knn < 1:
            raise NimbusError(f"knn must be >= 1, got {self.knn}")
        if self.random_points < 1:
            raise NimbusError(f"random_points must be >= 1, got {self.random_points}")


# Bounds a [queries, candidates] distance block of the k-NN search (about 16 MB of float32).
_KNN_BLOCK_ELEMENTS = 1 << 22
# Queries per block, and the neighbours along the Z-curve (each side) that bound the k-th distance.
_KNN_QUERY_CHUNK = 512
_KNN_WINDOW = 16


def _morton_codes(points: Tensor) -> Tensor:
    """Z-curve keys [N] int64 of points [N, 3] quantised to 21 bits per axis over their bounding box."""
    lo, hi = points.amin(0), points.amax(0)
    q = ((points - lo) / (hi - lo).clamp_min(1e-300) * ((1 << 21) - 1)).to(torch.int64)

    def spread(v):  # insert two zero bits between the 21 low bits of v
        v = (v | (v << 32)) & 0x1F00000000FFFF
        v = (v | (v << 16)) & 0x1F0000FF0000FF
        v = (v | (v << 8)) & 0x100F00F00F00F00F
        v = (v | (v << 4)) & 0x10C30C30C30C30C3
        return (v | (v << 2)) & 0x1249249249249249

    return spread(q[:, 0]) | (spread(q[:, 1]) << 1) | (spread(q[:, 2]) << 2)


def knn_mean_distance(points: Tensor, k: int = 3) -> Tensor:
    """Mean Euclidean distance of each point to its ``k`` nearest other points.

    Never builds an N x N matrix: the neighbours along a Z-order curve give each point
    an upper bound ``r`` on its k-th distance, so its true neighbours lie in the slab
    ``|x - x_q| <= r`` along the widest axis x, a contiguous range of the points sorted
    by x.  Each chunk of queries is compared (``torch.cdist`` + ``topk``) with
    the union of its slabs only, in blocks of at most ``_KNN_BLOCK_ELEMENTS``.
    Candidates are ranked with the fast float32 matrix-product distance (with spares)
    and re-measured in float64, so near-duplicate points do not suffer its cancellation
    error.  About 4 s for 100 000 points in a dense 3D blob on 2 cores, less for SfM
    points (which lie near surfaces).

    Parameters
    ----------
    points : Tensor, shape [N, 3]
    k : int
        Clipped to N - 1.

    Returns
    -------
    Tensor, shape [N], same dtype as ``points``; zeros when N < 2.
    """
    n = points.shape[0]
    k = min(k, n - 1)
    if k < 1:
        return torch.zeros(n, dtype=points.dtype, device=points.device)
    device = points.device
    exact = points.to(torch.float64)
    axis = int(torch.argmax(exact.amax(0) - exact.amin(0)))
    order = torch.argsort(exact[:, axis])
    sp = exact[order]                                  # sorted along `axis`
    xs = sp[:, axis].contiguous()
    fast = (sp - sp.mean(0)).to(torch.float32)

    # Upper bound on the k-th distance: the k-th smallest distance to the neighbours in
    # Morton (Z-curve) order, which are mostly spatial neighbours.
    morton_order = torch.argsort(_morton_codes(sp))
    zp = sp[morton_order]
    w = max(k, _KNN_WINDOW)
    offs = torch.cat([torch.arange(-w, 0, device=device), torch.arange(1, w + 1, device=device)])
    nb = torch.arange(n, device=device)[:, None] + offs[None]
    valid = (nb >= 0) & (nb < n)
    d = (zp[nb.clamp(0, n - 1)] - zp[:, None]).norm(dim=-1).masked_fill(~valid, math.inf)
    bound = torch.empty(n, dtype=torch.float64, device=device)
    bound[morton_order] = torch.topk(d, k, dim=1, largest=False).values[:, -1] * (1 + 1e-9) + 1e-12
    lo = torch.searchsorted(xs, xs - bound)
    hi = torch.searchsorted(xs, xs + bound, right=True)

    out = torch.empty(n, dtype=torch.float64, device=device)
    n_cand = k + 4  # spare candidates absorb the matrix-product rounding in the ranking
    for q0 in range(0, n, _KNN_QUERY_CHUNK):
        q1 = min(n, q0 + _KNN_QUERY_CHUNK)
        span = int(hi[q0:q1].max() - lo[q0:q1].min())
        step = max(1, _KNN_BLOCK_ELEMENTS // span)      # a far outlier widens the slab: fewer queries
        for a in range(q0, q1, step):
            b = min(q1, a + step)
            c0, c1 = int(lo[a:b].min()), int(hi[a:b].max())
            dist = torch.cdist(fast[a:b], fast[c0:c1])
            rows = torch.arange(b - a, device=device)
            self_col = rows + a - c0
            inside = (self_col >= 0) & (self_col < c1 - c0)
            dist[rows[inside], self_col[inside]] = math.inf  # the point itself (by index: duplicates count)
            cand = torch.topk(dist, min(n_cand, c1 - c0 - 1), dim=1, largest=False).indices + c0
            exact_d = (sp[cand] - sp[a:b, None]).norm(dim=-1)
            out[a:b] = torch.topk(exact_d, k, dim=1, largest=False).values.mean(1)
    result = torch.empty_like(out)
    result[order] = out
    return result.to(points.dtype)


def init_from_points(
    points: Tensor | np.ndarray,
    colors: Tensor | np.ndarray,
    config: GaussianInitConfig = GaussianInitConfig(),
    fallback_scale: float = 0.01,
) -> Gaussians:
    """Gaussians centred on sparse points (3DGS initialisation).

    Parameters
    ----------
    points : [N, 3] float
        Centres, world frame.
    colors : [N, 3]
        Colours, uint8 in 0..255 or float in [0, 1].
    config : GaussianInitConfig
    fallback_scale : float
        Scale used when N < 2 (no neighbours), world units.

    Returns
    -------
    Gaussians (float32, on the device of ``points`` if it is a tensor, else CPU): scale =
    mean distance to the ``config.knn`` nearest points (isotropic), identity rotation,
    opacity ``config.init_opacity``, DC colour from ``colors``, higher SH bands zero.
    """
    pts = torch.as_tensor(np.asarray(points) if not isinstance(points, Tensor) else points)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise NimbusError(f"points must have shape (N, 3), got {tuple(pts.shape)}")
    device = pts.device
    cols = colors if isinstance(colors, Tensor) else torch.as_tensor(np.asarray(colors))
    if tuple(cols.shape) != tuple(pts.shape):
        raise NimbusError(f"colors must have shape {tuple(pts.shape)}, got {tuple(cols.shape)}")
    if not torch.isfinite(pts.to(torch.float64)).all():
        raise NimbusError("sparse points contain NaN or inf")
    cols = cols.to(device)
    rgb = cols.to(torch.float32) / 255.0 if cols.dtype == torch.uint8 else cols.to(torch.float32)
    n = pts.shape[0]
    dist = knn_mean_distance(pts.to(torch.float64), config.knn) if n >= 2 else torch.full((n,), fallback_scale,
                                                                                         dtype=torch.float64)
    log_scale = torch.log(dist.clamp_min(config.min_scale)).to(torch.float32, copy=True).to(device)
    k = num_sh_bases(config.sh_degree)
    return Gaussians(
        means=pts.to(torch.float32).clone(),
        log_scales=log_scale[:, None].repeat(1, 3),
        quats=torch.tensor([1.0, 0.0, 0.0, 0.0], device=device).repeat(n, 1),
        opacity_logits=torch.full((n,), math.log(config.init_opacity / (1 - config.init_opacity)), device=device),
        sh_dc=rgb_to_sh(rgb)[:, None, :].contiguous(),
        sh_rest=torch.zeros(n, k - 1, 3, device=device),
    )


def init_from_scene(scene, config: GaussianInitConfig = GaussianInitConfig()) -> Gaussians:
    """Initial Gaussians for a :class:`nimbus.data.Scene`.

    Uses the scene's sparse points and colours when it has any; otherwise
    ``config.random_points`` random points with random colours placed from the training
    cameras (:func:`random_init_plan`: about their focus, or in their view frusta when they
    face forward).
    """
    if len(scene.points):
        return init_from_points(scene.points, scene.colors, config)
    cameras = random_init_cameras(scene)
    plan = plan_random_points(cameras, config.random)
    points, colors = sample_random_points(plan, cameras, config.random_points, config.seed)
    return init_from_points(points, colors, config, fallback_scale=plan.radius or plan.near)


def random_init_cameras(scene) -> list:
    """The cameras that place random starting points: the training views' (every view's when none is)."""
    views = scene.train_views or scene.views
    if not views:
        raise NimbusError("the scene has no views to place starting points from")
    return [v.camera for v in views]


def random_init_plan(scene, config: GaussianInitConfig = GaussianInitConfig()) -> RandomInitPlan:
    """Where :func:`init_from_scene` puts random points for ``scene`` when it has none (for records)."""
    return plan_random_points(random_init_cameras(scene), config.random)
