"""The compiled compositing kernel against a slow, obviously correct reference of the contract.

The reference decides, pixel by pixel in a plain Python loop over the pixel's tile list,
which Gaussians contribute (the skip and stop rules); the values are then computed with
differentiable float64 torch ops from those fixed lists, so autograd gives reference
gradients.  Scenes and tile lists are built here (no dependency on the torch rasterizer).
"""

from __future__ import annotations

import math
import os
import shutil
import subprocess
import sys
import time
import warnings
from pathlib import Path

import pytest
import torch

from nimbus.kernels import extension
from nimbus.kernels import raster

MAX_ALPHA = 0.99
MIN_ALPHA = 1.0 / 255.0
MIN_T = 1e-4


@pytest.fixture(scope="module", autouse=True)
def _kernel():
    if shutil.which("c++") is None and shutil.which("g++") is None:
        pytest.skip("no C++ compiler: the compiled kernel cannot be built here")
    # With a compiler present a failed build is a bug, not a reason to skip.
    assert raster.available(warn=False), raster.load_error()


# ----------------------------------------------------------------------------- scenes


def make_scene(n, width, height, seed, *, sigma_range=(0.6, 6.0), opacity_range=(0.05, 0.99),
               x_range=None, dtype=torch.float64):
    """Random anisotropic Gaussians in pixel space: dict of tensors plus 'radii' [M] (3 sigma)."""
    g = torch.Generator().manual_seed(seed)

    def u(lo, hi, *shape):
        return lo + (hi - lo) * torch.rand(*shape, generator=g, dtype=torch.float64)

    x_lo, x_hi = x_range if x_range is not None else (-4.0, width + 4.0)
    means = torch.stack([u(x_lo, x_hi, n), u(-4.0, height + 4.0, n)], dim=1)
    s = torch.exp(u(math.log(sigma_range[0]), math.log(sigma_range[1]), n, 2))
    theta = u(0, math.pi, n)
    rot = torch.stack([torch.cos(theta), -torch.sin(theta), torch.sin(theta), torch.cos(theta)], 1).view(n, 2, 2)
    cov = rot @ torch.diag_embed(s**2) @ rot.transpose(1, 2)
    inv = torch.linalg.inv(cov) if n else torch.zeros(0, 2, 2, dtype=torch.float64)
    scene = {
        "means2d": means,
        "conics": torch.stack([inv[:, 0, 0], inv[:, 0, 1], inv[:, 1, 1]], dim=1),
        "colors": u(0, 1, n, 3),
        "opacities": u(*opacity_range, n),
        "depths": u(1, 10, n),
        "radii": torch.ceil(3 * s.max(dim=1).values),
    }
    return {k: v.to(dtype) for k, v in scene.items()}


def bin_scene(scene, width, height, tile):
    """Tile lists: a Gaussian joins every tile its [mean - r, mean + r] square touches, sorted by depth."""
    tiles_x, tiles_y = -(-width // tile), -(-height // tile)
    means = scene["means2d"].tolist()
    radii = scene["radii"].tolist()
    order = sorted(range(len(means)), key=lambda i: (float(scene["depths"][i]), i))
    ids, offsets = [], [0]
    for ty in range(tiles_y):
        for tx in range(tiles_x):
            for i in order:
                (mx, my), r = means[i], radii[i]
                if (r > 0 and mx + r >= tx * tile and mx - r <= (tx + 1) * tile
                        and my + r >= ty * tile and my - r <= (ty + 1) * tile):
                    ids.append(i)
            offsets.append(len(ids))
    return torch.tensor(ids, dtype=torch.int64), torch.tensor(offsets, dtype=torch.int64)


def inputs(scene, width, height, tile, background=(0.2, 0.5, 0.9)):
    ids, offsets = bin_scene(scene, width, height, tile)
    dtype = scene["means2d"].dtype
    return dict(means2d=scene["means2d"], conics=scene["conics"], colors=scene["colors"],
                opacities=scene["opacities"], depths=scene["depths"], isect_ids=ids, tile_offsets=offsets,
                width=width, height=height, tile_size=tile, background=torch.tensor(background, dtype=dtype))


GRAD_NAMES = ("means2d", "conics", "colors", "opacities", "depths", "background")


# -------------------------------------------------------------------------- reference


def reference_lists(a):
    """Per pixel (row-major), the contributing Gaussians in order: the contract as a plain loop."""
    ids, off = a["isect_ids"].tolist(), a["tile_offsets"].tolist()
    means, conics = a["means2d"].double().tolist(), a["conics"].double().tolist()
    opac = a["opacities"].double().tolist()
    width, height, tile = a["width"], a["height"], a["tile_size"]
    tiles_x = -(-width // tile)
    lists = []
    for v in range(height):
        for u in range(width):
            t = (v // tile) * tiles_x + u // tile
            T, chosen = 1.0, []
            for k in range(off[t], off[t + 1]):
                i = ids[k]
                dx, dy = u + 0.5 - means[i][0], v + 0.5 - means[i][1]
                ca, cb, cc = conics[i]
                sigma = 0.5 * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
                if sigma < 0:
                    continue
                alpha = min(MAX_ALPHA, opac[i] * math.exp(-sigma))
                if alpha < MIN_ALPHA:
                    continue
                if T * (1 - alpha) < MIN_T:
                    break
                T *= 1 - alpha
                chosen.append(i)
            lists.append(chosen)
    return lists


def reference_values(a, lists, means_per_pair=None):
    """Differentiable float64 rgb, depth, alpha from fixed per-pixel lists.

    ``means_per_pair`` [P, K, 2] replaces the gathered means (to get per-pixel mean gradients).
    """
    width, height = a["width"], a["height"]
    P, K = width * height, max([len(c) for c in lists] + [1])
    idx = torch.zeros(P, K, dtype=torch.int64)
    valid = torch.zeros(P, K, dtype=torch.bool)
    for p, chosen in enumerate(lists):
        idx[p, : len(chosen)] = torch.tensor(chosen, dtype=torch.int64)
        valid[p, : len(chosen)] = True
    v, u = torch.meshgrid(torch.arange(height, dtype=torch.float64), torch.arange(width, dtype=torch.float64),
                          indexing="ij")
    px, py = (u.reshape(-1, 1) + 0.5), (v.reshape(-1, 1) + 0.5)
    if a["means2d"].shape[0] == 0:
        means_pk = torch.zeros(P, K, 2, dtype=torch.float64)
        conic_pk = torch.zeros(P, K, 3, dtype=torch.float64)
        col_pk = torch.zeros(P, K, 3, dtype=torch.float64)
        op_pk = z_pk = torch.zeros(P, K, dtype=torch.float64)
    else:
        means_pk = a["means2d"].double()[idx] if means_per_pair is None else means_per_pair
        conic_pk, col_pk = a["conics"].double()[idx], a["colors"].double()[idx]
        op_pk, z_pk = a["opacities"].double()[idx], a["depths"].double()[idx]
    dx, dy = px - means_pk[..., 0], py - means_pk[..., 1]
    sigma = 0.5 * (conic_pk[..., 0] * dx * dx + conic_pk[..., 2] * dy * dy) + conic_pk[..., 1] * dx * dy
    alpha = torch.where(valid, torch.clamp(op_pk * torch.exp(-sigma), max=MAX_ALPHA), 0.0)
    trans = torch.cumprod(1 - alpha, dim=1)
    t_excl = torch.cat([torch.ones(P, 1, dtype=torch.float64), trans[:, :-1]], dim=1)
    w = alpha * t_excl
    t_final = trans[:, -1]
    rgb = (w[..., None] * col_pk).sum(1) + t_final[:, None] * a["background"].double()
    depth = (w * z_pk).sum(1)
    return rgb.view(height, width, 3), depth.view(height, width), (1 - t_final).view(height, width)


def output_weights(width, height, seed=7):
    g = torch.Generator().manual_seed(seed)
    return (torch.randn(height, width, 3, generator=g, dtype=torch.float64),
            torch.randn(height, width, generator=g, dtype=torch.float64),
            torch.randn(height, width, generator=g, dtype=torch.float64))


def weighted_loss(outs, weights):
    return sum((o * w.to(o.dtype)).sum() for o, w in zip(outs, weights))


def reference_grads(a, lists, weights):
    """Reference outputs, gradients (GRAD_NAMES) and absgrad [M, 2], all float64."""
    leaves = {k: a[k].detach().double().requires_grad_() for k in GRAD_NAMES}
    ref = dict(a, **leaves)
    outs = reference_values(ref, lists)
    grads = torch.autograd.grad(weighted_loss(outs, weights), [leaves[k] for k in GRAD_NAMES], allow_unused=True)
    grads = {k: (torch.zeros_like(leaves[k]) if g is None else g) for k, g in zip(GRAD_NAMES, grads)}
    # absgrad: per-pixel mean gradients, from a copy of the means per (pixel, slot).
    m = a["means2d"].shape[0]
    absgrad = torch.zeros(m, 2, dtype=torch.float64)
    if m:
        K = max([len(c) for c in lists] + [1])
        idx = torch.zeros(len(lists), K, dtype=torch.int64)
        valid = torch.zeros(len(lists), K, dtype=torch.bool)
        for p, chosen in enumerate(lists):
            idx[p, : len(chosen)] = torch.tensor(chosen, dtype=torch.int64)
            valid[p, : len(chosen)] = True
        pair_means = a["means2d"].detach().double()[idx].requires_grad_()
        (g_pair,) = torch.autograd.grad(weighted_loss(reference_values(a, lists, pair_means), weights), pair_means)
        absgrad.index_add_(0, idx[valid], g_pair[valid].abs())
    return [o.detach() for o in outs], grads, absgrad


def kernel_grads(a, weights):
    leaves = {k: a[k].detach().clone().requires_grad_() for k in GRAD_NAMES}
    absgrad = torch.zeros(a["means2d"].shape[0], 2, dtype=a["means2d"].dtype)
    outs = raster.composite(**dict(a, **leaves), absgrad=absgrad)
    weighted_loss(outs, weights).backward()
    return [o.detach() for o in outs], {k: leaves[k].grad for k in GRAD_NAMES}, absgrad


def absmax(x):
    return float(x.abs().max()) if x.numel() else 0.0


def assert_close(actual, expected, rtol, atol, what):
    torch.testing.assert_close(actual.double(), expected.double(), rtol=rtol, atol=atol, msg=lambda m: f"{what}: {m}")


def check_against_reference(a, rtol, atol):
    lists = reference_lists(a)
    weights = output_weights(a["width"], a["height"])
    ref_outs, ref_grads, ref_abs = reference_grads(a, lists, weights)
    outs, grads, absgrad = kernel_grads(a, weights)
    for name, o, r in zip(("rgb", "depth", "alpha"), outs, ref_outs):
        assert o.shape == r.shape and o.dtype == a["means2d"].dtype
        assert_close(o, r, rtol, atol, name)
    for name in GRAD_NAMES:
        scale = absmax(ref_grads[name]) + 1.0
        assert_close(grads[name], ref_grads[name], rtol, atol * scale, f"grad {name}")
    assert_close(absgrad, ref_abs, rtol, atol * (absmax(ref_abs) + 1.0), "absgrad")
    return lists, outs


# ------------------------------------------------------------------------------ tests


def test_random_scene_float64_matches_reference():
    # 37x29 with 8 px tiles: partial tiles on both borders; Gaussians only on the left so
    # the right-hand tiles are empty.
    a = inputs(make_scene(90, 37, 29, seed=1, sigma_range=(0.6, 3.0), x_range=(-4.0, 12.0)), 37, 29, 8)
    offsets = a["tile_offsets"]
    assert (offsets[1:] == offsets[:-1]).any(), "scene should have empty tiles"
    lists, outs = check_against_reference(a, rtol=1e-9, atol=1e-10)
    assert max(len(c) for c in lists) > 5
    rgb = outs[0]
    assert torch.allclose(rgb[:, -3:], a["background"].expand(29, 3, 3))  # empty tiles show the background


def test_random_scene_float32_matches_float64_reference():
    a = inputs(make_scene(120, 40, 24, seed=2, dtype=torch.float32), 40, 24, 16)
    check_against_reference(a, rtol=1e-4, atol=2e-5)


def edge_case_scene():
    """30x22 px, 8 px tiles: huge, tiny, non-positive-definite, clamped, saturating, needle-like,
    invisible and off-image Gaussians."""
    n = 16
    scene = make_scene(n, 30, 22, seed=3)
    # Huge (covers the whole image), tiny (sub-pixel) and non-positive-definite conics.
    scene["conics"][0] = torch.tensor([1e-4, 0.0, 2e-4])
    scene["radii"][0] = 300
    scene["conics"][1] = torch.tensor([25.0, 3.0, 30.0])
    scene["conics"][2] = torch.tensor([0.5, 0.9, 0.5])  # det < 0: sigma < 0 along one diagonal
    scene["radii"][2] = 12
    # Clamped: opaque Gaussian centred on a pixel centre.
    scene["means2d"][3] = torch.tensor([10.5, 7.5])
    scene["opacities"][3] = 0.999
    scene["depths"][3] = 0.05  # in front of everything
    # Saturation: a stack of opaque, wide Gaussians in front of everything on the right.
    for i in range(4, 12):
        scene["means2d"][i] = torch.tensor([24.0 + 0.3 * i, 12.0])
        scene["conics"][i] = torch.tensor([0.02, 0.0, 0.02])
        scene["opacities"][i] = 0.9
        scene["depths"][i] = 0.1 + 0.01 * i
        scene["radii"][i] = 21
    # Needles (std ratio 20 and 400, rotated; the second is too ill-conditioned for the
    # kernel's block culling), a Gaussian below alpha 1/255 everywhere, and a large
    # off-image one reaching in from the left.
    for i, (ratio, theta) in zip((12, 13), ((20.0, 0.5), (400.0, 2.0))):
        rot = torch.tensor([[math.cos(theta), -math.sin(theta)], [math.sin(theta), math.cos(theta)]],
                           dtype=torch.float64)
        var = torch.tensor([(0.6 * ratio) ** 2, 0.36], dtype=torch.float64)
        inv = torch.linalg.inv(rot @ torch.diag(var) @ rot.T)
        scene["conics"][i] = torch.stack([inv[0, 0], inv[0, 1], inv[1, 1]])
        scene["means2d"][i] = torch.tensor([15.3, 11.2])
        scene["radii"][i] = 30
        scene["opacities"][i] = 0.8
    scene["opacities"][14] = 0.003
    scene["means2d"][15] = torch.tensor([-12.0, 6.0])
    scene["conics"][15] = torch.tensor([0.02, 0.005, 0.03])
    scene["radii"][15] = 25
    return scene


def test_edge_cases_match_reference():
    a = inputs(edge_case_scene(), 30, 22, 8)
    lists, outs = check_against_reference(a, rtol=1e-9, atol=1e-10)
    contributors = {i for chosen in lists for i in chosen}
    assert {12, 13, 15} <= contributors and 14 not in contributors
    # The stop rule fired: saturated pixels end with T >= 1e-4 and stop before the stack's end.
    alpha = outs[2]
    assert 1 - alpha[12, 24] >= MIN_T and 1 - alpha[12, 24] < 1e-2
    assert not set(range(4, 12)) <= set(lists[12 * 30 + 24])
    # The clamp: the opaque Gaussian reaches exactly 0.99 at its centre pixel (10, 7).
    assert lists[7 * 30 + 10][0] == 3
    leaves = {k: a[k].clone().requires_grad_() for k in GRAD_NAMES}
    pix = torch.zeros(22, 30)
    pix[7, 10] = 1.0
    rgb, _, alpha = raster.composite(**dict(a, **leaves))
    assert float(alpha[7, 10].detach()) >= MAX_ALPHA
    (alpha * pix.double()).sum().backward()
    assert float(leaves["opacities"].grad[3]) == 0.0  # clamped: no gradient to opacity or the mean
    assert float(leaves["means2d"].grad[3].abs().sum()) == 0.0


def test_edge_cases_float32_match_float64_reference():
    scene = {k: v.float() for k, v in edge_case_scene().items()}
    check_against_reference(inputs(scene, 30, 22, 8), rtol=1e-4, atol=2e-5)


def test_zero_gaussians():
    a = inputs(make_scene(0, 20, 10, seed=4), 20, 10, 16)
    assert a["isect_ids"].numel() == 0
    check_against_reference(a, rtol=1e-12, atol=1e-12)
    rgb, depth, alpha = raster.composite(**a)
    assert torch.equal(rgb, a["background"].expand(10, 20, 3))
    assert not depth.any() and not alpha.any()


def test_gradcheck_float64():
    a = inputs(make_scene(6, 11, 9, seed=5, sigma_range=(1.0, 3.0)), 11, 9, 4)
    assert a["isect_ids"].numel() > 0
    names = ("means2d", "conics", "colors", "opacities", "depths", "background")

    def fn(*xs):
        return raster.composite(**dict(a, **dict(zip(names, xs))))

    xs = tuple(a[k].clone().requires_grad_() for k in names)
    assert torch.autograd.gradcheck(fn, xs, eps=1e-6, atol=1e-6, rtol=1e-4)


def test_thread_count_does_not_change_results():
    a = inputs(make_scene(800, 64, 48, seed=6, dtype=torch.float32), 64, 48, 8)
    assert a["isect_ids"].numel() > 4096  # the kernel runs small jobs on one thread
    weights = output_weights(64, 48)
    before = torch.get_num_threads()
    try:
        runs = []
        for threads in (1, 2):
            torch.set_num_threads(threads)
            runs.append(kernel_grads(a, weights))
    finally:
        torch.set_num_threads(before)
    (o1, g1, abs1), (o2, g2, abs2) = runs
    assert all(torch.equal(x, y) for x, y in zip(o1, o2))
    assert all(torch.equal(g1[k], g2[k]) for k in GRAD_NAMES)
    assert torch.equal(abs1, abs2) and abs1.abs().sum() > 0


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_buffers_kept_between_calls_do_not_change_results(dtype):
    # The kernel keeps its boxes and gradient slots between calls; a larger call in between leaves
    # other content (and more of it) in them, which a later call must not read.
    small = inputs(make_scene(300, 40, 32, seed=11, dtype=dtype), 40, 32, 8)
    large = inputs(make_scene(1500, 72, 56, seed=12, dtype=dtype), 72, 56, 8)
    weights = output_weights(40, 32)
    o1, g1, abs1 = kernel_grads(small, weights)
    kernel_grads(large, output_weights(72, 56))
    o2, g2, abs2 = kernel_grads(small, weights)
    assert all(torch.equal(x, y) for x, y in zip(o1, o2))
    assert all(torch.equal(g1[k], g2[k]) for k in GRAD_NAMES)
    assert torch.equal(abs1, abs2) and abs1.abs().sum() > 0


@pytest.mark.parametrize("isa", raster.CPU_ISAS)
def test_each_isa_clone_matches_the_reference_and_the_generic_clone_bit_for_bit(isa):
    # The clones are forced one by one (NIMBUS_CPU_ISA does the same per process), so every path is
    # checked on one machine; a clone this CPU cannot run is skipped.
    if isa not in raster.cpu_isas():
        pytest.skip(f"this CPU (or build) cannot run the {isa} clone")
    a = inputs(make_scene(300, 40, 24, seed=11, dtype=torch.float32), 40, 24, 8)
    weights = output_weights(40, 24)
    before = raster.cpu_isa()
    try:
        assert raster.set_cpu_isa("generic") == "generic"
        o0, g0, abs0 = kernel_grads(a, weights)
        assert raster.set_cpu_isa(isa) == isa and raster.cpu_isa() == isa
        check_against_reference(a, rtol=1e-4, atol=2e-5)
        o1, g1, abs1 = kernel_grads(a, weights)
    finally:
        raster.set_cpu_isa(before)
    assert all(torch.equal(x, y) for x, y in zip(o0, o1))
    assert all(torch.equal(g0[k], g1[k]) for k in GRAD_NAMES) and torch.equal(abs0, abs1)


def test_absgrad_accumulates_into_caller_tensor():
    a = inputs(make_scene(40, 24, 16, seed=8), 24, 16, 8)
    acc = torch.zeros(40, 2, dtype=torch.float64)
    for _ in range(2):
        means = a["means2d"].clone().requires_grad_()
        rgb, _, _ = raster.composite(**dict(a, means2d=means), absgrad=acc)
        rgb.sum().backward()
    once = torch.zeros_like(acc)
    rgb, _, _ = raster.composite(**dict(a, means2d=a["means2d"].clone().requires_grad_()), absgrad=once)
    rgb.sum().backward()
    assert once.sum() > 0
    torch.testing.assert_close(acc, 2 * once)
    assert (once >= means.grad.abs() - 1e-12).all()  # |sum| <= sum |.|


def test_bad_tile_lists_raise_instead_of_crashing():
    a = inputs(make_scene(10, 16, 16, seed=9), 16, 16, 8)
    bad = a["isect_ids"].clone()
    bad[0] = 10
    with pytest.raises(RuntimeError, match="isect_ids"):
        raster.composite(**dict(a, isect_ids=bad))
    with pytest.raises(RuntimeError, match="tile_offsets"):
        raster.composite(**dict(a, tile_offsets=a["tile_offsets"][:-1]))
    with pytest.raises(TypeError):
        raster.composite(**dict(a, colors=a["colors"].float()))


def test_stale_build_lock_is_removed(tmp_path):
    lock = tmp_path / "lock"
    lock.write_text("")
    extension._clear_stale_lock(str(tmp_path))
    assert lock.exists()  # a fresh lock belongs to a build in progress
    old = lock.stat().st_mtime - 2 * extension._STALE_LOCK_S
    os.utime(lock, (old, old))
    extension._clear_stale_lock(str(tmp_path))
    assert not lock.exists()


def test_a_killed_build_does_not_make_later_loads_wait_forever(tmp_path, capsys, monkeypatch):
    lock = tmp_path / "lock"
    lock.write_text("")
    obj = tmp_path / "composite.o"
    obj.write_text("")
    old = lock.stat().st_mtime - 10.0
    for f in (lock, obj):  # nothing in the folder has changed for 10 s: its build was killed
        os.utime(f, (old, old))
    extension._wait_for_build(str(tmp_path), idle_s=5.0, poll_s=0.01)
    assert not lock.exists() and "stale compiler lock" in capsys.readouterr().err
    # A build in progress keeps writing: its lock is left alone until it goes.
    lock.write_text("")
    seen = []
    sleep = extension.time.sleep

    def release_on_second_poll(s):
        seen.append(s)
        if len(seen) == 2:
            lock.unlink()
        sleep(0)

    monkeypatch.setattr(extension.time, "sleep", release_on_second_poll)
    extension._wait_for_build(str(tmp_path), idle_s=5.0, poll_s=0.01)
    assert len(seen) == 2 and not lock.exists() and capsys.readouterr().err == ""


_HOLDER = """
import fcntl, os, sys, time
build_dir, hold_s = sys.argv[1], float(sys.argv[2])
with open(os.path.join(build_dir, "nimbus-build.lock"), "a") as fh:
    fcntl.flock(fh, fcntl.LOCK_EX)
    lock = os.path.join(build_dir, "lock")
    open(lock, "w").close()
    old = time.time() - 10 * 600.0  # torch's lock looks ancient and the folder idle: a stopped or niced build
    os.utime(lock, (old, old))
    open(os.path.join(build_dir, "ready"), "w").close()
    time.sleep(hold_s)
    os.remove(lock)  # torch's baton release at the end of the build
"""


def _start_holder(build_dir, hold_s: float) -> subprocess.Popen:
    """A process that holds ``build_dir``'s build lock for ``hold_s`` s (:data:`_HOLDER`), once it holds it."""
    holder = subprocess.Popen([sys.executable, "-c", _HOLDER, str(build_dir), str(hold_s)])
    deadline = time.monotonic() + 30
    while not (build_dir / "ready").exists():
        assert holder.poll() is None and time.monotonic() < deadline, "the lock holder did not start"
        time.sleep(0.02)
    return holder


@pytest.mark.skipif(extension.fcntl is None, reason="flock is POSIX-only")
def test_a_slow_live_build_is_waited_for_not_declared_stale(tmp_path, monkeypatch):
    """A build that writes nothing for a long time (niced, paused with SIGSTOP) still holds the OS lock: a second
    process waits for it and never removes torch's lock file under it (the idle heuristic would have)."""
    monkeypatch.setattr(extension, "_QUIET_WAIT_S", 0.2)
    holder = _start_holder(tmp_path, 1.5)
    try:
        said = []
        t0 = time.monotonic()
        with extension.build_turn(str(tmp_path), say=said.append):
            waited = time.monotonic() - t0
            assert not (tmp_path / "lock").exists()  # gone because its holder finished, not removed by us
        assert waited > 0.5
        assert said == [f"nimbus: waiting for another process to finish building the kernels in {tmp_path}"]
        assert holder.wait(timeout=30) == 0  # its own removal of torch's lock found the file
    finally:
        holder.kill()


@pytest.mark.skipif(extension.fcntl is None, reason="flock is POSIX-only")
def test_a_short_hold_is_waited_for_without_a_word(tmp_path, monkeypatch):
    """Another process loading a cached build holds the lock for a moment: waiting for it says nothing (the
    benchmark's workers start together, and each used to announce the other's load as a build)."""
    monkeypatch.setattr(extension, "_QUIET_WAIT_S", 20.0)
    holder = _start_holder(tmp_path, 0.5)
    try:
        said = []
        with extension.build_turn(str(tmp_path), say=said.append):
            assert not (tmp_path / "lock").exists()
        assert said == []
        assert holder.wait(timeout=30) == 0
    finally:
        holder.kill()


@pytest.mark.skipif(extension.fcntl is None, reason="flock is POSIX-only")
def test_torch_lock_of_a_killed_build_is_removed_at_once(tmp_path):
    holder = _start_holder(tmp_path, 60)
    holder.kill()  # killed mid-build: torch's lock file stays, the OS lock goes with the process
    holder.wait(timeout=30)
    assert (tmp_path / "lock").exists()
    said = []
    with extension.build_turn(str(tmp_path), say=said.append):
        assert not (tmp_path / "lock").exists()
    assert said == [f"nimbus: removed a stale compiler lock left by an interrupted build in {tmp_path}"]
    with extension.build_turn(str(tmp_path), say=said.append):  # nothing left over: nothing said
        pass
    assert len(said) == 1


def test_a_library_of_several_sources_compiles_as_one_translation_unit():
    # torch's headers are most of a small source's compile: parsed once per library, not once per file.
    ext = raster.EXTENSION
    if not ext.available(warn=False):
        pytest.skip(f"compiled rasterizer unavailable: {ext.load_error()}")
    ninja = Path(ext.build_dir(), "build.ninja").read_text()
    compiled = [line for line in ninja.splitlines() if line.startswith("build ") and ": compile " in line]
    assert len(compiled) == 1 and compiled[0].endswith("_unity.cpp"), compiled
    unity = Path(compiled[0].split(": compile ", 1)[1]).read_text()
    assert [line for line in unity.splitlines() if line.startswith("#include")] == [
        '#include "composite.cpp"', '#include "project.cpp"']


def test_the_unity_source_is_rewritten_only_when_it_changes(tmp_path):
    # A new file time would make ninja compile the library again at every load.
    ext = extension.Extension("nimbus_test_unity", ("composite.cpp", "project.cpp"), "k", "f")
    path = Path(ext._unity_source(str(tmp_path)))
    old = path.stat().st_mtime_ns - 10**9
    os.utime(path, ns=(old, old))
    assert Path(ext._unity_source(str(tmp_path))) == path and path.stat().st_mtime_ns == old
    path.write_text("// stale\n")
    ext._unity_source(str(tmp_path))
    assert '#include "project.cpp"' in path.read_text()
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]  # no temporary file left


def test_build_failure_falls_back_with_one_warning(monkeypatch):
    ext = raster.EXTENSION
    saved = dict(ext.state)

    def broken_build():
        raise RuntimeError("Error building extension 'x'\nc++: fatal error: no input files")

    monkeypatch.setattr(ext, "build", broken_build)
    ext.state.update(tried=False, ok=False, error=None, warned=False)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            assert raster.available() is False
            assert raster.available() is False
        assert len(caught) == 1 and "torch compositor" in str(caught[0].message)
        assert "no input files" in raster.load_error()
    finally:
        ext.state.clear()
        ext.state.update(saved)
    monkeypatch.setenv("NIMBUS_DISABLE_CPP", "1")
    assert raster.available() is False


def test_matches_torch_compositor_when_present():
    composite_torch = pytest.importorskip("nimbus.render.composite_torch")
    a = inputs(make_scene(150, 45, 30, seed=10, dtype=torch.float32), 45, 30, 16)
    weights = output_weights(45, 30)
    outs, grads, _ = kernel_grads(a, weights)
    leaves = {k: a[k].clone().requires_grad_() for k in GRAD_NAMES}
    ref = composite_torch.composite(**dict(a, **leaves))
    weighted_loss(ref, weights).backward()
    for name, o, r in zip(("rgb", "depth", "alpha"), outs, ref):
        assert_close(o, r.detach(), 1e-4, 2e-5, name)
    for name in GRAD_NAMES:
        scale = absmax(leaves[name].grad) + 1.0
        assert_close(grads[name], leaves[name].grad, 1e-4, 2e-5 * scale, f"grad {name}")
