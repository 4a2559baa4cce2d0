"""The tiled rasterizer against the dense reference and closed forms."""

from __future__ import annotations

import importlib
import math

import numpy as np
import pytest
import torch

from nimbus.data import Camera, Scene, View
from nimbus.errors import NimbusError
from nimbus.render import (
    GaussianInitConfig,
    Gaussians,
    RasterConfig,
    init_from_points,
    init_from_scene,
    rasterize,
    reference,
)
from nimbus.render import backends
from nimbus.render import gaussians as gaussians_module
from nimbus.render.backends import cpp as cpp_backend
from nimbus.render.backends import torch as torch_backend
from nimbus.render.backends.base import Backend
from nimbus.render.binning import bin_gaussians, tile_rects
from nimbus.render.composite_torch import CompositeConfig, composite
from nimbus.render.gaussians import knn_mean_distance
from nimbus.render.projection import ProjectionConfig, project_gaussians
from nimbus.render.reference import composite_dense, rasterize_reference
from nimbus.render.sh import C0, eval_sh, rgb_to_sh, sh_colors

# The package re-exports the function `rasterize`, which shadows the submodule attribute.
rasterize_module = importlib.import_module("nimbus.render.rasterize")

# Not multiples of the tile size: the last tile column and row are partial.
W, H, TILE = 27, 13, 8
CAM = Camera(W, H, fx=20.0, fy=22.0, cx=13.0, cy=6.5)
# Tiny work sizes so the small scenes still exercise sub-tiles, K chunks, several batches and
# sub-tiles leaving a batch early; the default splits 16 px tiles into 8 px sub-tiles.
SMALL = RasterConfig(tile_size=TILE, composite=CompositeConfig(subtile=4, chunk=3, batch_elements=4 * 16 * 3))
NO_SPLIT = RasterConfig(tile_size=TILE, composite=CompositeConfig(subtile=TILE, chunk=5))
DEFAULT = RasterConfig(tile_size=16)
BG = (0.2, 0.5, 0.9)


def make_gaussians(n, seed=0, dtype=torch.float64, opacity=(-2.0, 3.0), scale=(0.05, 0.4), depth=4.0, sh_degree=3):
    g = torch.Generator().manual_seed(seed)

    def rnd(*shape):
        return torch.rand(*shape, generator=g, dtype=dtype)

    means = (rnd(n, 3) * 2 - 1) * torch.tensor([2.0, 1.4, 1.0], dtype=dtype) + torch.tensor([0, 0, depth], dtype=dtype)
    log_scales = torch.log(scale[0] + rnd(n, 3) * (scale[1] - scale[0]))
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    logits = opacity[0] + rnd(n) * (opacity[1] - opacity[0])
    k = (sh_degree + 1) ** 2
    return Gaussians(means, log_scales, quats, logits, torch.randn(n, 1, 3, generator=g, dtype=dtype),
                     0.3 * torch.randn(n, k - 1, 3, generator=g, dtype=dtype))


def with_edge_cases(gs: Gaussians) -> Gaussians:
    """Append Gaussians behind the camera, off-screen, huge, tiny and straddling the image border."""
    dtype = gs.means.dtype
    extra_means = torch.tensor([
        [0.0, 0.0, -2.0],     # behind the camera
        [0.1, 0.0, 0.005],    # in front of the camera but before the near plane
        [30.0, 0.0, 4.0],     # far off-screen to the right
        [0.0, -25.0, 4.0],    # far above
        [0.3, 0.2, 3.0],      # huge (covers every tile)
        [-0.4, 0.1, 2.5],     # tiny (sub-pixel; the 0.3 px^2 dilation keeps it visible)
        [-2.5, 0.0, 4.0],     # straddles the left border
        [0.0, 1.7, 4.0],      # straddles the bottom border
    ], dtype=dtype)
    extra_scales = torch.log(torch.tensor([[0.3] * 3, [0.3] * 3, [0.3] * 3, [0.3] * 3, [4.0, 3.0, 2.0],
                                           [1e-4] * 3, [0.3] * 3, [0.3] * 3], dtype=dtype))
    n = extra_means.shape[0]
    g = torch.Generator().manual_seed(99)
    k = gs.sh_rest.shape[1]
    return Gaussians(
        torch.cat([gs.means, extra_means]),
        torch.cat([gs.log_scales, extra_scales]),
        torch.cat([gs.quats, torch.randn(n, 4, generator=g, dtype=dtype)]),
        torch.cat([gs.opacity_logits, torch.full((n,), 1.0, dtype=dtype)]),
        torch.cat([gs.sh_dc, torch.randn(n, 1, 3, generator=g, dtype=dtype)]),
        torch.cat([gs.sh_rest, 0.3 * torch.randn(n, k, 3, generator=g, dtype=dtype)]),
    )


def saturating(dtype=torch.float64) -> Gaussians:
    """Many large, nearly opaque Gaussians: most pixels reach T < 1e-4 and stop early."""
    return make_gaussians(40, seed=3, dtype=dtype, opacity=(4.0, 7.0), scale=(0.3, 0.8), depth=5.0)


def _grads(outputs, gs: Gaussians, seed=1):
    g = torch.Generator().manual_seed(seed)
    weights = [torch.randn(x.shape, generator=g, dtype=torch.float64).to(x.dtype) for x in outputs[:3]]
    loss = sum((x * w).sum() for x, w in zip(outputs[:3], weights))
    return torch.autograd.grad(loss, list(gs.tensors().values()), allow_unused=True)


def left_columns_only(dtype=torch.float64) -> Gaussians:
    """Small Gaussians projecting left of u = 8, so the rightmost tile column stays empty."""
    gs = make_gaussians(12, seed=2, dtype=dtype, scale=(0.02, 0.08), depth=6.0)
    gs.means[:, 0] = -2.1 - 0.3 * torch.rand(12, generator=torch.Generator().manual_seed(2), dtype=dtype)
    return gs


SCENES = {
    "random": lambda dtype: make_gaussians(30, seed=0, dtype=dtype),
    "edge_cases": lambda dtype: with_edge_cases(make_gaussians(20, seed=1, dtype=dtype)),
    "saturating": saturating,
    "left_half_only": left_columns_only,
}


@pytest.mark.parametrize("scene", sorted(SCENES))
@pytest.mark.parametrize("config", [SMALL, NO_SPLIT, DEFAULT], ids=["small_chunks", "no_split", "default"])
def test_forward_matches_dense_reference_float32(scene, config):
    gs = SCENES[scene](torch.float32)
    rgb, depth, alpha, meta = rasterize(gs, CAM, background=BG, config=config)
    ref = rasterize_reference(gs, CAM, background=BG, config=config)
    assert rgb.shape == (H, W, 3) and depth.shape == (H, W) and alpha.shape == (H, W)
    torch.testing.assert_close(rgb, ref[0], atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(depth, ref[1], atol=2e-5, rtol=1e-5)
    torch.testing.assert_close(alpha, ref[2], atol=1e-5, rtol=1e-5)
    assert meta["num_intersections"] > 0


@pytest.mark.parametrize("scene", sorted(SCENES))
def test_gradients_match_dense_reference_float64(scene):
    gs = SCENES[scene](torch.float64).requires_grad_()
    fast = _grads(rasterize(gs, CAM, background=BG, config=SMALL), gs)
    ref = _grads(rasterize_reference(gs, CAM, background=BG, config=SMALL), gs)
    for name, a, b in zip(gs.tensors(), fast, ref):
        assert b is not None and torch.isfinite(b).all(), name
        torch.testing.assert_close(a, b, atol=1e-9, rtol=1e-7, msg=lambda m, name=name: f"{name}: {m}")


def test_gradients_float32_close_to_float64_reference():
    gs64 = with_edge_cases(make_gaussians(20, seed=4)).requires_grad_()
    gs32 = gs64.detach().to(dtype=torch.float32).requires_grad_()
    fast = _grads(rasterize(gs32, CAM, background=BG, config=DEFAULT), gs32)
    ref = _grads(rasterize_reference(gs64, CAM, background=BG, config=DEFAULT), gs64)
    for name, a, b in zip(gs64.tensors(), fast, ref):
        scale = b.abs().max().item() + 1e-12
        assert (a.double() - b).abs().max().item() <= 1e-3 * scale, name


def test_saturating_scene_exercises_the_stop_rule(monkeypatch):
    gs = saturating()
    rgb, _, alpha, _ = rasterize(gs, CAM, config=SMALL)
    assert alpha.max() > 0.999
    # Without the stop the reference differs: the rule is active in this scene, and the fast path follows it.
    monkeypatch.setattr(reference, "T_STOP", 0.0)
    rgb_nostop = rasterize_reference(gs, CAM, config=SMALL)[0]
    assert (rgb_nostop - rgb).abs().max() > 1e-6


def test_edge_cases_are_culled_and_projected():
    gs = with_edge_cases(make_gaussians(20, seed=1))
    _, _, _, meta = rasterize(gs, CAM, config=SMALL)
    visible = meta["visible"][20:].tolist()
    # behind, before near, off right, off top, huge, tiny, left border, bottom border
    assert visible == [False, False, False, False, True, True, True, True]
    assert meta["radii"].dtype == torch.int32 and (meta["radii"][20:24] == 0).all()
    assert (meta["means2d"][20:22] == 0).all()  # culled before the maths, scattered as zeros
    assert meta["radii"][24] > 2 * W  # the huge one covers everything
    assert meta["radii"][25] == math.ceil(3 * math.sqrt(0.3))  # the tiny one is just the dilation


def test_empty_tiles_show_background():
    gs = left_columns_only(torch.float32)
    rgb, depth, alpha, meta = rasterize(gs, CAM, background=BG, config=SMALL)
    right = slice(2 * TILE, W)
    assert (meta["means2d"][:, 0] < TILE).all()
    torch.testing.assert_close(rgb[:, right], torch.tensor(BG).expand(H, W - 2 * TILE, 3))
    assert (alpha[:, right] == 0).all() and (depth[:, right] == 0).all()
    assert alpha[:, :TILE].max() > 0.1


@pytest.mark.parametrize("where", ["none", "all_behind"])
def test_no_visible_gaussians_returns_background_and_backward_runs(where):
    n = 0 if where == "none" else 5
    gs = make_gaussians(n, dtype=torch.float32)
    if where == "all_behind":
        gs.means[:, 2] = -3.0
    gs.requires_grad_()
    rgb, depth, alpha, meta = rasterize(gs, CAM, background=BG, config=SMALL)
    torch.testing.assert_close(rgb, torch.tensor(BG).expand(H, W, 3))
    assert (alpha == 0).all() and (depth == 0).all() and meta["num_intersections"] == 0
    (rgb.sum() + depth.sum() + alpha.sum()).backward()
    assert gs.means.grad is not None and gs.means.grad.shape == (n, 3) and (gs.means.grad == 0).all()


def test_means2d_grad_is_retained_and_matches_reference():
    gs = make_gaussians(25, seed=5).requires_grad_()
    out = rasterize(gs, CAM, config=SMALL)
    ref = rasterize_reference(gs, CAM, config=SMALL)
    (out[0].sum() + out[2].sum()).backward()
    (ref[0].sum() + ref[2].sum()).backward()
    g = rasterize_module.means2d_grad(out[3])
    assert g.shape == (25, 2) and g.abs().sum() > 0
    torch.testing.assert_close(g, ref[3]["means2d"].grad, atol=1e-9, rtol=1e-7)
    assert (g[~out[3]["visible"]] == 0).all()


def test_binning_needs_no_tile_mask_for_faint_gaussians():
    # Opacity < 0.35: alpha falls below 1/255 inside 3 sigma, so the tile boxes lose nothing and the
    # fast path must equal a reference that ignores tiles altogether.
    gs = make_gaussians(30, seed=6, opacity=(-4.0, -0.7))
    out = rasterize(gs, CAM, background=BG, config=SMALL)
    ref = rasterize_reference(gs, CAM, background=BG, config=SMALL, respect_tiles=False)
    for a, b in zip(out[:3], ref[:3]):
        torch.testing.assert_close(a, b, atol=1e-12, rtol=1e-10)


def test_bin_gaussians_against_brute_force():
    g = torch.Generator().manual_seed(7)
    m = 40
    means2d = torch.rand(m, 2, generator=g) * torch.tensor([W + 20.0, H + 20.0]) - 10
    radii = torch.randint(0, 12, (m,), generator=g).to(torch.int32)
    depths = torch.rand(m, generator=g)
    isect, offsets = bin_gaussians(means2d, radii, depths, W, H, TILE)
    rect = tile_rects(means2d, radii, W, H, TILE)
    tiles_x = math.ceil(W / TILE)
    assert offsets.shape == (tiles_x * math.ceil(H / TILE) + 1,) and offsets[-1] == isect.numel()
    for t in range(offsets.numel() - 1):
        ids = isect[offsets[t]:offsets[t + 1]].tolist()
        tx, ty = t % tiles_x, t // tiles_x
        expected = [i for i in range(m)
                    if radii[i] > 0 and rect[i, 0] <= tx < rect[i, 2] and rect[i, 1] <= ty < rect[i, 3]]
        assert sorted(ids) == expected
        assert (depths[ids].diff() >= 0).all()
        for i in expected:  # the rectangle is the tiles overlapped by the radius box
            assert means2d[i, 0] - radii[i] < (tx + 1) * TILE and means2d[i, 0] + radii[i] > tx * TILE


def test_composite_gradcheck_including_background():
    g = torch.Generator().manual_seed(8)
    m, w, h, ts = 7, 10, 7, 4
    means2d = (torch.rand(m, 2, generator=g, dtype=torch.float64) * torch.tensor([w, h])).requires_grad_()
    cov = torch.rand(m, 2, generator=g, dtype=torch.float64) * 4 + 1.0
    conics = torch.stack([1 / cov[:, 0], torch.zeros(m, dtype=torch.float64) + 0.05, 1 / cov[:, 1]], 1)
    conics.requires_grad_()
    colors = torch.rand(m, 3, generator=g, dtype=torch.float64).requires_grad_()
    opac = (0.3 + 0.6 * torch.rand(m, generator=g, dtype=torch.float64)).requires_grad_()
    depths = (1 + torch.rand(m, generator=g, dtype=torch.float64)).requires_grad_()
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64, requires_grad=True)
    radii = torch.full((m,), 8, dtype=torch.int32)
    isect, offsets = bin_gaussians(means2d, radii, depths, w, h, ts)
    cfg = CompositeConfig(chunk=2, batch_elements=2 * ts * ts)

    def fn(*args):
        return composite(*args[:5], isect, offsets, w, h, ts, args[5], config=cfg)

    assert torch.autograd.gradcheck(fn, (means2d, conics, colors, opac, depths, bg), eps=1e-6, atol=1e-6,
                                    fast_mode=True)
    dense = composite_dense(means2d, conics, colors, opac, depths, radii, w, h, ts, bg)
    for a, b in zip(fn(means2d, conics, colors, opac, depths, bg), dense):
        torch.testing.assert_close(a, b)


def test_composite_with_indefinite_conics_matches_dense():
    # The contract allows any conic: where sigma < 0 the Gaussian is skipped, so no culling may apply.
    g = torch.Generator().manual_seed(16)
    m, w, h, ts = 12, 19, 11, 8
    means2d = (torch.rand(m, 2, generator=g, dtype=torch.float64) * torch.tensor([w, h])).requires_grad_()
    a = 0.05 + 0.3 * torch.rand(m, generator=g, dtype=torch.float64)
    c = 0.05 + 0.3 * torch.rand(m, generator=g, dtype=torch.float64)
    b = torch.where(torch.arange(m) % 2 == 0, 1.5 * torch.sqrt(a * c), 0.2 * torch.sqrt(a * c))  # even: indefinite
    conics = torch.stack([a, b, c], 1).requires_grad_()
    colors = torch.rand(m, 3, generator=g, dtype=torch.float64).requires_grad_()
    opac = (0.2 + 0.7 * torch.rand(m, generator=g, dtype=torch.float64)).requires_grad_()
    depths = (1 + torch.rand(m, generator=g, dtype=torch.float64)).requires_grad_()
    bg = torch.tensor([0.3, 0.3, 0.3], dtype=torch.float64)
    radii = torch.full((m,), 30, dtype=torch.int32)
    isect, offsets = bin_gaussians(means2d, radii, depths, w, h, ts)
    leaves = (means2d, conics, colors, opac, depths)
    fast = composite(*leaves, isect, offsets, w, h, ts, bg, config=CompositeConfig(subtile=4, chunk=4))
    dense = composite_dense(*leaves, radii, w, h, ts, bg)
    for x, y in zip(fast, dense):
        torch.testing.assert_close(x, y)
    assert (dense[2] > 0).all() and dense[2].min() < 0.99  # drawn everywhere, not saturated
    weights = [torch.randn(x.shape, generator=g, dtype=torch.float64) for x in fast]
    g_fast = torch.autograd.grad(sum((x * u).sum() for x, u in zip(fast, weights)), leaves)
    g_dense = torch.autograd.grad(sum((x * u).sum() for x, u in zip(dense, weights)), leaves)
    for x, y in zip(g_fast, g_dense):
        torch.testing.assert_close(x, y)


def test_projection_of_isotropic_gaussian_closed_form():
    f, z, s = 50.0, 5.0, 0.2
    cam = Camera(64, 48, f, f, 30.0, 20.0)
    means = torch.tensor([[0.0, 0.0, z]], dtype=torch.float64)
    quats = torch.tensor([[0.7, 0.1, -0.3, 0.2]], dtype=torch.float64)  # rotation is irrelevant for a sphere
    log_scales = torch.full((1, 3), math.log(s), dtype=torch.float64)
    viewmat = torch.eye(4, dtype=torch.float64)
    p = project_gaussians(means, quats, log_scales, viewmat, torch.as_tensor(cam.K), 64, 48)
    var = (f * s / z) ** 2 + 0.3
    torch.testing.assert_close(p.means2d, torch.tensor([[30.0, 20.0]], dtype=torch.float64))
    torch.testing.assert_close(p.conics, torch.tensor([[1 / var, 0.0, 1 / var]], dtype=torch.float64))
    torch.testing.assert_close(p.depths, torch.tensor([z], dtype=torch.float64))
    assert p.radii.tolist() == [math.ceil(3 * math.sqrt(var))]


def test_projection_follows_camera_pose_and_clamps_far_off_axis():
    cam = Camera.look_at(eye=[1.0, 2.0, -3.0], target=[0.0, 0.0, 0.0], up=[0.0, -1.0, 0.0], width=40, height=30,
                         fov_x_deg=60.0)
    pts = np.array([[0.1, -0.2, 0.3], [0.0, 0.0, 0.0]])
    uv, z = cam.project(pts)
    n = len(pts)
    viewmat = torch.as_tensor(cam.world_to_camera)
    p = project_gaussians(torch.as_tensor(pts), torch.tensor([[1.0, 0, 0, 0]] * n, dtype=torch.float64),
                          torch.full((n, 3), -3.0, dtype=torch.float64), viewmat, torch.as_tensor(cam.K), 40, 30)
    torch.testing.assert_close(p.means2d, torch.as_tensor(uv))
    torch.testing.assert_close(p.depths, torch.as_tensor(z))
    # Far off-axis: the Jacobian is evaluated at the clamped x/z, so the footprint stays bounded.
    far = torch.tensor([[100.0, 0.0, 1.0]], dtype=torch.float64)
    q = project_gaussians(far, torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64),
                          torch.full((1, 3), math.log(0.1), dtype=torch.float64), torch.eye(4, dtype=torch.float64),
                          torch.as_tensor(cam.K), 40, 30, ProjectionConfig())
    tan = 20 / cam.fx * 1.3
    jx = math.hypot(cam.fx, cam.fx * tan) * 0.1  # |J row| * s with x/z clamped to 1.3 tan(fov/2)
    torch.testing.assert_close(1 / q.conics[0, 0], torch.tensor(jx ** 2 + 0.3, dtype=torch.float64))


def test_camera_and_tensor_inputs_agree():
    gs = make_gaussians(20, seed=9, dtype=torch.float32)
    a = rasterize(gs, CAM, config=SMALL)
    b = rasterize(gs, viewmat=torch.as_tensor(CAM.world_to_camera), K=torch.as_tensor(CAM.K), width=W, height=H,
                  config=SMALL)
    for x, y in zip(a[:3], b[:3]):
        torch.testing.assert_close(x, y)


def test_sh_degree0_colour_and_orthonormal_basis():
    dc = torch.randn(6, 1, 3, dtype=torch.float64)
    means = torch.randn(6, 3, dtype=torch.float64)
    torch.testing.assert_close(sh_colors(0, dc, means, torch.zeros(3, dtype=torch.float64)),
                               torch.clamp_min(C0 * dc[:, 0] + 0.5, 0))
    torch.testing.assert_close(rgb_to_sh(torch.tensor(0.7, dtype=torch.float64)) * C0 + 0.5,
                               torch.tensor(0.7, dtype=torch.float64))
    # The 16 basis functions are orthonormal on the sphere (catches a wrong constant or sign-free typo).
    n = 20000
    i = torch.arange(n, dtype=torch.float64) + 0.5
    zc = 1 - 2 * i / n
    phi = math.pi * (1 + 5 ** 0.5) * i
    dirs = torch.stack([torch.sqrt(1 - zc ** 2) * torch.cos(phi), torch.sqrt(1 - zc ** 2) * torch.sin(phi), zc], 1)
    basis = torch.stack([eval_sh(3, torch.eye(16, dtype=torch.float64)[k][None, :, None].expand(n, 16, 1), dirs)[:, 0]
                         for k in range(16)], 1)
    gram = basis.T @ basis * (4 * math.pi / n)
    torch.testing.assert_close(gram, torch.eye(16, dtype=torch.float64), atol=2e-3, rtol=0)


def test_lower_sh_degree_ignores_higher_bands():
    gs = make_gaussians(15, seed=10, dtype=torch.float32)
    a = rasterize(gs, CAM, sh_degree=1, config=SMALL)[0]
    gs.sh_rest[:, 3:] += 5.0
    b = rasterize(gs, CAM, sh_degree=1, config=SMALL)[0]
    c = rasterize(gs, CAM, config=SMALL)[0]
    torch.testing.assert_close(a, b)
    assert (a - c).abs().max() > 1e-3


def test_knn_scale_and_init_from_points(monkeypatch):
    line = np.array([[x, 0.0, 0.0] for x in range(5)])
    d = knn_mean_distance(torch.as_tensor(line), 3)
    torch.testing.assert_close(d, torch.tensor([2.0, 4 / 3, 4 / 3, 4 / 3, 2.0], dtype=torch.float64))
    # Blocked search (tiny blocks and windows) agrees with brute force, duplicates and an outlier included.
    monkeypatch.setattr(gaussians_module, "_KNN_BLOCK_ELEMENTS", 64)
    monkeypatch.setattr(gaussians_module, "_KNN_QUERY_CHUNK", 16)
    monkeypatch.setattr(gaussians_module, "_KNN_WINDOW", 2)
    pts = torch.rand(200, 3, generator=torch.Generator().manual_seed(11), dtype=torch.float64) * 100 + 1000
    pts[5] = pts[6]
    pts[7] = torch.tensor([5000.0, 0.0, 0.0], dtype=torch.float64)
    brute = torch.cdist(pts, pts, compute_mode="donot_use_mm_for_euclid_dist")
    brute.fill_diagonal_(math.inf)
    expected = brute.topk(3, largest=False).values.mean(1)
    torch.testing.assert_close(knn_mean_distance(pts, 3), expected)

    colors = np.array([[255, 0, 128]] * 5, dtype=np.uint8)
    gs = init_from_points(line, colors, GaussianInitConfig(sh_degree=2))
    torch.testing.assert_close(gs.scales[:, 0], d.float())
    torch.testing.assert_close(gs.opacities, torch.full((5,), 0.1))
    torch.testing.assert_close(gs.sh_dc[:, 0] * C0 + 0.5, torch.tensor([[1.0, 0.0, 128 / 255]] * 5))
    assert gs.sh_rest.shape == (5, 8, 3) and gs.sh_degree == 2 and (gs.sh_rest == 0).all()
    torch.testing.assert_close(gs.quats, torch.tensor([[1.0, 0, 0, 0]] * 5))


def test_init_from_scene_with_and_without_points():
    cams = [Camera.look_at([4 * math.cos(a), 0.0, 4 * math.sin(a)], [0, 0, 0], [0, -1, 0], 8, 6, 60.0)
            for a in (0.0, 2.0, 4.0)]
    views = [View(name=f"v{i}", camera=c) for i, c in enumerate(cams)]
    empty = Scene(views=views)
    cfg = GaussianInitConfig(random_points=500, sh_degree=0)
    gs = init_from_scene(empty, cfg)
    # No points: a ball about the cameras' focus (the origin they look at), radius half their distance.
    assert len(gs) == 500 and gs.sh_rest.shape == (500, 0, 3)
    assert (gs.means.norm(dim=1) <= 0.5 * 4 + 1e-5).all()
    assert torch.isfinite(gs.log_scales).all()
    pts = np.random.default_rng(0).normal(size=(50, 3))
    with_points = Scene(views=views, points=pts, colors=np.zeros((50, 3), np.uint8))
    gs2 = init_from_scene(with_points, cfg)
    torch.testing.assert_close(gs2.means.double(), torch.as_tensor(pts), atol=1e-6, rtol=0)


def test_backend_selection(monkeypatch):
    gs = make_gaussians(10, seed=12, dtype=torch.float32)
    with pytest.raises(NimbusError, match="unknown rasterizer backend"):
        rasterize(gs, CAM, backend="opengl")
    with pytest.raises(NimbusError, match="gsplat"):
        if backends.available("gsplat", "cuda"):
            pytest.skip("gsplat and CUDA are available here")
        rasterize(gs, CAM, backend="gsplat")
    monkeypatch.setattr(cpp_backend, "kernel_available", lambda: False)
    rgb, _, _, meta = rasterize(gs, CAM, backend="auto", config=SMALL)
    assert meta["backend"] == "torch"
    torch.testing.assert_close(rgb, rasterize(gs, CAM, backend="torch", config=SMALL)[0])
    with pytest.raises(NimbusError, match="cpp"):
        rasterize(gs, CAM, backend="cpp")


def _fake_rasterize(gaussians, viewmat, K, width, height, sh_degree, background, config, absgrad):
    rgb, depth, alpha, meta = torch_backend.rasterize(gaussians, viewmat, K, width, height, sh_degree, background,
                                                      config, absgrad)
    return 1 - rgb, depth, alpha, dict(meta, backend="fake")


# A backend is one module defining a Backend and one line in backends.REGISTRY: here, this module.
FAKE_BACKEND = Backend(name="fake", rasterize=_fake_rasterize, available=lambda device: True)


def test_a_backend_is_one_definition_and_one_registry_line(monkeypatch):
    monkeypatch.setitem(backends.REGISTRY, "fake", f"{__name__}:FAKE_BACKEND")
    gs = make_gaussians(12, seed=40).requires_grad_()
    rgb, _, _, meta = rasterize(gs, CAM, background=BG, backend="fake", config=SMALL)
    ref, _, _, ref_meta = rasterize(gs, CAM, background=BG, backend="torch", config=SMALL)
    assert meta["backend"] == "fake"
    torch.testing.assert_close(rgb, 1 - ref)
    rgb.sum().backward()
    assert meta["means2d"].grad.shape == (12, 2)
    # Without auto_rank it is never chosen by "auto"; it does not collect absgrad, and says so by name.
    assert rasterize(gs, CAM, backend="auto", config=SMALL)[3]["backend"] != "fake"
    with pytest.raises(NimbusError, match="backend 'fake' does not collect absgrad"):
        rasterize(gs, CAM, backend="fake", absgrad=torch.zeros(12, 2, dtype=torch.float64))
    monkeypatch.delitem(backends.REGISTRY, "fake")
    with pytest.raises(NimbusError, match="unknown rasterizer backend 'fake'; choose one of auto, torch, cpp, gsplat"):
        rasterize(gs, CAM, backend="fake")


@pytest.mark.parametrize("name", list(backends.REGISTRY))
def test_every_backend_returns_the_same_meta(name):
    device = "cuda" if name == "gsplat" else "cpu"
    if not backends.available(name, device):
        pytest.skip(f"backend {name} is not available here")
    n = 28
    gs = with_edge_cases(make_gaussians(20, seed=41, dtype=torch.float32)).to(device).requires_grad_()
    rgb, depth, alpha, meta = rasterize(gs, CAM, background=BG, backend=name, config=DEFAULT)
    assert set(meta) == {"means2d", "radii", "depths", "visible", "num_intersections", "backend", "width", "height",
                         "row_scale"}
    assert (meta["row_scale"] is not None) == (name == "cpp")  # the only backend that folds gradient factors
    assert meta["backend"] == name and (meta["width"], meta["height"]) == (W, H)
    assert rgb.shape == (H, W, 3) and depth.shape == (H, W) and alpha.shape == (H, W)
    assert meta["means2d"].shape == (n, 2) and meta["depths"].shape == (n,)
    assert meta["radii"].shape == (n,) and meta["radii"].dtype == torch.int32
    assert meta["visible"].shape == (n,) and meta["visible"].dtype == torch.bool
    assert isinstance(meta["num_intersections"], int)
    (rgb.sum() + alpha.sum()).backward()
    grad = meta["means2d"].grad
    assert grad is not None and grad.shape == (n, 2) and grad.abs().sum() > 0
    assert (grad[~meta["visible"]] == 0).all()  # culled Gaussians keep their row, with zero gradient
    assert rasterize_module.means2d_grad(meta) is grad


def test_gsplats_means2d_becomes_n_by_2_with_its_gradient():
    from nimbus.render.backends.gsplat import first_camera

    x = torch.randn(5, 2, dtype=torch.float64, requires_grad=True)
    batched = (x * 3)[None]  # gsplat's [1, N, 2], consumed by its rasterizer
    flat = first_camera(batched)
    assert flat.shape == (5, 2)
    w = torch.randn(1, 5, 2, dtype=torch.float64)
    for _ in range(2):  # added up over backward passes, as a retained gradient is
        (batched * w).sum().backward(retain_graph=True)
    torch.testing.assert_close(flat.grad, 2 * w[0])
    assert first_camera(batched.detach()).grad is None


def test_absgrad_is_refused_by_name_where_it_is_not_collected():
    gs = make_gaussians(6, seed=42)
    with pytest.raises(NimbusError, match="backend 'torch' does not collect absgrad .backends that do: cpp"):
        rasterize(gs, CAM, backend="torch", absgrad=torch.zeros(6, 2, dtype=torch.float64))


def test_cpp_backend_matches_torch_when_available():
    if not backends.available("cpp"):
        pytest.skip("C++ compositing kernel not available")
    gs = with_edge_cases(make_gaussians(30, seed=13, dtype=torch.float32)).requires_grad_()
    a = rasterize(gs, CAM, background=BG, backend="cpp", config=DEFAULT)
    b = rasterize(gs, CAM, background=BG, backend="torch", config=DEFAULT)
    for x, y in zip(a[:3], b[:3]):
        torch.testing.assert_close(x, y, atol=1e-5, rtol=1e-5)
    for name, x, y in zip(gs.tensors(), _grads(a, gs), _grads(b, gs)):
        torch.testing.assert_close(x, y, atol=1e-4, rtol=1e-3, msg=lambda m, name=name: f"{name}: {m}")


def _needs_cpp():
    if not backends.available("cpp"):
        pytest.skip("C++ kernel not available")
    from nimbus.kernels import raster

    return raster


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("degree", [0, 3])
def test_cpp_row_scale_is_scaling_the_gradients_afterwards_bit_for_bit(dtype, degree):
    _needs_cpp()
    gs = with_edge_cases(make_gaussians(40, seed=50 + degree, dtype=dtype)).requires_grad_()
    n = len(gs)
    w = torch.rand(n, generator=torch.Generator().manual_seed(3), dtype=dtype) * 2.5 + 0.5
    w[:4] = 1.0
    params = list(gs.tensors().values())

    def grads(factors):
        rgb, depth, alpha, meta = rasterize(gs, CAM, sh_degree=degree, background=BG, backend="cpp", config=DEFAULT)
        assert meta["row_scale"] is not None
        meta["row_scale"].weights = factors  # set after the forward, before the backward: what GGS does
        out = torch.autograd.grad(rgb.square().sum() + depth.sum() + alpha.sum(), params, allow_unused=True)
        return out, meta["row_scale"].applied

    plain, applied_plain = grads(None)
    scaled, applied = grads(w)
    assert (applied_plain, applied) == (0, 1)
    for name, a, b in zip(gs.tensors(), plain, scaled):
        if a is None:  # degree 0: no gradient for the higher bands either way
            assert b is None, name
            continue
        assert torch.equal(a.mul(w.reshape((n,) + (1,) * (a.dim() - 1))), b), name
    with pytest.raises(NimbusError, match="RowScale.weights must be a"):
        grads(w[:-1])


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_cpp_projection_and_shading_match_torch_autograd_float64(degree):
    raster = _needs_cpp()
    gs = with_edge_cases(make_gaussians(40, seed=20 + degree, dtype=torch.float64)).requires_grad_()
    gs.quats.data[3] = 0.0  # a zero quaternion: the norm clamp's gradient path
    viewmat, K, _, _ = rasterize_module.camera_tensors(CAM, torch.float64)
    cfg = ProjectionConfig()
    ours = raster.project_and_shade(gs.means, gs.quats, gs.log_scales, gs.opacity_logits, gs.sh_dc,
                                           gs.sh_rest, viewmat, K, W, H, degree, cfg)
    proj = project_gaussians(gs.means, gs.quats, gs.log_scales, viewmat, K, W, H, cfg)
    ref = torch_backend.project_and_shade(gs, viewmat, K, W, H, degree, cfg)
    n, vis = len(gs), ref.visible_ids

    def full(v):
        return torch.zeros((n,) + v.shape[1:], dtype=v.dtype).index_put((vis,), v)

    theirs = (proj.means2d, proj.conics, full(ref.vis_colors), full(ref.vis_opacities), proj.depths)
    torch.testing.assert_close(ours[5], proj.radii, atol=0, rtol=0)
    assert (ours[5] > 0).sum() < n  # some edge cases are culled
    for x, y in zip(ours[:5], theirs):
        torch.testing.assert_close(x, y, atol=1e-10, rtol=1e-10)
    g = torch.Generator().manual_seed(5)
    weights = [torch.randn(x.shape, generator=g, dtype=torch.float64) for x in theirs]
    params = list(gs.tensors().values())
    ga = torch.autograd.grad(sum((x * w).sum() for x, w in zip(ours[:5], weights)), params, allow_unused=True)
    gb = torch.autograd.grad(sum((x * w).sum() for x, w in zip(theirs, weights)), params, allow_unused=True)
    for name, x, y in zip(gs.tensors(), ga, gb):
        if y is None:  # degree 0: the higher bands are unused on both paths
            assert x is None, name
            continue
        torch.testing.assert_close(x, y, atol=1e-10, rtol=1e-9, msg=lambda m, name=name: f"{name}: {m}")


def _cpp_projection(raster, gs, degree, weights_of, row_scale=None):
    """Outputs of the compiled projection and the six parameters' gradients of sum(output * weight)."""
    viewmat, K, _, _ = rasterize_module.camera_tensors(CAM, gs.means.dtype)
    params = [gs.means, gs.quats, gs.log_scales, gs.opacity_logits, gs.sh_dc, gs.sh_rest]
    holder = raster.RowScale()
    holder.weights = row_scale
    outs = raster.project_and_shade(*params, viewmat, K, W, H, degree, ProjectionConfig(), holder)
    loss = sum((x * w).sum() for x, w in zip(outs[:5], weights_of(outs)))
    return [o.detach() for o in outs], list(torch.autograd.grad(loss, params, allow_unused=True))


def _compositor_like_weights(seed, reach_culled=()):
    """Random output gradients on the drawn Gaussians only (what the compositor sends), plus a depth gradient on
    the culled Gaussians listed."""
    def weights_of(outs):
        g = torch.Generator().manual_seed(seed)
        drawn = outs[5] > 0
        ws = []
        for x in outs[:5]:
            w = torch.randn(x.shape, generator=g, dtype=x.dtype)
            ws.append(w * drawn.reshape((-1,) + (1,) * (x.dim() - 1)))
        for i in reach_culled:
            ws[4][i] = 1.5
        return ws
    return weights_of


@pytest.mark.parametrize("isa", ["avx2", "avx512"])
def test_cpp_projection_clones_agree_bit_for_bit(isa):
    """The projection runs eight Gaussians at a time on each instruction-set clone; every clone gives the
    generic clone's bits, forward and backward, with and without row factors, for a count that is not a
    multiple of eight."""
    raster = _needs_cpp()
    if isa not in raster.cpu_isas():
        pytest.skip(f"this CPU (or build) cannot run the {isa} clone")
    gs = with_edge_cases(make_gaussians(61, seed=41, dtype=torch.float32)).requires_grad_()
    n = len(gs)
    w = torch.rand(n, generator=torch.Generator().manual_seed(4)) + 0.5
    before = raster.cpu_isa()
    runs = {}
    try:
        for name in ("generic", isa):
            raster.set_cpu_isa(name)
            for scale in (None, w):
                outs, grads = _cpp_projection(raster, gs, 3, _compositor_like_weights(7, [n - 6]), scale)  # n - 6: culled, reached
                runs[name, scale is None] = [x.numpy().tobytes() for x in outs + grads]
    finally:
        raster.set_cpu_isa(before)
    assert runs["generic", True] == runs[isa, True] and runs["generic", False] == runs[isa, False]


def test_cpp_projection_gives_culled_gaussians_without_gradient_exact_zeros():
    """A culled Gaussian that no gradient reaches gets +0 in every parameter, even one whose maths would give NaN
    (an overflowing scale); a culled Gaussian that a gradient reaches (here its depth) gets the torch path's."""
    raster = _needs_cpp()
    gs = with_edge_cases(make_gaussians(21, seed=42, dtype=torch.float64))
    gs.log_scales.data[0] = 800.0  # exp overflows: not finite, so culled
    gs.means.data[0] = torch.tensor([0.0, 0.0, 4.0], dtype=torch.float64)
    gs.requires_grad_()
    n = len(gs)
    reached = n - 6  # far off-screen to the right (with_edge_cases), in the depth range
    outs, grads = _cpp_projection(raster, gs, 3, _compositor_like_weights(9, [reached]))
    culled = (outs[5] == 0).nonzero().flatten().tolist()
    assert 0 in culled and reached in culled and len(culled) >= 4
    for i in culled:
        for name, g in zip(("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest"), grads):
            if i == reached and name in ("means", "quats", "log_scales"):
                continue
            assert torch.equal(g[i], torch.zeros_like(g[i])) and not torch.signbit(g[i]).any(), (i, name)
    assert grads[0][reached].abs().sum() > 0
    viewmat, K, _, _ = rasterize_module.camera_tensors(CAM, torch.float64)
    proj = project_gaussians(gs.means, gs.quats, gs.log_scales, viewmat, K, W, H, ProjectionConfig())
    ref = torch.autograd.grad(proj.depths[reached] * 1.5, [gs.means])[0]
    torch.testing.assert_close(grads[0][reached], ref[reached], atol=1e-12, rtol=1e-10)


def test_cpp_binning_equals_torch_binning():
    raster = _needs_cpp()
    for dtype in (torch.float32, torch.float64):
        gs = with_edge_cases(make_gaussians(60, seed=31, dtype=dtype))
        viewmat, K, _, _ = rasterize_module.camera_tensors(CAM, dtype)
        proj = project_gaussians(gs.means, gs.quats, gs.log_scales, viewmat, K, W, H)
        proj.depths[5] = proj.depths[9]  # a depth tie, broken by index on both paths
        for tile in (4, TILE, 16):
            ids_t, off_t = bin_gaussians(proj.means2d, proj.radii, proj.depths, W, H, tile)
            ids_c, off_c = raster.bin_gaussians(proj.means2d, proj.radii, proj.depths, W, H, tile)
            assert ids_t.numel() > 0
            assert torch.equal(ids_c, ids_t) and torch.equal(off_c, off_t)
        empty = raster.bin_gaussians(proj.means2d, torch.zeros_like(proj.radii), proj.depths, W, H, TILE)
        assert empty[0].numel() == 0 and not empty[1].any()


def test_cpp_binning_of_many_gaussians_is_the_same_on_any_thread_count():
    """Binning a realistic count of Gaussians, with many depth ties, gives the torch lists on any thread count."""
    raster = _needs_cpp()
    g = torch.Generator().manual_seed(3)
    n, w, h = 30000, 200, 150
    means2d = torch.rand(n, 2, generator=g) * torch.tensor([w + 40.0, h + 40.0]) - 20.0
    radii = torch.randint(0, 30, (n,), generator=g, dtype=torch.int32)
    depths = torch.randint(1, 200, (n,), generator=g).float() / 16  # many ties, broken by index
    ids_t, off_t = bin_gaussians(means2d, radii, depths, w, h, 16)
    threads = torch.get_num_threads()
    try:
        for th in (1, 2, 3):
            torch.set_num_threads(th)
            ids_c, off_c = raster.bin_gaussians(means2d, radii, depths, w, h, 16)
            assert torch.equal(ids_c, ids_t) and torch.equal(off_c, off_t), th
    finally:
        torch.set_num_threads(threads)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_cpp_binning_orders_signed_zero_negative_and_nan_depths_as_torch_sort(dtype):
    """The compiled binning sorts depths by their bits (a radix sort): -0 ties with +0, negative depths come
    first, NaN last, ties in index order, as the torch path's stable sort does."""
    raster = _needs_cpp()
    g = torch.Generator().manual_seed(8)
    n, w, h = 3000, 64, 48
    means2d = torch.rand(n, 2, generator=g, dtype=dtype) * torch.tensor([w, h], dtype=dtype)
    radii = torch.randint(0, 12, (n,), generator=g, dtype=torch.int32)
    depths = (torch.randint(-40, 40, (n,), generator=g).to(dtype) / 8)
    depths[depths == 0] = torch.where(torch.arange(n)[depths == 0] % 2 == 0, -0.0, 0.0).to(dtype)
    depths[::97] = float("nan")
    depths[::89] = torch.tensor([float("inf"), -float("inf"), 1e-30, -1e-30], dtype=dtype).repeat(n)[: len(depths[::89])]
    assert torch.signbit(depths[depths == 0]).any() and not torch.signbit(depths[depths == 0]).all()
    ids_t, off_t = bin_gaussians(means2d, radii, depths, w, h, 8)
    ids_c, off_c = raster.bin_gaussians(means2d, radii, depths, w, h, 8)
    assert ids_t.numel() > 1000
    assert torch.equal(ids_c, ids_t) and torch.equal(off_c, off_t)


def test_cpp_full_pipeline_matches_torch_float64_and_collects_absgrad():
    _needs_cpp()
    gs = with_edge_cases(make_gaussians(30, seed=17, dtype=torch.float64)).requires_grad_()
    a = rasterize(gs, CAM, background=BG, backend="cpp", config=SMALL, sh_degree=2)
    b = rasterize(gs, CAM, background=BG, backend="torch", config=SMALL, sh_degree=2)
    for x, y in zip(a[:3], b[:3]):
        torch.testing.assert_close(x, y, atol=1e-10, rtol=1e-10)
    for key in ("radii", "depths", "visible", "num_intersections"):
        assert torch.equal(torch.as_tensor(a[3][key]), torch.as_tensor(b[3][key])), key
    for name, x, y in zip(gs.tensors(), _grads(a, gs), _grads(b, gs)):
        torch.testing.assert_close(x, y, atol=1e-10, rtol=1e-9, msg=lambda m, name=name: f"{name}: {m}")
    absgrad = torch.zeros(len(gs), 2, dtype=torch.float64)
    out = rasterize(gs, CAM, background=BG, backend="cpp", config=SMALL, absgrad=absgrad)
    out[0].sum().backward()
    grad2d = rasterize_module.means2d_grad(out[3])
    assert (absgrad >= grad2d.abs() - 1e-12).all() and absgrad.sum() > 0
    assert (absgrad[~out[3]["visible"]] == 0).all()
    with pytest.raises(NimbusError, match="absgrad"):
        rasterize(gs, CAM, backend="torch", absgrad=absgrad)


def test_cpp_backend_with_a_camera_that_needs_gradients_matches_torch():
    _needs_cpp()
    gs = make_gaussians(20, seed=18, dtype=torch.float64)
    viewmat, K, _, _ = rasterize_module.camera_tensors(CAM, torch.float64)
    grads = []
    for backend in ("cpp", "torch"):
        vm = viewmat.clone().requires_grad_()
        rgb, _, _, meta = rasterize(gs, viewmat=vm, K=K, width=W, height=H, backend=backend, config=SMALL)
        rgb.sum().backward()
        assert meta["backend"] == backend
        grads.append(vm.grad)
    torch.testing.assert_close(grads[0], grads[1], atol=1e-10, rtol=1e-9)


def test_torch_backend_on_cuda():
    if not torch.cuda.is_available():
        pytest.skip("no CUDA device")
    gs = make_gaussians(30, seed=14, dtype=torch.float32)
    cpu = rasterize(gs, CAM, background=BG, config=SMALL)
    gpu = rasterize(gs.to("cuda"), CAM, background=BG, config=SMALL)
    assert gpu[0].device.type == "cuda"
    for x, y in zip(cpu[:3], gpu[:3]):
        torch.testing.assert_close(x, y.cpu(), atol=1e-5, rtol=1e-5)


def test_gsplat_backend_matches_torch():
    pytest.importorskip("gsplat")
    if not torch.cuda.is_available():
        pytest.skip("gsplat needs CUDA")
    gs = make_gaussians(30, seed=15, dtype=torch.float32, opacity=(-2.0, 1.0))
    ours = rasterize(gs, CAM, background=BG, config=RasterConfig(tile_size=16))
    theirs = rasterize(gs.to("cuda").requires_grad_(), CAM, background=BG, backend="gsplat",
                       config=RasterConfig(tile_size=16))
    # gsplat 1.5.x clamps alpha at 0.999 instead of 0.99 and bins with opacity-aware radii: close, not equal.
    for x, y in zip(ours[:3], theirs[:3]):
        diff = (x - y.cpu()).abs()
        assert diff.mean() < 2e-3 and diff.max() < 5e-2
    assert (ours[3]["visible"] == theirs[3]["visible"].cpu()).float().mean() > 0.9
    both = ours[3]["visible"] & theirs[3]["visible"].cpu()
    torch.testing.assert_close(ours[3]["depths"][both], theirs[3]["depths"].cpu()[both])
    theirs[0].sum().backward()
    assert rasterize_module.means2d_grad(theirs[3]).shape == (len(gs), 2)
