"""Posed captures without sparse points: triangulation with the poses fixed (cached), the fallback, the record.

The test data are built-in scenes exported as transforms.json, with and without their points: a few
neighbouring views of the garden orbit at the ``small`` size (SIFT needs more than ``tiny``'s 64 x 48
pixels), and the whole ``tiny`` garden for the random fallback.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging

import numpy as np
import pytest

from nimbus.cli_util import run_cli
from nimbus.data.builtin import SIZES, get_scene, render_builtin
from nimbus.data.builtin.raycast import RenderSettings, render_view
from nimbus.data.io import load_scene, write_scene
from nimbus.data.scene import Scene, View, llff_test_names
from nimbus.data.triangulate import (MIN_TRIANGULATED_POINTS, TriangulationConfig, pose_neighbour_pairs,
                                     triangulate_posed, triangulation_key)
from nimbus.errors import NimbusError
from nimbus.train.config import preset
from nimbus.train.runner import Runner
from weather_synth.commands import sfm as sfm_command

N_VIEWS = 7  # 000 is the test view (LLFF rule), 001-006 are triangulated: about 9 degrees apart on the orbit


@pytest.fixture(scope="module")
def garden_views():
    """Seven neighbouring views of the garden orbit at the small size (2 x 2 samples per pixel), in memory."""
    sc, size = get_scene("garden"), SIZES["small"]
    world = sc.config.world(0)
    cams = sc.config.cameras(40, size.width, size.height, 0)[:N_VIEWS]
    views = []
    for i, cam in enumerate(cams):
        r = render_view(world, cam, RenderSettings(samples_per_axis=2))
        views.append(View(f"{i:03d}.png", cam, image=r.image, depth=r.depth, sky=r.sky))
    return Scene(tuple(views), frozenset(llff_test_names([v.name for v in views])))


@pytest.fixture(scope="module")
def garden_few(garden_views, tmp_path_factory):
    """``garden_views`` exported as transforms.json without points (the images, depths and split are files)."""
    return write_scene(garden_views, tmp_path_factory.mktemp("posed") / "garden", format="transforms")


@pytest.fixture
def cache(tmp_path, monkeypatch):
    """Every test gets its own user cache (never the real one)."""
    folder = tmp_path / "user-cache"
    monkeypatch.setenv("NIMBUS_CACHE", str(folder))
    return folder


def _snapshot(folder):
    return {p.relative_to(folder): (p.stat().st_size, p.stat().st_mtime_ns) for p in folder.rglob("*")}


def _depth_error(points, views):
    """Per point, the smallest relative difference between its z-depth and the depth map, over the views it falls in."""
    best = np.full(len(points), np.inf)
    for v in views:
        uv, z = v.camera.project(points)
        u = np.floor(uv).astype(int)
        ok = (z > 0) & (u[:, 0] >= 0) & (u[:, 0] < v.camera.width) & (u[:, 1] >= 0) & (u[:, 1] < v.camera.height)
        true = v.load_depth()[u[ok, 1], u[ok, 0]]
        err = np.full(len(points), np.inf)
        err[ok] = np.abs(z[ok] - true) / true
        best = np.minimum(best, err)
    return best


def test_triangulation_with_known_poses_lands_on_the_true_surfaces(garden_few, cache):
    before = _snapshot(garden_few)
    scene = load_scene(garden_few)
    assert scene.source_format == "transforms" and len(scene.points) == 0
    views = scene.train_views
    tri = triangulate_posed(views)
    assert len(tri.points) >= 200, tri.info  # about 420 from six 240 x 180 views
    err = _depth_error(tri.points, views)
    assert np.median(err) < 0.01 and np.mean(err < 0.02) > 0.75, np.percentile(err, [50, 75, 90])
    assert (tri.errors < 4.0).all() and (tri.track_lengths >= 2).all()
    assert tri.colors.dtype == np.uint8 and tri.colors.std() > 10  # coloured from the photos, not one grey
    assert tri.info["views"] == 6 and tri.info["pairs"] == 15 and not tri.info["reused"]
    # Cached by content in the user cache, and nothing written into the scene folder.
    assert [p.name for p in (cache / "triangulated").iterdir()] == [f"{tri.info['key']}.npz"]
    assert _snapshot(garden_few) == before
    again = triangulate_posed(views)
    assert again.info["reused"] and again.info["key"] == tri.info["key"]
    np.testing.assert_array_equal(again.points, tri.points)
    np.testing.assert_array_equal(again.colors, tri.colors)
    # Other poses are another entry: a camera moved by 1 cm changes the key.
    moved = [dataclasses.replace(views[0], camera=views[0].camera.with_pose(views[0].camera.R,
                                                                            views[0].camera.t + [0.01, 0, 0])),
             *views[1:]]
    assert triangulation_key(moved, TriangulationConfig()) != tri.info["key"]
    # The in-memory views (the same images as arrays) triangulate to the same points, under their own key.
    memory = triangulate_posed([dataclasses.replace(v, image=v.load_image(), image_path=None) for v in views])
    assert not memory.info["reused"]
    np.testing.assert_allclose(memory.points, tri.points, atol=1e-9)


def test_pose_pairs_pick_overlapping_neighbours():
    """Beyond the exhaustive limit each view is matched with its nearest by pose: on an orbit, its neighbours."""
    cams = get_scene("garden").config.cameras(40, 64, 48, 0)
    pairs = pose_neighbour_pairs([View(f"{i:03d}.png", c) for i, c in enumerate(cams)], 4)
    assert {min(j - i, 40 - (j - i)) for i, j in pairs} == {1, 2} and len(pairs) == 80


def test_points_less_capture_trains_from_triangulated_points(garden_few, cache, caplog, tmp_path, monkeypatch):
    import nimbus.train.init_points as init_points

    scene = load_scene(garden_few)
    config = dataclasses.replace(preset("tiny"), iterations=2, init_densify=0)  # densified below
    with caplog.at_level(logging.WARNING, logger="nimbus.train.init_points"):
        # Six small views give about 420 points: fewer than the threshold, so random points about the focus.
        low = Runner("3dgs", scene, config, tmp_path / "low", progress=False)
        monkeypatch.setattr(init_points, "MIN_TRIANGULATED_POINTS", 100)
        runner = Runner("3dgs", scene, config, tmp_path / "run", progress=False)
    rec = low.init_points
    n = rec["triangulation"]["points"]
    assert rec["source"] == "focus" and n < MIN_TRIANGULATED_POINTS and rec["points"] == config.init_random_points
    assert len(low.scene.points) == 0  # random points are not measurements: not the scene's points
    assert runner.init_points["source"] == "triangulated" and runner.init_points["points"] == n
    assert runner.init_points["triangulation"]["reused"]  # the first runner made the cache entry
    assert len(runner.scene.points) == n == runner.method.num_gaussians
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 2 and all(line.startswith("init: the scene has no sparse points") for line in lines)
    assert f"triangulation found {n} points in 6 posed training views (< {MIN_TRIANGULATED_POINTS})" in lines[0]
    assert "random points in a ball of radius" in lines[0]
    assert f"triangulated {n} points from 6 posed training views" in lines[1] and str(cache) in lines[1]
    results = runner.run()
    assert results["init_points"] == runner.init_points
    saved = json.loads((tmp_path / "run" / "results.json").read_text())
    assert saved["init_points"]["source"] == "triangulated"
    log = [json.loads(line) for line in (tmp_path / "run" / "train_log.jsonl").read_text().splitlines()]
    assert log[0]["event"] == "init_points" and log[0]["source"] == "triangulated"
    # Switched off: straight to random points, and no triangulation is attempted.
    off = Runner("3dgs", scene, dataclasses.replace(config, init_triangulate=False), tmp_path / "off", progress=False)
    assert off.init_points["triangulation"] == {"skipped": "triangulation is off (init_triangulate=false)"}
    # Densified (by default): the triangulated points and pixels of the training views, said and recorded.
    assert preset("tiny").init_densify > 0 and preset("fast").init_densify > 0
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="nimbus.train.init_points"):
        dense = Runner("3dgs", scene, dataclasses.replace(config, init_densify=600), tmp_path / "dense", progress=False)
    rec = dense.init_points
    assert rec["source"] == "triangulated" and rec["triangulation"]["points"] == n
    assert rec["points"] == n + rec["densify"]["samples"] == len(dense.scene.points) == dense.method.num_gaussians
    assert rec["densify"]["samples"] + rec["densify"]["dropped"] == 600 and rec["densify"]["far"] > 0
    [line] = [r.getMessage() for r in caplog.records]
    assert f"densified with {rec['densify']['samples']} pixels" in line and "init_densify=600" in line


def test_points_less_tiny_garden_starts_about_the_subject(tmp_path, cache, caplog):
    full = render_builtin("garden", "tiny")
    target = np.asarray(get_scene("garden").config.target)
    with_points = load_scene(write_scene(full, tmp_path / "with", format="transforms"))
    bare = dataclasses.replace(full, points=np.zeros((0, 3)), colors=np.zeros((0, 3), np.uint8))
    without = load_scene(write_scene(bare, tmp_path / "without", format="transforms"))
    assert len(with_points.points) == len(full.points) > 0 and len(without.points) == 0
    config = dataclasses.replace(preset("tiny"), iterations=2)
    with caplog.at_level(logging.WARNING, logger="nimbus.train.init_points"):
        given = Runner("3dgs", with_points, config, tmp_path / "a", progress=False)
        assert caplog.records == []  # a scene with points starts from them, silently
        runner = Runner("3dgs", without, config, tmp_path / "b", progress=False)
    assert given.init_points == {"source": "scene", "points": len(full.points)}
    rec = runner.init_points
    assert rec["source"] == "focus" and "too small to triangulate" in rec["triangulation"]["skipped"]
    assert not cache.exists()  # nothing was triangulated, so nothing was cached
    np.testing.assert_allclose(rec["random"]["center"], target, atol=0.1)
    means = runner.gaussians().means.detach().double().numpy()  # world coordinates
    centroid = without.camera_centers.mean(0)
    assert np.linalg.norm(np.median(means, axis=0) - target) < 0.2
    assert np.linalg.norm(np.median(means, axis=0) - centroid) > 1.0
    [line] = [r.getMessage() for r in caplog.records]
    assert "too small to triangulate" in line and "about the cameras' focus" in line
    assert runner.run()["init_points"]["random"]["kind"] == "focus"


def _args(*argv):
    parser = argparse.ArgumentParser()
    sfm_command.add_arguments(parser)
    return parser.parse_args(argv)


def test_sfm_known_poses_command(garden_few, cache, tmp_path, capsys):
    before = _snapshot(garden_few)
    out = tmp_path / "with-points"
    assert run_cli(lambda _: sfm_command.run(_args("--known-poses", str(garden_few), "--out", str(out)))) == 0
    captured = capsys.readouterr()
    written = load_scene(out)
    n = len(written.points)
    assert n > 0 and f"triangulated {n} points from 6 posed training views" in captured.out
    assert f"fewer than {MIN_TRIANGULATED_POINTS} points" in captured.out  # and says what training will do
    assert "cached" in captured.err and str(cache) in captured.err
    assert written.test_names == {"000.png"} and written.names == load_scene(garden_few).names
    assert _snapshot(garden_few) == before
    # The trainer reads the same cache entry: the command warms it.
    assert triangulate_posed(load_scene(garden_few).train_views).info["reused"]
    # Without --out only the cache is written; the second time it is reused.
    assert run_cli(lambda _: sfm_command.run(_args("--known-poses", str(garden_few)))) == 0
    assert "reused the cached triangulation" in capsys.readouterr().err


@pytest.mark.parametrize("argv, message", [
    (["PHOTOS", "--known-poses", "SCENE"], "not both"),
    (["--known-poses", "SCENE", "--fov", "60"], "--fov"),
    ([], "give PHOTOS_DIR and --out"),
])
def test_sfm_known_poses_usage_errors(argv, message, garden_few, capsys):
    argv = [str(garden_few) if a == "SCENE" else a for a in argv]
    assert run_cli(lambda _: sfm_command.run(_args(*argv))) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and message in err and err.count("\n") == 1


def test_sfm_known_poses_refuses_images_too_small(tmp_path, cache, capsys):
    tiny = render_builtin("garden", "tiny")
    bare = write_scene(dataclasses.replace(tiny, points=np.zeros((0, 3)), colors=np.zeros((0, 3), np.uint8)),
                       tmp_path / "tiny")
    assert run_cli(lambda _: sfm_command.run(_args("--known-poses", str(bare)))) == 2
    assert "too small to triangulate" in capsys.readouterr().err and not cache.exists()


def _foreground_points(views, max_depth, step=7):
    """Stand-ins for triangulated points: every ``step``-th pixel of each view nearer than ``max_depth``, on the
    surface."""
    pts, cols = [], []
    for v in views:
        cam, depth, img = v.camera, v.load_depth(), v.load_image()
        vv, uu = np.mgrid[step // 2:cam.height:step, step // 2:cam.width:step]
        z = depth[vv, uu]
        ok = np.isfinite(z) & (z < max_depth)
        uv = np.stack([uu[ok] + 0.5, vv[ok] + 0.5], 1)
        rays = np.stack([(uv[:, 0] - cam.cx) / cam.fx, (uv[:, 1] - cam.cy) / cam.fy, np.ones(len(uv))], 1)
        pts.append((rays * z[ok][:, None] - cam.t) @ cam.R)
        cols.append((img[vv[ok], uu[ok]] * 255).astype(np.uint8))
    return np.concatenate(pts), np.concatenate(cols)


def test_densified_cloud_covers_the_backdrop_and_is_deterministic(garden_views):
    from nimbus.data.densify import DensifyConfig, densify_points

    views = garden_views.train_views[:3]
    depths = np.concatenate([v.load_depth().ravel() for v in views])
    max_depth = float(np.percentile(depths[np.isfinite(depths)], 60))  # SIFT-like: nothing on the far 40 %
    pts, cols = _foreground_points(views, max_depth)
    config = DensifyConfig(samples=1500, seed=3, sweep=False)  # the rules without measurement (the sweep: below)
    dense, dense_cols, info = densify_points(views, pts, cols, config)
    np.testing.assert_array_equal(dense[:len(pts)], pts)  # the triangulated points come first, unchanged
    added = dense[len(pts):]
    assert len(added) == info["samples"] == info["near"] + info["far"] and info["samples"] + info["dropped"] == 1500
    assert info["far"] > 200 and info["near"] > 200 and info["swept"] == 0
    # The backdrop is covered: points beyond every triangulated depth, along rays of far pixels.
    z_tri = np.concatenate([v.camera.project(pts)[1] for v in views[:1]])
    uv, z = views[0].camera.project(added)
    beyond = z > z_tri[z_tri > 0].max()
    assert beyond.sum() > 50
    u = np.floor(uv[beyond]).astype(int)
    inside = (u[:, 0] >= 0) & (u[:, 0] < views[0].camera.width) & (u[:, 1] >= 0) & (u[:, 1] < views[0].camera.height)
    true = views[0].load_depth()[u[inside, 1], u[inside, 0]]
    assert np.mean(~np.isfinite(true) | (true > max_depth)) > 0.9  # far points sit on far pixels (or the sky)
    # Near samples take the depth of the surface about them.
    err = _depth_error(added[np.linalg.norm(added - views[0].camera.center, axis=1) < max_depth], views)
    assert np.median(err) < 0.05
    # Coloured from the photos, and the same seed gives the same cloud; another seed another.
    assert dense_cols.dtype == np.uint8 and dense_cols[len(pts):].std() > 10
    again = densify_points(views, pts, cols, config)
    np.testing.assert_array_equal(again[0], dense)
    np.testing.assert_array_equal(again[1], dense_cols)
    with pytest.raises(NimbusError, match="set init_densify to at most"):  # more than the views' pixels
        densify_points(views, pts, cols, dataclasses.replace(config, samples=10**9))
    other = densify_points(views, pts, cols, dataclasses.replace(config, seed=4))[0]
    assert other.shape[1] == 3 and not np.array_equal(other[len(pts):len(pts) + 100], added[:100])


def test_swept_depths_are_measured_and_replace_guesses(garden_views):
    """The plane sweep measures sample depths on the garden's photos close to the true depth, and densifying with it
    keeps samples the rules alone drop (depth edges) or put on the guessed backdrop."""
    from nimbus.data.densify import DensifyConfig, densify_points
    from nimbus.data.sweep import sweep_depths

    views = garden_views.train_views[:3]
    cams, imgs = [v.camera for v in views], [v.load_image() for v in views]
    rng = np.random.default_rng(0)
    uv = rng.uniform([4, 4], [cams[1].width - 4, cams[1].height - 4], (400, 2))
    z = sweep_depths(cams, imgs, 1, uv, near=0.5, far=500.0)
    true = views[1].load_depth()[uv[:, 1].astype(int), uv[:, 0].astype(int)]
    measured = np.isfinite(z)
    err = np.abs(z[measured] / true[measured] - 1)
    # Two neighbours only (a scene has more): 48 % measured, median error 2.2 %, 79 % within 10 % when written.
    assert measured.mean() > 0.3 and np.median(err) < 0.03 and np.mean(err < 0.1) > 0.7

    depths = np.concatenate([v.load_depth().ravel() for v in views])
    max_depth = float(np.percentile(depths[np.isfinite(depths)], 60))
    pts, cols = _foreground_points(views, max_depth)
    guessed, _, g_info = densify_points(views, pts, cols, DensifyConfig(samples=1500, seed=3, sweep=False))
    swept, _, s_info = densify_points(views, pts, cols, DensifyConfig(samples=1500, seed=3))
    assert s_info["swept"] > 300 and s_info["samples"] == s_info["swept"] + s_info["near"] + s_info["far"]
    assert s_info["samples"] + s_info["dropped"] == 1500 and s_info["dropped"] < g_info["dropped"]
    assert s_info["far"] < g_info["far"] and s_info["config"]["sweep_config"]["steps"] == 64
    within = [np.mean(_depth_error(cloud[len(pts):], views) < 0.1) for cloud in (guessed, swept)]
    assert within[1] >= within[0]


def test_densify_leaves_scenes_with_points_alone(garden_views, cache):
    from nimbus.train.init_points import choose_init_points

    pts, cols = _foreground_points(garden_views.train_views[:2], 1e9, step=20)
    scene = dataclasses.replace(garden_views, points=pts, colors=cols)
    init = choose_init_points(scene, dataclasses.replace(preset("tiny"), init_densify=5000))
    assert init.scene is scene and init.record == {"source": "scene", "points": len(pts)} and init.line is None
    assert not cache.exists()
