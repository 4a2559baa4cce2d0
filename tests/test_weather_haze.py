"""Haze against closed forms, the world-space medium's multi-view consistency, and the extremes."""

import numpy as np
import pytest

from nimbus.data.camera import Camera
from nimbus.errors import NimbusError
from weather_synth.compose import ComposeConfig, compose
from weather_synth.haze import (
    HazeConfig,
    HazeModel,
    apply_haze,
    homogeneous_transmission,
    onerestore_depth_map,
    onerestore_transmission,
)
from weather_synth.medium import HeightFogMedium, HomogeneousMedium, RayIntegrator, estimate_up, fractal_noise

W, H = 40, 30


def camera(eye=(0.0, -6.0, 1.5), target=(0.0, 0.0, 0.5), fov=70, w=W, h=H):
    return Camera.look_at(eye, target, (0, 0, 1), w, h, fov)


def ray_distance_brute(cam, z):
    """Ray distance from first principles: |z * K^-1 (u + 0.5, v + 0.5, 1)|."""
    u, v = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
    pix = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(cam.K).T
    return z * np.linalg.norm(pix, axis=-1)


def rng_image(seed=0):
    return np.random.default_rng(seed).random((H, W, 3), dtype=np.float32)


def physical(beta=None, **kw):
    return HazeModel(HazeConfig(mode="homogeneous", beta=beta, **kw), seed=0, depth_scale=5.0)


# --- closed forms -------------------------------------------------------------------------------
def test_homogeneous_transmission_is_exp_minus_beta_ray_distance():
    cam = camera()
    z = np.random.default_rng(1).uniform(0.5, 20, (H, W)).astype(np.float32)
    vh = physical(beta=0.13).view("a", cam, z)
    np.testing.assert_allclose(vh.transmission, np.exp(-0.13 * ray_distance_brute(cam, z)), rtol=1e-5)
    # Ray distance, not z: at equal z an image corner is farther than the centre, so hazier.
    flat = physical(beta=0.13).view("a", cam, np.full((H, W), 5.0, np.float32)).transmission
    assert flat[0, 0] < flat[H // 2, W // 2] - 1e-3


def test_visibility_gives_two_percent_contrast_at_v():
    vh = physical(visibility=8.0).view("a", camera(), np.full((H, W), 1.0, np.float32))
    assert vh.beta == pytest.approx(3.912 / 8.0)
    # A surface at ray distance V keeps 2 % of its contrast.
    assert float(np.exp(-vh.beta * 8.0)) == pytest.approx(0.02, rel=1e-3)
    # Default: visibility 5 depth scales.
    assert physical().view("a", camera(), np.ones((H, W), np.float32)).beta == pytest.approx(3.912 / 25.0)


def test_homogeneous_haze_gives_equal_transmission_at_equal_distance_in_any_view():
    med = physical(beta=0.2)
    cams = [camera(), camera(eye=(5.0, 2.0, 3.0)), camera(eye=(-3.0, -3.0, 0.5), fov=40, w=24, h=20)]
    for cam in cams:
        # z chosen so every pixel is exactly 7 units away along its ray.
        z = (7.0 / np.linalg.norm(cam.pixel_rays(np.float64), axis=-1)).astype(np.float32)
        t = med.view("v", cam, z).transmission
        np.testing.assert_allclose(t, np.exp(-0.2 * 7.0), rtol=1e-5)


def test_height_fog_exponential_part_matches_numerical_integration():
    fog = HeightFogMedium(density=0.3, falloff=0.7, up=(0, 0, 1), origin=(0, 0, 1), noise_amplitude=0.0)
    rng = np.random.default_rng(2)
    o = rng.normal(size=(6, 3))
    d = rng.normal(size=(6, 3))
    d[0] = (1, 0, 0)  # horizontal: the x -> 0 limit of the closed form
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    L = rng.uniform(0.5, 6, 6)
    s = np.linspace(0, 1, 20001)[None, :] * L[:, None]
    p = o[:, None] + s[..., None] * d[:, None]
    beta = fog.extinction(p)
    numeric = np.trapezoid(beta, s, axis=1)
    np.testing.assert_allclose(fog.optical_depth(o, d, L), numeric, rtol=1e-6)
    # Infinite rays: finite looking up (the fog thins out), infinite level or down.
    up, down = np.array([0.0, 0.6, 0.8]), np.array([0.0, 0.6, -0.8])
    tau_up = fog.optical_depth(np.zeros(3), up, np.inf)
    assert tau_up == pytest.approx(0.3 * np.exp(0.7) / (0.7 * 0.8))
    assert np.isinf(fog.optical_depth(np.zeros(3), down, np.inf))


def test_optical_depth_is_additive_along_a_ray():
    """Exact for the closed-form part; for the noise part up to quadrature error, which shrinks with the step."""
    rng = np.random.default_rng(3)
    o = rng.normal(size=(5, 3))
    d = rng.normal(size=(5, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    L1, L2 = rng.uniform(0.5, 4, 5), rng.uniform(0.5, 4, 5)
    errors = []
    for step in (None, 1.5 / 32):
        fog = HeightFogMedium(density=0.4, falloff=0.5, noise_amplitude=0.8, noise_scale=1.5, noise_far=50,
                              seed=9, step=step)
        whole = fog.optical_depth(o, d, L1 + L2)
        parts = fog.optical_depth(o, d, L1) + fog.optical_depth(o + L1[:, None] * d, d, L2)
        np.testing.assert_allclose(whole, parts, rtol=5e-4)
        errors.append(np.max(np.abs(whole - parts) / whole))
        assert np.all(fog.noise_depth(o, d, L1 + L2) != 0)  # the noise part is really there
    assert errors[1] < errors[0] / 10 and errors[1] < 2e-5, errors
    smooth = HeightFogMedium(density=0.4, falloff=0.5, noise_amplitude=0.0)
    np.testing.assert_allclose(smooth.optical_depth(o, d, L1 + L2),
                               smooth.optical_depth(o, d, L1) + smooth.optical_depth(o + L1[:, None] * d, d, L2),
                               rtol=1e-12)


def test_one_fog_seen_from_two_views_agrees():
    """A world point has one extinction; a camera placed on another camera's ray sees the rest of that ray."""
    fog = HeightFogMedium(density=0.25, falloff=0.4, noise_amplitude=0.7, noise_scale=2.0, noise_far=30, seed=5)
    a = camera(eye=(0.0, -8.0, 2.0), target=(0.0, 0.0, 0.0))
    P = np.array([0.0, 0.0, 0.0])  # a's principal ray passes through P
    B = a.center + 0.4 * (P - a.center)  # a second camera on that ray, looking at P
    b = camera(eye=B, target=P, fov=50, w=31, h=21)
    zb = np.full((21, 31), np.inf, np.float32)
    dist_a, dist_b = np.linalg.norm(P - a.center), np.linalg.norm(P - B)
    tau_a = fog.optical_depth(a.center, (P - a.center) / dist_a, dist_a)
    tau_ab = fog.optical_depth(a.center, (P - a.center) / dist_a, dist_a - dist_b)
    tau_b_exact = fog.optical_depth(B, (P - B) / dist_b, dist_b)
    assert tau_a == pytest.approx(tau_ab + tau_b_exact, rel=1e-4)
    # The per-view tabulated integrator of camera b agrees at its centre pixel (odd size: exact centre ray).
    zb[10, 15] = dist_b
    tau_b_view = RayIntegrator(fog, b, stride=1)(np.where(np.isfinite(zb), zb, np.inf))[10, 15]
    assert tau_b_view == pytest.approx(tau_b_exact, rel=2e-3)
    # Same seed, same field; the field does not depend on which camera asks.
    pts = np.random.default_rng(0).normal(size=(10, 3))
    again = HeightFogMedium(density=0.25, falloff=0.4, noise_amplitude=0.7, noise_scale=2.0, noise_far=30, seed=5)
    np.testing.assert_array_equal(fog.extinction(pts), again.extinction(pts))
    other = HeightFogMedium(density=0.25, falloff=0.4, noise_amplitude=0.7, noise_scale=2.0, noise_far=30, seed=6)
    assert not np.allclose(fog.extinction(pts), other.extinction(pts))


def test_view_integrator_matches_exact_rays():
    """The tabulated per-view integral (every 4th pixel, 48 distances) against per-pixel quadrature."""
    fog = HeightFogMedium(density=0.2, falloff=0.3, noise_amplitude=0.6, noise_scale=3.0, noise_far=20, seed=1)
    cam = camera(fov=50, w=96, h=72)
    z = np.random.default_rng(4).uniform(1, 15, (72, 96)).astype(np.float32)
    z[:3] = np.inf  # sky rows
    r = z.astype(np.float64) * np.linalg.norm(cam.pixel_rays(np.float64), axis=-1)
    dirs, origin = cam.world_rays(np.float64)
    exact = fog.optical_depth(origin, dirs, np.minimum(r, np.inf))
    approx = RayIntegrator(fog, cam, stride=4)(r)
    finite = np.isfinite(exact)
    np.testing.assert_allclose(approx[finite], exact[finite], rtol=0.02, atol=1e-3)
    np.testing.assert_array_equal(np.isfinite(approx), finite)


def test_heterogeneous_mode_is_one_medium_for_all_views():
    model = HazeModel(HazeConfig(mode="heterogeneous", beta=0.1), seed=3, depth_scale=4.0, up=(0, 0, 1))
    z = np.full((H, W), 6.0, np.float32)
    t1 = model.view("a", camera(), z).transmission
    t2 = model.view("b", camera(), z).transmission  # same pose, another name: same fog
    np.testing.assert_array_equal(t1, t2)
    assert 0 < t1.min() < t1.max() < 1
    assert model.describe()["medium"]["kind"] == "height_fog"


def test_noise_is_smooth_and_in_range():
    p = np.random.default_rng(0).uniform(-20, 20, (5000, 3))
    n = fractal_noise(p, seed=1)
    assert n.min() >= 0 and n.max() <= 1 and n.std() > 0.05
    eps = 1e-4
    assert np.max(np.abs(fractal_noise(p + eps, seed=1) - n)) < 1e-2


def test_up_is_recovered_from_upright_cameras():
    cams = [camera(eye=(6 * np.cos(a), 6 * np.sin(a), 2.0)) for a in np.linspace(0, 2 * np.pi, 8, endpoint=False)]
    np.testing.assert_allclose(estimate_up(cams), (0, 0, 1), atol=1e-6)


# --- OneRestore protocol -------------------------------------------------------------------------
def test_onerestore_depth_map_is_8bit_normalised_inverse_depth():
    r = np.linspace(1, 50, W * H).reshape(H, W)
    r[0, :5] = np.inf
    D = onerestore_depth_map(r)
    assert D.max() == 1.0 and D.min() == 0.0
    assert D[-1, -1] == 0.0 or D[-1, -1] < D[1, 0]  # farther = darker
    np.testing.assert_allclose(D * 255, np.round(D * 255), atol=1e-4)
    assert D[0, 5] == 1.0 and np.all(D[0, :5] == 0)


def test_onerestore_transmission_formula_and_floor():
    rng = np.random.default_rng(5)
    r = rng.uniform(1, 30, (H, W))
    t = onerestore_transmission(r, beta=1.7, box_size=1, quantize=False)
    inv = 1 / r
    D = (inv - inv.min()) / (inv.max() - inv.min())
    np.testing.assert_allclose(t, np.exp(-1.7 * np.minimum(1 - D, 0.7)), rtol=1e-5)
    t22 = onerestore_transmission(r, beta=2.0)
    assert t22.min() >= np.exp(-1.4) - 1e-6 and t22.max() <= 1


def test_onerestore_samples_per_view_in_the_papers_ranges():
    model = HazeModel(HazeConfig(), seed=11, depth_scale=1.0)
    z = np.random.default_rng(0).uniform(1, 9, (H, W)).astype(np.float32)
    vals = [model.view(f"{i:03d}.png", camera(), z) for i in range(12)]
    betas = [v.beta for v in vals]
    assert all(1 <= b <= 2 for b in betas) and len(set(betas)) == 12
    for v in vals:
        assert 0.6 <= v.airlight[0] <= 0.9 and np.all(v.airlight == v.airlight[0])  # grey
    again = HazeModel(HazeConfig(), seed=11, depth_scale=1.0).view("003.png", camera(), z)
    assert again.beta == vals[3].beta
    scene_wide = HazeModel(HazeConfig(sampling="scene"), seed=11, depth_scale=1.0)
    assert scene_wide.view("a", camera(), z).beta == scene_wide.view("b", camera(), z).beta


# --- extremes ---------------------------------------------------------------------------------
@pytest.mark.parametrize("mode", ["onerestore", "homogeneous", "heterogeneous"])
def test_beta_zero_leaves_the_image_bit_for_bit(mode):
    J = rng_image()
    z = np.random.default_rng(1).uniform(1, 9, (H, W)).astype(np.float32)
    z[0] = np.inf
    model = HazeModel(HazeConfig(mode=mode, beta=0.0), seed=0, depth_scale=3.0)
    vh = model.view("a", camera(), z)
    assert np.all(vh.transmission == 1)
    for linear in (False, True):
        out = compose(J, vh, [], ComposeConfig(linear=linear))
        np.testing.assert_array_equal(out, J)


def test_infinite_beta_gives_pure_airlight_except_at_zero_distance():
    z = np.random.default_rng(1).uniform(1, 9, (H, W)).astype(np.float32)
    z[0, 0] = 0.0
    vh = physical(beta=np.inf, airlight=(0.2, 0.5, 0.9)).view("a", camera(), z)
    out = compose(rng_image(), vh, [])
    assert not np.isnan(out).any()
    np.testing.assert_allclose(out[1:], np.broadcast_to([0.2, 0.5, 0.9], out[1:].shape), atol=1e-6)
    np.testing.assert_array_equal(out[0, 0], rng_image()[0, 0])


def test_zero_nan_and_infinite_depth():
    z = np.full((H, W), 4.0, np.float32)
    z[0, 0], z[0, 1], z[0, 2] = 0.0, np.inf, np.nan
    for model in (physical(beta=0.3, airlight=0.8), HazeModel(HazeConfig(beta=1.5, airlight=(0.8,) * 3), 0, 1.0),
                  HazeModel(HazeConfig(mode="heterogeneous", beta=0.3), 0, 4.0)):
        vh = model.view("a", camera(), z)
        t = vh.transmission
        assert np.isfinite(t).all() and t.min() >= 0 and t.max() <= 1
        # NaN depth is read as "no surface", like inf.
        np.testing.assert_array_equal(t, model.view("a", camera(), np.where(np.isnan(z), np.inf, z)).transmission)
        if model.config.physical:  # (onerestore normalises and box-filters: neighbours mix)
            assert t[0, 0] == 1.0  # a surface at the camera
    t = physical(beta=0.3).view("a", camera(), z).transmission
    assert t[0, 1] == 0.0  # sky: pure airlight
    assert np.all(homogeneous_transmission(np.array([np.inf, 0.0]), 0.0) == 1)  # beta 0: no 0 * inf


@pytest.mark.parametrize("airlight", [0.0, 1.0])
@pytest.mark.parametrize("fill", [0.0, 1.0])
def test_black_white_images_and_airlight_bounds(airlight, fill):
    J = np.full((H, W, 3), fill, np.float32)
    t = np.linspace(0, 1, H * W, dtype=np.float32).reshape(H, W)
    out = apply_haze(J, t, airlight)
    assert np.isfinite(out).all() and out.min() >= 0 and out.max() <= 1
    np.testing.assert_allclose(out[..., 0], fill * t + airlight * (1 - t), atol=1e-6)


@pytest.mark.parametrize("kwargs, fragment", [
    (dict(beta=-0.5), "beta must be >= 0"),
    (dict(airlight=(0.5, 1.2, 0.5)), "airlight must be"),
    (dict(airlight=(-0.1,) * 3), "airlight must be"),
    (dict(airlight_range=(0.5, 1.5)), "airlight range"),
    (dict(beta_range=(2.0, 1.0)), "beta range"),
    (dict(visibility=10.0), "physical haze mode"),
    (dict(mode="smog"), "unknown haze mode"),
])
def test_out_of_range_haze_parameters_are_refused(kwargs, fragment):
    with pytest.raises(NimbusError, match=fragment):
        HazeConfig(**kwargs)
    with pytest.raises(NimbusError, match="beta must be >= 0"):
        HomogeneousMedium(-1.0)
    with pytest.raises(NimbusError, match="visibility must be a positive"):
        HazeConfig(mode="homogeneous", visibility=0.0)


def test_max_distance_caps_the_sky_like_onerestores_cap():
    z = np.full((H, W), 3.0, np.float32)
    z[:5] = np.inf
    cam = camera()
    vh = physical(beta=0.2, max_distance=10.0).view("a", cam, z)
    r_sky = 10.0  # every sky ray is cut at 10 units
    np.testing.assert_allclose(vh.transmission[:5], np.exp(-0.2 * r_sky), rtol=1e-5)
    np.testing.assert_allclose(vh.transmission[5:], np.exp(-0.2 * ray_distance_brute(cam, z)[5:]), rtol=1e-5)
