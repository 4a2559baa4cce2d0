"""The ``tabletop`` built-in scene: an indoor orbit around a bonsai on a table.

Checks what makes it an indoor near-object capture (cameras at 0.5 to 3 object sizes,
looking at the object; depths and points inside the room; the sky mask only through the
window) and that its object carries detail a reconstruction must keep.  The generic
checks every built-in scene passes are in ``tests/test_builtin_scenes.py``.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import uniform_filter

from nimbus.data.builtin import SIZES, get_scene, list_scenes, render_builtin
from nimbus.data.builtin.raycast import camera_rays, subpixel_offsets, trace
from nimbus.data.builtin.tabletop import OBJECT_MATERIALS, TabletopConfig

CFG: TabletopConfig = get_scene("tabletop").config


@pytest.fixture(scope="module")
def scene():
    return render_builtin("tabletop", "tiny", seed=0)


def _object_pixels(view, world) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel (centre ray): whether it sees the central object, and the world point it hits."""
    offsets, _, _ = subpixel_offsets(1)
    dirs, origin = camera_rays(view.camera, offsets)
    t, idx = trace(world.primitives, view.camera, dirs, origin)
    is_object = np.array([p.material in OBJECT_MATERIALS for p in world.primitives])
    points = origin[:, None, None] + t[0][None] * dirs[:, 0]
    return is_object[idx[0]], np.moveaxis(points, 0, -1)


def _world_points(view) -> np.ndarray:
    """(H, W, 3) world points of the pixel-centre rays, from the rendered z-depth."""
    cam = view.camera
    pts = cam.pixel_rays(np.float64) * view.depth[..., None].astype(np.float64)
    return (pts - cam.t) @ cam.R


def _in_room(points: np.ndarray, tol: float = 0.13) -> np.ndarray:
    """Whether points lie in the room grown by ``tol`` metres (default: the window sill, which a camera
    sees through the opening 0.12 m beyond the wall, plus 1 cm)."""
    hx, hy = CFG.room_half_size
    return ((np.abs(points[..., 0]) <= hx + tol) & (np.abs(points[..., 1]) <= hy + tol)
            & (points[..., 2] >= -tol) & (points[..., 2] <= CFG.room_height + tol))


def test_registered():
    assert "tabletop" in list_scenes() and isinstance(CFG, TabletopConfig)


def test_same_seed_same_scene_other_seed_other_tree(scene):
    again = render_builtin("tabletop", "tiny", seed=0, workers=1)
    for a, b in zip(scene.views, again.views):
        np.testing.assert_array_equal(a.image, b.image)
        np.testing.assert_array_equal(a.depth, b.depth)
        np.testing.assert_array_equal(a.sky, b.sky)
    np.testing.assert_array_equal(scene.points, again.points)
    np.testing.assert_array_equal(scene.colors, again.colors)
    # Another seed grows another tree (not just other textures).
    trees = [[p for p in CFG.world(s).primitives if p.material == "leaves"] for s in (0, 1)]
    assert [p.center for p in trees[0]] != [p.center for p in trees[1]]


def test_shapes_and_manifest(scene):
    preset = SIZES["tiny"]
    assert len(scene) == preset.n_views and scene.test_names == {"000.png", "008.png"}
    for v in scene.views:
        assert v.image.shape == (preset.height, preset.width, 3) and v.image.dtype == np.float32
        assert v.depth.shape == v.sky.shape == (preset.height, preset.width)
        assert v.depth.dtype == np.float32 and v.sky.dtype == bool and np.all(np.isfinite(v.depth))
        assert 0.15 < v.image.mean() < 0.7 and v.image.std() > 0.05  # lit, and textured
    meta = scene.metadata
    assert meta["scene"] == "tabletop" and meta["scene_config"]["object_size"] == CFG.object_size


def test_sky_only_through_the_window(scene):
    """The backdrop shows only through the window: a few per cent of a view that sees it, else nothing."""
    fractions = np.array([v.sky.mean() for v in scene.views])
    assert np.all(fractions < 0.1)
    assert (fractions > 0.005).sum() >= 2 and (fractions == 0).sum() >= 8
    wall_y, x0, x1, z0, z1 = CFG.window
    for v in scene.views:
        if not v.sky.any():
            continue
        # Every sky pixel's ray crosses the window wall's plane inside the opening.
        rays = v.camera.pixel_rays(np.float64)[v.sky] @ v.camera.R  # world directions
        centre = v.camera.center
        s = (wall_y - centre[1]) / rays[:, 1]
        cross = centre + s[:, None] * rays
        assert np.all(s > 0)
        assert np.all((cross[:, 0] > x0) & (cross[:, 0] < x1) & (cross[:, 2] > z0) & (cross[:, 2] < z1))
        # ... and ends far beyond the room.
        assert v.depth[v.sky].min() > 5 * max(CFG.room_half_size)


def test_depths_and_points_lie_in_the_room(scene):
    hx, hy = CFG.room_half_size
    diagonal = float(np.sqrt((2 * hx) ** 2 + (2 * hy) ** 2 + CFG.room_height ** 2))
    for v in scene.views:
        solid = ~v.sky
        assert v.depth.min() > 0.2 and v.depth[solid].max() < diagonal
        pts = _world_points(v)[solid]
        assert _in_room(pts).mean() > 0.999
        # Walls, floor and ceiling close the room: some pixel lies on its boundary in every view.
        assert (~_in_room(pts, tol=-0.02)).mean() > 0.1
    # Sparse points: all on surfaces inside the room (tiny skips the backdrop), some on the object,
    # and where a view sees them, at its rendered depth.
    pts = scene.points
    assert 500 <= len(pts) <= 4000 and _in_room(pts).all()
    near_object = np.linalg.norm(pts - np.array(CFG.object_center), axis=1) < 0.5 * CFG.object_size
    assert near_object.mean() > 0.02
    v = scene.views[5]
    uv, z = v.camera.project(pts)
    ok = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < v.camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] < v.camera.height)
    u, w = uv[ok].astype(int).T
    assert ok.sum() > 100 and (np.abs(v.depth[w, u] - z[ok]) < 0.05 * z[ok]).mean() > 0.4


def test_cameras_orbit_the_object_at_half_to_three_object_sizes(scene):
    centre = np.array(CFG.object_center)
    dist = np.array([np.linalg.norm(v.camera.center - centre) for v in scene.views]) / CFG.object_size
    assert np.all((dist >= 0.5) & (dist <= 3.0))
    assert 0.5 <= CFG.near_distance < CFG.far_distance <= 3.0
    # The orbit moves in and out over the whole configured range: close-ups and room views both.
    assert dist.min() < CFG.near_distance + 0.15 and dist.max() > CFG.far_distance - 0.15
    azimuth = np.sort([np.arctan2(*(v.camera.center - centre)[[1, 0]]) for v in scene.views])
    assert np.diff(np.r_[azimuth, azimuth[0] + 2 * np.pi]).max() < np.radians(40)  # all the way round
    for v in scene.views:
        (u, w), z = (a[0] for a in v.camera.project(centre[None]))
        assert z > 0 and abs(u - v.camera.cx) < 0.1 * v.camera.width and abs(w - v.camera.cy) < 0.1 * v.camera.height
        assert _in_room(v.camera.center, tol=-0.3) and v.camera.center[2] > CFG.table_height + 0.2


def test_object_fits_its_size_and_carries_fine_detail(scene):
    """The object stays inside its stated size, fills a good part of every view, and blurring it
    (what a reconstruction that loses the tree's detail renders) costs several dB."""
    world = CFG.world(0)
    n_object = sum(p.material in OBJECT_MATERIALS for p in world.primitives)
    assert n_object >= 100  # leaves, branches, roots, moss, pebbles, pot
    psnrs, coverage = [], []
    for v in scene.views:
        is_obj, points = _object_pixels(v, world)
        assert is_obj.any()
        r = np.linalg.norm(points[is_obj] - np.array(CFG.object_center), axis=1)
        assert r.max() <= 0.5 * CFG.object_size + 1e-3
        blurred = np.stack([uniform_filter(v.image[..., c], 5) for c in range(3)], axis=-1)
        lost = np.where(is_obj[..., None], blurred, v.image)
        psnrs.append(10 * np.log10(1.0 / np.mean((lost - v.image) ** 2)))
        coverage.append(is_obj.mean())
    assert min(coverage) > 0.03 and max(coverage) > 0.15
    assert np.mean(psnrs) < 32.0 and min(psnrs) < 29.0
