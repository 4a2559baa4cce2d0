"""Haze depth for scenes without depth maps: the recon source, its cache, auto, and the depth-consistency figure."""

import dataclasses
import json

import numpy as np
import pytest

from conftest import make_tiny_scene
from nimbus.data.camera import Camera
from nimbus.data.scene import Scene, View
from nimbus.errors import NimbusError
from nimbus.train import depth_recon
from weather_synth.cli import main as synth_main
from weather_synth.depth import DepthConfig, DepthSource, pick_depth_source
from weather_synth.depth_consistency import (depth_consistency, nearest_views, pair_consistency,
                                             scene_depth_consistency)

W, H = 48, 36


# --- closed form: views of the ground plane z = 0 --------------------------------------------------
def plane_depth(cam: Camera) -> np.ndarray:
    """Exact z-depth of the plane z = 0 seen by ``cam`` (inf where a ray misses it)."""
    d, o = cam.world_rays(np.float64)
    with np.errstate(divide="ignore"):
        s = -o[2] / d[..., 2]
    z = s * (d @ cam.R[2])
    return np.where(s > 0, z, np.inf).astype(np.float32)


def plane_cameras():
    a = Camera.look_at((0.0, -3.0, 3.0), (0.0, 0.0, 0.0), (0, 0, 1), W, H, 60)
    b = Camera.look_at((0.6, -3.0, 3.1), (0.2, 0.1, 0.0), (0, 0, 1), W, H, 60)
    return a, b


def test_exact_plane_depth_agrees_everywhere_it_is_seen_twice():
    a, b = plane_cameras()
    p = pair_consistency(a, plane_depth(a), b, plane_depth(b))
    assert p.agree > 0.7 * W * H and p.disagree == 0 and p.fraction == 1.0
    assert p.agree + p.outside + p.occluded + p.sky + p.disagree == W * H


def test_perturbed_depth_disagrees_farther_and_is_occluded_nearer():
    a, b = plane_cameras()
    za, zb = plane_depth(a), plane_depth(b)
    far = pair_consistency(a, za, b, zb * 1.2)  # b sees 20 % beyond where a's points are: they would be visible
    assert far.fraction == 0.0 and far.disagree > 0.7 * W * H
    near = pair_consistency(a, za, b, zb * 0.8)  # b sees something nearer: a's points are hidden, not checked
    assert near.fraction is None and near.occluded > 0.7 * W * H
    within = pair_consistency(a, za, b, zb * 1.03)  # inside the 5 % tolerance
    assert within.fraction == 1.0


def test_half_perturbed_depth_scores_the_share_of_pixels_landing_on_the_intact_half():
    a, b = plane_cameras()
    za, zb = plane_depth(a), plane_depth(b)
    zb_bad = zb.copy()
    zb_bad[:, W // 2:] *= 1.3
    got = pair_consistency(a, za, b, zb_bad).fraction
    # Closed form: a's pixels reprojected into b (plane points), and where they land.
    pts = np.concatenate([(za[..., None] * a.pixel_rays(np.float64)).reshape(-1, 3) - a.t]) @ a.R
    uv, z = b.project(pts)
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H) & (z > 0)
    expected = np.mean(uv[inside, 0] < W // 2)
    assert 0.2 < expected < 0.8
    assert abs(got - expected) < 0.03  # the 2 x 2 footprint decides the pixels on the seam


def test_sky_in_both_views_is_not_counted_and_sky_behind_a_surface_disagrees():
    a, b = plane_cameras()
    sky_a = np.full((H, W), np.inf, np.float32)
    p = pair_consistency(a, sky_a, b, np.full((H, W), np.inf, np.float32))
    assert p.sky > 0.7 * W * H and p.agree == p.disagree == 0 and p.fraction is None
    q = pair_consistency(a, plane_depth(a), b, np.full((H, W), np.inf, np.float32))  # b sees sky where a sees ground
    assert q.fraction == 0.0


def test_nearest_view_is_the_closest_camera_centre():
    cams = [Camera.look_at((x, -3.0, 1.0), (x, 0.0, 0.0), (0, 0, 1), W, H, 60) for x in (0.0, 0.5, 2.0, 2.2)]
    assert nearest_views(cams).tolist() == [1, 0, 3, 2]
    res = depth_consistency(cams, lambda i: plane_depth(cams[i]), ["a", "b", "c", "d"])
    assert res["mean"] == pytest.approx(1.0) and [v["neighbour"] for v in res["views"]] == ["b", "a", "d", "c"]


# --- auto -------------------------------------------------------------------------------------------
def test_auto_picks_the_best_available_source():
    with_depth = make_tiny_scene(n_views=3, depth=True)
    assert pick_depth_source(with_depth)[0] == "scene"
    bare = make_tiny_scene(n_views=3)
    assert pick_depth_source(bare, DepthConfig(model="m.onnx"))[0] == "onnx:m.onnx"
    source, reason = pick_depth_source(bare)
    assert source == "recon" and "no view has a depth map" in reason
    partial = bare.with_views([dataclasses.replace(bare.views[0], depth=with_depth.views[0].depth),
                               *bare.views[1:]])
    assert pick_depth_source(partial) == ("recon", "2 of 3 views have no depth map; no ONNX model configured "
                                                   "(depth.model), so a 3DGS fit to the views")
    two = make_tiny_scene(n_views=2)  # too few views to fit: the points, densified
    assert pick_depth_source(two)[0] == "sparse"
    nothing = Scene(two.views)  # no points either
    with pytest.raises(NimbusError, match="no depth for haze.*depths/<name>.npy"):
        pick_depth_source(nothing)


def test_auto_says_what_it_picked():
    lines = []
    src = DepthSource(make_tiny_scene(n_views=3, depth=True), DepthConfig("auto"), log=lines.append)
    assert src.kind == "scene" and lines == ["depth: auto picked scene (every view has a depth map)"]
    d = src.describe()
    assert d["source"] == "scene" and d["requested"] == "auto" and d["reason"] == "every view has a depth map"
    assert DepthSource(make_tiny_scene(n_views=3, depth=True), DepthConfig("scene"), log=None).describe().keys() \
        == {"source", "config"}


# --- recon ------------------------------------------------------------------------------------------
TINY_FIT = DepthConfig("recon", recon_iterations=6, recon_cache="none")


@pytest.mark.slow  # ~0.1 s of fitting, but ~5 s when it is the first test to load the compositing kernel
def test_recon_cache_is_reused_and_keyed_by_content(tmp_path, monkeypatch):
    scene = make_tiny_scene(n_views=3)
    fits = []
    real_fit = depth_recon.fit_recon_depth
    monkeypatch.setattr(depth_recon, "fit_recon_depth", lambda *a, **k: fits.append(1) or real_fit(*a, **k))
    config = dataclasses.replace(TINY_FIT, recon_cache=str(tmp_path / "cache"))
    first_log, second_log = [], []
    first = DepthSource(scene, config, log=first_log.append)
    second = DepthSource(scene, config, log=second_log.append)
    assert len(fits) == 1
    assert any("fitting 3DGS to 3 views" in line for line in first_log)
    assert any("using the cached fit" in line for line in second_log) and not any("fitting" in x for x in second_log)
    for v in scene.views:
        assert np.array_equal(first(v)[0], second(v)[0], equal_nan=True)
    assert first.describe() == second.describe()  # a cached run writes the same manifest
    assert len(list((tmp_path / "cache").glob("recon-*.npz"))) == 1
    assert not list((tmp_path / "cache").glob(".recon-fit.tmp-*"))  # the trainer's run folder is gone
    # Another image, or other settings: another key, a new fit.
    changed = scene.with_views([dataclasses.replace(scene.views[0], image=scene.views[0].image[::-1].copy()),
                                *scene.views[1:]])
    DepthSource(changed, config, log=None)
    DepthSource(scene, dataclasses.replace(config, recon_min_alpha=0.3), log=None)
    assert len(fits) == 3
    # A damaged cache file is refitted, not trusted.
    for f in (tmp_path / "cache").glob("recon-*.npz"):
        f.write_bytes(b"junk")
    DepthSource(scene, config, log=None)
    assert len(fits) == 4


def test_recon_refuses_too_few_views_and_bad_settings():
    with pytest.raises(NimbusError, match="needs at least 3"):
        DepthSource(make_tiny_scene(n_views=2), TINY_FIT, log=None)
    with pytest.raises(NimbusError, match="unknown preset"):
        DepthSource(make_tiny_scene(n_views=3), dataclasses.replace(TINY_FIT, recon_preset="huge"), log=None)


@pytest.mark.slow
def test_recon_depth_of_a_built_in_scene_is_finite_and_close_to_the_exact_depth():
    """garden tiny without its depth maps, 100 iterations: the rendered depth is finite on the surfaces and close
    to the exact depth (measured: median relative error 0.11, finite on >= 97 % of each view's surface pixels)."""
    from nimbus.data.builtin import render_builtin

    scene = render_builtin("garden", "tiny")
    bare = scene.with_views([dataclasses.replace(v, depth=None, depth_path=None) for v in scene.views])
    src = DepthSource(bare, dataclasses.replace(TINY_FIT, recon_iterations=100), log=None)
    rel = []
    for v in scene.views:
        exact, sky = v.load_depth(), v.load_sky()
        z, _ = src(v)
        assert np.all(np.isinf(z[sky]))  # the sky mask still puts the sky at infinity
        assert np.isfinite(z[~sky]).mean() > 0.9
        ok = ~sky & np.isfinite(z)
        rel.append(np.abs(z[ok] - exact[ok]) / exact[ok])
    assert np.median(np.concatenate(rel)) < 0.2


# --- the manifest and preview -------------------------------------------------------------------------
def cli(*argv) -> int:
    try:
        return synth_main([str(a) for a in argv]) or 0
    except SystemExit as e:
        return e.code


def test_degrade_auto_recon_writes_the_pick_and_the_figure_and_reuses_the_fit(tmp_path, capsys, monkeypatch):
    from nimbus.data.io import write_scene

    monkeypatch.setenv("NIMBUS_CACHE", str(tmp_path / "nimbus-cache"))
    scene_dir = write_scene(make_tiny_scene(n_views=4), tmp_path / "scene")
    out = tmp_path / "out"
    args = ["degrade", scene_dir, "--out", out, "--weather", "H,R", "--quiet", "--set", "depth.recon_iterations=6"]
    assert cli(*args) == 0
    err = capsys.readouterr().err
    assert "depth: auto picked recon (no view has a depth map" in err and "recon depth: fitting 3DGS" in err
    assert list((tmp_path / "nimbus-cache" / "depth").glob("recon-*.npz"))  # the default cache folder
    m = json.loads((out / "H" / "manifest.json").read_text())
    depth = m["scene"]["depth"]
    assert depth["source"] == "recon" and depth["requested"] == "auto" and "no view has a depth map" in depth["reason"]
    assert m["config"]["depth"]["source"] == "auto" and "recon_cache" not in depth["config"]
    cons = depth["consistency"]
    assert 0 <= cons["mean"] <= 1 and cons["tolerance"] == 0.05 and set(cons["views"]) == {f"{i:03d}.png"
                                                                                            for i in range(4)}
    assert cli(*args, "--overwrite") == 0
    err = capsys.readouterr().err
    assert "using the cached fit" in err and "fitting 3DGS" not in err
    assert json.loads((out / "H" / "manifest.json").read_text())["scene"]["depth"] == depth
    assert cli("preview", out, "--out", tmp_path / "sheet.png") == 0
    printed = capsys.readouterr().out
    assert f"depth: recon (picked by auto: no view has a depth map" in printed
    assert f"consistency {cons['mean']:.3f}" in printed


def test_manifest_figure_of_exact_depth(tmp_path):
    """Scene depth maps (exact on a plane) give a figure of 1 in the manifest."""
    from weather_synth.config import protocol_config
    from weather_synth.dataset import degrade_scene
    from weather_synth.settings import parse_weather

    cams = [Camera.look_at((x, -3.0, 3.0), (x, 0.0, 0.0), (0, 0, 1), W, H, 60) for x in (0.0, 0.3, 0.6)]
    rng = np.random.default_rng(0)
    views = tuple(View(f"{i}.png", c, image=rng.random((H, W, 3), dtype=np.float32), depth=plane_depth(c))
                  for i, c in enumerate(cams))
    scene = Scene(views)
    degrade_scene(scene, tmp_path / "out", parse_weather("H"), protocol_config(), progress=False)
    m = json.loads((tmp_path / "out" / "H" / "manifest.json").read_text())
    assert m["scene"]["depth"]["consistency"]["mean"] == 1.0
    assert scene_depth_consistency(scene, lambda v: v.load_depth())["mean"] == 1.0
