"""NimbusGS building blocks against closed forms: scattering, airlight, PLM, GGS, losses, auto evidence, config."""

import dataclasses
import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from nimbus.config_set import apply_overrides
from nimbus.data.camera import Camera
from nimbus.errors import NimbusError
from nimbus.methods.nimbusgs.airlight import (ConstantAirlight, NetworkAirlight, SHAirlight, dark_channel_window,
                                      estimate_airlight, view_descriptor, window_min)
from nimbus.methods.nimbusgs.auto import haze_evidence, particle_evidence, particle_thresholds, residual_tail_counts
from nimbus.methods.nimbusgs.config import NimbusConfig, paper_m_init, parse_components, preset
from nimbus.methods.nimbusgs.ggs import (GGSFactors, ggs_weights, lower_median, robust_normalise, sample_error,
                                scale_gradients)
from nimbus.methods.nimbusgs.losses import dcp_loss, soft_dark_channel
from nimbus.methods.nimbusgs.particulate import (ResidualStore, ViewConsistency, ViewGeometry, consistency_excess,
                                         extract_residual, is_refresh_step, neighbours, particle_mask,
                                         tophat_window, white_tophat)
from nimbus.restore.classical import classical_restore
from nimbus.methods.nimbusgs.scattering import (Box, ExtinctionGrid, UniformExtinction, camera_rays, density_scale_for,
                                        gaussian_extinction_map, march, march_interval, ray_box_interval,
                                        surface_in_box)


def _camera(width=16, height=12, eye=(0.0, 0.0, 0.0), target=(0.0, 0.0, 1.0), up=(0.0, -1.0, 0.0)):
    return Camera.look_at(eye, target, up, width, height, fov_x_deg=60)


def _homogeneous_grid(box, beta, resolution=4):
    grid = ExtinctionGrid(box, resolution, 0.0, 1.0)
    with torch.no_grad():
        grid.features.fill_(0.0)
        grid.log_scale.fill_(math.log(beta / math.log(2.0)))  # softplus(0) = ln 2
    return grid


def _march_view(field, cam, z, alpha=1.0, samples=32, near=0.01, alpha_min=0.5, grad=False):
    rays = camera_rays(cam)
    depth = torch.full((cam.height, cam.width), z * alpha)
    a = torch.full((cam.height, cam.width), alpha)
    ts, te = march_interval(rays, field.lo, field.hi, depth, a, near, alpha_min)
    with torch.set_grad_enabled(grad):
        return march(field, rays.origin, rays.dirs, ts, te, samples), rays, ts, te


# --- CSM ----------------------------------------------------------------------------------
def test_homogeneous_grid_gives_beer_lambert_and_airlight_closed_form():
    beta, z, near = 0.3, 4.0, 0.01
    cam = _camera()
    grid = _homogeneous_grid(Box((-50.0,) * 3, (50.0,) * 3), beta)
    res, rays, ts, te = _march_view(grid, cam, z, near=near)
    distance = z * rays.z_to_distance - near
    torch.testing.assert_close(te - ts, distance)
    torch.testing.assert_close(res.transmission, torch.exp(-beta * distance), rtol=1e-5, atol=1e-6)
    airlight = torch.tensor([0.7, 0.8, 0.9])
    P = res.scatter[:, None] * airlight
    torch.testing.assert_close(P, airlight * (1 - res.transmission[:, None]), rtol=1e-5, atol=1e-6)
    # Uniform extinction is the same closed form.
    uni = UniformExtinction(Box((-50.0,) * 3, (50.0,) * 3), beta / math.log(2.0))
    res_u, *_ = _march_view(uni, cam, z, near=near)
    torch.testing.assert_close(res_u.transmission, res.transmission, rtol=1e-5, atol=1e-6)


def test_rays_point_into_the_scene():
    """A medium only in front of the camera attenuates; only behind it does not (the released code's bug)."""
    cam = _camera()  # at the origin, looking along +z
    front = _homogeneous_grid(Box((-20.0, -20.0, 2.0), (20.0, 20.0, 6.0)), 0.5)
    behind = _homogeneous_grid(Box((-20.0, -20.0, -6.0), (20.0, 20.0, -2.0)), 0.5)
    res_front, *_ = _march_view(front, cam, z=10.0)
    res_behind, *_ = _march_view(behind, cam, z=10.0)
    assert float(res_front.transmission.max()) < 0.2
    assert torch.all(res_behind.transmission == 1.0) and torch.all(res_behind.scatter == 0.0)
    # The same with a posed camera looking at the medium from the side, and away from it.
    box = Box((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
    medium = _homogeneous_grid(box, 2.0)
    toward = _camera(eye=(0.0, -6.0, 0.5), target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0))
    away = _camera(eye=(0.0, -6.0, 0.5), target=(0.0, -12.0, 0.0), up=(0.0, 0.0, 1.0))
    r_toward, *_ = _march_view(medium, toward, z=20.0, alpha=0.0)  # no surface: march to the box exit
    r_away, *_ = _march_view(medium, away, z=20.0, alpha=0.0)
    center = (toward.height // 2) * toward.width + toward.width // 2
    assert float(r_toward.transmission[center]) < math.exp(-2.0 * 1.5)
    assert torch.all(r_away.transmission == 1.0)


def test_rays_missing_the_box_and_surfaces_before_it_are_clear_and_finite():
    cam = _camera()
    grid = _homogeneous_grid(Box((30.0, 30.0, 30.0), (31.0, 31.0, 31.0)), 5.0)
    res, *_ = _march_view(grid, cam, z=100.0)
    assert torch.all(res.transmission == 1.0) and torch.all(res.scatter == 0.0)
    entry, exit_ = ray_box_interval(torch.zeros(3), torch.tensor([[1.0, 0.0, 0.0]]), torch.tensor([1.0, -1, -1]),
                                    torch.tensor([2.0, 1, 1]))  # axis-aligned ray: zero components
    assert torch.isfinite(entry).all() and float(entry) == pytest.approx(1.0) and float(exit_) == pytest.approx(2.0)
    ahead = _homogeneous_grid(Box((-5.0, -5.0, 5.0), (5.0, 5.0, 9.0)), 5.0)
    res, *_ = _march_view(ahead, cam, z=2.0)  # the surface hides the medium
    assert torch.all(res.transmission == 1.0)


def test_march_is_stable_at_the_extremes():
    cam = _camera()
    for beta in (0.0, 1e4):
        grid = _homogeneous_grid(Box((-50.0,) * 3, (50.0,) * 3), max(beta, 1e-30))
        res, *_ = _march_view(grid, cam, z=5.0, grad=True)
        (res.transmission.sum() + res.scatter.sum()).backward()
        res = type(res)(res.transmission.detach(), res.scatter.detach())
        assert torch.isfinite(res.transmission).all() and torch.isfinite(res.scatter).all()
        assert torch.isfinite(grid.features.grad).all() and torch.isfinite(grid.log_scale.grad).all()
        if beta == 0.0:
            assert torch.allclose(res.transmission, torch.ones(1))
        else:
            assert float(res.transmission.max()) < 1e-6 and torch.allclose(res.scatter, torch.ones(1))


def test_grid_is_trilinear_zero_outside_and_tv_measures_variation():
    box = Box((0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
    grid = ExtinctionGrid(box, 2, 0.0, 1.0)
    with torch.no_grad():
        grid.features.zero_()
        grid.features[0, 0, :, :, 1] = 2.0  # x = 1 side
        assert float(grid.tv()) > 0
    x = torch.tensor([[0.5, 0.5, 0.5], [0.0, 0.2, 0.7], [1.5, 0.5, 0.5]])
    with torch.no_grad():
        b = grid(x)
    sp = torch.nn.functional.softplus
    torch.testing.assert_close(b[:2], sp(torch.tensor([1.0, 0.0])))
    assert float(b[2]) == 0.0
    with torch.no_grad():
        grid.features.fill_(0.3)
        assert float(grid.tv()) == 0.0


def test_gaussian_driven_extinction_and_density_scale_closed_forms():
    alpha = torch.full((2, 3), 0.5)
    beta_img = 0.2 * alpha  # blended constant beta 0.2
    ts, te = torch.zeros(6), torch.full((6,), 5.0)
    res = gaussian_extinction_map(beta_img, alpha, ts, te)
    torch.testing.assert_close(res.transmission, torch.full((6,), math.exp(-1.0)))
    torch.testing.assert_close(res.scatter, 1 - res.transmission)
    scale = density_scale_for(0.5, 10.0)
    assert math.exp(-math.log(2.0) * scale * 10.0) == pytest.approx(0.5)


def test_box_is_the_aabb_enlarged_about_its_centre():
    box = Box.around(np.array([[0.0, 0, 0], [2, 4, 6]]), 2.0)
    assert box.lo == pytest.approx((-1.0, -2.0, -3.0)) and box.hi == pytest.approx((3.0, 6.0, 9.0))
    flat = Box.around(np.zeros((3, 3)), 2.0)  # degenerate cloud: still a (small) box
    assert all(h > l for l, h in zip(flat.lo, flat.hi))


def test_content_box_leaves_out_the_backdrop():
    rng = np.random.default_rng(0)
    content = rng.uniform(-2, 2, (500, 3))
    backdrop = rng.normal(size=(60, 3))
    backdrop = backdrop / np.linalg.norm(backdrop, axis=1, keepdims=True) * 90.0  # a 90 m dome
    points = np.concatenate([content, backdrop])
    cameras = np.array([[0.0, 0, 0], [0.5, 0, 0]])
    box = Box.around_content(points, cameras, 2.0, content_factor=4.0)
    plain = Box.around(content, 2.0)
    assert box.lo == pytest.approx(plain.lo) and box.hi == pytest.approx(plain.hi)
    everything = Box.around_content(points, cameras, 2.0, content_factor=0.0)  # 0: the paper's AABB
    assert max(everything.hi) > 150 and everything == Box.around(points, 2.0)


def test_surface_in_box_marks_rays_that_end_at_a_surface_inside():
    cam = _camera()
    rays = camera_rays(cam)
    lo, hi = torch.tensor([-5.0, -5.0, -1.0]), torch.tensor([5.0, 5.0, 6.0])
    shape = (cam.height, cam.width)
    near = surface_in_box(rays, lo, hi, torch.full(shape, 3.0), torch.ones(shape), 0.5)
    assert bool(near.all())  # z = 3 lies inside for every pixel of a 60 degree view
    beyond = surface_in_box(rays, lo, hi, torch.full(shape, 50.0), torch.ones(shape), 0.5)
    assert not bool(beyond.any())  # a backdrop past the box exit
    sky = surface_in_box(rays, lo, hi, torch.full(shape, 0.1), torch.full(shape, 0.05), 0.5)
    assert not bool(sky.any())  # too little accumulated alpha to be a surface
    missed = surface_in_box(rays, lo + 100, hi + 100, torch.full(shape, 3.0), torch.ones(shape), 0.5)
    assert not bool(missed.any())


# --- airlight -----------------------------------------------------------------------------
def test_network_airlight_gradients_are_nn_linear_ones_to_rounding():
    torch.manual_seed(0)
    net = NetworkAirlight(16, compiled=False)  # the torch layers (the kernel: tests/test_airlight_cpp.py)
    torch.nn.init.normal_(net.mlp[-1].weight, std=0.3)
    dirs = torch.nn.functional.normalize(torch.randn(500, 3), dim=1)
    t, desc, target = torch.rand(500), torch.rand(6), torch.rand(500, 3)
    a = net(dirs, t, desc)
    (a - target).square().mean().backward()
    ours = [p.grad.clone() for p in net.parameters()]
    net.zero_grad()
    x = torch.cat([dirs, t[:, None], desc.expand(500, 6)], dim=1)
    plain = torch.sigmoid(torch.logit(desc[:3].clamp(0.02, 0.98)) + net.mlp(x))
    (plain - target).square().mean().backward()
    torch.testing.assert_close(a, plain, rtol=1e-6, atol=1e-7)
    for g, p in zip(ours, net.parameters()):
        torch.testing.assert_close(g, p.grad, rtol=1e-5, atol=1e-8)


def test_airlight_variants_start_at_the_dark_channel_estimate():
    img = torch.zeros(20, 30, 3)
    img[:5, :8] = torch.tensor([0.8, 0.85, 0.9])  # the haziest (brightest dark channel) region
    a = estimate_airlight(img, 3)
    torch.testing.assert_close(a, torch.tensor([0.8, 0.85, 0.9]))
    desc = view_descriptor(img, 3)
    dirs = torch.nn.functional.normalize(torch.randn(7, 3), dim=-1)
    t = torch.rand(7)
    for module in (NetworkAirlight(16), ConstantAirlight(a), SHAirlight(a, 2)):
        out = module(dirs, t, desc)
        assert out.shape == (7, 3) and torch.all((out > 0) & (out < 1))
        torch.testing.assert_close(out, a.expand(7, 3), rtol=1e-4, atol=1e-4)


# --- PLM ----------------------------------------------------------------------------------
def test_residual_store_is_compact_and_exact_to_8_bits():
    store = ResidualStore([(12, 16), (6, 8)])
    assert store.nbytes == 12 * 16 * 3 + 6 * 8 * 3
    r = torch.rand(12, 16, 3)
    store.set(0, r, iteration=7)
    assert store.data[0].dtype == torch.uint8 and store.nbytes == 12 * 16 * 3 + 6 * 8 * 3
    assert float((store.get(0) - r).abs().max()) <= 0.5 / 255 + 1e-6
    assert torch.all(store.get(1) == 0)
    assert not store.is_stale(0, 7) and store.is_stale(0, 8) and store.is_stale(1, 0)
    inp, con = torch.tensor([0.5, 0.2, 1.0]), torch.tensor([0.3, 0.4, 0.1])
    torch.testing.assert_close(extract_residual(inp, con), torch.tensor([0.2, 0.0, 0.9]))


def _plane_views(n=4, flower=(0.3, 0.2), particle_view=0, particle_px=(20, 8)):
    """Cameras side by side looking at a textured plane z = 5 with a bright dot on it, and a dot in one view only."""
    cams, images = [], []
    for i in range(n):
        eye = np.array([0.15 * i, 0.0, 0.0])
        cam = Camera(32, 24, 20.0, 20.0, 16.0, 12.0, np.eye(3), -eye)
        rays = cam.pixel_rays(np.float64) * 5.0
        X, Y = rays[..., 0] + eye[0], rays[..., 1]
        img = 0.3 + 0.1 * np.sin(3 * X)[..., None] * np.ones(3)
        img[(np.abs(X - flower[0]) < 0.15) & (np.abs(Y - flower[1]) < 0.15)] = 0.9  # on the surface: every view
        if i == particle_view:
            img[particle_px[1], particle_px[0]] = 0.95  # in this view only
        cams.append(cam)
        images.append(torch.from_numpy(img.astype(np.float32)))
    geometry = [ViewGeometry(c, torch.full((24, 32), 5.0), torch.ones(24, 32, dtype=torch.bool)) for c in cams]
    return cams, images, geometry


def test_view_consistency_separates_particles_from_surface_detail():
    cams, images, geometry = _plane_views()
    others = neighbours(cams, 3)
    assert others[0] == [1, 2, 3] and others[3][0] == 2
    excess = consistency_excess(0, images, geometry, others[0])
    u, v = cams[0].project(np.array([[0.3, 0.2, 5.0]]))[0][0].astype(int)
    assert float(excess[v, u]) < 0.05  # the flower is on the surface in every view
    assert float(excess[8, 20]) > 0.5  # the particle is in view 0 only
    composite = images[1].clone()  # a model without the dot and the particle
    composite[:] = 0.3 + 0.1 * torch.sin(3 * torch.from_numpy(cams[0].pixel_rays(np.float64)[..., 0] * 5.0))[..., None]
    mask = particle_mask(images[0], composite.float(), 3.0, excess)
    assert bool(mask[8, 20]) and not bool(mask[v, u])
    without_check = particle_mask(images[0], composite.float(), 3.0, None)
    assert bool(without_check[v, u])  # a per-pixel test alone cannot tell the flower from a particle
    r = extract_residual(images[0], composite.float(), 3.0, excess)
    assert float(r[8, 20].min()) > 0.5 and float(r[v, u].max()) == 0.0
    unknown = [ViewGeometry(g.camera, g.depth, torch.zeros_like(g.valid)) for g in geometry]
    assert torch.isnan(consistency_excess(0, images, unknown, others[0])).all()  # no surface: no verdict


def test_kept_consistency_check_is_the_same_as_the_one_off_function():
    cams, images, geometry = _plane_views()
    check = ViewConsistency(cams, images, 3)
    assert check.others == neighbours(cams, 3)
    for moved in (geometry, [ViewGeometry(g.camera, g.depth * 1.01, g.valid) for g in geometry]):  # a later refresh
        batched = check.excesses(moved)
        for i in range(len(cams)):
            once = consistency_excess(i, images, moved, check.others[i])
            for kept in (check.excess(i, moved), batched[i]):
                assert torch.equal(torch.isnan(once), torch.isnan(kept))
                assert torch.equal(once.nan_to_num(), kept.nan_to_num())  # bit for bit


def _rough_views(n=7, seed=0):
    """Rotated cameras around a bumpy surface, partly invalid renders, noisy inputs: every branch of the check
    (out of view, behind a neighbour's surface, no valid neighbour) is taken somewhere."""
    gen = np.random.default_rng(seed)
    cams, images, geometry = [], [], []
    for i in range(n):
        a = 0.12 * (i - n // 2)
        R = np.array([[np.cos(a), 0.0, -np.sin(a)], [0.0, 1.0, 0.0], [np.sin(a), 0.0, np.cos(a)]])
        cam = Camera(40, 30, 31.0, 29.0, 20.3, 14.6, R, np.array([0.4 * (i - n // 2), 0.05 * i, 0.3]))
        depth = torch.from_numpy(4.0 + gen.uniform(-0.6, 0.6, (30, 40))).float()
        valid = torch.from_numpy(gen.uniform(size=(30, 40)) > 0.2)
        cams.append(cam)
        images.append(torch.from_numpy(gen.uniform(size=(30, 40, 3))).float())
        geometry.append(ViewGeometry(cam, depth, valid))
    return cams, images, geometry


def test_batched_consistency_check_is_the_reference_bit_for_bit(monkeypatch):
    # The torch paths alone (the compiled kernel, used where it builds, has its own test against them).
    monkeypatch.setattr("nimbus.kernels.consistency.usable", lambda *a, **k: False)
    cams, images, geometry = _rough_views()
    for count, batch in ((3, 1 << 21), (4, 2 * 4 * 30 * 40)):  # all views in one batch; two views per batch
        check = ViewConsistency(cams, images, count)
        check.BATCH_ELEMENTS = batch
        batched = check.excesses(geometry)
        known = 0
        for i in range(len(cams)):
            once = consistency_excess(i, images, geometry, check.others[i])
            assert torch.equal(torch.isnan(once), torch.isnan(batched[i]))
            assert torch.equal(once.nan_to_num(), batched[i].nan_to_num())
            known += int((~torch.isnan(once)).sum())
        assert 0 < known < len(cams) * 30 * 40  # some pixels have a verdict, some have none
    # Views of different sizes cannot be stacked: each view is checked on its own, with the same result.
    small = Camera(20, 15, 15.5, 14.5, 10.1, 7.3, cams[0].R, cams[0].t)
    mixed = [ViewGeometry(small, geometry[0].depth[::2, ::2].clone(), geometry[0].valid[::2, ::2].clone()),
             *geometry[1:]]
    images = [images[0][::2, ::2].clone(), *images[1:]]
    check = ViewConsistency([g.camera for g in mixed], images, 3)
    for i, kept in enumerate(check.excesses(mixed)):
        once = consistency_excess(i, images, mixed, check.others[i])
        assert torch.equal(once.nan_to_num(), kept.nan_to_num())


def test_faint_inconsistent_particle_enters_r_only_when_consistency_decides():
    cams, images, geometry = _plane_views()
    excess = consistency_excess(0, images, geometry, neighbours(cams, 3)[0])
    composite = images[0].clone()
    noisy = composite + 0.16 * torch.rand(composite.shape, generator=torch.Generator().manual_seed(0)) - 0.08
    noisy[8, 20] = 0.95 - 0.08  # the model misfits everywhere by +-0.08 and lacks most of a faint particle:
    # its 0.08 residual is below 3 robust sigmas of the misfit, but no neighbour sees it
    strict = particle_mask(images[0], noisy, 3.0, excess, "all")
    loose = particle_mask(images[0], noisy, 3.0, excess, "unchecked")
    assert bool(loose[8, 20]) and not bool(strict[8, 20])
    assert loose.float().mean() < 0.5  # the consistent misfit stays out of R
    assert loose.sum() >= strict.sum()


def test_tophat_caps_the_residual_to_small_bright_structures():
    assert tophat_window(240, 0.03) == 7 and tophat_window(240, 0.0) == 0 and tophat_window(20, 0.03) == 3
    img = torch.full((24, 32, 3), 0.4)
    img[5, 6] = 0.9  # a flake, 1 px
    img[12:22, 10:30] = 0.8  # a bright wall, wider than the window
    th = white_tophat(img, 5)
    torch.testing.assert_close(th[5, 6], torch.full((3,), 0.5))
    assert float(th[12:22, 10:30].max()) < 1e-6 and float(th[0, :].max()) < 1e-6  # borders: no false structure
    # A render gone dark over the wall (a hole) and lacking the flake: without the cap the
    # hole enters R and would never get a gradient; with it only the flake does.
    composite = torch.full_like(img, 0.4)
    composite[12:22, 10:30] = 0.0
    free = extract_residual(img, composite)
    capped = extract_residual(img, composite, bound=th)
    assert float(free[15, 20].min()) > 0.7 and float(capped[15, 20].max()) == 0.0
    torch.testing.assert_close(capped[5, 6], torch.full((3,), 0.5))


@pytest.mark.parametrize("window", [3, 7, 11])
def test_tophat_is_the_square_opening_bit_for_bit(window):
    """The separable passes give what one square pool over the replicated borders gives, NaN included."""
    img = torch.rand(19, 27, 3, generator=torch.Generator().manual_seed(window))
    img[4, 9, 1] = float("nan")
    pad = window // 2
    x = img.permute(2, 0, 1)[None]
    eroded = -F.max_pool2d(F.pad(-x, (pad,) * 4, mode="replicate"), window, stride=1)
    opened = F.max_pool2d(F.pad(eroded, (pad,) * 4, mode="replicate"), window, stride=1)
    want = (x - opened).clamp_min(0.0)[0].permute(1, 2, 0)
    assert torch.equal(white_tophat(img, window).isnan(), want.isnan())
    assert torch.equal(white_tophat(img, window).nan_to_num(-1.0), want.nan_to_num(-1.0))


def test_refresh_cadence():
    steps = [it for it in range(1, 101) if is_refresh_step(it, m_init=40, interval=15)]
    assert steps == [55, 70, 85, 100]


# --- GGS ----------------------------------------------------------------------------------
def _ggs_inputs(n=6):
    depths = torch.linspace(1.0, 6.0, n)
    radii = torch.arange(1, n + 1, dtype=torch.int32)
    means2d = torch.stack([torch.arange(n, dtype=torch.float32) + 0.5, torch.full((n,), 0.5)], -1)
    error = torch.zeros(1, n)
    return depths, radii, means2d, error, torch.ones(n, dtype=torch.bool)


def test_ggs_factors_follow_the_paper_equation():
    d, r, m, e, vis = _ggs_inputs()
    bare = (0.0, math.inf)
    w, _ = ggs_weights(d, r, m, e, vis, GGSFactors(depth=True, radius=False, error=False, clip=bare))
    dn = (d - 1) / 5
    torch.testing.assert_close(w, dn / dn.mean())
    w, _ = ggs_weights(d, r, m, e, vis, GGSFactors(depth=False, radius=True, error=False, clip=bare))
    torch.testing.assert_close(w, r.float() / r.float().mean())
    err = torch.tensor([[0.0, 1.0, 2.0, 3.0, 4.0, 100.0]])
    w, _ = ggs_weights(d, r, m, err, vis, GGSFactors(depth=False, radius=False, error=True, clip=bare))
    assert torch.all(torch.diff(w) > 0)  # more error, more weight; the outlier is bounded by the sigmoid
    en = robust_normalise(err[0])
    torch.testing.assert_close(w, torch.sigmoid(en) / torch.sigmoid(en).mean())
    w, _ = ggs_weights(d, r, m, err, vis, GGSFactors(clip=bare))
    assert float(w[0]) == 0.0 and float(w.mean()) == pytest.approx(1.0)  # the nearest has d_norm = 0
    w, _ = ggs_weights(d, r, m, err, vis, GGSFactors(clip=(0.5, 3.0)))
    assert float(w.min()) >= 0.5 and float(w.max()) <= 3.0
    off, _ = ggs_weights(d, r, m, err, vis, GGSFactors(depth=False, radius=False, error=False))
    assert torch.all(off == 1.0)


def test_kth_smallest_is_the_partitions_value_on_hostile_arrays():
    """The bracketed selection gives np.partition's value on ties, sorted, sparse and heavy-tailed data, at any rank
    (and falls back where its sample misleads it)."""
    from nimbus.methods.nimbusgs.ggs import kth_smallest

    rng = np.random.default_rng(0)
    n = 20_000
    arrays = [rng.random(n).astype(np.float32), np.round(rng.random(n) * 3).astype(np.float32),
              np.sort(rng.random(n)), np.sort(rng.random(n))[::-1].copy(), rng.standard_cauchy(n),
              np.zeros(n, np.float32)]
    arrays[-1][rng.integers(0, n, 5)] = 1.0
    # The strided sample sees only zeros where the upper half is ones everywhere else: the bracket misses.
    trap = np.ones(n, np.float32)
    trap[:: n // 1024] = 0.0
    arrays.append(trap)
    for a in arrays:
        for k in (0, 1, n // 3, (n - 1) // 2, n - 2, n - 1):
            assert kth_smallest(a, k) == np.partition(a, k)[k]


def test_visible_rows_are_torchs_nonzero():
    from nimbus.methods.nimbusgs.ggs import visible_rows

    g = torch.Generator().manual_seed(0)
    sparse = torch.rand(200_003, generator=g) < 0.27
    strided = (torch.rand(40, generator=g) < 0.5)[::2]
    for v in (sparse, torch.zeros(5, dtype=torch.bool), torch.ones(9, dtype=torch.bool),
              torch.zeros(0, dtype=torch.bool), strided):
        got, expect = visible_rows(v), v.nonzero().squeeze(1)
        assert got.dtype == expect.dtype == torch.int64 and torch.equal(got, expect)


@pytest.mark.parametrize("n", [1, 2, 7, 8, 100_001])
def test_lower_median_is_torchs_median(n):
    g = torch.Generator().manual_seed(n)
    for x in (torch.rand(n, generator=g), torch.randint(0, 3, (n,), generator=g).float(),  # ties
              torch.rand(n, generator=g, dtype=torch.float64)):
        m = lower_median(x)
        assert m.dtype == x.dtype and m.dim() == 0 and torch.equal(m, x.median())
    x = torch.rand(n, generator=g)
    x[n // 2] = float("nan")  # torch's median is NaN then; so is ours
    assert torch.isnan(lower_median(x))


def test_ggs_weights_are_those_of_the_equation_written_out():
    """The index_select / selection-median implementation against the equation in plain torch ops."""
    g = torch.Generator().manual_seed(3)
    n, h, w = 5000, 30, 40
    d = torch.rand(n, generator=g) * 5 + 0.5
    r = torch.randint(0, 6, (n,), generator=g, dtype=torch.int32)
    m = (torch.rand(n, 2, generator=g) * 1.4 - 0.2) * torch.tensor([w, h])
    err = torch.rand(h, w, generator=g)
    vis = r > 0
    got, _ = ggs_weights(d, r, m, err, vis, GGSFactors(clip=(0.5, 3.0)))
    dv, rv, mv = d[vis], r[vis].float(), m[vis]
    grid = torch.stack([mv[:, 0] / w * 2 - 1, mv[:, 1] / h * 2 - 1], -1).reshape(1, 1, -1, 2)
    e = torch.nn.functional.grid_sample(err[None, None], grid, mode="bilinear", padding_mode="border",
                                        align_corners=False).reshape(-1)
    med = e.median()
    en = (e - med) / (e - med).abs().median()
    wv = (dv - dv.min()) / (dv.max() - dv.min()) * (rv / 3.0) * torch.sigmoid(en)
    want = torch.ones(n)
    want[vis] = (wv / wv.mean()).clamp(0.5, 3.0)
    assert torch.equal(got, want)


def test_ggs_degenerate_cases_are_finite():
    d, r, m, e, vis = _ggs_inputs()
    same = torch.full_like(d, 3.0)  # d_max = d_min
    w, _ = ggs_weights(same, r, m, e, vis, GGSFactors(radius=False, error=False))
    assert torch.all(w == 1.0)
    w, _ = ggs_weights(d, r, m, torch.zeros(1, 6), vis, GGSFactors())  # MAD = 0
    assert torch.isfinite(w).all()
    assert torch.all(robust_normalise(torch.full((5,), 2.0)) == 0)
    none = torch.zeros(6, dtype=torch.bool)
    w, info = ggs_weights(d, r, m, e, none)
    assert torch.all(w == 1.0) and info["visible"] == 0
    one = torch.zeros(6, dtype=torch.bool)
    one[0] = True  # a single visible Gaussian: d_max = d_min and MAD = 0 at once
    w, _ = ggs_weights(d, r, m, e, one)
    assert torch.isfinite(w).all() and float(w[0]) == 1.0
    empty = ggs_weights(torch.zeros(0), torch.zeros(0, dtype=torch.int32), torch.zeros(0, 2), e,
                        torch.zeros(0, dtype=torch.bool))[0]
    assert empty.shape == (0,)


def test_ggs_scales_gradient_rows_and_samples_error_at_pixel_centres():
    err = torch.arange(12, dtype=torch.float32).reshape(3, 4)
    pos = torch.tensor([[0.5, 0.5], [3.5, 2.5], [1.0, 0.5]])  # two centres and a midpoint
    torch.testing.assert_close(sample_error(err, pos), torch.tensor([0.0, 11.0, 0.5]))
    t = {"a": torch.zeros(3, 2, requires_grad=True), "b": torch.zeros(3, requires_grad=True)}
    (t["a"].sum() + t["b"].sum()).backward()
    scaled, finite = scale_gradients(t, torch.tensor([1.0, 2.0, 0.5]))
    assert finite and [id(g) for g in scaled] == [id(t["a"].grad), id(t["b"].grad)]
    torch.testing.assert_close(t["a"].grad, torch.tensor([[1.0, 1.0], [2.0, 2.0], [0.5, 0.5]]))
    torch.testing.assert_close(t["b"].grad, torch.tensor([1.0, 2.0, 0.5]))
    t["b"].grad[1] = float("inf")  # the scaling pass is the guard of what it scaled
    assert not scale_gradients(t, torch.tensor([1.0, 2.0, 0.5]))[1]
    t["b"].grad[1] = 3.0
    assert not scale_gradients(t, torch.tensor([1.0, float("nan"), 0.5]))[1]  # a product that is not finite


# --- losses and restoration ---------------------------------------------------------------
@pytest.mark.parametrize("patch", [1, 4, 7, 11, 40])  # even, odd, and wider than the 9 x 13 image
def test_window_min_is_the_square_minimum_filter_in_value_and_gradient(patch):
    """window_min runs the dark channel's square minimum as a column pass and a row pass; on an image without
    ties both pick the same pixel, so the values equal max_pool2d's over the square window, and so does the gradient
    up to the order in which a pixel that is the minimum of several windows sums their gradients."""
    x = torch.rand(9, 13, generator=torch.Generator().manual_seed(patch), requires_grad=True)
    weights = torch.rand(9, 13, generator=torch.Generator().manual_seed(99))
    got = window_min(x, patch)
    p = dark_channel_window(patch, 9, 13)
    want = -F.max_pool2d(-x[None, None], p, stride=1, padding=p // 2)[0, 0, :9, :13]
    assert torch.equal(got, want)
    (g_got,) = torch.autograd.grad((got * weights).sum(), x)
    (g_want,) = torch.autograd.grad((want * weights).sum(), x)
    torch.testing.assert_close(g_got, g_want, rtol=1e-6, atol=1e-6)
    assert torch.equal(g_got != 0, g_want != 0) and float(g_got.abs().sum()) > 0  # the same pixels


def test_dark_channel_loss():
    img = torch.full((9, 9, 3), 0.6)
    assert float(dcp_loss(img, 3, 0.1)) == pytest.approx(0.6)
    img[4, 4] = 0.0  # one black pixel darkens its whole 3x3 neighbourhood
    dark = soft_dark_channel(img, 3, 0.1)
    assert float(dark[3:6, 3:6].max()) == 0.0 and float(dark[0, 0]) == pytest.approx(0.6)
    rgb = torch.tensor([[[0.2, 0.5, 0.9]]])
    soft = float(soft_dark_channel(rgb, 1, 0.1))
    assert 0.2 <= soft < 0.5 and float(soft_dark_channel(rgb, 1, 0.0)) == pytest.approx(0.2)
    # A mask keeps the prior to its pixels; the mean stays over all pixels (a full mask is the paper's loss).
    img = torch.full((9, 9, 3), 0.6, requires_grad=True)
    full = torch.ones(9, 9, dtype=torch.bool)
    with torch.no_grad():
        assert float(dcp_loss(img, 3, 0.1, mask=full)) == pytest.approx(float(dcp_loss(img, 3, 0.1)))
    half = full.clone()
    half[:, 5:] = False  # e.g. sky on the right
    loss = dcp_loss(img, 1, 0.0, mask=half)
    assert float(loss.detach()) == pytest.approx(0.6 * 45 / 81)
    loss.backward()
    assert float(img.grad[:, 5:].abs().max()) == 0.0 and float(img.grad[:, :5].abs().sum(-1).min()) > 0


def test_classical_restore_removes_thin_streaks():
    img = torch.full((16, 16, 3), 0.3)
    img[:, 7] = 1.0  # a one-pixel bright streak
    out = classical_restore(img)
    assert out.shape == img.shape and float(out.min()) >= 0 and float(out.max()) <= 1
    assert float((out[:, 7] - out[:, 3]).abs().max()) < 0.05


# --- auto evidence ------------------------------------------------------------------------
def test_haze_evidence_from_dark_channel_and_depth():
    rng = np.random.default_rng(0)
    cams = [_camera(32, 24, eye=(0.0, 0.0, float(i) * 0.1)) for i in range(3)]
    # A ground plane of points at depths 2..20 across the image rows.
    u, v = np.meshgrid(np.arange(32) + 0.5, np.arange(24) + 0.5)
    z = 2 + 18 * (v / 24.0)
    pts = np.stack([(u - 16) / cams[0].fx * z, (v - 12) / cams[0].fy * z, z], -1).reshape(-1, 3)
    clean = [torch.from_numpy(rng.uniform(0, 1, (24, 32, 3)).astype(np.float32)) for _ in cams]
    t = torch.from_numpy(np.exp(-0.15 * z).astype(np.float32))[..., None]
    hazy = [img * t + 0.85 * (1 - t) for img in clean]
    ev_clean = haze_evidence(clean, cams, pts, 5, 0.2, 0.5)
    ev_hazy = haze_evidence(hazy, cams, pts, 5, 0.2, 0.5)
    assert not ev_clean.present and ev_hazy.present
    assert ev_hazy.dark_depth_corr > 0.5 > abs(ev_clean.dark_depth_corr)
    assert ev_hazy.transmission_estimate < ev_clean.transmission_estimate
    no_points = haze_evidence(hazy, cams, np.zeros((0, 3)), 5, 0.2, 0.5)
    assert no_points.dark_depth_corr == 0.0 and no_points.present


def test_particle_evidence_sees_additive_thin_structures():
    gen = torch.Generator().manual_seed(0)
    con = torch.rand(48, 64, 3, generator=gen) * 0.5
    noise = (torch.rand(48, 64, 1, generator=gen) - 0.5) * 0.1
    fit = con + noise  # symmetric misfit only
    rainy = fit.clone()
    for col in range(3, 64, 7):
        rainy[5:40, col] += 0.5  # bright streaks
    clean_ev = particle_evidence([residual_tail_counts(fit, con)], 0.3)
    rain_ev = particle_evidence([residual_tail_counts(rainy, con)], 0.3)
    assert not clean_ev.present and rain_ev.present and rain_ev.energy > clean_ev.energy


def test_particles_seen_through_a_veil_are_judged_by_the_haze_pair():
    """Streaks behind a veil (transmission 0.4) with the larger misfit of a hazy fit: both statistics drop to less
    than half, the default haze pair still declares them, and a symmetric misfit is not declared by either pair."""
    gen = torch.Generator().manual_seed(0)
    h, w = 96, 128

    def misfit(scale):  # Laplace: a misfit with tails on both sides
        u = torch.rand(h, w, 1, generator=gen) - 0.5
        return -scale * torch.sign(u) * torch.log1p(-2 * u.abs())

    def veil(x):
        return x * 0.4 + 0.8 * 0.6

    scene = torch.rand(h, w, 3, generator=gen) * 0.5
    streaks = torch.zeros(h, w, 3)
    streaks[5:88, 3::9] = 0.3
    m_clear, m_hazy = misfit(0.02), misfit(0.04)
    cfg = NimbusConfig()

    def evidence(image, composite, hazy):
        return particle_evidence([residual_tail_counts(image, composite)], *particle_thresholds(cfg, hazy), hazy=hazy)

    clear_rain = evidence(scene + streaks + m_clear, scene, False)
    hazy_rain = evidence(veil(scene + streaks) + m_hazy, veil(scene), True)
    assert clear_rain.present and hazy_rain.present and hazy_rain.hazy and not clear_rain.hazy
    assert hazy_rain.asymmetry < clear_rain.asymmetry / 2 and hazy_rain.energy < clear_rain.energy / 2
    # The pair follows the haze decision, and the decision is "asymmetry >= a and energy >= e" with that pair.
    a, e = particle_thresholds(cfg, True)
    assert (a, e) == (cfg.auto_particle_threshold_haze, cfg.auto_particle_energy_haze)
    assert (a, e) != particle_thresholds(cfg, False)
    assert (hazy_rain.asymmetry_threshold, hazy_rain.energy_threshold) == (a, e)
    for hazy in (False, True):
        ev = evidence(veil(scene + streaks) + m_hazy, veil(scene), hazy)
        ta, te = particle_thresholds(cfg, hazy)
        assert ev.present == (ev.asymmetry >= ta and ev.energy >= te)
    assert not evidence(scene + m_clear, scene, False).present
    # Under haze the default pair is met by any evidence (PLM always on: on the validation cells PLM's gain under
    # haze does not follow the evidence); a pair above a symmetric misfit's statistics leaves it out.
    symmetric = [residual_tail_counts(veil(scene) + m_hazy, veil(scene))]
    assert particle_evidence(symmetric, *particle_thresholds(cfg, True), hazy=True).present
    strict = dataclasses.replace(cfg, auto_particle_threshold_haze=0.14, auto_particle_energy_haze=0.0002)
    assert not particle_evidence(symmetric, *particle_thresholds(strict, True), hazy=True).present
    assert particle_evidence([residual_tail_counts(veil(scene + streaks) + m_hazy, veil(scene))],
                             *particle_thresholds(strict, True), hazy=True).present


def test_the_hazy_particle_pair_depends_on_the_view_size():
    cfg = dataclasses.replace(preset("tiny"), auto_particle_threshold_haze=-1.0, auto_particle_energy_haze=0.0,
                              auto_large_view_pixels=10_000, auto_particle_threshold_haze_large=0.2,
                              auto_particle_energy_haze_large=0.001)
    assert particle_thresholds(cfg, True, 64 * 48) == (-1.0, 0.0)
    assert particle_thresholds(cfg, True, None) == (-1.0, 0.0)
    assert particle_thresholds(cfg, True, 10_000) == particle_thresholds(cfg, True, 240 * 180) == (0.2, 0.001)
    # the haze-free pair does not depend on the size
    assert particle_thresholds(cfg, False, 64 * 48) == particle_thresholds(cfg, False, 240 * 180) == (
        cfg.auto_particle_threshold, cfg.auto_particle_energy)


# --- config and registry --------------------------------------------------------------------
def test_config_presets_variants_and_validation():
    tiny, fast, paper = preset("tiny"), preset("fast"), preset("paper")
    assert (paper.m_init, paper.m_joint, paper.grid_resolution, paper.ray_samples) == (4000, 26000, 128, 64)
    assert (paper.lambda_dssim, paper.ggs_r0, paper.refresh_interval) == (0.4, 3.0, 100)
    assert (paper.lr_scales_init, paper.lr_extinction, paper.lr_airlight) == (2e-3, 5e-3, 5e-4)
    for c in (tiny, fast):
        assert 0 < c.m_init < c.iterations and c.m_init / c.iterations == pytest.approx(4000 / 30000, rel=0.25)
    longer = apply_overrides(fast, {"iterations": "6000"})
    assert longer.m_init == 2 * fast.m_init and longer.densify_until == 2 * fast.densify_until
    assert apply_overrides(fast, {"components": "csm,ggs", "ggs_clip": "0,10"}).forced_components == {"csm", "ggs"}
    assert paper_m_init(fast, 1000) == 100 and paper_m_init(paper, 15000) == 15000
    assert parse_components("auto") is None and parse_components("none") == frozenset()
    with pytest.raises(NimbusError, match="components"):
        apply_overrides(fast, {"components": "csm,fog"})
    with pytest.raises(NimbusError, match="m_init"):
        NimbusConfig(iterations=100, m_init=100)
    with pytest.raises(NimbusError, match="extinction"):
        apply_overrides(fast, {"extinction": "voxels"})
    with pytest.raises(NimbusError, match="unknown preset"):
        preset("huge")
    with pytest.raises(NimbusError, match="residual_tophat"):
        apply_overrides(fast, {"residual_tophat": "2"})
    with pytest.raises(NimbusError, match="residual_outlier_scope"):
        apply_overrides(fast, {"residual_outlier_scope": "some"})


def test_named_methods_are_registered_with_their_settings():
    from nimbus.methods.nimbusgs.method import NimbusGS
    from nimbus.methods.registry import get_method

    assert get_method("nimbus").preset("tiny").components == "auto"
    assert get_method("nimbus-no-ggs").preset("tiny").forced_components == {"csm", "plm"}
    assert get_method("nimbus-uniform-extinction").preset("fast").extinction == "uniform"
    assert get_method("nimbus-minit-1k").preset("fast").m_init == 100
    assert get_method("nimbus-minit-15k").preset("paper").m_init == 15000
    spec = get_method("nimbus-no-plm")
    assert spec.load() is NimbusGS and spec.name == "nimbus-no-plm"
    assert get_method("nimbus").load() is NimbusGS


# --- per-view density (view_density) ----------------------------------------------------------------------------
def _medium(view_density: bool, views: int = 3):
    from nimbus.methods.nimbusgs.degradation import Medium

    cfg = apply_overrides(preset("tiny"), {"view_density": str(view_density).lower(), "airlight": "constant"})
    box = Box((-50.0,) * 3, (50.0,) * 3)
    return Medium(cfg, box, 0.7, 4.0, torch.tensor([0.7, 0.8, 0.9]), seed=0, device=torch.device("cpu"),
                  views=views)


def test_view_density_raises_each_views_transmission_to_its_factor():
    medium = _medium(True)
    with torch.no_grad():
        medium.view_log_density.copy_(torch.tensor([math.log(2.0), 0.0, math.log(0.25)]))
    # Factors are normalised to a geometric mean of 1: they cannot trade with the field's own scale.
    factors = torch.stack([medium.view_density(v) for v in range(3)])
    torch.testing.assert_close(factors.log().sum(), torch.tensor(0.0), atol=1e-6, rtol=0)
    torch.testing.assert_close(factors[0] / factors[1], torch.tensor(2.0))
    cam = _camera()
    rays = camera_rays(cam)
    render = {"depth": torch.full((cam.height, cam.width), 3.0), "alpha": torch.ones(cam.height, cam.width)}
    desc = torch.tensor([0.7, 0.8, 0.9, 0.5, 0.5, 0.5])
    t_field, p_field = medium.forward(rays, render, desc)  # no training view: the field alone
    assert 0.05 < float(t_field.detach().mean()) < 0.95
    for v in range(3):
        t, p = medium.forward(rays, render, desc, view_index=v)
        torch.testing.assert_close(t, t_field ** factors[v], rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(p, (1 - t) * torch.tensor([0.7, 0.8, 0.9]), rtol=1e-5, atol=1e-6)
    # The factor is learned: the transmission's gradient reaches it, and it survives the state round trip.
    t, _ = medium.forward(rays, render, desc, view_index=0)
    t.sum().backward()
    assert medium.view_log_density.grad is not None and float(medium.view_log_density.grad.abs().sum()) > 0
    copy = _medium(True)
    copy.load_state_dict(medium.state_dict())
    torch.testing.assert_close(copy.view_log_density, medium.view_log_density.detach())


def test_view_density_off_is_the_field_alone():
    medium = _medium(False)
    assert medium.view_log_density is None and medium.view_density(0) is None
    assert "view_density" not in {g["name"] for g in medium.param_groups()}
    assert medium.state_dict()["view_log_density"] is None
    _medium(False).load_state_dict(medium.state_dict())


def test_ablations_are_variants_of_one_registry_entry(capsys):
    from nimbus.cli.train import main
    from nimbus.methods.registry import ENTRIES, METHODS, NIMBUS_VARIANTS

    assert [e.name for e in ENTRIES] == ["3dgs", "restore-3dgs", "robust-3dgs", "medium-3dgs", "nimbus"]
    assert len(METHODS) == len(ENTRIES) + len(NIMBUS_VARIANTS)
    for v in NIMBUS_VARIANTS:  # each variant is the nimbus entry's class and presets with its own changes
        spec = METHODS[f"nimbus-{v.suffix}"]
        assert spec.base == "nimbus" and spec.target == METHODS["nimbus"].target
        config = spec.preset("tiny")
        for key, value in v.changes.items():
            assert getattr(config, key) == (value(METHODS["nimbus"].preset("tiny")) if callable(value) else value)
    assert METHODS["nimbus-ggs-no-depth"].preset("tiny").components == "csm,plm,ggs"
    with pytest.raises(SystemExit) as exit_:
        main(["--method", "help"])
    assert exit_.value.code == 0
    listing = capsys.readouterr().out
    assert all(name in listing for name in METHODS)
    assert "\n  nimbus-minit-15k " in listing and "\nnimbus " in listing
