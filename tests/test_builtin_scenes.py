"""Built-in procedural scenes: ray-caster geometry, rendering sanity, multi-view consistency,
determinism, writing, the ``nimbus-synth scene`` command, and (slow) that SfM can register them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from nimbus.cli_util import ArgumentParser, run_cli
from nimbus.data.builtin import SIZES, get_scene, list_scenes, render_builtin, write_builtin
from nimbus.data.builtin.raycast import (Backdrop, Box, Capsule, Cylinder, Ground, Rect, RenderSettings, Sphere,
                                         camera_rays, render_view, subpixel_offsets, surface_normal, trace)
from nimbus.data.builtin.textures import fbm, spots, value_noise
from nimbus.data.camera import Camera
from nimbus.errors import NimbusError
from weather_synth.commands import scene as scene_cmd

SCENE_NAMES = list_scenes()
# Scenes whose backdrop (sky) surrounds them; indoors (tabletop) the backdrop shows only through a window,
# which tests/test_builtin_tabletop.py checks.
OUTDOOR = ("garden", "street")


@pytest.fixture(scope="module")
def tiny_scenes():
    """Every built-in scene rendered once at tiny size (seed 0)."""
    return {name: render_builtin(name, "tiny", seed=0) for name in SCENE_NAMES}


# --- ray caster -----------------------------------------------------------------------------
def _random_rays(n: int, seed: int, origin=(0.0, 0.0, 2.5)) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(3, n))
    d /= np.linalg.norm(d, axis=0)
    return np.asarray(origin, np.float32), d.astype(np.float32)


@pytest.mark.parametrize("prim", [
    Sphere((2.0, 0.5, 1.2), 0.7, "m"),
    Box((1.5, -1.0, 0.8), (0.4, 0.9, 0.3), "m", yaw=0.6),
    Box((-1.2, 0.3, 1.1), (0.5, 0.2, 0.6), "m"),
    Cylinder((0.4, 1.6), 0.2, 1.9, 0.5, "m"),
    Ground(0.0, 5.0, "m"),
    Backdrop((0.0, 0.0, 0.0), 30.0, "m"),
    Capsule((0.3, 0.2, 1.0), (1.0, -0.4, 1.6), 0.2, "m"),
    Capsule((-0.8, 0.1, 0.4), (-0.8, 0.1, 2.0), 0.15, "m"),
    Rect((0.0, 2.0, 1.5), (1.5, 0.0, 1.0), "m"),
    Rect((0.5, -0.2, 4.0), (2.0, 1.0, 0.0), "m"),
], ids=["sphere", "box-yaw", "box", "cylinder", "ground", "backdrop", "capsule", "capsule-vertical", "rect-wall",
        "rect-ceiling"])
def test_primitive_hits_lie_on_the_surface(prim):
    o, d = _random_rays(4000, 1)
    t = prim.intersect(o, d)
    hit = np.isfinite(t)
    assert 0.01 < hit.mean() <= 1.0
    p, n = surface_normal(prim, o, d[:, hit], t[hit])
    np.testing.assert_allclose(np.linalg.norm(n, axis=0), 1.0, atol=1e-5)
    p = p.astype(np.float64)
    if isinstance(prim, (Sphere, Backdrop)):
        np.testing.assert_allclose(np.linalg.norm(p - np.array(prim.center)[:, None], axis=0), prim.radius, rtol=1e-4)
    elif isinstance(prim, Ground):
        np.testing.assert_allclose(p[2], prim.height, atol=1e-5)
        assert np.all(np.hypot(p[0], p[1]) <= prim.radius + 1e-4)
    elif isinstance(prim, Rect):
        q = p - np.array(prim.center)[:, None]
        k = prim.half_size.index(0.0)
        np.testing.assert_allclose(q[k], 0.0, atol=1e-5)  # on the plane
        assert np.all(np.abs(q) <= np.array(prim.half_size)[:, None] + 1e-5)  # inside the rectangle
        np.testing.assert_array_equal(np.abs(n[k]), 1.0)
    elif isinstance(prim, Capsule):
        a, b = np.array(prim.a)[:, None], np.array(prim.b)[:, None]
        s = np.clip(np.sum((p - a) * (b - a), axis=0) / np.sum((b - a) ** 2), 0.0, 1.0)
        np.testing.assert_allclose(np.linalg.norm(p - a - s * (b - a), axis=0), prim.radius, rtol=1e-4)
        assert ((s > 0) & (s < 1)).any() and ((s == 0) | (s == 1)).any()  # rays hit the body and the ends
    elif isinstance(prim, Box):
        c, s = np.cos(prim.yaw), np.sin(prim.yaw)
        q = p - np.array(prim.center)[:, None]
        local = np.stack([c * q[0] + s * q[1], -s * q[0] + c * q[1], q[2]]) / np.array(prim.half_size)[:, None]
        np.testing.assert_allclose(np.abs(local).max(axis=0), 1.0, atol=1e-4)  # on the boundary
    else:
        radial = np.hypot(p[0] - prim.center[0], p[1] - prim.center[1])
        on_side = np.abs(radial - prim.radius) < 1e-4
        on_cap = (np.abs(p[2] - prim.z0) < 1e-4) | (np.abs(p[2] - prim.z1) < 1e-4)
        assert np.all(on_side | on_cap) and on_side.any() and on_cap.any()
        assert np.all((p[2] > prim.z0 - 1e-4) & (p[2] < prim.z1 + 1e-4))
    if not isinstance(prim, Backdrop):
        # Solid objects are seen from outside: the normal faces the ray.
        assert np.all(np.sum(n * d[:, hit], axis=0) < 1e-6)


def test_box_hit_matches_ray_marching():
    """A brute-force march along each ray finds the same first entry into the box."""
    box = Box((1.0, 0.5, 1.0), (0.6, 0.3, 0.4), "m", yaw=0.4)
    o, d = _random_rays(300, 2)
    t = box.intersect(o, d)
    steps = np.linspace(0, 4, 40001)[:, None]  # 0.1 mm steps
    c, s = np.cos(box.yaw), np.sin(box.yaw)
    for k in np.flatnonzero(np.isfinite(t))[:25]:
        pts = o[None, :].astype(np.float64) + steps * d[:, k][None, :] - np.array(box.center)
        local = np.stack([c * pts[:, 0] + s * pts[:, 1], -s * pts[:, 0] + c * pts[:, 1], pts[:, 2]], axis=1)
        inside = np.all(np.abs(local) <= np.array(box.half_size), axis=1)
        assert abs(steps[np.argmax(inside), 0] - t[k]) < 2e-4


def test_capsule_hit_matches_ray_marching():
    """A brute-force march finds the same first point within the radius of the capsule's segment."""
    cap = Capsule((0.6, 0.2, 1.2), (1.2, -0.3, 1.9), 0.12, "m")
    o, d = _random_rays(3000, 3)
    t = cap.intersect(o, d)
    hits = np.flatnonzero(np.isfinite(t))
    assert len(hits) > 25
    steps = np.linspace(0, 4, 40001)[:, None]  # 0.1 mm steps
    a, ba = np.array(cap.a), np.array(cap.b) - np.array(cap.a)
    for k in hits[:25]:
        pts = o[None, :].astype(np.float64) + steps * d[:, k][None, :] - a
        s = np.clip(pts @ ba / (ba @ ba), 0.0, 1.0)
        inside = np.linalg.norm(pts - s[:, None] * ba, axis=1) <= cap.radius
        assert abs(steps[np.argmax(inside), 0] - t[k]) < 2e-4
    missed = np.flatnonzero(~np.isfinite(t))[:200]
    for k in missed:  # and a ray it misses never comes within the radius
        pts = o[None, :].astype(np.float64) + steps[::10] * d[:, k][None, :] - a
        s = np.clip(pts @ ba / (ba @ ba), 0.0, 1.0)
        assert np.linalg.norm(pts - s[:, None] * ba, axis=1).min() > cap.radius - 1e-3


def test_rect_needs_exactly_one_zero_half_size():
    with pytest.raises(ValueError, match="one zero half-size"):
        Rect((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), "m")
    with pytest.raises(ValueError, match="one zero half-size"):
        Rect((0.0, 0.0, 0.0), (0.0, 1.0, 0.0), "m")


def test_center_rays_match_camera_world_rays():
    cam = Camera.look_at((3, -2, 1.5), (0, 0, 0.5), (0, 0, 1), 24, 18, 55)
    offsets, n_color, centre = subpixel_offsets(2)
    assert n_color == 4 and centre == 4 and tuple(offsets[centre]) == (0.5, 0.5)
    dirs, origin = camera_rays(cam, offsets)
    ref, ref_origin = cam.world_rays(np.float64)
    np.testing.assert_allclose(np.moveaxis(dirs[:, centre], 0, -1), ref, atol=1e-6)
    np.testing.assert_allclose(origin, ref_origin, atol=1e-6)
    assert subpixel_offsets(3)[2] == 4 and tuple(subpixel_offsets(3)[0][4]) == (0.5, 0.5)


@pytest.mark.parametrize("name", SCENE_NAMES)
def test_culling_and_adaptive_sampling_match_the_reference(name):
    """The fast path (screen-space culling, adaptive supersampling) against the plain reference."""
    cfg = get_scene(name).config
    world = cfg.world(0)
    cam = cfg.cameras(16, 48, 36, 0)[5]
    offsets, _, _ = subpixel_offsets(2)
    dirs, origin = camera_rays(cam, offsets)
    t_fast, i_fast = trace(world.primitives, cam, dirs, origin, cull=True)
    t_ref, i_ref = trace(world.primitives, cam, dirs, origin, cull=False)
    np.testing.assert_array_equal(i_fast, i_ref)
    np.testing.assert_array_equal(t_fast, t_ref)
    fast = render_view(world, cam, RenderSettings(2))
    ref = render_view(world, cam, RenderSettings(2, adaptive_threshold=None, cull=False))
    np.testing.assert_array_equal(fast.depth, ref.depth)
    np.testing.assert_array_equal(fast.sky, ref.sky)
    assert np.abs(fast.image - ref.image).mean() < 0.01


def test_one_sample_per_pixel_renders_the_centre_ray():
    """samples_per_axis=1 with adaptive sampling on: no other sample to refine with, so it is the reference."""
    cfg = get_scene("garden").config
    cam = cfg.cameras(16, 48, 36, 0)[5]
    world = cfg.world(0)
    fast = render_view(world, cam, RenderSettings(1))
    ref = render_view(world, cam, RenderSettings(1, adaptive_threshold=None, cull=False))
    np.testing.assert_array_equal(fast.image, ref.image)
    np.testing.assert_array_equal(fast.depth, ref.depth)


def test_noise_is_smooth_seeded_and_in_range():
    rng = np.random.default_rng(0)
    x = (rng.random((5000, 3)) * 40 - 20).astype(np.float32)
    v = value_noise(x, 3)
    assert v.dtype == np.float32 and v.min() >= 0 and v.max() <= 1 and v.std() > 0.1
    np.testing.assert_array_equal(v, value_noise(x, 3))
    assert np.abs(v - value_noise(x, 4)).mean() > 0.1
    near = value_noise(x + np.float32(1e-3), 3)
    assert np.abs(near - v).max() < 0.01  # continuous: no jumps at cell borders
    f = fbm(x[:, :2], 4, 1)
    assert f.min() >= 0 and f.max() <= 1
    cover, _ = spots(x[:, :2], 5, density=0.5)
    assert 0.01 < (cover > 0.5).mean() < 0.3 and cover.min() >= 0 and cover.max() <= 1


# --- rendered scenes -------------------------------------------------------------------------
@pytest.mark.parametrize("name", SCENE_NAMES)
def test_tiny_scene_is_sane(tiny_scenes, name):
    scene = tiny_scenes[name]
    preset = SIZES["tiny"]
    assert len(scene) == preset.n_views and scene.source_format == "builtin"
    assert scene.names[:2] == ["000.png", "001.png"]
    assert scene.test_names == {"000.png", "008.png"}
    depths = []
    for v in scene.views:
        assert v.image.shape == (preset.height, preset.width, 3) and v.image.dtype == np.float32
        assert v.image.min() >= 0 and v.image.max() <= 1 and v.image.std() > 0.05
        assert v.depth.dtype == np.float32 and v.depth.shape == v.image.shape[:2]
        assert np.all(np.isfinite(v.depth)) and v.depth.min() > 0.3
        assert v.sky.dtype == bool and v.sky.mean() < 0.6
        if name in OUTDOOR:
            assert v.sky.mean() > 0.01
        if v.sky.any():
            # The backdrop is far: every backdrop pixel is deeper than every object pixel nearby.
            assert v.depth[v.sky].min() > 0.5 * v.depth.max()
        depths.append(v.depth)
    d = np.stack(depths)
    assert d.max() / d.min() >= 20
    assert scene.metadata["scene"] == name and scene.metadata["seed"] == 0
    assert scene.metadata["depth_range"] == pytest.approx([float(d.min()), float(d.max())])


@pytest.mark.parametrize("name", SCENE_NAMES)
def test_sparse_points_lie_on_visible_surfaces(tiny_scenes, name):
    scene = tiny_scenes[name]
    assert 500 <= len(scene.points) <= 4000 and scene.colors.dtype == np.uint8
    assert len(np.unique(scene.points, axis=0)) == len(scene.points)
    v = scene.views[1]
    uv, z = v.camera.project(scene.points)
    ok = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < v.camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] < v.camera.height)
    u, w = uv[ok].astype(int).T
    on_surface = np.abs(v.depth[w, u] - z[ok]) < 0.05 * z[ok]
    assert ok.sum() > 100 and on_surface.mean() > 0.3


@pytest.mark.parametrize("name", SCENE_NAMES)
def test_views_agree_on_geometry_and_colour(tiny_scenes, name):
    """Unproject view A's pixels with their z-depth, reproject into view B: B's depth and colour agree."""
    scene = tiny_scenes[name]
    for a, b in ((1, 2), (5, 6)):
        va, vb = scene.views[a], scene.views[b]
        ca, cb = va.camera, vb.camera
        pts_cam = ca.pixel_rays(np.float64) * va.depth[..., None].astype(np.float64)
        pts = (pts_cam.reshape(-1, 3) - ca.t) @ ca.R
        uv, z = cb.project(pts)
        u, v = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
        inside = (z > 0) & (u >= 0) & (u < cb.width) & (v >= 0) & (v < cb.height)
        assert inside.mean() > 0.5
        zb = vb.depth[v[inside], u[inside]]
        agree = np.abs(zb - z[inside]) < 0.03 * z[inside]
        assert agree.mean() > 0.6, f"{name}: only {agree.mean():.2f} of reprojected pixels agree in depth"
        col_a = va.image.reshape(-1, 3)[inside][agree]
        col_b = vb.image[v[inside], u[inside]][agree]
        assert np.median(np.abs(col_a - col_b).max(axis=1)) < 0.12
        # The same test with ray distances instead of z-depths must fail (checks the convention).
        ray_dist = ca.ray_distance_from_z(va.depth)
        pts_wrong = ((ca.pixel_rays(np.float64) * ray_dist[..., None]).reshape(-1, 3) - ca.t) @ ca.R
        _, z_wrong = cb.project(pts_wrong)
        assert (np.abs(zb - z_wrong[inside]) < 0.03 * z_wrong[inside]).mean() < agree.mean() - 0.1


def test_thread_count_does_not_change_the_output(tiny_scenes):
    one = render_builtin("street", "tiny", seed=0, workers=1)
    two = tiny_scenes["street"]
    for a, b in zip(one.views, two.views):
        np.testing.assert_array_equal(a.image, b.image)
        np.testing.assert_array_equal(a.depth, b.depth)
    np.testing.assert_array_equal(one.points, two.points)


def test_seed_changes_the_scene_but_not_its_layout():
    a, b = render_builtin("garden", "tiny", seed=0), render_builtin("garden", "tiny", seed=1)
    assert np.abs(a.views[3].image - b.views[3].image).mean() > 0.02
    centres_a, centres_b = a.camera_centers, b.camera_centers
    assert np.abs(np.linalg.norm(centres_a[:, :2], axis=1) - np.linalg.norm(centres_b[:, :2], axis=1)).max() < 0.5


def test_bad_names_sizes_and_seeds_are_user_errors():
    with pytest.raises(NimbusError, match="garden"):
        render_builtin("forest")
    with pytest.raises(NimbusError, match="tiny"):
        render_builtin("garden", size="huge")
    with pytest.raises(NimbusError, match="seed"):
        render_builtin("garden", seed=-1)


# --- writing ----------------------------------------------------------------------------------
def _tree_bytes(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_same_seed_writes_identical_bytes(tmp_path):
    a = write_builtin("street", tmp_path / "a", "tiny", seed=3)
    b = write_builtin("street", tmp_path / "b", "tiny", seed=3)
    files_a, files_b = _tree_bytes(a), _tree_bytes(b)
    assert {"manifest.json", "train_list.txt", "test_list.txt", "images/000.png", "depths/000.npy",
            "sky/000.png"} <= set(files_a)
    assert any(k.startswith("sparse/0/") for k in files_a)
    assert files_a.keys() == files_b.keys()
    different = [k for k in files_a if files_a[k] != files_b[k]]
    assert not different
    assert [p.name for p in tmp_path.iterdir()] and not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_written_scene_reads_back(tmp_path):
    from nimbus.data.io import load_scene

    out = write_builtin("garden", tmp_path / "g", "tiny", seed=0)
    mem = render_builtin("garden", "tiny", seed=0)
    disk = load_scene(out)
    assert disk.names == mem.names and disk.test_names == mem.test_names
    v, w = disk.views[4], mem.views[4]
    assert np.abs(v.load_image() - w.image).max() <= 0.5 / 255 + 1e-6
    np.testing.assert_array_equal(v.load_depth(), w.depth)
    np.testing.assert_array_equal(v.load_sky(), w.sky)
    np.testing.assert_allclose(v.camera.world_to_camera, w.camera.world_to_camera, atol=1e-9)
    np.testing.assert_allclose(disk.points, mem.points, atol=1e-9)


# --- command line -----------------------------------------------------------------------------
def _scene_cli(argv: list[str]) -> int:
    """``nimbus-synth scene ARGS`` through this subcommand's own parser (the error handling the CLI uses)."""
    def main(args):
        parser = ArgumentParser(prog="nimbus-synth scene")
        scene_cmd.add_arguments(parser)
        return scene_cmd.run(parser.parse_args(args))

    return run_cli(main, argv)


def test_cli_list(capsys):
    assert _scene_cli(["--list"]) == 0
    out = capsys.readouterr().out
    for name in SCENE_NAMES + list(SIZES):
        assert name in out


def test_cli_unknown_scene_is_one_error_line(capsys, tmp_path):
    assert _scene_cli(["forest", "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert "error: unknown built-in scene 'forest'" in err and "garden" in err and "Traceback" not in err
    assert not (tmp_path / "x").exists()


def test_cli_writes_and_refuses_a_non_empty_out(capsys, tmp_path):
    out = tmp_path / "scene"
    assert _scene_cli(["garden", "--size", "tiny", "--out", str(out)]) == 0
    summary = capsys.readouterr().out
    assert "16 views" in summary and "depth" in summary
    before = _tree_bytes(out)
    assert _scene_cli(["garden", "--size", "tiny", "--out", str(out), "--seed", "2"]) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert _tree_bytes(out) == before
    assert _scene_cli(["garden", "--size", "tiny", "--out", str(out), "--seed", "2", "--overwrite"]) == 0
    assert _tree_bytes(out)["images/003.png"] != before["images/003.png"]


def test_cli_is_registered_in_nimbus_synth(capsys):
    from weather_synth import cli

    cli.build_parser()
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["scene", "--list"])
    assert exit_info.value.code == 0
    assert "garden" in capsys.readouterr().out


# --- structure from motion (slow) ------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("name", SCENE_NAMES)
def test_small_scene_is_registered_by_sfm(tmp_path, name):
    """Real texture: COLMAP (pycolmap SIFT + incremental mapping) registers >= 90 % of the small views."""
    from nimbus.data.sfm import run_sfm

    out = write_builtin(name, tmp_path / "scene", "small", seed=0)
    result = run_sfm(out / "images", tmp_path / "sfm", camera_model="SIMPLE_PINHOLE", single_camera=True)
    assert result.total == SIZES["small"].n_views
    assert result.registered >= 0.9 * result.total, f"{name}: {result.registered}/{result.total} registered"


def test_backdrop_points_are_optional_and_merged_by_distance():
    from nimbus.data.builtin.points import PointCloudConfig, sample_points

    # Two cameras 0.2 m apart looking down +z: the left half of the image is a wall at 5 m,
    # the right half a backdrop at 200 m (40x farther: 6 octaves of the median distance).
    cams = [Camera(40, 30, 30.0, 30.0, 20.0, 15.0, np.eye(3), np.array([-x, 0.0, 0.0])) for x in (0.0, 0.2)]
    depth = np.full((30, 40), 5.0, np.float32)
    depth[:, 20:] = 200.0
    mask = depth > 100
    images = [np.full((30, 40, 3), 0.5, np.float32)] * 2
    args = (cams, images, [depth] * 2, [mask] * 2)
    cfg = PointCloudConfig(view_stride=1, pixel_stride=1, voxel_fraction=0.03, max_points=10**6)  # voxel ~ 1 px at 5 m
    near_only, _ = sample_points(*args, cfg, seed=0)
    assert len(near_only) and np.all(near_only[:, 2] < 10)
    pts, _ = sample_points(*args, PointCloudConfig(**{**cfg.__dict__, "include_backdrop": True}), seed=0)
    far = pts[:, 2] > 100
    assert far.any() and (~far).any()
    # 1200 backdrop samples, far apart at 200 m: without distance-scaled voxels each would stay a point.
    assert far.sum() < 0.5 * 2 * mask.sum()
