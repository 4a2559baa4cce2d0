"""Speed and memory of the weather synthesizer (``nimbus-synth degrade``).

Usage::

    python -m tools.speed.synth [--scene DIR | --size standard] [--weather all] [--protocol onerestore]
                                [--memory-views 12]

Degrades a scene (default: the built-in garden at ``standard`` size, 48 views of
320 x 240, rendered first and not timed) in every requested setting into a
temporary folder and prints, per setting, the seconds, views per second and the
mean transmission / particle coverage, then the total wall-clock and CPU
seconds.  The issue's target is seven settings x 48 views at 320 x 240 in
under 20 s on the 2-core development machine.

Baseline (same run): reading every view and writing it back as PNG once per
setting, the I/O floor of any synthesizer writing this dataset; the ratio says
what the weather itself costs on top.

Memory (streaming): the peak traced allocation during the run with the first
``--memory-views`` views and with all views; they should be about equal (the
scene's own in-memory images are allocated before tracing starts).
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
import tracemalloc
from pathlib import Path

from nimbus.data.images import encode_png
from nimbus.utils.fs import atomic_write_bytes
from weather_synth.config import protocol_config
from weather_synth.dataset import degrade_scene
from weather_synth.settings import parse_weather


def _load(args):
    if args.scene:
        from nimbus.data.io import load_scene

        return load_scene(args.scene)
    from nimbus.data.builtin import render_builtin

    return render_builtin("garden", args.size, seed=0)


def _baseline(scene, settings, out: Path) -> float:
    """Seconds to read each view and write it as PNG once per setting (no weather)."""
    t0 = time.perf_counter()
    for s in settings:
        for v in scene.views:
            atomic_write_bytes(out / s.name / v.name, encode_png(v.load_image()))
    return time.perf_counter() - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", default=None, help="scene folder (default: render the built-in garden)")
    parser.add_argument("--size", default="standard", help="built-in size when no --scene is given")
    parser.add_argument("--weather", default="all")
    parser.add_argument("--protocol", default="onerestore", choices=["onerestore", "physical"])
    parser.add_argument("--memory-views", type=int, default=12, help="0 skips the memory comparison")
    args = parser.parse_args()

    t0 = time.perf_counter()
    scene = _load(args)
    settings = parse_weather(args.weather)
    config = protocol_config(args.protocol, seed=0)
    cam = scene.views[0].camera
    print(f"scene: {len(scene)} views {cam.width}x{cam.height} ({time.perf_counter() - t0:.1f} s to load, not timed); "
          f"{len(settings)} settings, protocol {args.protocol}, {os.cpu_count()} CPUs")

    tmp = Path(tempfile.mkdtemp(prefix="bench-synth-"))
    try:
        t0, c0 = time.perf_counter(), time.process_time()
        summaries = degrade_scene(scene, tmp / "out", settings, config, progress=False)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        print(f"{'setting':<8} {'seconds':>8} {'views/s':>8} {'mean t':>7} {'particles':>9}")
        for s in summaries:
            t = f"{s.mean_transmission:.3f}" if s.mean_transmission is not None else "-"
            print(f"{s.setting:<8} {s.seconds:>8.2f} {s.views / s.seconds:>8.1f} {t:>7} {s.particle_coverage:>8.1%}")
        n = len(settings) * len(scene)
        print(f"total: {wall:.2f} s wall, {cpu:.2f} s CPU for {n} view-settings "
              f"({1000 * wall / n:.1f} ms each); target < 20 s for 7 x 48 views at 320x240")
        base = _baseline(scene, settings, tmp / "baseline")
        print(f"baseline (read + PNG write only): {base:.2f} s; synthesizer / baseline = {wall / base:.2f}x")

        if args.memory_views > 0 and args.memory_views < len(scene):
            peaks = []
            for k in (args.memory_views, len(scene)):
                sub = scene.with_views(scene.views[:k])
                shutil.rmtree(tmp / "mem", ignore_errors=True)
                tracemalloc.start()
                degrade_scene(sub, tmp / "mem", settings[:1], config, progress=False)
                peaks.append(tracemalloc.get_traced_memory()[1] / 2**20)
                tracemalloc.stop()
            print(f"peak traced memory, setting {settings[0].name}: {args.memory_views} views {peaks[0]:.1f} MiB, "
                  f"{len(scene)} views {peaks[1]:.1f} MiB (streaming: about equal)")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
