"""The built-in scenes: geometry, materials and camera rigs.

Units are metres, world up is +z.  Each scene is a frozen config dataclass
(documented defaults) with ``world(seed)`` and ``cameras(n_views, width, height,
seed)``; the seed moves objects and cameras by a few centimetres / degrees and
shifts every texture, so different seeds give different but statistically alike
scenes while the same seed gives the same scene bit for bit.

* ``garden`` -- a 360-degree orbit around a patio table in a garden (modelled on
  Mip-NeRF360 garden / bicycle): textured lawn and flagstones, a table with
  objects, bushes, planters, a bench, near and far trees, a shed, a fence, and a
  backdrop sphere painted with hills, fields and a cloudy sky.
* ``street`` -- a forward-facing capture (a jittered grid of cameras looking
  down a long street, like Deblur-NeRF factory / LLFF): asphalt with markings and
  a zebra crossing, raised pavements, building façades with windows receding
  to 100 m, crates, bollards, lamp posts, parked cars, trees, and a skyline
  backdrop.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nimbus.data.builtin.raycast import Backdrop, Box, Cylinder, Ground, Lighting, Material, Sphere, World
from nimbus.data.builtin.textures import bricks, checker, fbm, hash01, mix, smoothstep, spots, value_noise
from nimbus.data.camera import Camera

UP = (0.0, 0.0, 1.0)


# --- material helpers ---------------------------------------------------------------------------
def texture_seed(seed: int, salt: int) -> int:
    """An independent texture seed per (scene seed, material)."""
    return (seed * 7919 + salt * 104729) & 0x7FFFFFFF


def texture_offset(seed: int, salt: int, dim: int) -> np.ndarray:
    """A seed-dependent texture-space shift (metres), so seeds differ everywhere, not only in the hash."""
    cells = np.array([[seed, salt, k] for k in range(dim)])
    return (hash01(cells, 99) * 100.0).astype(np.float32)


def face_uv(p: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Planar (u, v) coordinates on a face: vertical faces use (horizontal tangent, z), others (x, y)."""
    vertical = np.abs(n[:, 2]) < 0.5
    u = np.where(vertical, -n[:, 1] * p[:, 0] + n[:, 0] * p[:, 1], p[:, 0])
    v = np.where(vertical, p[:, 2], p[:, 1])
    return u.astype(np.float32), v.astype(np.float32)


def coords_xy(p: np.ndarray, off: np.ndarray, scale: float) -> np.ndarray:
    return (p[:, :2] + off[:2]) * np.float32(scale)


def coords_xyz(p: np.ndarray, off: np.ndarray, scale: float) -> np.ndarray:
    return (p + off[:3]) * np.float32(scale)


# Flower / leaf colours scattered on the lawn: white, yellow, violet, red, brown.
_FLOWERS = np.array([(0.95, 0.95, 0.9), (0.95, 0.82, 0.15), (0.55, 0.3, 0.8), (0.85, 0.2, 0.2),
                     (0.4, 0.24, 0.1)], np.float32)


# Flagstone colours: sandstone, slate, grey granite, red sandstone, pale limestone.
_STONES = np.array([(0.72, 0.62, 0.45), (0.38, 0.42, 0.46), (0.58, 0.57, 0.55), (0.62, 0.4, 0.32),
                    (0.82, 0.8, 0.72)], np.float32)


def pick(palette: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Colour per point from a palette (K, 3) by a uniform value ``u`` in [0, 1)."""
    return palette[np.minimum((u * len(palette)).astype(np.int64), len(palette) - 1)]


def split_by(cond: np.ndarray, fn_true, fn_false, p: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Evaluate one of two colour functions per point (each only on its own points: textures are costly)."""
    out = np.empty((len(p), 3), np.float32)
    for sel, fn in ((cond, fn_true), (~cond, fn_false)):
        if np.any(sel):
            out[sel] = fn(p[sel], n[sel])
    return out


def grass_material(seed: int, patio_radius: float) -> Material:
    """Lawn with large colour patches, bare-earth spots and fine blades; flagstones inside ``patio_radius``."""
    s = texture_seed(seed, 1)
    off = texture_offset(seed, 1, 3)

    def lawn(p, n):
        patches = fbm(coords_xy(p, off, 0.3), 3, s)
        detail = fbm(coords_xy(p, off, 3.0), 3, s + 1)
        blades = value_noise(coords_xy(p, off, 16.0), s + 2)
        col = mix((0.16, 0.33, 0.09), (0.42, 0.55, 0.17), patches)
        col = col * (0.55 + 0.6 * detail * (0.6 + 0.4 * blades))[:, None]
        earth = smoothstep(0.58, 0.66, fbm(coords_xy(p, off, 0.8), 2, s + 3))
        col = mix(col, (0.42, 0.31, 0.2), 0.85 * earth * (0.6 + 0.4 * detail))
        # Flowers and fallen leaves: two sizes of scattered high-contrast blobs (what SIFT detects).
        for scale, salt in ((2.0, 6), (5.0, 8)):
            cover, cell = spots(coords_xy(p, off, scale), s + salt, density=0.55)
            col = mix(col, pick(_FLOWERS, hash01(cell, s + salt + 7)), cover)
        return col

    def patio(p, n):
        # Flagstones of varied stone colours with grain and lichen spots, dark joints: distinctive corners.
        stone, sid = bricks(p[:, 0] + off[0], p[:, 1] + off[1], 0.45, 0.3, 0.035)
        base = pick(_STONES, hash01(sid, s + 4))
        grain = fbm(coords_xy(p, off, 8.0), 3, s + 5)
        stone_col = base * (0.6 + 0.7 * grain)[:, None]
        cover, cell = spots(coords_xy(p, off, 7.0), s + 6, density=0.4, radius=(0.1, 0.25))
        stone_col = mix(stone_col, mix((0.2, 0.22, 0.12), (0.85, 0.8, 0.45), hash01(cell, s + 7)), 0.8 * cover)
        return mix((0.12, 0.11, 0.1), stone_col, stone)

    def albedo(p, n):
        return split_by(p[:, 0] ** 2 + p[:, 1] ** 2 < patio_radius ** 2, patio, lawn, p, n)

    return Material(albedo)


def wood_material(seed: int, salt: int, base=(0.55, 0.36, 0.2), dark=(0.3, 0.18, 0.09), rings: float = 9.0) -> Material:
    """Wood: stripes along x and y warped by noise (grain), view-independent."""
    s = texture_seed(seed, salt)
    off = texture_offset(seed, salt, 3)

    def albedo(p, n):
        warp = fbm(coords_xyz(p, off, 1.5), 2, s)
        g = 0.5 + 0.5 * np.sin(rings * (p[:, 0] + 0.7 * p[:, 1] + 0.4 * p[:, 2] + off[0]) + 6.0 * warp)
        fine = value_noise(coords_xyz(p, off, 25.0), s + 1)
        return mix(dark, base, np.clip(0.7 * g + 0.3 * fine, 0, 1))

    return Material(albedo)


def brick_material(seed: int, salt: int, brick=(0.62, 0.27, 0.18), mortar=(0.78, 0.76, 0.7)) -> Material:
    """Red bricks with per-brick tint on vertical faces, stone caps on top faces."""
    s = texture_seed(seed, salt)
    off = texture_offset(seed, salt, 3)

    def albedo(p, n):
        u, v = face_uv(p, n)
        is_b, bid = bricks(u + off[0], v + off[1], 0.22, 0.075, 0.012)
        tint = hash01(bid, s)
        grain = value_noise(coords_xyz(p, off, 30.0), s + 1)
        bcol = np.asarray(brick, np.float32) * (0.7 + 0.45 * tint)[:, None] * (0.85 + 0.2 * grain)[:, None]
        return mix(mortar, bcol, is_b)

    return Material(albedo)


def foliage_material(seed: int, salt: int, light=(0.35, 0.55, 0.15), dark=(0.06, 0.2, 0.05),
                     flower=None) -> Material:
    """Leafy solid texture (3D fBm), optionally with sparse flower dots."""
    s = texture_seed(seed, salt)
    off = texture_offset(seed, salt, 3)

    def albedo(p, n):
        leaves = fbm(coords_xyz(p, off, 6.0), 3, s)
        col = mix(dark, light, smoothstep(0.3, 0.7, leaves))
        # Fine leaf clusters: a higher-frequency, high-contrast layer.
        fine = value_noise(coords_xyz(p, off, 22.0), s + 2)
        col = col * (0.55 + 0.8 * fine)[:, None]
        if flower is not None:
            dots = smoothstep(0.7, 0.76, value_noise(coords_xyz(p, off, 14.0), s + 1))
            col = mix(col, flower, dots)
        return col

    return Material(albedo)


def bark_material(seed: int, salt: int) -> Material:
    s = texture_seed(seed, salt)
    off = texture_offset(seed, salt, 3)

    def albedo(p, n):
        ang = np.arctan2(n[:, 1], n[:, 0])
        ridges = value_noise(np.stack([ang * 4.0, (p[:, 2] + off[2]) * 3.0], axis=1), s)
        fine = value_noise(coords_xyz(p, off, 20.0), s + 1)
        return mix((0.17, 0.12, 0.08), (0.45, 0.36, 0.27), 0.7 * ridges + 0.3 * fine)

    return Material(albedo)


def checker_material(seed: int, salt: int, a, b, scale: float) -> Material:
    """3D checker (a beach ball / tablecloth look) with slight noise."""
    s = texture_seed(seed, salt)
    off = texture_offset(seed, salt, 3)

    def albedo(p, n):
        c = checker(coords_xyz(p, off, scale))
        noise = value_noise(coords_xyz(p, off, scale * 4.0), s)
        return mix(a, b, c) * (0.88 + 0.2 * noise)[:, None]

    return Material(albedo)


def painted_material(seed: int, salt: int, color, stripes=None, stripe_freq: float = 6.0) -> Material:
    """Painted surface: a base colour, grime noise and optional horizontal stripes of a second colour."""
    s = texture_seed(seed, salt)
    off = texture_offset(seed, salt, 3)

    def albedo(p, n):
        grime = fbm(coords_xyz(p, off, 4.0), 3, s)
        col = np.broadcast_to(np.asarray(color, np.float32), p.shape) * (0.7 + 0.45 * grime)[:, None]
        if stripes is not None:
            band = (np.floor((p[:, 2] + off[2]) * stripe_freq).astype(np.int64) & 1).astype(np.float32)
            col = mix(col, stripes, band * 0.9)
        return col

    return Material(albedo)


def sky_backdrop_material(seed: int, salt: int, center, radius: float, horizon: str = "hills") -> Material:
    """Emissive backdrop: sky gradient with fBm clouds above a painted horizon.

    ``horizon`` is ``"hills"`` (rolling green/blue hills over patchwork fields) or
    ``"skyline"`` (a distant city skyline of blocks over grey ground).
    """
    s = texture_seed(seed, salt)
    off = texture_offset(seed, salt, 3)
    c = np.asarray(center, np.float32)

    def sky(p, n):
        # Gradient plus clouds projected on a cloud layer (coordinates ~ direction / elevation).
        w = (p - c) / np.float32(radius)
        e = w[:, 2]
        col = mix((0.8, 0.86, 0.93), (0.32, 0.52, 0.84), np.sqrt(np.clip(e, 0, 1)))
        cloud_uv = w[:, :2] / np.maximum(e, 0.03)[:, None] * np.float32(1.2) + off[:2]
        clouds = smoothstep(0.5, 0.75, fbm(cloud_uv, 4, s))
        return mix(col, (0.97, 0.97, 0.98), 0.9 * clouds)

    def hills(p, n):
        e = (p[:, 2] - c[2]) / np.float32(radius)
        tex = fbm(coords_xyz(p, off, 0.25), 4, s + 2)
        col = mix((0.12, 0.25, 0.14), (0.5, 0.6, 0.42), tex)
        woods = spots(coords_xyz(p, off, 0.6)[:, [0, 2]] + coords_xyz(p, off, 0.6)[:, [1]], s + 4, density=0.5)[0]
        col = mix(col, (0.08, 0.16, 0.08), 0.8 * woods)  # copses of trees: distant blobs
        col = mix(col, (0.55, 0.62, 0.7), smoothstep(0.0, 0.15, e))  # aerial perspective
        _, fid = bricks(p[:, 0] * 0.08 + off[0], p[:, 1] * 0.08 + off[1], 1.0, 0.7, 0.04)
        fields = mix((0.3, 0.42, 0.17), (0.62, 0.58, 0.3), hash01(fid, s + 3)) * (0.75 + 0.35 * tex)[:, None]
        return mix(col, fields, (e < 0).astype(np.float32))

    def skyline(p, n):
        w = (p - c) / np.float32(radius)
        e = w[:, 2]
        az = np.arctan2(w[:, 1], w[:, 0])
        block = np.floor((az + np.pi) * 40.0).astype(np.int64)[:, None]
        tone = hash01(block, s + 2)
        win = checker(np.stack([(az + np.pi) * 400.0, e * 250.0], axis=1)) * (hash01(block, s + 3) > 0.4)
        col = mix((0.36, 0.38, 0.44), (0.6, 0.6, 0.62), tone) * (0.85 + 0.2 * win)[:, None]
        col = mix(col, (0.62, 0.66, 0.74), 0.35)  # distant: washed out
        ground = mix((0.35, 0.34, 0.32), (0.5, 0.48, 0.45), fbm(coords_xy(p, off, 0.2), 3, s + 4))
        return mix(col, ground, (e < 0).astype(np.float32))

    def albedo(p, n):
        w = (p - c) / np.float32(radius)
        e = w[:, 2]
        hor = np.hypot(w[:, 0], w[:, 1]) + 1e-6
        if horizon == "hills":
            # Silhouette height (sine of elevation) as noise on the azimuth circle: periodic by construction.
            circle = np.stack([w[:, 0] / hor, w[:, 1] / hor], axis=1)
            low = e < 0.15  # the highest possible hill top
            top = np.full(len(p), -1.0, np.float32)
            top[low] = 0.03 + 0.12 * fbm(circle[low] * np.float32(2.5) + off[:2], 4, s + 1)
            return split_by(e < top, hills, sky, p, n)
        block = np.floor((np.arctan2(w[:, 1], w[:, 0]) + np.pi) * 40.0).astype(np.int64)[:, None]
        top = 0.02 + 0.1 * hash01(block, s + 1) ** 2
        return split_by(e < top, skyline, sky, p, n)

    return Material(albedo, emissive=True)


def look_at(eye, target, width: int, height: int, fov_x_deg: float) -> Camera:
    return Camera.look_at(eye, target, UP, width, height, fov_x_deg)


# --- garden ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class GardenConfig:
    """A 360-degree orbit around a garden table (Mip-NeRF360 garden / bicycle style).

    Attributes
    ----------
    orbit_radius : float
        Mean horizontal camera distance from the table, metres (default 4.0).
    orbit_height : float
        Mean camera height, metres (default 1.8: looking down on the patio, so near objects
        hide less of it).
    height_wobble : float
        Amplitude of the camera height's variation around the orbit, metres (default 0.3).
    target : tuple of float
        Point every camera looks at (default the table top, (0, 0, 0.6)).
    fov_x_deg : float
        Horizontal field of view, degrees (default 62).
    pose_jitter : float
        Std of the seed-dependent camera position / target jitter, metres (default 0.05).
    object_jitter : float
        Std of the seed-dependent object position jitter, metres (default 0.08).
    ground_radius : float
        Radius of the textured ground disc, metres (default 30).
    patio_radius : float
        Radius of the flagstone patio around the table, metres (default 1.6).
    backdrop_radius : float
        Radius of the sky / hills backdrop sphere, metres (default 90).
    """

    orbit_radius: float = 4.0
    orbit_height: float = 1.8
    height_wobble: float = 0.3
    target: tuple[float, float, float] = (0.0, 0.0, 0.6)
    fov_x_deg: float = 62.0
    pose_jitter: float = 0.05
    object_jitter: float = 0.08
    ground_radius: float = 30.0
    patio_radius: float = 1.6
    backdrop_radius: float = 90.0

    def world(self, seed: int) -> World:
        rng = np.random.default_rng([seed, 1])

        def j(x, y):
            dx, dy = rng.normal(0.0, self.object_jitter, 2)
            return float(x + dx), float(y + dy)

        mats = {
            "grass": grass_material(seed, self.patio_radius),
            "table": wood_material(seed, 2, rings=14.0),
            "bench": wood_material(seed, 3, base=(0.62, 0.45, 0.28), rings=7.0),
            "vase": painted_material(seed, 4, (0.72, 0.36, 0.2), stripes=(0.9, 0.85, 0.7), stripe_freq=18.0),
            "ball": checker_material(seed, 5, (0.9, 0.85, 0.2), (0.15, 0.3, 0.75), 9.0),
            "cloth": checker_material(seed, 6, (0.85, 0.15, 0.12), (0.92, 0.9, 0.85), 8.0),
            "brick": brick_material(seed, 7),
            "bush": foliage_material(seed, 8, flower=(0.9, 0.3, 0.5)),
            "leaves": foliage_material(seed, 9),
            "leaves_far": foliage_material(seed, 10, light=(0.3, 0.45, 0.2), dark=(0.08, 0.18, 0.08)),
            "bark": bark_material(seed, 11),
            "shed": painted_material(seed, 12, (0.45, 0.55, 0.6), stripes=(0.3, 0.38, 0.42), stripe_freq=5.0),
            "roof": painted_material(seed, 13, (0.45, 0.2, 0.16)),
            "post": wood_material(seed, 14, base=(0.7, 0.66, 0.58), dark=(0.45, 0.4, 0.33)),
            "sky": sky_backdrop_material(seed, 15, (0.0, 0.0, 0.0), self.backdrop_radius, "hills"),
        }
        prims: list = [Ground(0.0, self.ground_radius, "grass"),
                       Backdrop((0.0, 0.0, 0.0), self.backdrop_radius, "sky")]
        # Table with objects (the orbit's centre of attention).
        prims += [Cylinder((0.0, 0.0), 0.0, 0.04, 0.3, "table"), Cylinder((0.0, 0.0), 0.0, 0.68, 0.06, "table"),
                  Cylinder((0.0, 0.0), 0.68, 0.74, 0.6, "table"),
                  Sphere((0.18, 0.1, 0.9), 0.16, "vase"), Sphere((-0.25, -0.12, 0.86), 0.12, "ball"),
                  Box((-0.08, 0.28, 0.79), (0.14, 0.1, 0.05), "cloth", yaw=0.4)]
        # Near ring (inside the orbit): planters, bushes, a ball, a bench, a small tree.
        for (x, y), yaw in (((1.9, 0.8), 0.3), ((-1.2, 1.75), -0.5)):
            x, y = j(x, y)
            prims += [Box((x, y, 0.2), (0.5, 0.25, 0.2), "brick", yaw=yaw), Sphere((x, y, 0.45), 0.27, "bush")]
        for x, y, r in ((-2.0, -0.8, 0.4), (0.9, -2.0, 0.35), (0.3, 2.2, 0.3)):
            x, y = j(x, y)
            prims.append(Sphere((x, y, 0.8 * r), r, "bush"))
        x, y = j(0.9, 1.7)
        prims.append(Sphere((x, y, 0.22), 0.22, "ball"))
        bx, by = j(-0.7, -2.0)
        prims += [Box((bx, by, 0.45), (0.75, 0.22, 0.03), "bench", yaw=0.15),
                  Box((bx - 0.6, by - 0.09, 0.21), (0.04, 0.2, 0.21), "bench", yaw=0.15),
                  Box((bx + 0.6, by + 0.09, 0.21), (0.04, 0.2, 0.21), "bench", yaw=0.15)]
        prims += self._tree(*j(1.8, -1.3), 2.0, 0.1, 0.5, rng, "leaves")
        # Middle distance: trees, a shed, a fence arc.
        for (x, y), h in (((7.0, 3.0), 4.0), ((-6.5, -5.0), 5.0), ((3.0, -8.0), 4.5), ((-4.0, 8.5), 3.5)):
            prims += self._tree(*j(x, y), h, 0.2, 1.3, rng, "leaves")
        sx, sy = j(-8.0, 3.0)
        prims += [Box((sx, sy, 1.2), (1.5, 1.1, 1.2), "shed", yaw=0.3),
                  Box((sx, sy, 2.5), (1.7, 1.3, 0.12), "roof", yaw=0.3)]
        for k in range(14):
            a = np.radians(-50 + 10 * k)
            prims.append(Cylinder((float(11 * np.cos(a)), float(11 * np.sin(a))), 0.0, 1.1, 0.07, "post"))
            if k < 13:
                am = np.radians(-45 + 10 * k)
                prims.append(Box((float(11 * np.cos(am)), float(11 * np.sin(am)), 0.8), (0.05, 0.95, 0.06), "post",
                                 yaw=float(am)))
        # Far: big trees near the edge of the lawn.
        for k in range(8):
            a = 2 * np.pi * (k + 0.3 * rng.random()) / 8
            r = 18.0 + 8.0 * rng.random()
            prims += self._tree(float(r * np.cos(a)), float(r * np.sin(a)), 7.0 + 4.0 * rng.random(), 0.4, 3.0, rng,
                                "leaves_far")
        return World(tuple(prims), mats, Lighting(), frozenset({"sky"}))

    @staticmethod
    def _tree(x, y, height, trunk_r, crown_r, rng, leaves) -> list:
        """A trunk cylinder and a crown of overlapping spheres."""
        prims = [Cylinder((x, y), 0.0, height, trunk_r, "bark")]
        for k in range(4):
            a = 2 * np.pi * k / 4 + rng.random()
            off = 0.45 * crown_r
            z = height + crown_r * (0.1 + 0.3 * rng.random())
            prims.append(Sphere((x + off * np.cos(a), y + off * np.sin(a), z), crown_r * (0.65 + 0.15 * rng.random()),
                                leaves))
        prims.append(Sphere((x, y, height + 0.5 * crown_r), 0.8 * crown_r, leaves))
        return prims

    def cameras(self, n_views: int, width: int, height: int, seed: int) -> list[Camera]:
        rng = np.random.default_rng([seed, 2])
        phase = rng.uniform(0, 2 * np.pi)
        cams = []
        for i in range(n_views):
            a = phase + 2 * np.pi * i / n_views
            r = self.orbit_radius * (1.0 + 0.04 * np.sin(3 * a)) + rng.normal(0, self.pose_jitter)
            z = self.orbit_height + self.height_wobble * np.sin(2 * a + phase) + rng.normal(0, self.pose_jitter)
            eye = np.array([r * np.cos(a), r * np.sin(a), z])
            target = np.asarray(self.target) + rng.normal(0, self.pose_jitter, 3)
            cams.append(look_at(eye, target, width, height, self.fov_x_deg))
        return cams


# --- street ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class StreetConfig:
    """A forward-facing capture down a long street (Deblur-NeRF factory / LLFF style).

    Attributes
    ----------
    grid_width, grid_height : float
        Extent of the camera grid across (x) and up (z), metres (defaults 2.0, 0.8): wide
        enough for SfM to triangulate the street from the small-size images.
    eye_height : float
        Height of the grid's centre, metres (default 1.6).
    look_distance : float
        Distance down the street of the point the cameras look at, metres (default 40).
    fov_x_deg : float
        Horizontal field of view, degrees (default 60).
    pose_jitter : float
        Std of the seed-dependent camera position jitter, metres (default 0.04); the look-at
        target is jittered by 10 times as much, i.e. about 0.6 degrees.
    object_jitter : float
        Std of the seed-dependent object position jitter, metres (default 0.1).
    road_half_width : float
        Half width of the carriageway, metres (default 3.5).
    pavement_width : float
        Width of each raised pavement, metres (default 2.5).
    street_length : float
        How far the façades recede, metres (default 100).
    backdrop_radius : float
        Radius of the sky / skyline backdrop sphere, metres (default 160).
    """

    grid_width: float = 2.0
    grid_height: float = 0.8
    eye_height: float = 1.6
    look_distance: float = 40.0
    fov_x_deg: float = 60.0
    pose_jitter: float = 0.04
    object_jitter: float = 0.1
    road_half_width: float = 3.5
    pavement_width: float = 2.5
    street_length: float = 100.0
    backdrop_radius: float = 160.0

    def world(self, seed: int) -> World:
        rng = np.random.default_rng([seed, 3])
        rw, pw, L = self.road_half_width, self.pavement_width, self.street_length

        def j(v):
            return float(v + rng.normal(0.0, self.object_jitter))

        s = texture_seed(seed, 20)
        off = texture_offset(seed, 20, 3)

        def road(p, n):
            x, y = p[:, 0], p[:, 1]
            grain = fbm(coords_xy(p, off, 2.0), 3, s)
            speck = value_noise(coords_xy(p, off, 18.0), s + 1)
            col = mix((0.16, 0.16, 0.17), (0.38, 0.37, 0.36), 0.6 * grain + 0.4 * speck)
            patches = smoothstep(0.6, 0.65, fbm(coords_xy(p, off, 0.4), 2, s + 2))
            col = mix(col, (0.1, 0.1, 0.11), 0.7 * patches)
            # Light gravel and dark stains: scattered blobs of two sizes.
            cover, cell = spots(coords_xy(p, off, 1.5), s + 5, density=0.5)
            col = mix(col, mix((0.05, 0.05, 0.06), (0.62, 0.6, 0.56), hash01(cell, s + 6) > 0.5), cover)
            cover, cell = spots(coords_xy(p, off, 5.0), s + 7, density=0.5)
            col = mix(col, mix((0.08, 0.08, 0.08), (0.7, 0.68, 0.62), hash01(cell, s + 8) > 0.4), cover)
            dashes = (np.abs(x) < 0.08) & (np.mod(y + off[1], 4.0) < 2.0)
            zebra = (y > 9.0) & (y < 12.0) & (np.mod(x + 10.0, 1.0) < 0.5) & (np.abs(x) < rw - 0.3)
            edge = (np.abs(np.abs(x) - (rw - 0.25)) < 0.06)
            paint = (dashes | zebra | edge).astype(np.float32) * (0.75 + 0.25 * grain)
            return mix(col, (0.9, 0.9, 0.86), paint)

        def pavement(p, n):
            u, v = face_uv(p, n)
            tile, tid = bricks(v + off[1], u + off[0], 0.5, 0.5, 0.02)
            tint = hash01(tid, s + 3)
            grain = value_noise(coords_xyz(p, off, 12.0), s + 4)
            col = mix((0.52, 0.5, 0.47), (0.74, 0.7, 0.64), tint) * (0.8 + 0.3 * grain)[:, None]
            return mix((0.3, 0.29, 0.28), col, tile)

        def facade_factory(salt: int):
            base_tone = rng.random()
            s2 = texture_seed(seed, salt)
            off2 = texture_offset(seed, salt, 3)

            def facade(p, n):
                u, v = face_uv(p, n)
                wall_a = mix((0.72, 0.66, 0.55), (0.62, 0.36, 0.26), np.full(len(p), base_tone, np.float32))
                is_b, bid = bricks(u + off2[0], v, 0.3, 0.1, 0.015)
                tint = hash01(bid, s2)
                wall = wall_a * (0.8 + 0.3 * tint * is_b + 0.1 * is_b)[:, None]
                # Windows: 1.2 x 1.5 m on a 2.6 x 3.2 m grid, above the ground floor's 0.9 m sill.
                fu = np.mod(u + off2[0], 2.6)
                fv = np.mod(v - 0.9, 3.2)
                window = (fu > 0.7) & (fu < 1.9) & (fv < 1.5) & (v > 0.9)
                frame = window & ((fu < 0.78) | (fu > 1.82) | (fv < 0.08) | (fv > 1.42) | (np.abs(fu - 1.3) < 0.04))
                col = wall
                # Glass reflects a blurry sky: noise, evaluated on window pixels only.
                col[window] = mix((0.12, 0.16, 0.24), (0.5, 0.6, 0.72),
                                  fbm(coords_xyz(p[window], off2, 0.7), 3, s2 + 1))
                return mix(col, (0.88, 0.87, 0.83), frame.astype(np.float32))

            return Material(facade)

        mats = {
            "road": Material(road),
            "pavement": Material(pavement),
            "crate": wood_material(seed, 21, base=(0.7, 0.52, 0.3), rings=20.0),
            "bollard": painted_material(seed, 22, (0.15, 0.15, 0.16), stripes=(0.9, 0.75, 0.1), stripe_freq=5.0),
            "pole": painted_material(seed, 23, (0.2, 0.3, 0.25)),
            "lamp": painted_material(seed, 24, (0.95, 0.92, 0.8)),
            "car_red": painted_material(seed, 25, (0.7, 0.12, 0.1)),
            "car_blue": painted_material(seed, 26, (0.15, 0.3, 0.65)),
            "car_white": painted_material(seed, 27, (0.85, 0.85, 0.82)),
            "glass": painted_material(seed, 28, (0.15, 0.2, 0.28)),
            "leaves": foliage_material(seed, 29),
            "bark": bark_material(seed, 30),
            "ball": checker_material(seed, 31, (0.95, 0.95, 0.9), (0.1, 0.1, 0.1), 7.0),
            "sky": sky_backdrop_material(seed, 32, (0.0, 0.0, 0.0), self.backdrop_radius, "skyline"),
        }
        prims: list = [Ground(0.0, self.backdrop_radius * 0.9, "road"),
                       Backdrop((0.0, 0.0, 0.0), self.backdrop_radius, "sky")]
        for side in (-1, 1):
            cx = side * (rw + 0.5 * pw)
            prims.append(Box((cx, 0.5 * L - 5.0, 0.075), (0.5 * pw, 0.5 * L + 5.0, 0.075), "pavement"))
            # Buildings: segments of random length, height and setback along the pavement's back edge.
            y, k = -6.0, 0
            while y < L:
                length = float(rng.uniform(7.0, 14.0))
                h = float(rng.uniform(6.0, 18.0))
                setback = float(rng.uniform(0.0, 1.2))
                depth = 10.0
                x_front = side * (rw + pw + setback)
                name = f"facade_{'l' if side < 0 else 'r'}{k}"
                mats[name] = facade_factory(40 + 2 * k + (side > 0))
                prims.append(Box((x_front + side * 0.5 * depth, y + 0.5 * length, 0.5 * h),
                                 (0.5 * depth, 0.5 * length - 0.05, 0.5 * h), name))
                y += length
                k += 1
            for yb in np.arange(3.0, 40.0, 4.0):
                prims.append(Cylinder((side * (rw - 0.2), j(yb)), 0.0, 0.9, 0.09, "bollard"))
            for yl in np.arange(6.0, L, 16.0):
                xl = side * (rw + 0.4)
                yl = j(yl)
                prims += [Cylinder((xl, yl), 0.0, 5.0, 0.08, "pole"), Sphere((xl, yl, 5.15), 0.25, "lamp")]
            for yt in (14.0, 34.0, 58.0):
                xt, yt = side * (rw + 1.6), j(yt + 4.0 * side)
                prims += [Cylinder((xt, yt), 0.0, 3.0, 0.15, "bark"), Sphere((xt, yt, 3.6), 1.2, "leaves"),
                          Sphere((xt + 0.5, yt - 0.4, 3.2), 0.8, "leaves")]
        # Parked cars (body + cabin + wheels).
        for (side, yc), mat in zip(((-1, 13.0), (1, 22.0), (-1, 32.0), (1, 45.0), (-1, 62.0)),
                                   ("car_red", "car_white", "car_blue", "car_red", "car_white")):
            xc, yc = side * (rw - 1.2), j(yc)
            prims += [Box((xc, yc, 0.7), (0.85, 2.1, 0.4), mat), Box((xc, yc - 0.2, 1.35), (0.75, 1.1, 0.3), "glass")]
            for dy in (-1.4, 1.4):
                for dx in (-0.85, 0.85):
                    prims.append(Cylinder((xc + dx, yc + dy), 0.0, 0.6, 0.05, "bollard"))
        # Near objects: stacked crates and a ball in the foreground.
        cx, cy = j(-1.6), j(3.0)
        prims += [Box((cx, cy, 0.3), (0.3, 0.3, 0.3), "crate", yaw=0.2),
                  Box((cx + 0.1, cy + 0.05, 0.85), (0.25, 0.25, 0.25), "crate", yaw=-0.3),
                  Box((j(2.2), j(5.0), 0.35), (0.35, 0.35, 0.35), "crate", yaw=0.6),
                  Sphere((j(0.8), j(6.5), 0.3), 0.3, "ball"),
                  Box((j(-0.9), j(2.2), 0.2), (0.2, 0.2, 0.2), "crate", yaw=0.9)]
        # The street ends at a tall block across it: the far wall of the scene.
        prims.append(Box((0.0, L + 6.0, 11.0), (rw + pw + 8.0, 5.0, 11.0), "facade_end"))
        mats["facade_end"] = facade_factory(90)
        return World(tuple(prims), mats, Lighting(), frozenset({"sky"}))

    def grid_shape(self, n_views: int) -> tuple[int, int]:
        """(rows, cols) of the camera grid: the most square-ish factorisation with cols >= rows."""
        rows = int(np.floor(np.sqrt(n_views)))
        while n_views % rows:
            rows -= 1
        return rows, n_views // rows

    def cameras(self, n_views: int, width: int, height: int, seed: int) -> list[Camera]:
        rng = np.random.default_rng([seed, 4])
        rows, cols = self.grid_shape(n_views)
        cams = []
        for r in range(rows):
            for c in range(cols):
                x = (c / max(cols - 1, 1) - 0.5) * self.grid_width
                z = self.eye_height + (0.5 - r / max(rows - 1, 1)) * self.grid_height
                eye = np.array([x, 0.0, z]) + rng.normal(0, self.pose_jitter, 3)
                target = np.array([0.0, self.look_distance, self.eye_height]) + rng.normal(0, 10 * self.pose_jitter, 3)
                cams.append(look_at(eye, target, width, height, self.fov_x_deg))
        return cams
