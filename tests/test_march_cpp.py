"""The ray march's fast paths (compiled kernel, telescoped torch) against the term-by-term reference."""

from __future__ import annotations

import shutil

import pytest
import torch

from nimbus.errors import NimbusError
from nimbus.kernels import march as march_kernel
from nimbus.methods.nimbusgs.scattering import Box, ExtinctionGrid, UniformExtinction, march, march_reference


@pytest.fixture(scope="module")
def kernel():
    if shutil.which("c++") is None and shutil.which("g++") is None:
        pytest.skip("no C++ compiler: the compiled kernel cannot be built here")
    # With a compiler present a failed build is a bug, not a reason to skip.
    assert march_kernel.available(), "compiled library unavailable"


def _grid(dtype, resolution=(5, 6, 7), seed=0, std=1.5):
    gen = torch.Generator().manual_seed(seed)
    grid = ExtinctionGrid(Box((-1.0, -0.5, 0.0), (1.5, 1.0, 2.0)), 4, std, 0.8, gen).to(dtype)
    z, y, x = resolution  # a non-cubic grid catches swapped axes
    with torch.no_grad():
        grid.features = torch.nn.Parameter(torch.randn((1, 1, z, y, x), generator=gen, dtype=dtype) * std)
        grid.features[0, 0, -1, -1, -1] = 25.0  # above softplus's threshold
    return grid


def _rays(dtype, n=400, seed=1):
    """Rays from outside and inside the box, some missing it, with empty, reversed and face-touching intervals."""
    gen = torch.Generator().manual_seed(seed)
    origin = torch.tensor([0.2, 0.1, -1.5], dtype=dtype)
    dirs = torch.randn(n, 3, generator=gen, dtype=dtype) * 0.6
    dirs[:, 2] = 1.0
    dirs[:4] = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]], dtype=dtype)
    dirs = dirs / dirs.norm(dim=-1, keepdim=True)
    t_start = torch.rand(n, generator=gen, dtype=dtype) * 2.0
    t_end = t_start + torch.rand(n, generator=gen, dtype=dtype) * 3.0
    t_end[4] = t_start[4]             # empty
    t_end[5] = t_start[5] - 0.5       # reversed: empty as well
    t_start[0], t_end[0] = 1.5, 3.5   # along +z from the box's lower face (z = 0) to its upper one (z = 2)
    t_start[1], t_end[1] = 1.5625, 3.5625  # with 16 samples, the last one exactly on the upper face
    return origin, dirs, t_start, t_end


def _loss(res, weights):
    return (res.transmission * weights[0] + res.scatter * weights[1]).sum()


def _values_and_grads(fn, grid, rays, weights):
    grid.zero_grad(set_to_none=True)
    res = fn(grid, *rays)
    _loss(res, weights).backward()
    return res, grid.features.grad.clone(), grid.log_scale.grad.clone()


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-10), (torch.float32, 2e-5)])
def test_compiled_march_matches_reference_values_and_gradients(kernel, dtype, tol):
    grid, rays = _grid(dtype), _rays(dtype)
    weights = torch.randn(2, rays[1].shape[0], generator=torch.Generator().manual_seed(2), dtype=dtype)
    ref, g_ref, ls_ref = _values_and_grads(lambda f, *r: march_reference(f, *r, samples=16), grid, rays, weights)
    out, g_out, ls_out = _values_and_grads(lambda f, *r: march(f, *r, samples=16, backend="cpp"), grid, rays,
                                           weights)
    t_ref = ref.transmission.detach()
    assert float(t_ref.min()) < 0.2 and float(t_ref[4]) == 1.0  # dense and empty rays
    torch.testing.assert_close(out.transmission, ref.transmission, rtol=tol, atol=tol)
    torch.testing.assert_close(out.scatter, ref.scatter, rtol=tol, atol=tol)
    assert float(g_ref.abs().max()) > 1e-3
    torch.testing.assert_close(g_out, g_ref, rtol=tol, atol=tol * float(g_ref.abs().max()))
    torch.testing.assert_close(ls_out, ls_ref, rtol=tol, atol=tol)


def test_compiled_march_gradcheck(kernel):
    grid, (origin, dirs, ts, te) = _grid(torch.float64, (3, 4, 5)), _rays(torch.float64, n=12)
    feats = grid.features.detach().clone().requires_grad_()
    torch.autograd.gradcheck(
        lambda f: march_kernel.grid_optical_depth(f, grid.lo, grid.hi, origin, dirs, ts, te, 5), (feats,))


def test_compiled_march_is_the_same_bits_at_any_thread_count(kernel):
    grid, rays = _grid(torch.float32, (16, 16, 16), std=0.5), _rays(torch.float32, n=20_000)
    weights = torch.randn(2, 20_000, generator=torch.Generator().manual_seed(3))
    threads = torch.get_num_threads()
    try:
        results = []
        for n in (1, 2, 2):
            torch.set_num_threads(n)
            results.append(_values_and_grads(lambda f, *r: march(f, *r, samples=8, backend="cpp"), grid, rays,
                                             weights))
    finally:
        torch.set_num_threads(threads)
    (one, g1, _), (two, g2, _), (again, g2b, _) = results
    assert torch.equal(one.transmission, two.transmission)  # the forward is per ray
    assert torch.equal(g2, g2b)
    # The rays are split into parts by their number alone (20 000 rays: 8 parts), not by the threads: a cell
    # trained with --jobs 2 (1 thread) equals the same cell with 2 threads.
    assert torch.equal(g1, g2)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("samples", [1, 16, 70])  # 70: more than one 64-sample chunk per ray
def test_kept_backward_is_the_same_bits_as_evaluating_again(kernel, dtype, samples):
    """The differentiated march keeps each sample's softplus' from its forward (march_forward_keep); its backward
    must equal march_backward's, which evaluates every sample again, bit for bit, and so must the forward."""
    grid, (origin, dirs, ts, te) = _grid(dtype, (6, 7, 8)), _rays(dtype, n=5000)
    feats = grid.features.detach()[0, 0].clone()
    feats[-3:, -3:, -3:] = 30.0  # a corner above softplus's threshold (softplus' = 1 there)
    args = (feats, origin, dirs, ts, te, grid.lo.to(dtype), grid.hi.to(dtype))
    ops = torch.ops.nimbus_march
    plain = ops.march_forward(*args, samples)
    kept_s, kept = ops.march_forward_keep(*args, samples)
    assert torch.equal(plain, kept_s) and kept.shape == (5000, samples)
    assert float((kept == 0).float().mean()) > 0.05  # samples outside the box
    assert samples == 1 or float((kept == 1).float().mean()) > 0  # the corner is sampled
    grad_s = torch.randn(5000, generator=torch.Generator().manual_seed(5), dtype=dtype)
    grad_s[::7] = 0.0
    again = ops.march_backward(*args, samples, grad_s)
    assert float(again.abs().max()) > 1e-3
    assert torch.equal(ops.march_backward_kept(*args, samples, kept, grad_s), again)
    with pytest.raises(RuntimeError, match="kept must be"):
        ops.march_backward_kept(*args, samples, kept[:, :-1].contiguous(), grad_s)


@pytest.mark.parametrize("samples", [1, 5, 16, 70])
def test_lane_paths_are_the_same_bits_as_one_sample_at_a_time(kernel, samples):
    """On an AVX2 CPU the float32 forward and kept backward locate kLanes samples at a time (and gather the
    forward's corners); they must give the per-sample code's numbers bit for bit, ray by ray and voxel by voxel.
    (Without AVX2 both settings run the generic code and the comparison holds trivially.)"""
    grid, (origin, dirs, ts, te) = _grid(torch.float32, (9, 7, 8)), _rays(torch.float32, n=3000)
    dirs = dirs.clone()
    dirs[6] = float("nan")  # a broken ray: no sample located, in both paths
    feats = grid.features.detach()[0, 0].clone()
    feats[:2, :2, :2] = 30.0  # above softplus's threshold
    args = (feats, origin, dirs, ts, te, grid.lo, grid.hi)
    ops = torch.ops.nimbus_march
    grad_s = torch.randn(3000, generator=torch.Generator().manual_seed(9))
    grad_s[::5] = 0.0
    results = []
    previous = ops.march_set_lane_paths(True)
    try:
        for lanes in (True, False):
            ops.march_set_lane_paths(lanes)
            s, kept = ops.march_forward_keep(*args, samples)
            results.append((ops.march_forward(*args, samples), s, kept,
                            ops.march_backward_kept(*args, samples, kept, grad_s)))
    finally:
        ops.march_set_lane_paths(previous)
    assert float(results[0][1][6]) == 0.0 and float((results[0][2] == 0).float().mean()) > 0.05
    assert float(results[0][3].abs().max()) > 1e-3
    for a, b in zip(*results):
        assert torch.equal(a, b)


def test_torch_march_matches_reference_including_interval_gradients():
    grid, (origin, dirs, ts, te) = _grid(torch.float64), _rays(torch.float64)
    weights = torch.randn(2, ts.shape[0], generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    outs = []
    for fn in (march_reference, lambda *a: march(*a, backend="torch"),
               lambda *a: march(*a, backend="auto")):  # an interval with gradient: auto marches in torch
        grid.zero_grad(set_to_none=True)
        t0, t1 = ts.clone().requires_grad_(), te.clone().requires_grad_()
        res = fn(grid, origin, dirs, t0, t1, 16)
        _loss(res, weights).backward()
        outs.append((res.transmission, res.scatter, grid.features.grad, t0.grad, t1.grad))
    assert float(outs[0][4].abs().max()) > 1e-3
    for out in outs[1:]:
        for a, b in zip(out, outs[0]):
            torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-10)


def test_march_backend_validation(kernel):
    uniform = UniformExtinction(Box((-1.0,) * 3, (1.0,) * 3), 0.5)
    origin, dirs, ts, te = _rays(torch.float32, n=8)
    ref = march_reference(uniform, origin, dirs, ts, te, 8)
    res = march(uniform, origin, dirs, ts, te, 8)  # auto: a field the kernel does not know runs in torch
    torch.testing.assert_close(res.transmission, ref.transmission)
    with pytest.raises(NimbusError, match="backend 'cpp'"):
        march(uniform, origin, dirs, ts, te, 8, backend="cpp")
    with pytest.raises(NimbusError, match="unknown march backend"):
        march(uniform, origin, dirs, ts, te, 8, backend="cuda")
    grid = _grid(torch.float32)
    d = dirs.clone().requires_grad_()  # the kernel does not differentiate the rays: auto marches in torch
    march(grid, origin, d, ts, te, 8).transmission.sum().backward()
    assert d.grad is not None and float(d.grad.abs().max()) > 0
    with pytest.raises(NimbusError, match="backend 'cpp'"):
        march(grid, origin, d, ts, te, 8, backend="cpp")


def _torch_tv(features):
    b = torch.nn.functional.softplus(features)
    return sum(torch.diff(b, dim=d).abs().mean() for d in range(3))


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 1e-5)])
def test_compiled_grid_tv_matches_torch_values_and_gradients(kernel, dtype, tol):
    """L_TV in one compiled pass equals ExtinctionGrid.tv's torch expression: on a non-cubic grid, with voxels
    above softplus's threshold and two equal neighbours (|x|'s derivative at 0 is 0 in both)."""
    feats = torch.randn(9, 7, 11, generator=torch.Generator().manual_seed(6), dtype=dtype) * 5
    feats[0, 0, :4] = 25.0
    feats[3, 2, 5] = feats[3, 2, 6]
    feats.requires_grad_()
    got, want = march_kernel.grid_tv(feats), _torch_tv(feats)
    torch.testing.assert_close(got, want, rtol=tol, atol=0)
    (g_got,) = torch.autograd.grad(got * 3.0, feats)
    (g_want,) = torch.autograd.grad(want * 3.0, feats)
    assert float(g_want.abs().max()) > 1e-3
    torch.testing.assert_close(g_got, g_want, rtol=tol, atol=tol * float(g_want.abs().max()))
    torch.autograd.gradcheck(march_kernel.grid_tv, (torch.randn(3, 4, 5, dtype=torch.float64, requires_grad=True),))


def test_grid_tv_is_the_same_bits_at_any_thread_count_and_extinction_grid_uses_it(kernel):
    grid = _grid(torch.float32, (20, 18, 16), std=0.7)
    threads = torch.get_num_threads()
    try:
        results = []
        for n in (1, 2):
            torch.set_num_threads(n)
            grid.zero_grad(set_to_none=True)
            value = grid.tv()
            value.backward()
            results.append((value.detach(), grid.features.grad.clone(), grid.log_scale.grad.clone()))
    finally:
        torch.set_num_threads(threads)
    assert all(torch.equal(a, b) for a, b in zip(*results))
    value, g_feat, g_scale = results[0]
    grid.zero_grad(set_to_none=True)
    want = sum(torch.diff(grid.values(), dim=d).abs().mean() for d in range(3))  # the torch path of tv()
    want.backward()
    torch.testing.assert_close(value, want.detach(), rtol=1e-5, atol=0)
    torch.testing.assert_close(g_feat, grid.features.grad, rtol=1e-5, atol=1e-5 * float(g_feat.abs().max()))
    torch.testing.assert_close(g_scale, grid.log_scale.grad, rtol=1e-5, atol=0)
