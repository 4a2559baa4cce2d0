"""Render time of the built-in scenes, per scene and size.

Usage::

    python -m tools.speed.scenes [--sizes tiny small standard] [--scenes garden street tabletop]
                                 [--workers 2] [--reference-views 4]

Prints one row per (scene, size): views, image size, samples per pixel, render
threads, total seconds of :func:`nimbus.data.builtin.render_builtin` (wall clock;
rendering and sparse points, no files written) and per view, the process's CPU
seconds (all threads), and the depth range.  The development machine's two cores
are shared with other jobs, so read wall and CPU seconds together.

With ``--reference-views N`` (N > 0) each row also renders its first N views one
by one, with the default settings and with the slow reference (every sample
shaded, no culling; see :class:`nimbus.data.builtin.raycast.RenderSettings`), and
prints both seconds per view, the speed-up and the mean absolute pixel difference
(all measured in this run, single-threaded).
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np

from nimbus.data.builtin import RENDER_WORKERS, SCENES, SIZES, get_scene, get_size, render_builtin
from nimbus.data.builtin.raycast import render_view


def _reference(name: str, size: str, n_views: int) -> tuple[float, float, float]:
    """Seconds per view of the default and the reference path, and their mean |pixel difference|."""
    sc, preset = get_scene(name), get_size(size)
    world = sc.config.world(0)
    cams = sc.config.cameras(preset.n_views, preset.width, preset.height, 0)[:n_views]
    fast = preset.render_settings
    slow = replace(fast, adaptive_threshold=None, cull=False)
    timings, images = [], []
    for settings in (fast, slow):
        t0 = time.perf_counter()
        images.append([render_view(world, c, settings).image for c in cams])
        timings.append((time.perf_counter() - t0) / len(cams))
    diff = float(np.mean([np.abs(a - b).mean() for a, b in zip(*images)]))
    return timings[0], timings[1], diff


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", nargs="+", default=list(SIZES), choices=list(SIZES))
    parser.add_argument("--scenes", nargs="+", default=sorted(SCENES), choices=sorted(SCENES))
    parser.add_argument("--workers", type=int, default=RENDER_WORKERS, help="render threads")
    parser.add_argument("--reference-views", type=int, default=0,
                        help="also time the unculled, fully supersampled reference on this many views")
    args = parser.parse_args()

    head = (f"{'scene':<8} {'size':<9} {'views':>5} {'WxH':>8} {'spp':>4} {'thr':>3} {'total s':>8} {'s/view':>7} "
            f"{'cpu s':>7} {'depth m':>13}")
    if args.reference_views > 0:
        head += f" {'fast s/v':>8} {'ref s/v':>8} {'speed-up':>8} {'mean|diff|':>10}"
    print(head)
    for name in args.scenes:
        for size in args.sizes:
            p = SIZES[size]
            t0, c0 = time.perf_counter(), time.process_time()
            scene = render_builtin(name, size, seed=0, workers=args.workers)
            wall, cpu = time.perf_counter() - t0, time.process_time() - c0
            depths = np.stack([v.depth for v in scene.views])
            row = (f"{name:<8} {size:<9} {len(scene):>5} {f'{p.width}x{p.height}':>8} {p.samples_per_axis ** 2:>4} "
                   f"{args.workers:>3} {wall:>8.2f} {wall / len(scene):>7.3f} {cpu:>7.2f} "
                   f"{f'{depths.min():.2f}-{depths.max():.1f}':>13}")
            if args.reference_views > 0:
                fast, ref, diff = _reference(name, size, min(args.reference_views, p.n_views))
                row += f" {fast:>8.3f} {ref:>8.3f} {ref / fast:>7.1f}x {diff:>10.4f}"
            print(row, flush=True)


if __name__ == "__main__":
    main()
