"""Forward + backward time and peak memory of the full rasterizer, per backend and size.

Usage::

    python -m tools.speed.rasterizer [--backends torch cpp] [--sizes small medium large] [--repeats 3]
                                     [--threads 1 2]

One row per (size, backend, threads): Gaussians visible, tile intersections, mean pixel alpha,
forward / backward / total wall milliseconds of ``rasterize()`` (median of the repeats, after
one warm-up), the best total (the least disturbed by other processes), the process CPU time
of a forward+backward (all threads; on a shared, loaded machine the steadier figure: wall
time includes waiting for a core),
peak resident memory added by rendering (``ru_maxrss`` of a fresh process after the
runs minus before the first; each row runs in its own process), and the speed-up over
the naive dense reference (``nimbus.render.reference``) measured in the same run; the
reference is timed at the small size only ("n/a" elsewhere: too slow, nothing is
extrapolated).  Backends that are not available are reported as such and skipped.
Each row is followed by its per-stage breakdown (medians of separately timed runs of
the same pipeline: projection + SH shading, binning, compositing forward, and the whole
backward), and each size ends with the ratios torch / cpp and 1 thread / 2 threads,
all from the same run.

The scene is random but shaped like a trained one: N Gaussians uniform over the view
(plus an 8 px margin) at depths 2..8, anisotropic, randomly rotated, with screen-space
standard deviations log-uniform in 0.7..6 px (3-sigma radii about 2..18 px, so deep
pixels have ~100 Gaussians in their tile lists), half of them faint (opacity 0.05..0.5)
and half strong (0.5..0.99) so most pixels saturate after a few tens, SH degree 3.
Same distribution as ``tools.speed.composite_cpp``; 16 px tiles; float32.

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


def _staged(gs, cam, backend: str, cfg):
    """One forward+backward of ``backend``'s pipeline with each stage timed (seconds)."""
    import importlib

    import torch

    from nimbus.render import binning, composite_torch
    from nimbus.render.backends import torch as torch_backend

    rz = importlib.import_module("nimbus.render.rasterize")
    viewmat, K, width, height = rz.resolve_camera(gs, cam, None, None, None, None)
    bg = torch.zeros(3, dtype=gs.means.dtype)
    t0 = time.perf_counter()
    if backend == "cpp":
        from nimbus.kernels import raster

        means2d, conics, colors, opac, depths, radii = raster.project_and_shade(
            gs.means, gs.quats, gs.log_scales, gs.opacity_logits, gs.sh_dc, gs.sh_rest, viewmat, K, width, height,
            gs.sh_degree, cfg.projection)
        t1 = time.perf_counter()
        ids, offsets = raster.bin_gaussians(means2d, radii, depths, width, height, cfg.tile_size)
        t2 = time.perf_counter()
        out = raster.composite(means2d, conics, colors, opac, depths, ids, offsets, width, height, cfg.tile_size,
                               bg)
    else:
        s = torch_backend.project_and_shade(gs, viewmat, K, width, height, gs.sh_degree, cfg.projection)
        t1 = time.perf_counter()
        ids, offsets = binning.bin_gaussians(s.vis_means2d, s.vis_radii, s.vis_depths, width, height,
                                             cfg.tile_size)
        t2 = time.perf_counter()
        out = composite_torch.composite(s.vis_means2d, s.vis_conics, s.vis_colors, s.vis_opacities, s.vis_depths,
                                        ids, offsets, width, height, cfg.tile_size, bg, config=cfg.composite)
    t3 = time.perf_counter()
    torch.autograd.backward(list(out), [torch.ones_like(x) for x in out])
    t4 = time.perf_counter()
    return {"project+sh": t1 - t0, "bin": t2 - t1, "composite": t3 - t2, "backward": t4 - t3}


def _measure(size: str, backend: str, repeats: int, threads: int, queue) -> None:
    """Child process: time one (size, backend, threads) and report through ``queue``."""
    import torch

    torch.set_num_threads(threads)

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
    fwd_t, bwd_t, cpu_t = [], [], []
    stats = {}
    for i in range(repeats + 1):  # the first run is a warm-up (and builds/loads a compiled kernel)
        for t in gs.tensors().values():
            t.grad = None
        c0 = time.process_time()
        t0 = time.perf_counter()
        rgb, depth, alpha, meta = render()
        t1 = time.perf_counter()
        if grads is None:
            gen = torch.Generator().manual_seed(1)
            grads = [torch.randn(x.shape, generator=gen) for x in (rgb, depth, alpha)]
        torch.autograd.backward([rgb, depth, alpha], grads)
        t2 = time.perf_counter()
        c2 = time.process_time()
        if i > 0:
            fwd_t.append(t1 - t0)
            bwd_t.append(t2 - t1)
            cpu_t.append(c2 - c0)
        stats = {"visible": int(meta["visible"].sum()), "isect": meta.get("num_intersections", -1),
                 "alpha": float(alpha.detach().mean())}
    peak_mb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - base_kb) / 1024
    totals = [a + b for a, b in zip(fwd_t, bwd_t)]
    stages = {}
    if backend != "reference":
        runs = []
        for _ in range(repeats):
            for t in gs.tensors().values():
                t.grad = None
            runs.append(_staged(gs, cam, backend, cfg))
        stages = {k: _median_ms([r[k] for r in runs]) for k in runs[0]}
    queue.put(dict(stats, fwd=_median_ms(fwd_t), bwd=_median_ms(bwd_t), total=_median_ms(totals),
                   best=1e3 * min(totals), cpu=_median_ms(cpu_t), peak_mb=peak_mb, stages=stages,
                   threads=torch.get_num_threads()))


def run_case(size: str, backend: str, repeats: int, threads: int = 1) -> dict:
    """Run :func:`_measure` in a fresh process (so its peak RSS is its own)."""
    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    proc = ctx.Process(target=_measure, args=(size, backend, repeats, threads, queue))
    proc.start()
    result = queue.get()
    proc.join()
    return result


def backend_available(backend: str) -> bool:
    if backend == "reference":
        return True
    from nimbus.render import backends

    return backends.available(backend, "cuda" if backend == "gsplat" else "cpu")


def _row(width, height, n, backend, threads, r, vs) -> str:
    return (f"{width:>3}x{height:<4} {n:>6} {backend:>9} {threads:>3} {r['visible']:>7} {r['isect']:>8} "
            f"{r['alpha']:>5.2f} | {r['fwd']:>8.1f} {r['bwd']:>8.1f} {r['total']:>8.1f} {r['best']:>8.1f} "
            f"{r['cpu']:>8.1f} {r['peak_mb']:>7.1f} | {vs}")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--backends", nargs="+", default=["torch", "cpp"], choices=["torch", "cpp", "gsplat"])
    parser.add_argument("--sizes", nargs="+", default=list(SIZES), choices=list(SIZES))
    parser.add_argument("--repeats", type=int, default=3, help="timed runs per figure (median), after a warm-up")
    parser.add_argument("--threads", nargs="+", type=int, default=[1, 2], help="torch.set_num_threads values")
    parser.add_argument("--no-reference", action="store_true", help="skip the dense reference at the small size")
    args = parser.parse_args(argv)

    from tools.speed import load_average, openmp_wait

    print(f"rasterizer forward+backward, float32, 16 px tiles, SH degree 3, median of {args.repeats} runs (ms); "
          f"cpu = process CPU time of one f+b (all threads); peak = added resident memory (MB); "
          f"{openmp_wait()}, load average {load_average()} (wall times include waiting for a core)")
    print(f"{'size':>8} {'N':>6} {'backend':>9} {'thr':>3} {'visible':>7} {'isect':>8} {'alpha':>5} | "
          f"{'fwd':>8} {'bwd':>8} {'f+b':>8} {'best':>8} {'cpu':>8} {'peak':>7} | {'ref/this':>8}")
    for size in args.sizes:
        width, height, n = SIZES[size]
        ref_total = None
        if size == "small" and not args.no_reference:
            ref = run_case(size, "reference", 1)
            ref_total = ref["total"]
            print(_row(width, height, n, "reference", 1, dict(ref, isect="-"), f"{1.0:>7.1f}x"), flush=True)
        results = {}
        for backend in args.backends:
            if not backend_available(backend):
                print(f"{width:>3}x{height:<4} {n:>6} {backend:>9}   (not available here, skipped)", flush=True)
                continue
            for threads in args.threads:
                r = results[backend, threads] = run_case(size, backend, args.repeats, threads)
                vs = f"{ref_total / r['total']:>7.1f}x" if ref_total else f"{'n/a':>8}"
                print(_row(width, height, n, backend, threads, r, vs), flush=True)
                print(f"{'':>17} stages (ms): " + ", ".join(f"{k} {v:.1f}" for k, v in r["stages"].items()),
                      flush=True)
        ratios = []
        for threads in args.threads:
            if ("torch", threads) in results and ("cpp", threads) in results:
                t, c = results["torch", threads], results["cpp", threads]
                ratios.append(f"torch/cpp {threads} thr: wall {t['total'] / c['total']:.1f}x, "
                              f"cpu {t['cpu'] / c['cpu']:.1f}x")
        for backend in args.backends:
            one, two = results.get((backend, 1)), results.get((backend, 2))
            if one and two:
                ratios.append(f"{backend} 1 thr/2 thr: wall {one['total'] / two['total']:.2f}x "
                              f"(best {one['best'] / two['best']:.2f}x)")
        if ratios:
            print(f"{'':>17} " + "; ".join(ratios), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
