"""Speed of the compiled compositing kernel (forward + backward), 1 vs 2 threads, vs torch.

Usage::

    python -m tools.speed.composite_cpp [--repeats 5] [--no-torch]

Prints one row per (image size, Gaussian count): the intersection count, the mean
pixel alpha, forward and forward+backward wall milliseconds of
``nimbus.kernels.raster.composite`` with 1 and 2 threads (``torch.set_num_threads``; median
of the repeats after one warm-up), the 2-vs-1-thread speed-up, the CPU time used with 2
threads relative to 1 thread (1.00 = no parallel overhead; on a machine shared with
other jobs the wall speed-up understates what an idle machine gives, this does not),
and, when ``nimbus.render.composite_torch`` exists, the torch compositor's
forward+backward time in the same run (default thread count; one timed run above the
smallest size) and its ratio to the 2-thread kernel.

Inputs are synthetic but shaped like projected scenes: means uniform over the image
(plus a margin), anisotropic footprints with sigma log-uniform in 0.7..6 px (3-sigma
radii about 2..18 px), opacities half faint (0.05..0.5) and half strong (0.5..0.99), so
pixels composite about 60 Gaussians before saturating (97 % reach T < 1e-3), 16 px
tiles, float32.  The same distribution as ``tools.speed.rasterizer``.
"""

from __future__ import annotations

import argparse
import math
import statistics
import time

import torch

from nimbus.kernels import raster

SIZES = ((64, 48, 2_000), (160, 120, 20_000), (320, 240, 50_000))
TILE = 16
SIGMA_PX = (0.7, 6.0)
MARGIN_PX = 8.0


def make_inputs(width: int, height: int, n: int, seed: int = 0) -> dict:
    """Random projected Gaussians and their tile lists (float32), as composite() takes them."""
    g = torch.Generator().manual_seed(seed)

    def u(lo, hi, *shape):
        return lo + (hi - lo) * torch.rand(*shape, generator=g)

    means = torch.stack([u(-MARGIN_PX, width + MARGIN_PX, n), u(-MARGIN_PX, height + MARGIN_PX, n)], 1)
    s = torch.exp(u(math.log(SIGMA_PX[0]), math.log(SIGMA_PX[1]), n, 2))
    theta = u(0, math.pi, n)
    c, sn = torch.cos(theta), torch.sin(theta)
    rot = torch.stack([c, -sn, sn, c], 1).view(n, 2, 2)
    cov = rot @ torch.diag_embed(s**2 + 0.3) @ rot.transpose(1, 2)
    inv = torch.linalg.inv(cov)
    strong = torch.rand(n, generator=g) < 0.5
    opac = torch.where(strong, u(0.5, 0.99, n), u(0.05, 0.5, n))
    depths = u(1.0, 20.0, n)
    radii = torch.ceil(3 * torch.sqrt(torch.linalg.eigvalsh(cov)[:, 1]))
    ids, offsets = bin_tiles(means, radii, depths, width, height, TILE)
    return dict(means2d=means, conics=torch.stack([inv[:, 0, 0], inv[:, 0, 1], inv[:, 1, 1]], 1),
                colors=u(0, 1, n, 3), opacities=opac, depths=depths, isect_ids=ids, tile_offsets=offsets,
                width=width, height=height, tile_size=TILE, background=torch.zeros(3))


def bin_tiles(means, radii, depths, width, height, tile):
    """Vectorised tile binning: each Gaussian joins the tiles its 2r square touches; depth-sorted per tile."""
    tiles_x, tiles_y = -(-width // tile), -(-height // tile)
    lo = torch.floor((means - radii[:, None]) / tile).clamp(min=0).long()
    hi = torch.ceil((means + radii[:, None]) / tile).long()
    hi = torch.minimum(hi, torch.tensor([tiles_x, tiles_y]))
    w, h = (hi - lo).clamp(min=0).unbind(1)
    counts = w * h
    gauss = torch.repeat_interleave(torch.arange(means.shape[0]), counts)
    local = torch.arange(gauss.numel()) - (torch.cumsum(counts, 0) - counts)[gauss]
    tile_id = (lo[gauss, 1] + local // w[gauss]) * tiles_x + lo[gauss, 0] + local % w[gauss]
    rank = torch.argsort(torch.argsort(depths))
    order = torch.argsort(tile_id * means.shape[0] + rank[gauss])
    offsets = torch.searchsorted(tile_id[order], torch.arange(tiles_x * tiles_y + 1))
    return gauss[order].contiguous(), offsets


def time_fn(fn, repeats: int) -> tuple[float, float]:
    """Median wall and process-CPU time of fn() in milliseconds, after one warm-up call."""
    fn()
    wall, cpu = [], []
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - w0)
        cpu.append(time.process_time() - c0)
    return 1e3 * statistics.median(wall), 1e3 * statistics.median(cpu)


def fwd_bwd(composite, a: dict, grads) -> callable:
    floats = ("means2d", "conics", "colors", "opacities", "depths")

    def run():
        leaves = {k: a[k].detach().requires_grad_() for k in floats}
        outs = composite(**dict(a, **leaves))
        torch.autograd.backward(outs, grads)

    return run


def fwd(composite, a: dict) -> callable:
    def run():
        with torch.no_grad():
            composite(**a)

    return run


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5, help="timed runs per figure (median)")
    parser.add_argument("--no-torch", action="store_true", help="skip the torch compositor baseline")
    args = parser.parse_args(argv)
    if not raster.available():
        print(f"compiled kernel unavailable: {raster.load_error()}")
        return 1
    composite_torch = None
    if not args.no_torch:
        try:
            from nimbus.render.composite_torch import composite as composite_torch
        except ImportError:
            pass
    threads_before = torch.get_num_threads()
    header = (f"{'size':>9} {'M':>6} {'I':>7} {'alpha':>5} | {'fwd 1t':>7} {'fwd 2t':>7} | "
              f"{'f+b 1t':>7} {'f+b 2t':>7} {'2t/1t':>6} {'cpu2/1':>6}")
    if composite_torch is not None:
        header += f" | {'torch f+b':>9} {'ratio':>6}"
    print(f"compositing forward / forward+backward, wall ms (median of {args.repeats}), tile {TILE}, "
          f"float32, {threads_before} threads available")
    print(header)
    try:
        for width, height, n in SIZES:
            a = make_inputs(width, height, n)
            with torch.no_grad():
                alpha = raster.composite(**a)[2]
            g = torch.Generator().manual_seed(1)
            grads = (torch.randn(height, width, 3, generator=g), torch.randn(height, width, generator=g),
                     torch.randn(height, width, generator=g))
            row = {}
            for threads in (1, 2):
                torch.set_num_threads(threads)
                row[f"f{threads}"], _ = time_fn(fwd(raster.composite, a), args.repeats)
                row[f"fb{threads}"], row[f"cpu{threads}"] = time_fn(fwd_bwd(raster.composite, a, grads),
                                                                    args.repeats)
            torch.set_num_threads(threads_before)
            line = (f"{width:>4}x{height:<4} {n:>6} {a['isect_ids'].numel():>7} {float(alpha.mean()):>5.2f} | "
                    f"{row['f1']:>7.1f} {row['f2']:>7.1f} | {row['fb1']:>7.1f} {row['fb2']:>7.1f} "
                    f"{row['fb1'] / row['fb2']:>5.2f}x {row['cpu2'] / row['cpu1']:>6.2f}")
            if composite_torch is not None:
                reps = args.repeats if n <= SIZES[0][2] else 1
                t_torch, _ = time_fn(fwd_bwd(composite_torch, a, grads), reps)
                line += f" | {t_torch:>9.1f} {t_torch / row['fb2']:>5.0f}x"
            print(line, flush=True)
    finally:
        torch.set_num_threads(threads_before)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
