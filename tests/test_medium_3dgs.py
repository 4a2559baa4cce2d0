"""medium-3dgs: the homogeneous-medium composite, its config, its state round trip, and what it recovers of a known
fog on a synthetic scene."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from nimbus.config_set import apply_overrides
from nimbus.data.camera import Camera
from nimbus.data.scene import Scene, View
from nimbus.errors import NimbusError
from nimbus.methods.base import Method
from nimbus.methods.medium_3dgs import (INIT_TRANSMISSION_RANGE, Medium3DGS, MediumConfig, compose_medium,
                                        estimate_medium, preset)
from nimbus.methods.registry import get_method
from nimbus.train.checkpoint import CHECKPOINT
from nimbus.train.runner import Runner

# The fog of the recovery test (per world unit; the wall scene's extent is about 2.5 units).
SIGMA_ATTN = (0.30, 0.22, 0.15)
SIGMA_BS = (0.20, 0.15, 0.10)
BACKSCATTER = (0.6, 0.7, 0.8)


def foggy_wall_scene(sigma_attn, sigma_bs, backscatter, n_views: int = 10, width: int = 40, height: int = 30,
                     seed: int = 0) -> Scene:
    """Cameras dollying towards a smoothly textured wall (z = 0, |x| <= 2, |y| <= 1.5) from 1.5 to 6 units, in a
    homogeneous fog; the sky around the wall is at infinite depth (it shows ``backscatter``).

    The fog is the model's own, applied with the true z-depth; the sparse points lie on the wall and are grey, so
    the initial colours carry no hint of the clean ones.
    """
    rng = np.random.default_rng(seed)
    phase = rng.uniform(0, 2 * np.pi, 3)
    freq = 0.4 * np.array([[0.9, 0.4], [0.5, 1.1], [1.3, -0.7]])  # cycles per unit, per channel
    sa, sb, b = (np.asarray(v, dtype=np.float64) for v in (sigma_attn, sigma_bs, backscatter))
    views = []
    for i, d in enumerate(np.linspace(1.5, 6.0, n_views)):
        off = rng.uniform(-0.5, 0.5, 2)
        cam = Camera.look_at((off[0], off[1], d), (0.3 * off[0], 0.3 * off[1], 0), (0, 1, 0), width, height, 50)
        dirs, origin = cam.world_rays(np.float64)
        t = -origin[2] / dirs[..., 2]
        hit = origin + t[..., None] * dirs
        wall = ((t > 0) & (np.abs(hit[..., 0]) <= 2) & (np.abs(hit[..., 1]) <= 1.5))[..., None]
        z = np.where(wall[..., 0], hit @ cam.R[2] + cam.t[2], 0.0)[..., None]
        clean = 0.35 + 0.25 * np.sin(2 * np.pi * (hit[..., :1] * freq[:, 0] + hit[..., 1:2] * freq[:, 1]) + phase)
        foggy = np.where(wall, clean * np.exp(-sa * z) + b * (1 - np.exp(-sb * z)), b)
        views.append(View(f"{i:03d}.png", cam, image=foggy.astype(np.float32)))
    xs, ys = np.meshgrid(np.arange(-2, 2 + 1e-9, 0.1), np.arange(-1.5, 1.5 + 1e-9, 0.1))
    points = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], 1)
    return Scene(tuple(views), frozenset({views[-1].name}), points, np.full((len(points), 3), 128, np.uint8))


def _cfg(**kw) -> MediumConfig:
    # Lambertian scene: no view-dependent colour that could stand in for the distance-dependent fog.
    return apply_overrides(preset("tiny"), {"sh_degree": "0", **kw})


# --- the composite ---------------------------------------------------------------------------------------------
def test_compose_is_the_model_for_covered_pixels_and_the_backscatter_for_empty_ones():
    g = torch.Generator().manual_seed(0)
    J = torch.rand(4, 5, 3, generator=g, dtype=torch.float64)
    z = 0.5 + 3 * torch.rand(4, 5, generator=g, dtype=torch.float64)
    alpha = torch.rand(4, 5, generator=g, dtype=torch.float64)
    alpha[0, 0], alpha[0, 1] = 1.0, 0.0
    sa, sb = torch.tensor([0.3, 0.2, 0.1], dtype=torch.float64), torch.tensor([0.05, 0.1, 0.4], dtype=torch.float64)
    B = torch.tensor([0.6, 0.7, 0.8], dtype=torch.float64)
    # A surface of colour J at depth z covering alpha of the pixel, the rest at infinity (it shows B).
    out = compose_medium(alpha[..., None] * J, alpha * z, alpha, sa, sb, B)
    a = alpha[..., None]
    surface = J * torch.exp(-sa * z[..., None]) + B * (1 - torch.exp(-sb * z[..., None]))
    torch.testing.assert_close(out["degraded"], a * surface + (1 - a) * B)
    torch.testing.assert_close(out["degraded"][0, 1], B)  # nothing covered: the sky shows the backscatter
    torch.testing.assert_close(out["transmission"], a * torch.exp(-sa * z[..., None]))
    torch.testing.assert_close(out["backscatter"], B * (1 - a * torch.exp(-sb * z[..., None])))
    clear = compose_medium(J, z, torch.ones_like(z), torch.zeros(3, dtype=torch.float64),
                           torch.zeros(3, dtype=torch.float64), B)
    torch.testing.assert_close(clear["degraded"], J)  # no medium: the clean image


# --- config, registry and protocol -----------------------------------------------------------------------------
def test_config_is_settable_and_checked():
    c = apply_overrides(preset("fast"), {"lr_medium": "0.02", "init_sigma_attn": "0.3", "init_backscatter": "0.5,0.6,0.7",
                                         "medium_from": "100"})
    assert c.lr_medium == 0.02 and c.init_sigma_attn == 0.3 and c.init_backscatter == (0.5, 0.6, 0.7)
    assert apply_overrides(c, {"iterations": "6000"}).medium_from == 200  # the warm-up stretches with the run
    assert apply_overrides(c, {"medium_from": "0", "iterations": "6000"}).medium_from == 0  # "no warm-up" stays so
    assert apply_overrides(c.with_changes({"medium_from": 0}), {"iterations": "6000"}).medium_from == 0
    assert c.medium_init == "data" and apply_overrides(c, {"medium_init": "fixed"}).medium_init == "fixed"
    for bad in ({"init_sigma_attn": "0"}, {"init_backscatter": "1"}, {"lr_medium": "-1"}, {"medium_from": "-2"},
                {"medium_init": "dcp"}):
        with pytest.raises(NimbusError, match="--set"):
            apply_overrides(c, bad)
    spec = get_method("medium-3dgs")
    assert spec.load() is Medium3DGS and isinstance(spec.preset("tiny"), MediumConfig)
    assert spec.preset("tiny").iterations == preset("tiny").iterations


# --- the data-driven initial medium ----------------------------------------------------------------------------
def _hazy_views(sigma: float, depth: float, airlight, n: int = 3, sky_rows: int = 8, size=(40, 48), seed: int = 0):
    """Views of a surface at one z-depth in a homogeneous medium, a sky band on top (it shows the airlight); every
    clean pixel has a zero channel (the dark-channel prior holds exactly), and sparse points at that depth."""
    rng = np.random.default_rng(seed)
    h, w = size
    b = np.asarray(airlight, np.float32)
    t = np.exp(-sigma * depth)
    images, cameras = [], []
    for i in range(n):
        clean = rng.uniform(0.2, 1.0, (h, w, 3)).astype(np.float32)
        clean[np.arange(h)[:, None], np.arange(w)[None, :], rng.integers(0, 3, (h, w))] = 0.0
        img = clean * t + b * (1 - t)
        img[:sky_rows] = b
        images.append(torch.from_numpy(img))
        cameras.append(Camera.look_at((0.2 * i, 0.0, depth), (0.2 * i, 0.0, 0.0), (0, 1, 0), w, h, 60))
    xs, ys = np.meshgrid(np.linspace(-0.3, 0.5, 9), np.linspace(-0.2, 0.2, 5))
    points = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], 1)
    return images, cameras, points


def test_estimate_medium_recovers_a_known_medium_where_the_dark_channel_prior_holds():
    images, cameras, points = _hazy_views(sigma=0.4, depth=2.5, airlight=(0.6, 0.7, 0.8))
    est = estimate_medium(images, cameras, points)
    # T = exp(-1) over the surface (most pixels), the points at z = 2.5, B from the sky of any view.
    assert est.transmission == pytest.approx(np.exp(-1.0), abs=1e-4)
    assert est.depth == pytest.approx(2.5, rel=1e-6) and est.points_used == 3 * 45
    assert est.sigma == pytest.approx(0.4, rel=1e-4)
    np.testing.assert_allclose(est.backscatter, (0.6, 0.7, 0.8), atol=1e-6)
    # A view without sky does not pull B down to its brightest surface: the capture's airlight is the brightest.
    skyless, _, _ = _hazy_views(sigma=0.4, depth=2.5, airlight=(0.6, 0.7, 0.8), sky_rows=0, seed=1)
    mixed = estimate_medium(skyless + images[:1], cameras[:3] + cameras[:1], points)
    np.testing.assert_allclose(mixed.backscatter, (0.6, 0.7, 0.8), atol=1e-6)


def test_estimate_medium_bounds_a_clear_capture_and_needs_points():
    images, cameras, points = _hazy_views(sigma=0.0, depth=2.0, airlight=(0.9, 0.9, 0.9))
    est = estimate_medium(images, cameras, points)
    # No veil: T = 1 is held at the range's top, so sigma is small and positive (softplus can start there).
    assert est.transmission == INIT_TRANSMISSION_RANGE[1]
    assert 0 < est.sigma == pytest.approx(-np.log(INIT_TRANSMISSION_RANGE[1]) / 2.0)
    assert estimate_medium(images, cameras, np.zeros((0, 3))) is None
    behind = points + np.array([0.0, 0.0, 10.0])  # every point behind every camera
    assert estimate_medium(images, cameras, behind) is None


def test_the_medium_starts_where_its_init_says(small_scene, tmp_path):
    data = Runner("medium-3dgs", small_scene, _cfg(iterations="4"), tmp_path / "data", progress=False,
                  device=torch.device("cpu"), checkpoints=False).method
    est = estimate_medium(data.train_images, [v.camera for v in data.train_views], data.scene.points)
    start = data.medium.values()
    torch.testing.assert_close(start["sigma_attn"], torch.full((3,), est.sigma))
    torch.testing.assert_close(start["sigma_bs"], torch.full((3,), est.sigma))
    torch.testing.assert_close(start["backscatter"], torch.tensor(est.backscatter))
    [(kind, info)] = data.setup_events()
    assert kind == "medium_init" and info["source"] == "data" and info["sigma"] == est.sigma
    fixed = Runner("medium-3dgs", small_scene, _cfg(iterations="4", medium_init="fixed", init_sigma_attn="0.3"),
                   tmp_path / "fixed", progress=False, device=torch.device("cpu"), checkpoints=False).method
    torch.testing.assert_close(fixed.medium.values()["sigma_attn"], torch.full((3,), 0.3))
    torch.testing.assert_close(fixed.medium.values()["backscatter"], torch.full((3,), 0.5))
    assert fixed.setup_events() == []
    bare = Scene(small_scene.views, small_scene.test_names, np.zeros((0, 3)), np.zeros((0, 3), np.uint8))
    none = Runner("medium-3dgs", bare, _cfg(iterations="4"), tmp_path / "bare", progress=False,
                  device=torch.device("cpu"), checkpoints=False).method
    [(kind, info)] = none.setup_events()
    assert kind == "medium_init" and info["source"] == "fixed"  # no points: the init_* fields, said in the log
    torch.testing.assert_close(none.medium.values()["sigma_attn"], torch.full((3,), 0.1))


@pytest.fixture(scope="module")
def small_scene():
    return foggy_wall_scene(SIGMA_ATTN, SIGMA_BS, BACKSCATTER, n_views=5, width=24, height=18)


def test_renders_the_clean_image_and_the_medium_extras_for_any_camera(small_scene, tmp_path):
    runner = Runner("medium-3dgs", small_scene, _cfg(iterations="4", far_from_medium="false"), tmp_path / "run",
                    progress=False, device=torch.device("cpu"))
    method = runner.method
    assert isinstance(method, Method)
    camera = method.train_views[0].camera
    with torch.no_grad():
        out = method.render(camera)
        black = method.render(camera, background=torch.zeros(3))
        white = method.render(camera, background=torch.ones(3))
    for key in ("rgb", "transmission", "backscatter", "degraded"):
        assert out[key].shape == (camera.height, camera.width, 3), key
    # The background enters the clean image only; the degraded composite puts the uncovered part at infinity.
    torch.testing.assert_close(white["rgb"] - black["rgb"], (1 - out["alpha"])[..., None].expand(-1, -1, 3))
    torch.testing.assert_close(white["degraded"], black["degraded"])
    torch.testing.assert_close(out["degraded"], black["rgb"] * out["transmission"] / out["alpha"].clamp_min(1e-6)[
        ..., None] + out["backscatter"], atol=1e-5, rtol=1e-4)


def test_the_clean_render_shows_the_mediums_far_light_where_no_gaussian_covers(small_scene, tmp_path):
    runner = Runner("medium-3dgs", small_scene, _cfg(iterations="4"), tmp_path / "run", progress=False,
                    device=torch.device("cpu"))
    method = runner.method
    assert method.cfg.far_from_medium
    camera = method.train_views[0].camera
    with torch.no_grad():
        black = method.render(camera, background=torch.zeros(3))
        white = method.render(camera, background=torch.ones(3))
        b = method.medium.values()["backscatter"]
        plain = Runner("medium-3dgs", small_scene, _cfg(iterations="4", far_from_medium="false"), tmp_path / "r2",
                       progress=False, device=torch.device("cpu")).method.render(camera, background=torch.zeros(3))
    assert (black["alpha"] < 0.5).any()  # some of the sky is uncovered in this view
    torch.testing.assert_close(white["rgb"], black["rgb"])  # the background colour is not used
    torch.testing.assert_close(black["rgb"], plain["rgb"] + (1 - black["alpha"])[..., None] * b)
    torch.testing.assert_close(black["degraded"], plain["degraded"])  # what training sees is the same


def test_state_dict_round_trip_and_resume(small_scene, tmp_path):
    cfg = _cfg(iterations="12", checkpoint_interval="6", log_interval="3", medium_from="4")
    full = Runner("medium-3dgs", small_scene, cfg, tmp_path / "full", seed=1, progress=False,
                  device=torch.device("cpu")).run()
    half = Runner("medium-3dgs", small_scene, cfg, tmp_path / "half", seed=1, progress=False,
                  device=torch.device("cpu"))
    step = half.method.train_iteration

    def interrupted(it):
        if it == 8:  # Ctrl-C after step 7 (past the warm-up), between checkpoints: the interrupt saves the state
            raise KeyboardInterrupt
        return step(it)

    half.method.train_iteration = interrupted
    with pytest.raises(KeyboardInterrupt):
        half.run()
    resumed = Runner("medium-3dgs", small_scene, cfg, tmp_path / "half", seed=1, progress=False,
                     device=torch.device("cpu"))
    resumed.load_checkpoint(tmp_path / "half" / CHECKPOINT)
    assert resumed.iteration == 7 and resumed.method._learning_medium
    out = resumed.run()
    assert out["psnr"] == full["psnr"] and out["medium"] == full["medium"]
    saved = json.loads((tmp_path / "full" / "results.json").read_text())["medium"]
    assert saved["sigma_attn"] != list(cfg.init_sigma_attn)  # the medium was learned
    # Reported per world unit: the training frame's value divided by its scale.
    np.testing.assert_allclose(np.array(saved["sigma_attn"]) * saved["frame_scale"], saved["sigma_attn_per_extent"])


# --- recovery of a known fog -----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def foggy_fit(tmp_path_factory):
    """900 iterations on the foggy wall, seed 0 (10 to 40 s on 2 cores, with the load).

    The colour learning rate is raised (0.0025 -> 0.02): the Gaussians start grey and must reach the clean colours,
    darker and more contrasted than the foggy ones, within a short run; at the 3DGS rate they cannot, and the
    medium then settles for much less fog (300 tiny-preset iterations: sigma_attn about 0.04 for 0.30).
    """
    scene = foggy_wall_scene(SIGMA_ATTN, SIGMA_BS, BACKSCATTER, seed=0)
    runner = Runner("medium-3dgs", scene, _cfg(iterations="900", lr_sh_dc="0.02"), tmp_path_factory.mktemp("fog"),
                    seed=0, progress=False, device=torch.device("cpu"), checkpoints=False)
    runner.train()
    return runner.method.medium_values()


@pytest.mark.slow
def test_recovers_a_known_fog_within_the_measured_tolerance(foggy_fit):
    """Measured (learned / true sigma per channel; B's largest error), the medium started from the views
    (``medium_init=data``: B exact from the sky, sigma grey 0.59 per extent unit, about 0.24 per world unit):

    ========  ===================  ===================  =======
    seed      sigma_attn           sigma_bs             B
    ========  ===================  ===================  =======
    0         1.16 1.23 1.26       1.12 1.15 1.23       0.001
    1         1.14 1.18 1.21       1.11 1.15 1.17       0.004
    2         1.11 1.16 1.23       1.10 1.15 1.21       0.004
    ========  ===================  ===================  =======

    From the old fixed start (sigma 0.1 per extent unit, B grey 0.5) the same runs gave 0.38 to 0.81 (attenuation),
    0.52 to 1.11 (backscatter) and B off by up to 0.119.  The asserted seed is 0.
    """
    np.testing.assert_allclose(foggy_fit["backscatter"], BACKSCATTER, atol=0.02)
    for key, truth in (("sigma_attn", SIGMA_ATTN), ("sigma_bs", SIGMA_BS)):
        ratio = np.array(foggy_fit[key]) / np.array(truth)
        assert np.all((ratio > 0.9) & (ratio < 1.45)), (key, ratio)


@pytest.fixture(scope="module")
def clear_fit(tmp_path_factory):
    """The same fit on the wall without fog (black sky)."""
    scene = foggy_wall_scene((0, 0, 0), (0, 0, 0), (0, 0, 0), seed=0)
    runner = Runner("medium-3dgs", scene, _cfg(), tmp_path_factory.mktemp("clear"), seed=0, progress=False,
                    device=torch.device("cpu"), checkpoints=False)
    runner.train()
    return runner.method.medium_values()


@pytest.mark.slow
def test_a_haze_free_scene_learns_no_backscatter(clear_fit):
    """The light the medium adds in front of the farthest view of the wall (6 units) stays near 0.

    Measured (seeds 0, 1, 2): sigma_bs 0.002 to 0.003 per unit, so B (1 - exp(-6 sigma_bs)) is 0.007 to 0.011;
    B itself stays near the start the views give (about 0.6: this grey-textured wall's dark channel is not dark,
    so the prior reads it as veiled), unidentifiable once sigma_bs is 0.
    """
    added = np.array(clear_fit["backscatter"]) * (1 - np.exp(-6.0 * np.array(clear_fit["sigma_bs"])))
    assert added.max() < 0.03, added
    assert max(clear_fit["sigma_bs"]) < 0.01


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="measured: on the haze-free wall sigma_attn settles at 0.086 to 0.102 per unit "
                   "(seeds 0-2) from the 0.06 the views give (the grey texture's dark channel reads as a veil); the "
                   "Gaussians' colours brighten to match, so the clean render is brighter than the input")
def test_a_haze_free_scene_keeps_the_attenuation_near_zero(clear_fit):
    assert max(clear_fit["sigma_attn"]) < 0.01
