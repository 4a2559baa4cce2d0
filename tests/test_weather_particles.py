"""Rain and snow: per-view reproducible particles, depth awareness, compositing orders, extremes."""

import numpy as np
import pytest

from nimbus.data.camera import Camera
from nimbus.data.scene import Scene, View
from nimbus.errors import NimbusError
from weather_synth.compose import ComposeConfig, compose, srgb_decode, srgb_encode
from weather_synth.config import SynthConfig, protocol_config
from weather_synth.haze import HazeConfig, HazeModel
from weather_synth.particles import ParticleSlice, fall_direction, image_fall_angle, motion_kernel
from weather_synth.rain import MAX_RAIN_AMOUNT, RainConfig, rain_preset, render_rain
from weather_synth.seeds import rng_for
from weather_synth.settings import parse_setting
from weather_synth.snow import MAX_SNOW_AMOUNT, SnowConfig, render_snow, snow_preset
from weather_synth.synth import Synthesizer

W, H = 96, 72
DOWN = np.array([0.0, 0.0, -1.0])


def camera(eye=(0.0, -6.0, 1.0), target=(0.0, 0.0, 1.0)):
    return Camera.look_at(eye, target, (0, 0, 1), W, H, 60)


def scene(n=3, depth=5.0):
    rng = np.random.default_rng(0)
    views = [View(f"{i:03d}.png", camera(eye=(6 * np.sin(i), -6 * np.cos(i), 1.0)),
                  image=rng.random((H, W, 3), dtype=np.float32),
                  depth=np.full((H, W), depth, np.float32)) for i in range(n)]
    return Scene(tuple(views))


def rain(seed=0, name="000.png", config=RainConfig(), **kw):
    return render_rain(camera(), rng_for(seed, "rain", name), config, DOWN, **kw)


def snow(seed=0, name="000.png", config=SnowConfig(), **kw):
    return render_snow(camera(), rng_for(seed, "snow", name), config, DOWN, **kw)


def total(slices):
    return sum(s.layer for s in slices)


def test_particles_are_reproducible_per_view_and_independent_between_views():
    for render in (rain, snow):
        a, again, b = render(name="000.png"), render(name="000.png"), render(name="001.png")
        np.testing.assert_array_equal(total(a.slices), total(again.slices))
        assert a.info == again.info
        assert not np.allclose(total(a.slices), total(b.slices))
        # Weakly correlated: particles do not repeat from view to view.
        corr = np.corrcoef(total(a.slices).ravel(), total(b.slices).ravel())[0, 1]
        assert abs(corr) < 0.2
        assert not np.allclose(total(render(seed=1).slices), total(a.slices))


def test_a_views_rain_is_the_same_in_every_setting():
    syn = Synthesizer(scene(), protocol_config(seed=3))
    v = syn.scene.views[1]
    r = syn.degrade(v, parse_setting("R"))
    hr = syn.degrade(v, parse_setting("H+R"))
    hrs = syn.degrade(v, parse_setting("H+R+S"))
    np.testing.assert_array_equal(r.layers["rain"], hr.layers["rain"])
    np.testing.assert_array_equal(r.layers["rain"], hrs.layers["rain"])
    np.testing.assert_array_equal(hr.layers["transmission"], hrs.layers["transmission"])
    assert r.info["seeds"]["rain"] == hrs.info["seeds"]["rain"]


def test_rain_layers_look_like_streaks_along_the_fall_direction():
    res = rain(config=rain_preset("heavy"))
    assert [l["name"] for l in res.info["layers"]] == ["dense", "middle", "sparse"]
    R = total(res.slices)
    assert 0 < R.max() <= 0.45 * 1.2 * 3 + 1e-6
    # Streaks are vertical for an upright camera and straight-down rain: far more vertical than horizontal structure.
    dv = np.abs(np.diff(R, axis=0)).mean()
    du = np.abs(np.diff(R, axis=1)).mean()
    assert du > 2 * dv
    assert res.info["angle_deg"] == pytest.approx(90.0, abs=1e-6)


def test_fall_angle_follows_the_camera_roll_and_wind():
    cam = camera()
    rolled = Camera(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy,
                    np.array([[0, 1, 0], [-1, 0, 0], [0, 0, 1.0]]) @ cam.R, [0, 0, 0])
    assert image_fall_angle(cam, DOWN) == pytest.approx(90.0)
    assert abs(image_fall_angle(rolled, DOWN)) in (pytest.approx(0.0, abs=1e-6), pytest.approx(180.0))
    tilted = fall_direction((0, 0, 1), 20.0, 90.0)  # wind across the view
    assert np.degrees(np.arccos(-tilted[2])) == pytest.approx(20.0)
    assert image_fall_angle(cam, tilted) != pytest.approx(90.0)


def test_motion_kernel_is_normalised_and_oriented():
    k = motion_kernel(15, 0.0)
    assert k.sum() == pytest.approx(1.0) and k.shape[0] >= 15
    rows = np.nonzero(k.sum(1) > 1e-3)[0]
    assert len(rows) <= 2  # horizontal line
    kv = motion_kernel(15, 90.0)
    assert len(np.nonzero(kv.sum(0) > 1e-3)[0]) <= 2


def test_snow_has_small_many_and_large_few_flakes():
    res = snow(config=snow_preset("heavy"))
    classes = {c["name"]: c for c in res.info["classes"]}
    assert set(classes) >= {"small", "large"}
    n_small = sum(s["count"] for s in classes["small"]["slices"])
    n_large = sum(s["count"] for s in classes["large"]["slices"])
    assert n_small > 5 * n_large > 0
    alpha = 1 - np.prod([1 - s.layer for s in res.slices], axis=0)
    assert alpha.min() >= 0 and alpha.max() <= 1 and alpha.max() > 0.5


@pytest.mark.parametrize("kind", ["rain", "snow"])
def test_depth_aware_particles_hide_behind_surfaces_and_shrink_with_distance(kind):
    render = rain if kind == "rain" else snow
    config = RainConfig(slices=3) if kind == "rain" else SnowConfig(slices=3)
    free = render(config=config, surface_depth=np.full((H, W), np.inf, np.float32), depth_scale=5.0, depth_aware=True)
    wall = render(config=config, surface_depth=np.full((H, W), 1e-3, np.float32), depth_scale=5.0, depth_aware=True)
    assert total(free.slices).max() > 0
    assert total(wall.slices).max() == 0  # a surface right at the lens hides every particle
    half = np.full((H, W), np.inf, np.float32)
    half[:, : W // 2] = 1e-3
    part = render(config=config, surface_depth=half, depth_scale=5.0, depth_aware=True)
    assert total(part.slices)[:, : W // 2].max() == 0 and total(part.slices)[:, W // 2:].max() > 0
    # Projected size ~ 1 / z: within a layer / class, nearer slices have longer streaks.
    groups = free.info["layers"] if kind == "rain" else free.info["classes"]
    for g in groups:
        zs = [s["z"] for s in g["slices"]]
        lengths = [s["length_px"] if kind == "rain" else s["streak_px"] for s in g["slices"]]
        order = np.argsort(zs)
        assert all(np.diff(np.asarray(lengths)[order]) <= 1e-9)
        # Exactly ~ 1 / z (snow streaks are clamped to >= 1 px, so only check rain).
        if kind == "rain":
            np.testing.assert_allclose(np.asarray(lengths) * np.asarray(zs), lengths[0] * zs[0], rtol=1e-6)


# --- compositing ----------------------------------------------------------------------------
def layers_for_compose(seed=0):
    rng = np.random.default_rng(seed)
    J = rng.random((H, W, 3), dtype=np.float32)
    R = np.where(rng.random((H, W)) < 0.1, 0.3, 0).astype(np.float32)
    S = np.where(rng.random((H, W)) < 0.1, 0.8, 0).astype(np.float32)
    z = rng.uniform(1, 10, (H, W)).astype(np.float32)
    return J, R, S, z


def test_onerestore_order_is_the_papers_formula():
    J, R, S, z = layers_for_compose()
    haze = HazeModel(HazeConfig(beta=1.3, airlight=(0.7,) * 3), 0, 1.0).view("a", camera(), z)
    out = compose(J, haze, [ParticleSlice("rain", R, 0.0), ParticleSlice("snow", S, 0.0)])
    t = haze.transmission[..., None]
    expected = np.clip(((J + R[..., None]) * (1 - S[..., None]) + S[..., None]) * t + 0.7 * (1 - t), 0, 1)
    np.testing.assert_allclose(out, expected, atol=1e-6)


def test_physical_order_attenuates_particles_over_their_own_distance():
    J, R, S, z = layers_for_compose(1)
    cam = camera()
    beta, A, zr, zs = 0.2, 0.6, 2.0, 4.0
    haze = HazeModel(HazeConfig(mode="homogeneous", beta=beta, airlight=(A,) * 3), 0, 1.0).view("a", cam, z)
    norm = np.linalg.norm(cam.pixel_rays(np.float64), axis=-1)
    Tr, Ts = np.exp(-beta * zr * norm)[..., None], np.exp(-beta * zs * norm)[..., None]
    out = compose(J, haze, [ParticleSlice("rain", R, zr), ParticleSlice("snow", S, zs)],
                  ComposeConfig(order="physical"))
    t = haze.transmission[..., None]
    hazy = J * t + A * (1 - t)
    # Snow (farther) first, then rain in front of it.
    expected = hazy * (1 - S[..., None]) + S[..., None] * (Ts + A * (1 - Ts)) + R[..., None] * Tr
    np.testing.assert_allclose(out, np.clip(expected, 0, 1), atol=1e-5)
    # A nearer particle is brighter (less veiled) than the same particle farther away.
    near = compose(J, haze, [ParticleSlice("rain", R, 0.5)], ComposeConfig(order="physical"))
    far = compose(J, haze, [ParticleSlice("rain", R, 8.0)], ComposeConfig(order="physical"))
    assert near[R > 0].mean() > far[R > 0].mean()


def test_linear_light_compositing_decodes_and_reencodes():
    J, R, S, z = layers_for_compose(2)
    out = compose(J, None, [ParticleSlice("rain", R, 0.0)], ComposeConfig(linear=True))
    expected = np.clip(srgb_encode(np.clip(srgb_decode(J) + R[..., None], 0, 1)), 0, 1)
    np.testing.assert_allclose(out, expected, atol=1e-5)
    np.testing.assert_allclose(srgb_decode(np.array([0.5]))[0], ((0.5 + 0.055) / 1.055) ** 2.4, rtol=1e-5)


# --- extremes ------------------------------------------------------------------------------------
@pytest.mark.parametrize("setting", ["R", "S", "R+S"])
def test_zero_intensity_particles_leave_the_image_unchanged(setting):
    sc = scene(2)
    cfg = SynthConfig(rain=rain_preset("medium", amount=0.0), snow=snow_preset("heavy", amount=0.0))
    res = Synthesizer(sc, cfg).degrade(sc.views[0], parse_setting(setting))
    np.testing.assert_array_equal(res.image, sc.views[0].image)
    assert res.particle_coverage == 0.0


@pytest.mark.parametrize("fill", [0.0, 1.0])
def test_huge_intensities_saturate_without_nan(fill):
    sc = scene(1)
    sc = sc.with_views([View("000.png", sc.views[0].camera, image=np.full((H, W, 3), fill, np.float32),
                             depth=sc.views[0].depth)])
    # The largest accepted amounts (issue 35 bounds them: beyond, nothing changes but the clipping).
    cfg = SynthConfig(rain=rain_preset("heavy", amount=MAX_RAIN_AMOUNT), snow=snow_preset("heavy", amount=MAX_SNOW_AMOUNT))
    for setting in ("R", "S", "H+R+S"):
        out = Synthesizer(sc, cfg).degrade(sc.views[0], parse_setting(setting)).image
        assert np.isfinite(out).all() and out.min() >= 0 and out.max() <= 1
    snowed = Synthesizer(sc, cfg).degrade(sc.views[0], parse_setting("S")).image
    assert snowed.mean() > 0.95  # buried in white


def test_bad_particle_parameters_are_refused():
    with pytest.raises(NimbusError, match="unknown rain intensity 'drizzle'"):
        rain_preset("drizzle")
    with pytest.raises(NimbusError, match="unknown snow intensity"):
        snow_preset("blizzard!")
    with pytest.raises(NimbusError, match="rain amount must be"):
        RainConfig(amount=-1)
    with pytest.raises(NimbusError, match="snow amount must be"):
        SnowConfig(amount=float("nan"))
    with pytest.raises(NimbusError, match="snow colour"):
        SnowConfig(color=2.0)
