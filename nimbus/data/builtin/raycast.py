"""A small analytic ray caster for the built-in scenes (vectorised numpy, CPU).

Geometry is a list of primitives with closed-form ray intersections: a ground
disc, axis-aligned rectangles, spheres, yaw-rotated boxes, vertical capped
cylinders, capsules of any orientation and a backdrop sphere seen from inside.
Every ray of an image is traced at once; the nearest hit wins.  Shading is view-independent (Lambert with a fixed sun plus a hemispheric
ambient term, no specular, no shadows), so a surface point has the same colour
in every view.

Conventions
-----------
* World "up" is +z.  Cameras follow :mod:`nimbus.data.camera` (OpenCV frame,
  world-to-camera pose, pixel (u, v) centred at (u + 0.5, v + 0.5)).
* Rays are unit vectors; ``t`` is the distance along the ray; z-depth is
  ``t * (d . forward)`` with ``forward`` the camera's +z axis in world space.
* Anti-aliasing: each pixel is sampled on an ``n x n`` regular grid of
  sub-pixel offsets ``((i + 0.5) / n, (j + 0.5) / n)`` from the pixel's corner
  and the colours are averaged.  Every sample is traced; shading (the costly
  part: procedural textures) is adaptive: a pixel is shaded at every sample
  only when its samples hit different primitives or its centre colour
  differs from a neighbour's (:class:`RenderSettings`), which matches full
  supersampling to about 0.002 mean absolute error at a fraction of the cost.
* Depth and mask come from the single ray through the pixel centre (for odd
  ``n`` that is the middle grid sample; for even ``n`` an extra centre ray is
  traced), so depth is exact geometry, never a blend of two surfaces.
* Screen-space culling: a bounded primitive is only tested against the rays of
  the pixels its projected bounding box covers.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Mapping, Sequence

import numpy as np

from nimbus.data.camera import Camera

# Hits closer than this (metres) are ignored, so a ray never hits the surface it starts on.
T_MIN = 1e-4


# --- primitives -------------------------------------------------------------------------
# Rays are passed structure-of-arrays: ``d`` has shape (3, N) (contiguous rows dx, dy, dz), which
# keeps every step an elementwise op on contiguous float32 rows (numpy reductions over a
# length-3 axis are an order of magnitude slower).  ``o`` is the shared origin, shape (3,).


def _box_corners(center, half_size, yaw: float) -> np.ndarray:
    """The 8 corners (8, 3) of a box with the given centre, half-sizes and yaw about +z."""
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], np.float64)
    local = signs * np.asarray(half_size, np.float64)
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return local @ rot.T + np.asarray(center, np.float64)


def _intersect_sphere(o, d, center, radius: float, inside: bool) -> np.ndarray:
    ox, oy, oz = (float(o[k] - center[k]) for k in range(3))
    b = d[0] * ox + d[1] * oy + d[2] * oz
    disc = b * b - (ox * ox + oy * oy + oz * oz - radius * radius)
    with np.errstate(invalid="ignore"):
        root = np.sqrt(disc)
    t = root - b if inside else -b - root  # far root from inside, near root from outside
    return np.where(t > T_MIN, t, np.inf).astype(np.float32)  # NaN (miss) compares False


@dataclass(frozen=True)
class Sphere:
    """A solid sphere (rays hit its outside)."""

    center: tuple[float, float, float]
    radius: float
    material: str

    def corners(self) -> np.ndarray:
        """Corners (8, 3) of a world box that contains the primitive (for screen-space culling)."""
        return _box_corners(self.center, (self.radius,) * 3, 0.0)

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        """Distance to the first hit for unit rays ``d`` (3, N) from ``o`` (3,); inf on a miss."""
        return _intersect_sphere(o, d, self.center, self.radius, inside=False)

    def normal(self, p: np.ndarray, d: np.ndarray, o: np.ndarray) -> np.ndarray:
        c = np.asarray(self.center, np.float32)[:, None]
        return ((p - c) / np.float32(self.radius)).astype(np.float32)


@dataclass(frozen=True)
class Backdrop:
    """A large sphere seen from inside: the far surface (sky, distant hills) every ray ends on."""

    center: tuple[float, float, float]
    radius: float
    material: str

    def corners(self) -> None:
        """Unbounded: every ray is tested."""
        return None

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        return _intersect_sphere(o, d, self.center, self.radius, inside=True)

    def normal(self, p: np.ndarray, d: np.ndarray, o: np.ndarray) -> np.ndarray:
        c = np.asarray(self.center, np.float32)[:, None]
        return ((c - p) / np.float32(self.radius)).astype(np.float32)


@dataclass(frozen=True)
class Ground:
    """The horizontal plane z = ``height`` clipped to a disc of ``radius`` around ``center`` (x, y)."""

    height: float
    radius: float
    material: str
    center: tuple[float, float] = (0.0, 0.0)

    def corners(self) -> None:
        """Unbounded: every ray is tested."""
        return None

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        with np.errstate(divide="ignore", invalid="ignore"):
            t = float(self.height - o[2]) / d[2]
            x = t * d[0] + float(o[0] - self.center[0])
            y = t * d[1] + float(o[1] - self.center[1])
            ok = (t > T_MIN) & (x * x + y * y <= self.radius ** 2)
        return np.where(ok, t, np.inf).astype(np.float32)

    def normal(self, p: np.ndarray, d: np.ndarray, o: np.ndarray) -> np.ndarray:
        n = np.zeros_like(p, dtype=np.float32)
        n[2] = 1.0
        return n


@dataclass(frozen=True)
class Box:
    """A box with centre, half-sizes along its own axes and a rotation ``yaw`` (radians) about +z."""

    center: tuple[float, float, float]
    half_size: tuple[float, float, float]
    material: str
    yaw: float = 0.0

    def corners(self) -> np.ndarray:
        return _box_corners(self.center, self.half_size, self.yaw)

    def _local(self, o: np.ndarray, d: np.ndarray) -> tuple[list[float], list[np.ndarray]]:
        """Origin and directions in the box frame (centred, rotated by -yaw about z)."""
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        ox, oy, oz = (float(o[k] - self.center[k]) for k in range(3))
        if self.yaw == 0.0:
            return [ox, oy, oz], [d[0], d[1], d[2]]
        return ([c * ox + s * oy, -s * ox + c * oy, oz],
                [np.float32(c) * d[0] + np.float32(s) * d[1], np.float32(-s) * d[0] + np.float32(c) * d[1], d[2]])

    def _slabs(self, o: np.ndarray, d: np.ndarray) -> tuple[list[np.ndarray], np.ndarray, list[np.ndarray]]:
        """Per-axis entry distances, the exit distance, and the local directions."""
        ol, dl = self._local(o, d)
        tnear, tfar = [], None
        with np.errstate(divide="ignore", invalid="ignore"):
            for k in range(3):
                inv = np.float32(1.0) / dl[k]
                t1 = (-self.half_size[k] - ol[k]) * inv
                t2 = (self.half_size[k] - ol[k]) * inv
                tnear.append(np.minimum(t1, t2))
                far = np.maximum(t1, t2)
                tfar = far if tfar is None else np.minimum(tfar, far)
        return tnear, tfar, dl

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        tnear, tfar, _ = self._slabs(o, d)
        t = np.maximum(np.maximum(tnear[0], tnear[1]), tnear[2])
        return np.where((t <= tfar) & (t > T_MIN), t, np.inf).astype(np.float32)

    def normal(self, p: np.ndarray, d: np.ndarray, o: np.ndarray) -> np.ndarray:
        tnear, _, dl = self._slabs(o, d)
        axis = np.argmax(np.stack(tnear), axis=0)  # the slab entered last is the face hit
        nl = np.zeros((3, p.shape[1]), np.float32)
        for k in range(3):
            nl[k] = np.where(axis == k, -np.sign(dl[k]), 0.0)  # the face the ray enters faces the ray
        c, s = np.float32(np.cos(self.yaw)), np.float32(np.sin(self.yaw))
        return np.stack([c * nl[0] - s * nl[1], s * nl[0] + c * nl[1], nl[2]]).astype(np.float32)


@dataclass(frozen=True)
class Cylinder:
    """A vertical capped cylinder: axis through (x, y) = ``center``, from z = ``z0`` to ``z1``."""

    center: tuple[float, float]
    z0: float
    z1: float
    radius: float
    material: str

    def corners(self) -> np.ndarray:
        half = 0.5 * (self.z1 - self.z0)
        return _box_corners((self.center[0], self.center[1], self.z0 + half), (self.radius, self.radius, half), 0.0)

    def _hits(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(t_side, t_cap): distances to the side wall and to the cap facing the ray (inf when missed)."""
        ox, oy, oz = float(o[0] - self.center[0]), float(o[1] - self.center[1]), float(o[2])
        dx, dy, dz = d[0], d[1], d[2]
        r2 = self.radius ** 2
        with np.errstate(divide="ignore", invalid="ignore"):
            a = dx * dx + dy * dy
            b = ox * dx + oy * dy
            disc = b * b - a * (ox * ox + oy * oy - r2)
            ts = (-b - np.sqrt(disc)) / a
            zs = oz + ts * dz
            ts = np.where((ts > T_MIN) & (zs >= self.z0) & (zs <= self.z1), ts, np.inf)
            cap_z = np.where(dz < 0, np.float32(self.z1), np.float32(self.z0))
            tc = (cap_z - oz) / dz
            x = ox + tc * dx
            y = oy + tc * dy
            tc = np.where((tc > T_MIN) & (x * x + y * y <= r2), tc, np.inf)
        return ts.astype(np.float32), tc.astype(np.float32)

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        ts, tc = self._hits(o, d)
        return np.minimum(ts, tc)

    def normal(self, p: np.ndarray, d: np.ndarray, o: np.ndarray) -> np.ndarray:
        ts, tc = self._hits(o, d)
        side = ts <= tc
        inv_r = np.float32(1.0 / self.radius)
        return np.stack([np.where(side, (p[0] - self.center[0]) * inv_r, 0.0),
                         np.where(side, (p[1] - self.center[1]) * inv_r, 0.0),
                         np.where(side, 0.0, -np.sign(d[2]))]).astype(np.float32)


@dataclass(frozen=True)
class Capsule:
    """A solid capsule: the points within ``radius`` of the segment from ``a`` to ``b`` (any orientation).

    Slanted branches and bent trunks (the tabletop scene's tree) are chains of capsules that
    share end points, which join without seams because each end is a full sphere.
    """

    a: tuple[float, float, float]
    b: tuple[float, float, float]
    radius: float
    material: str

    def corners(self) -> np.ndarray:
        lo = np.minimum(self.a, self.b) - self.radius
        hi = np.maximum(self.a, self.b) + self.radius
        return _box_corners(0.5 * (lo + hi), 0.5 * (hi - lo), 0.0)

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        # The union of a finite cylinder and two end spheres: its first hit is the nearest of the
        # side hit (kept only between the end planes) and the two spheres' near hits.  A ray that
        # would enter through an end plane enters the end sphere first, so the planes never count.
        ba = np.asarray(self.b, np.float64) - np.asarray(self.a, np.float64)
        oa = np.asarray(o, np.float64) - np.asarray(self.a, np.float64)
        baba, baoa, oaoa = float(ba @ ba), float(ba @ oa), float(oa @ oa)
        # float64: for a thin capsule far away the discriminant is a small difference of large terms.
        d64 = d.astype(np.float64)
        bard = d64[0] * ba[0] + d64[1] * ba[1] + d64[2] * ba[2]
        rdoa = d64[0] * oa[0] + d64[1] * oa[1] + d64[2] * oa[2]
        qa = baba - bard * bard
        qb = baba * rdoa - baoa * bard
        qc = baba * oaoa - baoa * baoa - self.radius ** 2 * baba
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (-qb - np.sqrt(qb * qb - qa * qc)) / qa
            y = baoa + t * bard
            t = np.where((t > T_MIN) & (y > 0.0) & (y < baba), t, np.inf)  # NaN (miss) compares False
        t = t.astype(np.float32)
        for end in (self.a, self.b):
            t = np.minimum(t, _intersect_sphere(o, d, end, self.radius, inside=False))
        return t

    def normal(self, p: np.ndarray, d: np.ndarray, o: np.ndarray) -> np.ndarray:
        a = np.asarray(self.a, np.float32)[:, None]
        ba = np.asarray(self.b, np.float32)[:, None] - a
        s = np.clip(np.sum((p - a) * ba, axis=0) / np.float32(np.sum(ba * ba)), 0.0, 1.0)
        n = p - a - s[None, :] * ba  # from the nearest point of the axis segment
        return (n / np.maximum(np.sqrt(np.sum(n * n, axis=0)), np.float32(1e-12))).astype(np.float32)


@dataclass(frozen=True)
class Rect:
    """An axis-aligned rectangle: ``half_size`` is zero along its normal axis (two-sided; the normal faces the ray).

    A room's floor, ceiling and walls seen from inside: one plane test per ray, where a wall
    built as a thin :class:`Box` needs three slabs (and covers most of the image).
    """

    center: tuple[float, float, float]
    half_size: tuple[float, float, float]
    material: str

    def __post_init__(self) -> None:
        if sorted(h == 0 for h in self.half_size) != [False, False, True]:
            raise ValueError(f"a Rect has exactly one zero half-size (its normal axis), got {self.half_size}")

    @property
    def axis(self) -> int:
        return list(self.half_size).index(0)

    def corners(self) -> np.ndarray:
        return _box_corners(self.center, self.half_size, 0.0)

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        k = self.axis
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.float32(self.center[k] - o[k]) / d[k]
            ok = t > T_MIN
            for i in range(3):
                if i != k:
                    ok &= np.abs(t * d[i] + np.float32(o[i] - self.center[i])) <= np.float32(self.half_size[i])
        return np.where(ok, t, np.inf).astype(np.float32)

    def normal(self, p: np.ndarray, d: np.ndarray, o: np.ndarray) -> np.ndarray:
        n = np.zeros_like(p, dtype=np.float32)
        n[self.axis] = -np.sign(d[self.axis])
        return n


Primitive = Sphere | Backdrop | Ground | Box | Cylinder | Capsule | Rect


def surface_normal(prim: Primitive, o: np.ndarray, d: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Hit points (3, N) and unit outward normals (3, N) of rays ``d`` (3, N) that hit ``prim`` at ``t`` (N,)."""
    p = (o.astype(np.float32)[:, None] + t[None, :] * d).astype(np.float32)
    return p, prim.normal(p, d, o)


# --- materials, lighting, world ------------------------------------------------------------
@dataclass(frozen=True)
class Material:
    """Surface colour as a function of world position.

    Attributes
    ----------
    albedo : callable
        ``albedo(p, n) -> (N, 3) float32`` in [0, 1] for hit points ``p`` (N, 3) and normals ``n`` (N, 3).
    emissive : bool
        True for self-lit surfaces (sky / distant backdrop): the albedo is the final colour, unshaded.
    """

    albedo: Callable[[np.ndarray, np.ndarray], np.ndarray]
    emissive: bool = False


@dataclass(frozen=True)
class Lighting:
    """View-independent lighting: ``albedo * (ambient * (1 - sky_bias + sky_bias * n_z) + sun * max(0, n . L))``.

    Attributes
    ----------
    sun_direction : tuple of float
        Direction towards the sun (world, normalised here); default high in the south-east.
    sun : float
        Direct-light strength, default 0.72.
    ambient : float
        Sky-light strength, default 0.38.
    sky_bias : float
        How much more ambient light an upward-facing surface gets than a vertical one, default 0.25.
    """

    sun_direction: tuple[float, float, float] = (0.45, -0.35, 0.82)
    sun: float = 0.72
    ambient: float = 0.38
    sky_bias: float = 0.25

    def shade(self, albedo: np.ndarray, n: np.ndarray) -> np.ndarray:
        L = np.asarray(self.sun_direction, np.float32)
        L = L / np.linalg.norm(L)
        lam = np.maximum(n @ L, 0.0)
        light = self.ambient * (1.0 - self.sky_bias + self.sky_bias * n[:, 2]) + self.sun * lam
        return (albedo * light[:, None].astype(np.float32)).astype(np.float32)


@dataclass(frozen=True)
class World:
    """Everything a view needs: primitives, their materials and the light.

    ``backdrop_materials`` names the materials whose pixels are the sky / backdrop mask.
    """

    primitives: tuple[Primitive, ...]
    materials: Mapping[str, Material]
    lighting: Lighting = field(default_factory=Lighting)
    backdrop_materials: frozenset[str] = frozenset()

    def __post_init__(self) -> None:
        missing = {p.material for p in self.primitives} - set(self.materials)
        if missing:
            raise ValueError(f"primitives use undefined materials: {sorted(missing)}")


# --- rays and rendering ---------------------------------------------------------------------
def subpixel_offsets(samples_per_axis: int) -> tuple[np.ndarray, int, int]:
    """Sub-pixel sample offsets from the pixel corner, shape (S, 2) as (du, dv) in [0, 1).

    Returns the offsets, the number of colour samples (``n * n``, the first ones) and
    the index of the pixel-centre sample used for depth and mask.
    """
    n = int(samples_per_axis)
    if n < 1:
        raise ValueError("samples_per_axis must be >= 1")
    g = (np.arange(n) + 0.5) / n
    dv, du = np.meshgrid(g, g, indexing="ij")
    offs = np.stack([du.ravel(), dv.ravel()], axis=1)
    if n % 2:
        return offs, n * n, (n * n) // 2
    return np.concatenate([offs, [[0.5, 0.5]]]), n * n, n * n


def camera_rays(camera: Camera, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit world-space ray directions for every sub-pixel offset and pixel.

    Parameters
    ----------
    camera : Camera
    offsets : ndarray, shape (S, 2)
        (du, dv) offsets from each pixel's top-left corner, in pixels; (0.5, 0.5) is the
        pixel centre and gives exactly :meth:`Camera.world_rays`' directions.

    Returns
    -------
    dirs : ndarray, shape (3, S, H, W), float32
        Structure-of-arrays: ``dirs[:, s, v, u]`` is the ray of sample ``s`` of pixel (u, v).
    origin : ndarray, shape (3,), float32
    """
    offsets = np.asarray(offsets, np.float64).reshape(-1, 2)
    u = np.arange(camera.width, dtype=np.float64)
    v = np.arange(camera.height, dtype=np.float64)
    x = (u[None, None, :] + offsets[:, 0, None, None] - camera.cx) / camera.fx  # (S, 1, W)
    y = (v[None, :, None] + offsets[:, 1, None, None] - camera.cy) / camera.fy  # (S, H, 1)
    # Small per-row / per-column factors in float64, the (S, H, W) arrays in float32.
    x, y = x.astype(np.float32), y.astype(np.float32)
    inv_norm = np.float32(1.0) / np.sqrt(x * x + y * y + np.float32(1.0))  # (S, H, W)
    cam = (x * inv_norm, y * inv_norm, inv_norm)
    # world = R^T cam: row k of the result is sum_j R[j, k] * cam_j
    R = camera.R.astype(np.float32)
    dirs = np.stack([R[0, k] * cam[0] + R[1, k] * cam[1] + R[2, k] * cam[2] for k in range(3)])
    return dirs.astype(np.float32), camera.center.astype(np.float32)


def _screen_box(camera: Camera, corners: np.ndarray) -> tuple[int, int, int, int] | None:
    """Pixel range (u0, u1, v0, v1), end-exclusive, that can see the inside of a box; None if none can.

    A box in front of the camera projects inside the 2D bounding box of its projected
    corners; a box straddling the camera plane gets the whole image (conservative).
    """
    pc = corners @ camera.R.T + camera.t
    z = pc[:, 2]
    if np.all(z <= T_MIN):
        return None
    if np.any(z <= 1e-3):
        return 0, camera.width, 0, camera.height
    u = camera.fx * pc[:, 0] / z + camera.cx
    v = camera.fy * pc[:, 1] / z + camera.cy
    # Pixel u sees continuous coordinates [u, u + 1); one pixel of margin for rounding.
    u0 = max(int(np.floor(u.min())) - 1, 0)
    u1 = min(int(np.floor(u.max())) + 2, camera.width)
    v0 = max(int(np.floor(v.min())) - 1, 0)
    v1 = min(int(np.floor(v.max())) + 2, camera.height)
    if u0 >= u1 or v0 >= v1:
        return None
    return u0, u1, v0, v1


def trace(primitives: Sequence[Primitive], camera: Camera, dirs: np.ndarray, origin: np.ndarray,
          cull: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Nearest hit of every ray.

    Parameters
    ----------
    primitives : sequence of primitives
    camera : Camera
        Used to restrict each bounded primitive to the pixels that can see it.
    dirs : ndarray, shape (3, S, H, W), float32
        Unit ray directions (:func:`camera_rays`).
    origin : ndarray, shape (3,), float32
    cull : bool
        Screen-space culling (default True); False tests every ray against every
        primitive (the slow reference, same result).

    Returns
    -------
    t : ndarray, shape (S, H, W), float32
        Distance to the nearest hit (inf where nothing is hit).
    index : ndarray, shape (S, H, W), int32
        Index of the primitive hit, -1 where nothing is hit.
    """
    _, S, H, W = dirs.shape
    t_best = np.full((S, H, W), np.inf, np.float32)
    idx = np.full((S, H, W), -1, np.int32)
    for k, prim in enumerate(primitives):
        corners = prim.corners()
        box = (0, W, 0, H) if (corners is None or not cull) else _screen_box(camera, corners)
        if box is None:
            continue
        u0, u1, v0, v1 = box
        sub = dirs[:, :, v0:v1, u0:u1]
        t = prim.intersect(origin, sub.reshape(3, -1)).reshape(sub.shape[1:])
        tb = t_best[:, v0:v1, u0:u1]  # a view: updated in place
        closer = t < tb
        np.copyto(tb, t, where=closer)
        np.copyto(idx[:, v0:v1, u0:u1], k, where=closer)
    return t_best, idx


@dataclass(frozen=True)
class RenderedView:
    """One rendered view.

    Attributes
    ----------
    image : ndarray, shape (H, W, 3), float32 in [0, 1]
    depth : ndarray, shape (H, W), float32
        z-depth of the pixel-centre ray's hit (finite everywhere: the backdrop is a surface).
    sky : ndarray, shape (H, W), bool
        True where the pixel-centre ray hits a backdrop material (sky, distant hills).
    """

    image: np.ndarray
    depth: np.ndarray
    sky: np.ndarray


def shade(world: World, origin: np.ndarray, dirs: np.ndarray, t: np.ndarray, index: np.ndarray) -> np.ndarray:
    """Colour of rays with known hits.

    Parameters
    ----------
    world : World
    origin : ndarray, shape (3,)
    dirs : ndarray, shape (3, N), float32
    t : ndarray, shape (N,), float32
    index : ndarray, shape (N,), int
        Primitive hit by each ray (all >= 0).

    Returns
    -------
    ndarray, shape (N, 3), float32 in [0, 1]
    """
    color = np.zeros((len(t), 3), np.float32)
    order = np.argsort(index, kind="stable")
    bounds = np.searchsorted(index[order], np.arange(len(world.primitives) + 1))
    for k, prim in enumerate(world.primitives):
        rows = order[bounds[k]:bounds[k + 1]]
        if len(rows) == 0:
            continue
        d = dirs[:, rows]
        p, n = surface_normal(prim, origin, d, t[rows])
        mat = world.materials[prim.material]
        albedo = np.clip(mat.albedo(p.T, n.T), 0.0, 1.0).astype(np.float32)
        color[rows] = albedo if mat.emissive else world.lighting.shade(albedo, n.T)
    return np.clip(color, 0.0, 1.0)


@dataclass(frozen=True)
class RenderSettings:
    """Sampling of one view.

    Attributes
    ----------
    samples_per_axis : int
        Anti-aliasing grid: ``n * n`` colour samples per pixel (default 2).
    adaptive_threshold : float or None
        Adaptive supersampling (default 0.05): every sample is traced, but only pixels whose
        samples hit different primitives (geometric edges) or whose centre colour differs from a
        4-neighbour's by more than this (max over channels, in [0, 1]) are shaded at every sample;
        the others take their centre sample's colour.  None shades every sample (the reference).
    cull : bool
        Screen-space culling of bounded primitives (default True; False is the slow reference).
    """

    samples_per_axis: int = 2
    adaptive_threshold: float | None = 0.05
    cull: bool = True


def _contrast(img: np.ndarray) -> np.ndarray:
    """Max absolute colour difference (over channels) of each pixel to its 4-neighbours, (H, W)."""
    H, W, _ = img.shape
    pad = np.pad(img, ((1, 1), (1, 1), (0, 0)), mode="edge")
    out = np.zeros((H, W), np.float32)
    for dy, dx in ((0, 1), (2, 1), (1, 0), (1, 2)):
        diff = np.abs(pad[dy:dy + H, dx:dx + W] - img)
        for c in range(3):  # channel by channel: a reduction over a length-3 axis is slow in numpy
            np.maximum(out, diff[..., c], out=out)
    return out


def render_view(world: World, camera: Camera, settings: RenderSettings = RenderSettings()) -> RenderedView:
    """Ray-cast one view of ``world`` (see :class:`RenderSettings` for the sampling)."""
    offsets, n_color, centre = subpixel_offsets(settings.samples_per_axis)
    dirs, origin = camera_rays(camera, offsets)
    t, idx = trace(world.primitives, camera, dirs, origin, settings.cull)
    if np.any(idx < 0):
        raise RuntimeError("some rays hit nothing: a built-in world must be closed by a backdrop")
    _, S, H, W = dirs.shape

    def shade_samples(samples: list[int], pixels: np.ndarray | None) -> np.ndarray:
        """Colours (len(samples), P, 3) of the given samples at the given flat pixels (None: all)."""
        d = dirs[:, samples].reshape(3, len(samples), H * W)
        tt, ii = t[samples].reshape(len(samples), H * W), idx[samples].reshape(len(samples), H * W)
        if pixels is not None:
            d, tt, ii = d[:, :, pixels], tt[:, pixels], ii[:, pixels]
        c = shade(world, origin, d.reshape(3, -1), tt.reshape(-1), ii.reshape(-1))
        return c.reshape(len(samples), -1, 3)

    if settings.adaptive_threshold is None:
        image = shade_samples(list(range(n_color)), None).mean(axis=0).reshape(H, W, 3)
    else:
        image = shade_samples([centre], None)[0].reshape(H, W, 3)
        edge = np.any(idx[:n_color] != idx[centre], axis=0)
        flagged = np.flatnonzero(edge | (_contrast(image) > settings.adaptive_threshold))
        others = [k for k in range(n_color) if k != centre]
        if len(flagged) and others:  # one sample per pixel: the centre is all there is
            total = shade_samples(others, flagged).sum(axis=0)
            if centre < n_color:  # the centre ray is one of the grid samples: reuse its colour
                total += image.reshape(-1, 3)[flagged]
            image.reshape(-1, 3)[flagged] = total / np.float32(n_color)

    f = camera.R[2].astype(np.float32)  # camera forward axis in world coordinates
    dc = dirs[:, centre]
    depth = (t[centre] * (f[0] * dc[0] + f[1] * dc[1] + f[2] * dc[2])).astype(np.float32)
    backdrop_ids = [k for k, p in enumerate(world.primitives) if p.material in world.backdrop_materials]
    mask = np.isin(idx[centre], backdrop_ids)
    return RenderedView(np.clip(image, 0.0, 1.0).astype(np.float32), depth, mask)
