"""The ``tabletop`` built-in scene: a bonsai on a table in a furnished room.

Modelled on Mip-NeRF360's indoor captures (bonsai, counter, kitchen): the cameras
orbit a detailed central object at 1.1 to 2.3 object sizes, and the room around it
(plank floor, papered and panelled walls, a bookcase, a sofa, a sideboard,
paintings, a rug, a floor lamp) fills the background.  The only backdrop is what
the window shows (sky over hills), so the sky mask is small and appears only in
views that see the window.

The central object is fine on purpose: a tree of capsule branches with pads of
small leaf spheres, surface roots and moss on the soil, in a glazed pot on feet.
At the ``small`` size a leaf sphere is a few pixels wide, so a reconstruction that
loses the tree's detail scores visibly worse on the test views.

Units are metres, world up is +z, the room's floor is z = 0 and its centre the
origin.  Materials shared with the outdoor scenes come from
:mod:`nimbus.data.builtin.scenes`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nimbus.data.builtin.raycast import Backdrop, Box, Capsule, Cylinder, Lighting, Material, Rect, Sphere, World
from nimbus.data.builtin.scenes import (bark_material, brick_material, checker_material, coords_xy, coords_xyz,
                                        face_uv, look_at, painted_material, pick, sky_backdrop_material, split_by,
                                        texture_offset, texture_seed, wood_material)
from nimbus.data.builtin.textures import bricks, fbm, hash01, mix, smoothstep, spots, value_noise
from nimbus.data.camera import Camera

# Book-spine colours: oxblood, navy, bottle green, ochre, cream, slate, plum.
_SPINES = np.array([(0.5, 0.1, 0.1), (0.12, 0.16, 0.4), (0.1, 0.32, 0.18), (0.78, 0.58, 0.2), (0.86, 0.82, 0.7),
                    (0.35, 0.38, 0.42), (0.4, 0.16, 0.35)], np.float32)

# Rug colours: madder red, indigo, ivory, saffron.
_RUG = np.array([(0.55, 0.12, 0.1), (0.12, 0.15, 0.38), (0.88, 0.84, 0.74), (0.85, 0.6, 0.18)], np.float32)

# Window opening on the +y wall: centre x, half width, sill and lintel heights (metres).
_WINDOW = (0.4, 0.65, 0.95, 2.05)

# Materials of the central object (the bonsai, its pot, soil and mat) and of nothing else.
OBJECT_MATERIALS = frozenset({"mat", "pot", "soil", "moss", "stone", "bark", "leaves"})

# How far the room's floor, ceiling and wall rectangles reach past the corners (metres).
EDGE = 0.01

# The rug under the table: centre and half-sizes (metres).
_RUG_BOX = ((0.1, -0.1, 0.004), (1.5, 1.1, 0.004))


# --- materials ----------------------------------------------------------------------------------
def plank_material(seed: int, salt: int, length: float = 1.3, width: float = 0.16, spot_scale: float = 4.0
                   ) -> Material:
    """Oak planks along x (per-plank tint, warped grain), with knots and stains of two sizes (the blobs
    SIFT finds; grain alone is a repetitive stripe) and dark joints.

    ``spot_scale`` is the number of knot cells per metre (stains are 3 times finer): more for
    surfaces seen from close by.
    """
    s = texture_seed(seed, salt)
    off = texture_offset(seed, salt, 3)

    def albedo(p, n):
        plank, pid = bricks(p[:, 0] + off[0], p[:, 1] + off[1], length, width, 0.006)
        tint = hash01(pid, s)
        warp = fbm(coords_xy(p, off, 3.0) * np.float32([0.3, 4.0]), 2, s + 1)
        grain = 0.5 + 0.5 * np.sin(90.0 * (p[:, 1] + off[1]) + 8.0 * warp)
        col = mix((0.36, 0.22, 0.12), (0.72, 0.52, 0.32), 0.55 * tint + 0.3 * grain + 0.15 * warp)
        knots, _ = spots(coords_xy(p, off, spot_scale), s + 2, density=0.5, radius=(0.08, 0.2))
        col = mix(col, (0.18, 0.1, 0.05), 0.85 * knots)
        stains, cell = spots(coords_xy(p, off, 3.0 * spot_scale), s + 3, density=0.3)
        col = mix(col, mix((0.16, 0.1, 0.06), (0.85, 0.72, 0.52), hash01(cell, s + 4) > 0.5), 0.6 * stains)
        return mix((0.12, 0.08, 0.05), col, plank)

    return Material(albedo)


def wall_material(seed: int, salt: int, paper, motif, panel=(0.42, 0.5, 0.44), dado: float = 0.9) -> Material:
    """Papered wall above a painted board panelling.

    Above ``dado`` metres: striped wallpaper in ``paper`` with a scattered ``motif`` (flowers of
    two sizes: what SIFT detects) and faint stains; below: vertical boards in ``panel`` with
    grooves, under a light dado rail.
    """
    s = texture_seed(seed, salt)
    off = texture_offset(seed, salt, 3)

    def paper_fn(p, n):
        u, v = face_uv(p, n)
        uv = np.stack([u + off[0], v + off[1]], axis=1)
        stripe = (np.floor(uv[:, 0] * 8.0).astype(np.int64) & 1).astype(np.float32)
        col = np.broadcast_to(np.asarray(paper, np.float32), p.shape) * (0.88 + 0.12 * stripe)[:, None]
        for scale, salt2 in ((6.0, 3), (14.0, 5)):
            cover, cell = spots(uv * np.float32(scale), s + salt2, density=0.6, radius=(0.15, 0.28))
            col = mix(col, np.asarray(motif, np.float32) * (0.7 + 0.5 * hash01(cell, s + salt2 + 1))[:, None], cover)
        stains = fbm(coords_xyz(p, off, 1.5), 3, s + 1)
        return col * (0.8 + 0.3 * stains)[:, None]

    def panel_fn(p, n):
        u, v = face_uv(p, n)
        board = np.mod(u + off[0], 0.14)
        groove = (board < 0.008).astype(np.float32)
        paint = fbm(coords_xyz(p, off, 6.0), 3, s + 6) * 0.6 + 0.4 * value_noise(coords_xyz(p, off, 40.0), s + 7)
        tint = hash01(np.floor((u + off[0]) / 0.14).astype(np.int64)[:, None], s + 8)
        col = np.broadcast_to(np.asarray(panel, np.float32), p.shape) * (0.65 + 0.25 * tint + 0.35 * paint)[:, None]
        col = mix(col, (0.12, 0.12, 0.1), 0.8 * groove)
        # Chipped paint and scuffs: boards alike in every other way must not all look the same to SIFT.
        for scale, salt2 in ((5.0, 9), (15.0, 11)):
            chips, cell = spots(np.stack([u + off[0], v + off[1]], axis=1) * np.float32(scale), s + salt2,
                                density=0.6)
            col = mix(col, mix((0.3, 0.22, 0.14), (0.92, 0.9, 0.84), hash01(cell, s + salt2 + 1) > 0.5), chips)
        rail = (np.abs(p[:, 2] - (dado - 0.03)) < 0.03).astype(np.float32)
        return mix(col, (0.85, 0.82, 0.74), rail)

    def albedo(p, n):
        return split_by(p[:, 2] > dado, paper_fn, panel_fn, p, n)

    return Material(albedo)


def ceiling_material(seed: int, salt: int) -> Material:
    """Off-white plaster with trowel marks and a square coffer grid (textured: SfM sees it from below)."""
    s = texture_seed(seed, salt)
    off = texture_offset(seed, salt, 3)

    def albedo(p, n):
        trowel = fbm(coords_xy(p, off, 2.0), 4, s)
        cell, _ = bricks(p[:, 0] + off[0], p[:, 1] + off[1], 0.8, 0.8, 0.05)
        col = mix((0.62, 0.6, 0.55), (0.9, 0.88, 0.82), trowel)
        flecks, _ = spots(coords_xy(p, off, 6.0), s + 1, density=0.4)
        col = mix(col, (0.45, 0.42, 0.38), 0.7 * flecks)
        return mix((0.5, 0.42, 0.32), col, cell)

    return Material(albedo)


def rug_material(seed: int, salt: int, center, half_size) -> Material:
    """A knotted rug: nested borders and a diamond field in four colours, with wool noise."""
    s = texture_seed(seed, salt)
    off = texture_offset(seed, salt, 3)
    c = np.asarray(center, np.float32)[:2]
    h = np.asarray(half_size, np.float32)[:2]

    def albedo(p, n):
        q = (p[:, :2] - c) / h  # in [-1, 1] on the rug's top
        edge = np.minimum(1.0 - np.abs(q[:, 0]), 1.0 - np.abs(q[:, 1]) * h[1] / h[0])
        band = np.floor(edge * 14.0).astype(np.int64)
        diamond = np.floor(np.abs(q[:, 0] * h[0] * 6.0 + off[0]) + np.abs(q[:, 1] * h[1] * 6.0 + off[1]))
        idx = np.where(band < 3, band, 3 + (diamond.astype(np.int64) % 3))
        col = _RUG[np.mod(idx, len(_RUG))]
        wool = value_noise(coords_xy(p, off, 90.0), s)
        motifs, cell = spots(coords_xy(p, off, 9.0), s + 1, density=0.5)
        col = mix(col, pick(_RUG, hash01(cell, s + 2)), motifs * (band >= 3))
        return col * (0.75 + 0.35 * wool)[:, None]

    return Material(albedo)


def printed_cloth_material(seed: int, salt: int, base=(0.86, 0.83, 0.74)) -> Material:
    """A printed linen runner: flowers of two sizes in the rug's colours on a woven ground."""
    s = texture_seed(seed, salt)
    off = texture_offset(seed, salt, 3)

    def albedo(p, n):
        weave = value_noise(coords_xy(p, off, 150.0), s)
        col = np.broadcast_to(np.asarray(base, np.float32), p.shape) * (0.85 + 0.2 * weave)[:, None]
        for scale, salt2 in ((18.0, 1), (45.0, 3)):
            cover, cell = spots(coords_xy(p, off, scale), s + salt2, density=0.55)
            col = mix(col, pick(_RUG, hash01(cell, s + salt2 + 1)), cover)
        return col

    return Material(albedo)


def fabric_material(seed: int, salt: int, a, b) -> Material:
    """Woven plaid upholstery: crossing bands of two colours with a fine weave."""
    s = texture_seed(seed, salt)
    off = texture_offset(seed, salt, 3)

    def albedo(p, n):
        q = coords_xyz(p, off, 1.0)
        bands = [(np.floor(q[:, k] * 7.0).astype(np.int64) % 3 == 0).astype(np.float32) for k in range(3)]
        plaid = np.clip(bands[0] + bands[1] + bands[2], 0.0, 2.0) * 0.5
        weave = value_noise(coords_xyz(p, off, 120.0), s)
        return mix(a, b, plaid) * (0.75 + 0.35 * weave)[:, None]

    return Material(albedo)


def painting_material(seed: int, salt: int, palette) -> Material:
    """An abstract oil painting: colour fields from fBm, brush-stroke noise, a few bright dabs."""
    s = texture_seed(seed, salt)
    off = texture_offset(seed, salt, 3)
    pal = np.asarray(palette, np.float32)

    def albedo(p, n):
        q = coords_xyz(p, off, 3.0)
        field = fbm(q, 3, s)
        col = pick(pal, np.clip(field * 1.6 - 0.3, 0.0, 0.999))
        strokes = value_noise(coords_xyz(p, off, 60.0) * np.float32([1.0, 1.0, 0.25]), s + 1)
        dabs, cell = spots(np.stack([q[:, 0] + q[:, 1], q[:, 2]], axis=1) * np.float32(4.0), s + 2, density=0.4)
        col = mix(col, pick(pal, hash01(cell, s + 3)) * 1.2, dabs)
        return col * (0.8 + 0.3 * strokes)[:, None]

    return Material(albedo)


def glaze_material(seed: int, salt: int, color=(0.22, 0.36, 0.42)) -> Material:
    """Glazed stoneware: a blue-green glaze pooling darker in bands, with crackle and iron speckles."""
    s = texture_seed(seed, salt)
    off = texture_offset(seed, salt, 3)

    def albedo(p, n):
        pool = fbm(coords_xyz(p, off, 25.0), 3, s)
        band = 0.5 + 0.5 * np.sin((p[:, 2] + off[2]) * 160.0 + 4.0 * pool)
        col = np.broadcast_to(np.asarray(color, np.float32), p.shape) * (0.6 + 0.5 * pool + 0.2 * band)[:, None]
        crackle = smoothstep(0.46, 0.5, value_noise(coords_xyz(p, off, 110.0), s + 1))
        col = mix(col, (0.85, 0.84, 0.78), 0.35 * crackle * (1 - crackle) * 4.0)
        speck = smoothstep(0.8, 0.85, value_noise(coords_xyz(p, off, 260.0), s + 2))
        return mix(col, (0.18, 0.1, 0.05), speck)

    return Material(albedo)


def leaf_material(seed: int, salt: int) -> Material:
    """Bonsai foliage: clusters of small leaves, a few millimetres across (fine, high-contrast detail)."""
    s = texture_seed(seed, salt)
    off = texture_offset(seed, salt, 3)

    def albedo(p, n):
        cluster = fbm(coords_xyz(p, off, 30.0), 2, s)
        col = mix((0.05, 0.17, 0.04), (0.36, 0.56, 0.14), smoothstep(0.3, 0.7, cluster))
        leaves = value_noise(coords_xyz(p, off, 220.0), s + 1)
        col = col * (0.45 + 0.9 * leaves)[:, None]
        tips = smoothstep(0.74, 0.8, value_noise(coords_xyz(p, off, 140.0), s + 2))
        return mix(col, (0.62, 0.72, 0.28), tips)  # new growth: pale tips

    return Material(albedo)


def soil_material(seed: int, salt: int) -> Material:
    """Bonsai soil: dark grit with pale akadama grains."""
    s = texture_seed(seed, salt)
    off = texture_offset(seed, salt, 3)

    def albedo(p, n):
        grit = value_noise(coords_xyz(p, off, 300.0), s)
        col = mix((0.12, 0.08, 0.05), (0.3, 0.22, 0.14), grit)
        grains, cell = spots(coords_xy(p, off, 120.0), s + 1, density=0.45)
        return mix(col, mix((0.5, 0.33, 0.2), (0.7, 0.55, 0.38), hash01(cell, s + 2)), grains)

    return Material(albedo)


def moss_material(seed: int, salt: int) -> Material:
    s = texture_seed(seed, salt)
    off = texture_offset(seed, salt, 3)

    def albedo(p, n):
        tuft = fbm(coords_xyz(p, off, 150.0), 2, s)
        return mix((0.12, 0.22, 0.05), (0.45, 0.58, 0.16), tuft)

    return Material(albedo)


# --- the scene ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class TabletopConfig:
    """An orbit around a bonsai on a table in a furnished room (Mip-NeRF360 bonsai / counter / kitchen style).

    Attributes
    ----------
    room_half_size : tuple of float
        Half the room's floor size along x and y, metres (default (2.5, 2.0)).
    room_height : float
        Floor to ceiling, metres (default 2.6).
    table_height : float
        Height of the table top, metres (default 0.75).
    object_size : float
        Diameter of the sphere around :attr:`object_center` that holds the central object
        (the bonsai, its pot and the mat under it), metres (default 0.6).  The tree is built
        to this size and the camera distances are given in multiples of it.
    near_distance, far_distance : float
        Range of the camera distance from the object's centre, in object sizes (defaults 1.1
        and 2.3), before the pose jitter: the orbit moves in and out twice per turn, so the
        views mix close-ups of the tree with views of the room around it.  Closer than about
        1.1 at 40 views, SfM loses the close-ups (too little overlap between neighbours).
    elevation_deg : tuple of float
        Range of the cameras' elevation above the object's centre, degrees (default (12, 38)).
    fov_x_deg : float
        Horizontal field of view, degrees (default 55).
    pose_jitter : float
        Std of the seed-dependent camera position / target jitter, metres (default 0.02).
    object_jitter : float
        Std of the seed-dependent jitter of the furniture, metres (default 0.04); the tree's
        shape itself is drawn from the seed.
    backdrop_radius : float
        Radius of the sky / hills backdrop sphere seen through the window, metres (default 40).
    """

    room_half_size: tuple[float, float] = (2.5, 2.0)
    room_height: float = 2.6
    table_height: float = 0.75
    object_size: float = 0.6
    near_distance: float = 1.1
    far_distance: float = 2.3
    elevation_deg: tuple[float, float] = (12.0, 38.0)
    fov_x_deg: float = 55.0
    pose_jitter: float = 0.02
    object_jitter: float = 0.04
    backdrop_radius: float = 40.0

    @property
    def object_center(self) -> tuple[float, float, float]:
        """Centre of the central object's bounding sphere (the bonsai stands on the table's centre)."""
        return (0.0, 0.0, self.table_height + 0.42 * self.object_size)

    @property
    def window(self) -> tuple[float, float, float, float, float]:
        """The window opening: (wall y, x min, x max, z min, z max), metres."""
        cx, hw, z0, z1 = _WINDOW
        return (self.room_half_size[1], cx - hw, cx + hw, z0, z1)

    def world(self, seed: int) -> World:
        rng = np.random.default_rng([seed, 6])
        hx, hy = self.room_half_size
        H = self.room_height

        def j(v: float) -> float:
            return float(v + rng.normal(0.0, self.object_jitter))

        mats = {
            "floor": plank_material(seed, 50),
            "ceiling": ceiling_material(seed, 51),
            "wall_a": wall_material(seed, 52, paper=(0.78, 0.72, 0.58), motif=(0.55, 0.2, 0.16)),
            "wall_b": wall_material(seed, 53, paper=(0.62, 0.7, 0.66), motif=(0.85, 0.8, 0.62),
                                    panel=(0.55, 0.4, 0.3)),
            # Every wall its own paper: a repeating brick wall left SfM without distinctive matches.
            "wall_c": wall_material(seed, 54, paper=(0.82, 0.64, 0.4), motif=(0.12, 0.2, 0.45),
                                    panel=(0.5, 0.26, 0.2)),
            "frame": painted_material(seed, 55, (0.9, 0.89, 0.84)),
            "table": plank_material(seed, 56, length=0.9, width=0.12, spot_scale=9.0),
            "runner": printed_cloth_material(seed, 78),
            "dark_wood": wood_material(seed, 57, base=(0.38, 0.24, 0.14), dark=(0.16, 0.09, 0.05), rings=22.0),
            "mat": checker_material(seed, 58, (0.86, 0.82, 0.7), (0.55, 0.2, 0.14), 40.0),
            "pot": glaze_material(seed, 59),
            "soil": soil_material(seed, 60),
            "moss": moss_material(seed, 61),
            "bark": bark_material(seed, 62),
            "leaves": leaf_material(seed, 63),
            "stone": painted_material(seed, 64, (0.55, 0.55, 0.52)),
            "mug": painted_material(seed, 65, (0.9, 0.86, 0.76), stripes=(0.2, 0.35, 0.6), stripe_freq=60.0),
            "fruit": checker_material(seed, 66, (0.9, 0.5, 0.1), (0.75, 0.15, 0.1), 30.0),
            "sofa": fabric_material(seed, 67, (0.3, 0.36, 0.5), (0.7, 0.62, 0.45)),
            "cushion": checker_material(seed, 68, (0.85, 0.75, 0.3), (0.3, 0.45, 0.3), 12.0),
            "rug": rug_material(seed, 76, *_RUG_BOX),
            "lamp": painted_material(seed, 69, (0.93, 0.88, 0.72), stripes=(0.8, 0.7, 0.5), stripe_freq=20.0),
            "metal": painted_material(seed, 70, (0.25, 0.24, 0.22)),
            "plant": leaf_material(seed, 71),
            "stem": bark_material(seed, 77),
            "planter": brick_material(seed, 72, brick=(0.7, 0.45, 0.3)),
            "painting_a": painting_material(seed, 73, [(0.15, 0.3, 0.55), (0.85, 0.75, 0.4), (0.7, 0.25, 0.15),
                                                       (0.2, 0.45, 0.25), (0.9, 0.9, 0.85)]),
            "painting_b": painting_material(seed, 74, [(0.6, 0.15, 0.3), (0.95, 0.6, 0.2), (0.1, 0.1, 0.2),
                                                       (0.4, 0.6, 0.8), (0.85, 0.8, 0.55)]),
            "sky": sky_backdrop_material(seed, 75, (0.0, 0.0, 0.0), self.backdrop_radius, "hills"),
        }
        for k in range(len(_SPINES)):
            mats[f"book{k}"] = painted_material(seed, 80 + k, tuple(_SPINES[k]), stripes=(0.8, 0.68, 0.3),
                                                stripe_freq=float(9 + 4 * k))
        # The shell is rectangles that overlap by EDGE at the corners, so no ray slips out between two.
        ex, ey, ez = hx + EDGE, hy + EDGE, 0.5 * H + EDGE
        prims: list = [Backdrop((0.0, 0.0, 0.0), self.backdrop_radius, "sky"),
                       Rect((0.0, 0.0, 0.0), (ex, ey, 0.0), "floor"), Rect((0.0, 0.0, H), (ex, ey, 0.0), "ceiling"),
                       Rect((-hx, 0.0, 0.5 * H), (0.0, ey, ez), "wall_a"),
                       Rect((0.0, -hy, 0.5 * H), (ex, 0.0, ez), "wall_b"),
                       Rect((hx, 0.0, 0.5 * H), (0.0, ey, ez), "wall_c")]
        prims += self._window_wall()
        prims += self._table_and_bonsai(rng)
        prims += self._furniture(j, rng)
        return World(tuple(prims), mats, Lighting(sun_direction=(0.25, 0.35, 0.9), sun=0.3, ambient=0.8,
                                                  sky_bias=0.15), frozenset({"sky"}))

    def _window_wall(self) -> list:
        """The +y wall around the window opening, the frame with its mullions, and the sill."""
        hx, H = self.room_half_size[0], self.room_height
        y, x0, x1, z0, z1 = self.window
        lo, hi = -hx - EDGE, hx + EDGE
        prims = [Rect((0.5 * (lo + x0), y, 0.5 * H), (0.5 * (x0 - lo), 0.0, 0.5 * H + EDGE), "wall_a"),
                 Rect((0.5 * (x1 + hi), y, 0.5 * H), (0.5 * (hi - x1), 0.0, 0.5 * H + EDGE), "wall_a"),
                 Rect((0.5 * (x0 + x1), y, 0.5 * z0), (0.5 * (x1 - x0), 0.0, 0.5 * z0), "wall_a"),
                 Rect((0.5 * (x0 + x1), y, 0.5 * (z1 + H)), (0.5 * (x1 - x0), 0.0, 0.5 * (H - z1)), "wall_a")]
        # Frame bars and mullions: rectangles 3 mm in front of the wall that overlap its edges by EDGE,
        # so no ray slips between wall and frame.  (Boxes straddle the camera plane of the views
        # beside the window and are then tested against every pixel.)
        f, yf = 0.035, y - 0.003
        xm, zm, hw, hh = 0.5 * (x0 + x1), 0.5 * (z0 + z1), 0.5 * (x1 - x0) + EDGE, 0.5 * (z1 - z0) + EDGE
        prims += [Rect((x0 + f - 0.5 * EDGE, yf, zm), (f + 0.5 * EDGE, 0.0, hh), "frame"),
                  Rect((x1 - f + 0.5 * EDGE, yf, zm), (f + 0.5 * EDGE, 0.0, hh), "frame"),
                  Rect((xm, yf, z1 - f + 0.5 * EDGE), (hw, 0.0, f + 0.5 * EDGE), "frame"),
                  Rect((xm, yf, z0 + f - 0.5 * EDGE), (hw, 0.0, f + 0.5 * EDGE), "frame"),
                  Rect((xm, yf, zm), (0.5 * f, 0.0, hh), "frame"),
                  Rect((xm, yf, zm + 0.1), (hw, 0.0, 0.5 * f), "frame"),
                  Box((xm, y - 0.08, z0 - 0.02), (hw + 0.1, 0.1, 0.02), "frame")]  # the sill
        return prims

    def _table_and_bonsai(self, rng: np.random.Generator) -> list:
        """The table with a mat, the bonsai (pot, soil, roots, trunk, branches, leaf pads) and a few items."""
        th, S = self.table_height, self.object_size
        prims: list = [Box((0.0, 0.0, th - 0.025), (0.62, 0.42, 0.025), "table"),
                       Box((0.0, 0.0, th + 0.002), (0.62, 0.2, 0.002), "runner")]
        for sx in (-1, 1):
            for sy in (-1, 1):
                prims.append(Box((sx * 0.55, sy * 0.35, 0.5 * (th - 0.05)), (0.03, 0.03, 0.5 * (th - 0.05)), "table"))
        prims += [Box((sx * 0.55, 0.0, th - 0.09), (0.02, 0.33, 0.04), "table") for sx in (-1, 1)]
        # Items on the table, away from the tree: a mug, two books, fruit.
        prims += [Cylinder((0.42, 0.2), th, th + 0.09, 0.04, "mug"),
                  Box((-0.4, -0.14, th + 0.015), (0.12, 0.09, 0.015), "book1", yaw=0.3),
                  Box((-0.4, -0.14, th + 0.045), (0.1, 0.075, 0.015), "book3", yaw=-0.1),
                  Sphere((0.36, -0.22, th + 0.04), 0.04, "fruit"), Sphere((0.44, -0.16, th + 0.035), 0.035, "fruit")]
        # The bonsai: sizes are fractions of the object size (0.6 m: a 20 cm pot, a 30 cm tree).
        mat_z = th + 0.006
        prims.append(Box((0.0, 0.0, th + 0.003), (0.19 * S, 0.16 * S, 0.003), "mat"))
        pot_r, pot_h = 0.18 * S, 0.13 * S
        z_pot = mat_z + 0.012
        for a in np.radians([45.0, 135.0, 225.0, 315.0]):
            prims.append(Box((0.8 * pot_r * np.cos(a), 0.8 * pot_r * np.sin(a), mat_z + 0.006), (0.012, 0.012, 0.006),
                             "pot"))
        z_top = z_pot + pot_h
        prims += [Cylinder((0.0, 0.0), z_pot, z_top, pot_r, "pot"),
                  Cylinder((0.0, 0.0), z_top - 0.02, z_top, pot_r + 0.008, "pot"),
                  Cylinder((0.0, 0.0), z_top, z_top + 0.004, pot_r - 0.01, "soil")]
        z_soil = z_top + 0.004
        for _ in range(5):  # moss mounds and pebbles on the soil
            a, r = rng.uniform(0, 2 * np.pi), rng.uniform(0.4, 0.85) * (pot_r - 0.03)
            prims.append(Sphere((r * np.cos(a), r * np.sin(a), z_soil - 0.006), 0.018, "moss"))
            a, r = rng.uniform(0, 2 * np.pi), rng.uniform(0.3, 0.9) * (pot_r - 0.02)
            prims.append(Sphere((r * np.cos(a), r * np.sin(a), z_soil), 0.007, "stone"))
        base = np.array([0.0, 0.0, z_soil])
        for a in np.radians(np.arange(0, 360, 72) + rng.uniform(0, 72)):  # surface roots (nebari)
            tip = base + np.array([0.12 * S * np.cos(a), 0.12 * S * np.sin(a), -0.003])
            prims.append(Capsule(tuple(base + [0, 0, 0.01]), tuple(tip), 0.01, "bark"))
        # Trunk: four bent capsules, tapering, leaning a little.
        nodes = [base]
        lean = rng.uniform(0, 2 * np.pi)
        for k in range(4):
            sway = 0.05 * S * np.array([np.cos(lean + 1.4 * k), np.sin(lean + 1.4 * k), 0.0])
            nodes.append(nodes[-1] + sway + np.array([0.0, 0.0, 0.14 * S]))
        radii = np.array([0.04, 0.032, 0.025, 0.018]) * S
        for k in range(4):
            prims.append(Capsule(tuple(nodes[k]), tuple(nodes[k + 1]), float(radii[k]), "bark"))
        # Branches from the upper trunk nodes, spread by the golden angle, each ending in a leaf pad.
        reach, golden = 0.3 * S, np.pi * (3.0 - np.sqrt(5.0))
        az0 = rng.uniform(0, 2 * np.pi)
        tips = [nodes[-1] + np.array([0.0, 0.0, 0.04 * S])]
        for b in range(7):
            start = nodes[1 + b % 3 + (b >= 6)]
            az = az0 + golden * b
            length = reach * (1.0 - 0.12 * (start[2] - base[2]) / (0.56 * S)) * rng.uniform(0.8, 1.0)
            out = np.array([np.cos(az), np.sin(az), 0.0])
            mid = start + 0.55 * length * out + np.array([0.0, 0.0, 0.05 * S * rng.uniform(0.3, 1.0)])
            tip = start + length * out + np.array([0.0, 0.0, 0.02 * S * rng.uniform(-1.0, 1.0)])
            tip[:2] -= out[:2] * max(0.0, float(np.hypot(*tip[:2])) - reach)  # keep the pad inside the object
            prims += [Capsule(tuple(start), tuple(mid), 0.012 * S, "bark"),
                      Capsule(tuple(mid), tuple(tip), 0.008 * S, "bark")]
            tips.append(tip)
        for tip in tips:  # leaf pads: flattened clusters of small spheres over each branch tip
            for _ in range(11):
                a, r = rng.uniform(0, 2 * np.pi), 0.07 * S * np.sqrt(rng.uniform())
                c = tip + np.array([r * np.cos(a), r * np.sin(a), 0.02 * S * rng.uniform(-0.3, 1.0)])
                prims.append(Sphere(tuple(float(x) for x in c), float(0.035 * S * rng.uniform(0.6, 1.0)), "leaves"))
        return prims

    def _furniture(self, j, rng: np.random.Generator) -> list:
        """Rug, bookcase, sofa, sideboard, paintings, floor lamp, corner plant, ceiling light."""
        hx, hy = self.room_half_size
        H = self.room_height
        prims: list = [Box(*_RUG_BOX, "rug")]
        # Bookcase against the -x wall: carcass, shelves and rows of books of random size and colour.
        bx, by, depth, width = -hx + 0.18, j(0.3), 0.17, 0.8
        prims += [Box((bx, by, 1.0), (depth, width, 0.02), "dark_wood"),
                  Box((bx, by - width, 1.0), (depth, 0.02, 1.0), "dark_wood"),
                  Box((bx, by + width, 1.0), (depth, 0.02, 1.0), "dark_wood"),
                  Box((bx - depth + 0.01, by, 1.0), (0.01, width, 1.0), "dark_wood")]
        for level in (0.05, 0.5, 1.0, 1.5, 1.98):
            prims.append(Box((bx, by, level), (depth, width, 0.02), "dark_wood"))
        for level in (0.07, 0.52, 1.02, 1.52):
            y = by - width + 0.03
            while True:
                w = float(rng.uniform(0.018, 0.04))
                h = float(rng.uniform(0.24, 0.38))
                if y + 2 * w > by + width - 0.03:
                    break
                book = f"book{int(rng.integers(0, len(_SPINES)))}"
                prims.append(Box((bx + 0.01, y + w, level + 0.5 * h), (depth - 0.03, w, 0.5 * h), book))
                y += 2 * w + 0.002
                if rng.random() < 0.08:
                    y += 0.08  # a gap on the shelf
        # Sofa against the -y wall with two cushions.
        sx, sy = j(-0.3), -hy + 0.45
        prims += [Box((sx, sy, 0.22), (1.0, 0.4, 0.2), "sofa"), Box((sx, sy - 0.3, 0.6), (1.0, 0.12, 0.35), "sofa"),
                  Box((sx - 1.0, sy, 0.4), (0.12, 0.42, 0.22), "sofa"),
                  Box((sx + 1.0, sy, 0.4), (0.12, 0.42, 0.22), "sofa"),
                  Box((sx - 0.55, sy - 0.12, 0.6), (0.22, 0.08, 0.2), "cushion", yaw=0.1),
                  Box((sx + 0.5, sy - 0.12, 0.6), (0.22, 0.08, 0.2), "cushion", yaw=-0.15)]
        # Sideboard against the +x wall, a plant in a planter and a lamp on it.
        cx, cy = hx - 0.25, j(-0.4)
        prims += [Box((cx, cy, 0.42), (0.23, 0.7, 0.4), "dark_wood"), Box((cx, cy, 0.83), (0.25, 0.72, 0.02), "table")]
        for dy in (-0.35, 0.35):
            prims.append(Box((cx - 0.235, cy + dy, 0.42), (0.005, 0.3, 0.3), "table"))  # door panels
            prims.append(Sphere((cx - 0.245, cy + dy - 0.22 * np.sign(dy), 0.5), 0.015, "metal"))
        prims += [Box((cx, cy + 0.45, 0.95), (0.1, 0.1, 0.1), "planter"),
                  Sphere((cx, cy + 0.45, 1.15), 0.16, "plant"), Sphere((cx + 0.03, cy + 0.35, 1.25), 0.1, "plant"),
                  Cylinder((cx, cy - 0.4), 0.85, 1.15, 0.012, "metal"),
                  Cylinder((cx, cy - 0.4), 1.1, 1.28, 0.1, "lamp")]
        # Paintings: above the sofa, on the -x wall beside the bookcase, above the sideboard, beside the window.
        # Each is a frame box on the wall and a canvas box 5 cm smaller and 6 mm prouder inside it.
        for (x, y, z), (hw, hh), mat in (((sx, -hy, 1.55), (0.45, 0.3), "painting_a"),
                                         ((-hx, by - 1.35, 1.5), (0.3, 0.38), "painting_b"),
                                         ((hx, cy, 1.6), (0.5, 0.32), "painting_a"),
                                         ((-1.4, hy, 1.45), (0.35, 0.45), "painting_b")):
            frame, canvas = (0.02, hw + 0.05, hh + 0.05), (0.026, hw, hh)
            if abs(abs(x) - hx) > 1e-9:  # on a y wall: thickness along y
                frame, canvas = (frame[1], frame[0], frame[2]), (canvas[1], canvas[0], canvas[2])
            prims += [Box((x, y, z), frame, "dark_wood"), Box((x, y, z), canvas, mat)]
        # Floor lamp in the (+x, -y) corner, a potted tree in the (-x, +y) corner, a ceiling light.
        lx, ly = hx - 0.35, -hy + 0.35
        prims += [Cylinder((lx, ly), 0.0, 0.03, 0.16, "metal"), Cylinder((lx, ly), 0.0, 1.5, 0.015, "metal"),
                  Cylinder((lx, ly), 1.45, 1.75, 0.2, "lamp")]
        px, py = -hx + 0.4, hy - 0.4
        prims += [Cylinder((px, py), 0.0, 0.4, 0.2, "planter"),
                  Capsule((px, py, 0.4), (px + 0.05, py - 0.05, 1.2), 0.03, "stem"),
                  Sphere((px + 0.05, py - 0.05, 1.35), 0.32, "plant"), Sphere((px - 0.1, py, 1.15), 0.22, "plant"),
                  Sphere((px + 0.15, py - 0.15, 1.2), 0.2, "plant")]
        prims += [Cylinder((0.0, 0.0), H - 0.3, H, 0.008, "metal"), Sphere((0.0, 0.0, H - 0.36), 0.1, "lamp")]
        return prims

    def cameras(self, n_views: int, width: int, height: int, seed: int) -> list[Camera]:
        """An orbit around the object that moves in and out (twice per turn) and up and down (three times)."""
        rng = np.random.default_rng([seed, 7])
        phase = rng.uniform(0, 2 * np.pi)
        centre = np.asarray(self.object_center)
        mid = 0.5 * (self.near_distance + self.far_distance) * self.object_size
        amp = 0.5 * (self.far_distance - self.near_distance) * self.object_size
        e_mid, e_amp = np.radians(np.mean(self.elevation_deg)), np.radians(0.5 * np.ptp(self.elevation_deg))
        cams = []
        for i in range(n_views):
            a = phase + 2 * np.pi * i / n_views
            dist = mid + amp * np.sin(2 * a + 0.5 * phase)
            elev = e_mid + e_amp * np.sin(3 * a + phase)
            eye = centre + dist * np.array([np.cos(elev) * np.cos(a), np.cos(elev) * np.sin(a), np.sin(elev)])
            eye = eye + rng.normal(0, self.pose_jitter, 3)
            target = centre + rng.normal(0, self.pose_jitter, 3)
            cams.append(look_at(eye, target, width, height, self.fov_x_deg))
        return cams
