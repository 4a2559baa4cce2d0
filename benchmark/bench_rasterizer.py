"""Forward + backward time and peak memory of the full rasterizer, per backend and size.

Usage::

    python -m benchmark.bench_rasterizer [--backends torch cpp] [--sizes small medium large] [--repeats 3]

One row per (size, backend): Gaussians visible, tile intersections, mean pixel alpha,
forward / backward / total milliseconds (median of the repeats, after one warm-up) and
the best total (the least disturbed by other processes),
peak resident memory added by rendering (``ru_maxrss`` of a fresh process after the
runs minus before the first; each row runs in its own process), and the speed-up over
the naive dense reference (``nimbus.render.reference``) measured in the same run; the
reference is timed at the small size only ("n/a" elsewhere: too slow, nothing is
extrapolated).  Backends that are not available are reported as such and skipped.

The scene is random but shaped like a trained one: N Gaussians uniform over the view
(plus an 8 px margin) at depths 2..8, anisotropic, randomly rotated, with screen-space
standard deviations log-uniform in 0.7..6 px (3-sigma radii about 2..18 px, so deep
pixels have ~100 Gaussians in their tile lists), half of them faint (opacity 0.05..0.5)
and half strong (0.5..0.99) so most pixels saturate after a few tens, SH degree 3.
Same distribution as ``benchmark.bench_composite_cpp``; 16 px tiles; float32.

On a machine shared with other busy processes, OpenMP's default spin-waiting makes
torch's multi-threaded ops erratic (10x slow-downs seen on 2 cores); run with
``OMP_WAIT_POLICY=PASSIVE`` (or ``OMP_NUM_THREADS=1``) for stable figures.
"""

from __future__ import annotations

import argparse
import math
import multiprocessing as mp
import resource
import statistics
import sys
import time

SIZES = {"small": (64, 48, 2_000), "medium": (160, 120, 20_000), "large": (320, 240, 50_000)}
SIGMA_PX = (0.7, 6.0)
MARGIN_PX = 8.0
DEPTH = (2.0, 8.0)
FOCAL_FACTOR = 0.8  # focal length in units of the image width (about 64 degrees horizontal FoV)


def make_scene(width: int, height: int, n: int, seed: int = 0):
    """(Gaussians, Camera): the random trained-like scene of the module docstring."""
    import torch

    from nimbus.data import Camera
    from nimbus.render import Gaussians

    g = torch.Generator().manual_seed(seed)

    def u(lo, hi, *shape):
        return lo + (hi - lo) * torch.rand(*shape, generator=g)

    f = FOCAL_FACTOR * width
    cam = Camera(width, height, f, f, width / 2, height / 2)
    z = u(*DEPTH, n)
    px = u(-MARGIN_PX, width + MARGIN_PX, n)
    py = u(-MARGIN_PX, height + MARGIN_PX, n)
    means = torch.stack([(px - cam.cx) * z / f, (py - cam.cy) * z / f, z], 1)
    sigma_px = torch.exp(u(math.log(SIGMA_PX[0]), math.log(SIGMA_PX[1]), n, 3))
    log_scales = torch.log(sigma_px * z[:, None] / f)
    strong = torch.rand(n, generator=g) < 0.5
    opac = torch.where(strong, u(0.5, 0.99, n), u(0.05, 0.5, n))
    return Gaussians(
        means=means,
        log_scales=log_scales,
        quats=torch.randn(n, 4, generator=g),
        opacity_logits=torch.log(opac / (1 - opac)),
        sh_dc=torch.randn(n, 1, 3, generator=g) * 0.8,
        sh_rest=torch.randn(n, 15, 3, generator=g) * 0.05,
    ), cam


def _median_ms(times: list[float]) -> float:
    return 1e3 * statistics.median(times)


def _measure(size: str, backend: str, repeats: int, queue) -> None:
    """Child process: time one (size, backend) and report through ``queue``."""
    import torch

    from nimbus.render import RasterConfig, rasterize
    from nimbus.render.reference import rasterize_reference

    width, height, n = SIZES[size]
    gs, cam = make_scene(width, height, n)
    gs.requires_grad_()
    cfg = RasterConfig(tile_size=16)
    grads = None

    if backend == "reference":
        def render():
            return rasterize_reference(gs, cam, config=cfg)
    else:
        def render():
            return rasterize(gs, cam, backend=backend, config=cfg)

    base_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    fwd_t, bwd_t = [], []
    stats = {}
    for i in range(repeats + 1):  # the first run is a warm-up (and builds/loads a compiled kernel)
        for t in gs.tensors().values():
            t.grad = None
        t0 = time.perf_counter()
        rgb, depth, alpha, meta = render()
        t1 = time.perf_counter()
        if grads is None:
            gen = torch.Generator().manual_seed(1)
            grads = [torch.randn(x.shape, generator=gen) for x in (rgb, depth, alpha)]
        torch.autograd.backward([rgb, depth, alpha], grads)
        t2 = time.perf_counter()
        if i > 0:
            fwd_t.append(t1 - t0)
            bwd_t.append(t2 - t1)
        stats = {"visible": int(meta["visible"].sum()), "isect": meta.get("num_intersections", -1),
                 "alpha": float(alpha.detach().mean())}
    peak_mb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - base_kb) / 1024
    totals = [a + b for a, b in zip(fwd_t, bwd_t)]
    queue.put(dict(stats, fwd=_median_ms(fwd_t), bwd=_median_ms(bwd_t), total=_median_ms(totals),
                   best=1e3 * min(totals), peak_mb=peak_mb,
                   threads=torch.get_num_threads()))


def run_case(size: str, backend: str, repeats: int) -> dict:
    """Run :func:`_measure` in a fresh process (so its peak RSS is its own)."""
    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    proc = ctx.Process(target=_measure, args=(size, backend, repeats, queue))
    proc.start()
    result = queue.get()
    proc.join()
    return result


def backend_available(backend: str) -> bool:
    if backend in ("torch", "reference"):
        return True
    import importlib

    rz = importlib.import_module("nimbus.render.rasterize")
    if backend == "cpp":
        return rz.cpp_available()
    if backend == "gsplat":
        return rz.gsplat_available()
    return False


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--backends", nargs="+", default=["torch", "cpp"], choices=["torch", "cpp", "gsplat"])
    parser.add_argument("--sizes", nargs="+", default=list(SIZES), choices=list(SIZES))
    parser.add_argument("--repeats", type=int, default=3, help="timed runs per figure (median), after a warm-up")
    parser.add_argument("--no-reference", action="store_true", help="skip the dense reference at the small size")
    args = parser.parse_args(argv)

    import os

    import torch

    print(f"rasterizer forward+backward, float32, 16 px tiles, median of {args.repeats} runs (ms); "
          f"peak = added resident memory (MB); {torch.get_num_threads()} threads, "
          f"OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY', 'unset')}")
    print(f"{'size':>8} {'N':>6} {'backend':>9} {'visible':>7} {'isect':>8} {'alpha':>5} | "
          f"{'fwd':>8} {'bwd':>8} {'f+b':>8} {'best':>8} {'peak':>7} | {'ref/this':>8}")
    for size in args.sizes:
        width, height, n = SIZES[size]
        ref_total = None
        if size == "small" and not args.no_reference:
            ref = run_case(size, "reference", 1)
            ref_total = ref["total"]
            print(f"{width:>3}x{height:<4} {n:>6} {'reference':>9} {ref['visible']:>7} {'-':>8} "
                  f"{ref['alpha']:>5.2f} | {ref['fwd']:>8.1f} {ref['bwd']:>8.1f} {ref['total']:>8.1f} "
                  f"{ref['best']:>8.1f} {ref['peak_mb']:>7.1f} | {1.0:>7.1f}x", flush=True)
        for backend in args.backends:
            if not backend_available(backend):
                print(f"{width:>3}x{height:<4} {n:>6} {backend:>9}   (not available here, skipped)", flush=True)
                continue
            r = run_case(size, backend, args.repeats)
            vs = f"{ref_total / r['total']:>7.1f}x" if ref_total else f"{'n/a':>8}"
            print(f"{width:>3}x{height:<4} {n:>6} {backend:>9} {r['visible']:>7} {r['isect']:>8} {r['alpha']:>5.2f} | "
                  f"{r['fwd']:>8.1f} {r['bwd']:>8.1f} {r['total']:>8.1f} {r['best']:>8.1f} {r['peak_mb']:>7.1f} | {vs}",
                  flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
