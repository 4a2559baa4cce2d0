"""Where a whole training iteration spends its time, 3DGS against NimbusGS, part by part.

Usage::

    python -m tools.speed.training [--scene builtin:garden] [--sizes tiny small]
                                   [--methods 3dgs nimbus-full nimbus] [--preset tiny]
                                   [--iterations N] [--warmup 10] [--threads 1,2]
                                   [--interleave 25]

For each size (``builtin:NAME:SIZE``; a scene folder is timed once, at its own size), each
method and each thread count, the method is built as ``nimbus-train`` builds it (its
registry preset, the runner's training frame, seed 0) and trained for the preset's
schedule (``--iterations`` rescales it, as ``--set iterations=N`` does), every step timed
after ``--warmup`` untimed ones.  The parts are timed by wrapping, for the run only, the
functions the method itself calls (nothing in ``nimbus`` changes and the arithmetic is
the same; each wrapper reads the clock, and on CUDA synchronises, around the call):

====================  ==================================================================
projection + SH       the backend's ``project_and_shade`` ("cpp", "torch")
binning               its ``bin_gaussians``
compositing fwd       its ``composite`` (gsplat: its whole ``rasterization`` call)
backward: raster      from the first gradient reaching the compositor's outputs to the
                      end of ``backward()`` (compositing + projection backward)
backward: rest        the rest of ``backward()`` (loss, and NimbusGS's medium)
loss                  ``method.loss`` (L1 + SSIM; NimbusGS: also L_DCP, L_TV, compose)
NimbusGS march        ``march_interval`` + ``march`` (forward)
NimbusGS airlight     the airlight network (forward)
GGS                   ``before_backward`` (the weights) + ``reweight_gradients`` (scaling, where
                      the rasterizer's backward did not fold the weights in)
optimiser step        ``optimizer_step`` (NimbusGS: with the medium's Adam)
densification         ``strategy.step_post_backward`` (statistics every step, densify and
                      prune at its steps), amortised
NimbusGS refresh      ``after_step``: the stage boundary (evidence, first R) and the periodic
                      R refreshes of ``refresh_mode=all``, amortised (a ``lazy`` refresh
                      runs inside the loss and counts there)
other                 the rest of ``train_iteration`` (view pick, guards, PSNR)
====================  ==================================================================

A part nested in another is counted once, in the inner one (the loss excludes the
march it calls), except inside densification and refresh, which are counted whole.
Columns: ``ms/call`` the median over the steps that called the part (amortised parts: the
largest call, a densification or refresh step), ``ms/it`` its total
over the timed steps divided by their number (the amortised cost), ``share`` of the
whole.  ``whole`` is the median (and mean) wall milliseconds of ``train_iteration``;
``raster`` the median per step of the rasterizer's forward + backward (the first four
rows).  The summary gives whole / raster, NimbusGS / 3DGS (medians of the same run) and
the 1 / 2 thread ratio.  On a machine shared with other jobs every figure includes
waiting for a core: the load average is printed, compare ratios from one run only.

By default (``--interleave 25``) every method at every thread count is built first and they
are trained at once, taking turns 25 steps at a time, so that a machine that drifts while the
tool runs (a virtual machine's neighbours, a laptop's clock) moves them all alike; memory is
then the sum of the runs'.  A machine whose speed changes within 25 steps still moves the
figures (docs/performance.md, round 11).  ``--interleave 0`` trains them one after another,
as the tool did before 2026-12-01.

``nimbus`` on a clean built-in scene usually turns its components off (that is what it is
for); ``nimbus-full`` times every component.  A ``nimbus-synth degrade`` setting folder
as ``--scene`` times them on weather.
"""

from __future__ import annotations

import argparse
import dataclasses
import re
import statistics
import tempfile
import time
from collections import defaultdict
from contextlib import ExitStack, contextmanager

import torch

from benchmark.tables.model import Block, Column, Row, Table
from benchmark.tables.writer import to_markdown
from tools.speed import load_average, openmp_wait

#: The parts, in table order: (key, label).
PARTS = (
    ("project", "projection + SH"),
    ("bin", "binning"),
    ("composite", "compositing fwd"),
    ("raster_bwd", "backward: raster"),
    ("rest_bwd", "backward: rest"),
    ("loss", "loss (L1 + SSIM, ...)"),
    ("march", "NimbusGS march fwd"),
    ("airlight", "NimbusGS airlight fwd"),
    ("ggs", "GGS"),
    ("optimizer", "optimiser step"),
    ("densify", "densification (amortised)"),
    ("refresh", "NimbusGS refresh (amortised)"),
    ("other", "other"),
)
RASTER_PARTS = ("project", "bin", "composite", "raster_bwd")
#: Parts timed whole: what they call is not timed separately.
WHOLE_PARTS = ("densify", "refresh")


class Probe:
    """Per-step exclusive wall seconds of the wrapped calls (see the module docstring)."""

    def __init__(self, device: torch.device) -> None:
        self.cuda = device.type == "cuda"
        self.steps: list[dict[str, float]] = []
        self.current: dict[str, float] = defaultdict(float)
        self.stack: list[list] = []  # [key, start, time spent in nested timed calls]
        self.whole = 0  # > 0 inside a WHOLE_PARTS call
        self.backward_start: float | None = None
        self.raster_grad_at: float | None = None

    def now(self) -> float:
        if self.cuda:
            torch.cuda.synchronize()
        return time.perf_counter()

    def wrap(self, key: str, fn):
        def timed(*args, **kwargs):
            if self.whole:
                return fn(*args, **kwargs)
            self.whole += key in WHOLE_PARTS
            frame = [key, self.now(), 0.0]
            self.stack.append(frame)
            try:
                return fn(*args, **kwargs)
            finally:
                spent = self.now() - frame[1]
                self.stack.pop()
                self.whole -= key in WHOLE_PARTS
                self.current[key] += spent - frame[2]
                if self.stack:
                    self.stack[-1][2] += spent
        return timed

    def wrap_composite(self, fn):
        """The compositor, timed, with a hook marking when backward reaches its outputs."""
        timed = self.wrap("composite", fn)

        def hooked(*args, **kwargs):
            out = timed(*args, **kwargs)
            if not self.whole and torch.is_grad_enabled():
                for t in out:
                    if isinstance(t, torch.Tensor) and t.requires_grad:
                        t.register_hook(self._raster_grad)
            return out
        return hooked

    def _raster_grad(self, grad):
        if self.backward_start is not None and self.raster_grad_at is None:
            self.raster_grad_at = self.now()

    def wrap_backward(self, fn):
        def timed(tensor, *args, **kwargs):
            if self.whole or self.stack:
                return fn(tensor, *args, **kwargs)
            self.backward_start, self.raster_grad_at = self.now(), None
            try:
                return fn(tensor, *args, **kwargs)
            finally:
                end = self.now()
                split = self.raster_grad_at if self.raster_grad_at is not None else end
                self.current["rest_bwd"] += split - self.backward_start
                self.current["raster_bwd"] += end - split
                self.backward_start = None
        return timed

    def step(self, fn):
        """Run one whole training step, recording its parts and ``whole``."""
        self.current = defaultdict(float)
        t0 = self.now()
        fn()
        whole = self.now() - t0
        self.current["other"] = whole - sum(self.current.values())
        self.current["whole"] = whole
        self.steps.append(dict(self.current))


def _patch(stack: ExitStack, owner, name: str, wrapper) -> None:
    """Replace ``owner.name`` by ``wrapper(original)`` until ``stack`` closes (frozen dataclasses too)."""
    original = getattr(owner, name)
    own = name in vars(owner)
    setter = object.__setattr__ if dataclasses.is_dataclass(owner) else setattr
    setter(owner, name, wrapper(original))
    if own:
        stack.callback(setter, owner, name, original)
    else:  # an instance's patched method: uncover the class's again
        stack.callback(object.__delattr__ if dataclasses.is_dataclass(owner) else delattr, owner, name)


@contextmanager
def instrumented(method, probe: Probe):
    """``method`` (built from :mod:`nimbus.methods`) with its parts timed by ``probe`` inside the block."""
    from nimbus.kernels import raster
    from nimbus.render import backends
    from nimbus.render.backends import torch as torch_backend

    with ExitStack() as stack:
        for module in (raster, torch_backend):
            _patch(stack, module, "project_and_shade", lambda f: probe.wrap("project", f))
            _patch(stack, module, "bin_gaussians", lambda f: probe.wrap("bin", f))
            _patch(stack, module, "composite", probe.wrap_composite)
        if method.device.type == "cuda" and backends.available("gsplat", method.device):
            import gsplat  # its one call is the whole forward rasterizer: counted as compositing

            _patch(stack, gsplat, "rasterization", probe.wrap_composite)
        _patch(stack, torch.Tensor, "backward", probe.wrap_backward)
        for name, key in (("loss", "loss"), ("before_backward", "ggs"), ("reweight_gradients", "ggs"),
                          ("optimizer_step", "optimizer"), ("after_step", "refresh")):
            _patch(stack, method, name, lambda f, key=key: probe.wrap(key, f))
        _patch(stack, method.strategy, "step_post_backward", lambda f: probe.wrap("densify", f))
        medium = getattr(method, "medium", None)
        if medium is not None:
            from nimbus.methods.nimbusgs import degradation

            _patch(stack, degradation, "march", lambda f: probe.wrap("march", f))
            _patch(stack, degradation, "march_interval", lambda f: probe.wrap("march", f))
            _patch(stack, medium.airlight, "forward", lambda f: probe.wrap("airlight", f))
        yield probe


def method_config(method_name: str, preset_name: str, iterations: int | None = None):
    """``(name, config)`` of a method spec as the speed tools take it: ``NAME`` or ``NAME:KEY=VALUE,...`` (``--set``
    overrides), the preset's config with them, ``iterations`` rescaling its schedule, and no decomposition images
    written (they are not what is measured)."""
    from nimbus.config_set import apply_overrides, parse_set_args
    from nimbus.methods.registry import get_method

    method_name, _, spec = method_name.partition(":")
    items = [item for item in re.split(r",(?=\w+=)", spec) if item]  # a value may hold commas: ggs_clip=0.5,3
    overrides = parse_set_args(items, flag=f"--methods {method_name}:")
    config = apply_overrides(get_method(method_name).preset(preset_name), overrides)
    if hasattr(config, "write_decomposition"):
        config = dataclasses.replace(config, write_decomposition=False)
    if iterations:
        config = config.with_changes({"iterations": iterations})
    return method_name, config


class TimedRun:
    """One method trained step by step under its own :class:`Probe`, so that several runs can take turns.

    ``name`` may carry ``--set`` overrides after a colon, ``nimbus:refresh_mode=all,airlight_stride=2``, so two
    variants of one method are timed side by side in one run.  Close it (or use it as a context manager) to
    delete its run folder.
    """

    def __init__(self, name: str, scene, preset_name: str, iterations: int | None, threads: int,
                 steps: int | None = None) -> None:
        from nimbus.train.runner import Runner

        self.threads = threads
        torch.set_num_threads(threads)
        method_name, self.config = method_config(name, preset_name, iterations)
        self._folder = tempfile.TemporaryDirectory(prefix="bench_training_")
        try:
            self.method = Runner(method_name, scene, self.config, self._folder.name, seed=0, progress=False,
                                 checkpoints=False).method
        except BaseException:
            self._folder.cleanup()
            raise
        self.probe = Probe(self.method.device)
        self.last = min(self.config.iterations, steps or self.config.iterations)
        self.done = 0

    @property
    def finished(self) -> bool:
        return self.done >= self.last or len(self.method.params) == 0

    def advance(self, count: int) -> None:
        """Train the next ``count`` steps (fewer at the end), timed, with this run's thread count."""
        torch.set_num_threads(self.threads)
        method, probe = self.method, self.probe
        with instrumented(method, probe):
            for _ in range(count):
                if self.finished:
                    break
                self.done += 1
                step = self.done
                probe.step(lambda: method.train_iteration(step))

    def result(self, warmup: int) -> dict:
        """Per-part figures of the steps after the first ``warmup`` (see :func:`summarise`)."""
        method = self.method
        cam = method.train_views[0].camera
        return dict(summarise(self.probe.steps[warmup:]), gaussians=len(method.params),
                    size=f"{cam.width}x{cam.height}", components=",".join(getattr(method, "components", [])) or "-",
                    iterations=self.config.iterations)

    def close(self) -> None:
        self._folder.cleanup()

    def __enter__(self) -> "TimedRun":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def time_method(method_name: str, scene, preset_name: str, iterations: int | None, warmup: int,
                threads: int, steps: int | None = None) -> dict:
    """Train ``method_name`` on ``scene`` and return its per-part figures (see :func:`summarise`)."""
    with TimedRun(method_name, scene, preset_name, iterations, threads, steps) as run:
        run.advance(run.last)
        return run.result(warmup)


def time_interleaved(names: list[str], threads: list[int], scene, preset_name: str, iterations: int | None,
                     warmup: int, steps: int | None = None, chunk: int = 25) -> dict[int, dict[str, dict]]:
    """Every method at every thread count, trained at once, taking turns ``chunk`` steps at a time.

    A machine that speeds up or slows down while the tool runs (a shared or virtual one, or a laptop's clock)
    then moves every run alike; run one after another, a drift of the machine between them reads as a difference
    of the methods or thread counts.  Returns ``{threads: {name: figures}}``.
    """
    with ExitStack() as stack:
        runs = {(th, name): stack.enter_context(TimedRun(name, scene, preset_name, iterations, th, steps))
                for th in threads for name in names}
        while not all(run.finished for run in runs.values()):
            for run in runs.values():
                run.advance(chunk)
        out: dict[int, dict[str, dict]] = {th: {} for th in threads}
        for (th, name), run in runs.items():
            out[th][name] = run.result(warmup)
        return out


def summarise(steps: list[dict[str, float]]) -> dict:
    """Milliseconds: per part ``(median per call, mean per step, calls)`` (for the amortised parts the largest
    call, not the median: most of their calls do next to nothing); ``whole`` and ``raster`` medians."""
    n = max(len(steps), 1)
    parts = {}
    for key, _ in PARTS:
        calls = [s[key] for s in steps if s.get(key)]
        typical = (max if key in WHOLE_PARTS else statistics.median)(calls) if calls else 0.0
        parts[key] = (1e3 * typical, 1e3 * sum(calls) / n, len(calls))
    whole = [s["whole"] for s in steps] or [0.0]
    raster = [sum(s.get(k, 0.0) for k in RASTER_PARTS) for s in steps] or [0.0]
    return {"parts": parts, "whole": 1e3 * statistics.median(whole), "whole_mean": 1e3 * statistics.fmean(whole),
            "raster": 1e3 * statistics.median(raster), "steps": len(steps)}


#: Per run (a column group): the part's typical milliseconds per call, its mean per iteration, its share.
COLUMNS = (Column("call", "ms/call", "ms/call", 1), Column("iteration", "ms/it", "ms/it", 1),
           Column("share", "share", "share", 0, unit="%"))


def table(title: str, runs: dict[str, dict]) -> Table:
    """A row per part, a column group per run (through the benchmark's table writer)."""
    names = list(runs)
    rows = []
    for key, label in PARTS:
        if all(runs[n]["parts"][key][2] == 0 for n in names):
            continue
        values = {}
        for n in names:
            med, per_it, _ = runs[n]["parts"][key]
            values.update({(n, "call"): med, (n, "iteration"): per_it, (n, "share"): 100 * per_it / runs[n]["whole_mean"]})
        rows.append(Row(label, values))
    rows += [Row("whole iteration (median / mean)",
                 {(n, c): v for n in names for c, v in (("call", runs[n]["whole"]), ("iteration", runs[n]["whole_mean"]),
                                                        ("share", 100.0))}, rule_before=True),
             Row("rasterizer fwd+bwd (median)", {(n, "call"): runs[n]["raster"] for n in names}),
             Row("whole / rasterizer", {(n, "call"): f"{runs[n]['whole'] / runs[n]['raster']:.2f}x"
                                        if runs[n]["raster"] else "n/a" for n in names}),
             Row("Gaussians at the end, components", {k: v for n in names for k, v in
                                                      (((n, "call"), str(runs[n]["gaussians"])),
                                                       ((n, "iteration"), runs[n]["components"]))})]
    return Table("training", "training", title, COLUMNS, names, [Block(rows, ranked=False)], lead=("part",))


def markdown(title: str, runs: dict[str, dict]) -> str:
    """The table in GitHub Markdown."""
    return to_markdown(table(title, runs))


def ratio_lines(results: dict, threads: list[int]) -> list[str]:
    """NimbusGS / 3DGS per size and thread count, and 1 / 2 (first / last) threads per method."""
    lines = []
    for (size, th), runs in results.items():
        if "3dgs" in runs:
            base = runs["3dgs"]
            for name, r in runs.items():
                if name != "3dgs":
                    lines.append(f"- {size}, {th} thr: {name} / 3dgs = {r['whole'] / base['whole']:.2f}x (median), "
                                 f"{r['whole_mean'] / base['whole_mean']:.2f}x (mean)")
    if len(threads) > 1:
        lo, hi = threads[0], threads[-1]
        for (size, th), runs in results.items():
            if th != lo or (size, hi) not in results:
                continue
            for name, r in runs.items():
                other = results[size, hi].get(name)
                if other:
                    lines.append(f"- {size}, {name}: {lo} thr / {hi} thr = {r['whole'] / other['whole']:.2f}x "
                                 f"(median), {r['whole_mean'] / other['whole_mean']:.2f}x (mean)")
    return lines


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="builtin:garden", help="builtin:NAME (timed at --sizes) or a scene folder")
    parser.add_argument("--sizes", nargs="+", default=["tiny", "small"], help="built-in scene sizes")
    parser.add_argument("--methods", nargs="+", default=["3dgs", "nimbus-full", "nimbus"],
                        help="registry names, each optionally with overrides: nimbus:refresh_mode=all")
    parser.add_argument("--preset", default="tiny", help="the methods' preset (its schedule is what is timed)")
    parser.add_argument("--iterations", type=int, default=None, help="rescale the preset's schedule to N steps")
    parser.add_argument("--steps", type=int, default=None,
                        help="stop after the first N steps of the schedule (default: all of it)")
    parser.add_argument("--warmup", type=int, default=10, help="untimed first steps")
    parser.add_argument("--threads", default=None, help="comma-separated torch thread counts, e.g. 1,2")
    parser.add_argument("--interleave", type=int, default=25, metavar="N",
                        help="train every method at every thread count at once, N steps each in turn, so that a "
                             "drift of the machine moves them alike (default 25); 0: one after another")
    args = parser.parse_args(argv)
    if args.interleave < 0:
        parser.error("--interleave must be 0 or more")

    from nimbus.train.run_folder import BUILTIN_PREFIX, load_scene_arg

    threads = [int(t) for t in args.threads.split(",")] if args.threads else [torch.get_num_threads()]
    specs = ([f"{args.scene}:{s}" for s in args.sizes] if args.scene.startswith(BUILTIN_PREFIX)
             and args.scene.count(":") == 1 else [args.scene])
    order = f"interleaved {args.interleave} steps at a time" if args.interleave else "one run after another"
    print(f"training iteration, preset {args.preset}, medians after {args.warmup} warm-up steps, {order}; "
          f"{openmp_wait()}; load average {load_average()}\n", flush=True)
    results: dict[tuple[str, int], dict] = {}
    for spec in specs:
        scene = load_scene_arg(spec)
        if args.interleave:
            timed = time_interleaved(args.methods, threads, scene, args.preset, args.iterations, args.warmup,
                                     args.steps, args.interleave)
        for th in threads:
            if args.interleave:
                runs = results[spec, th] = timed[th]
            else:
                runs = results[spec, th] = {}
                for name in args.methods:
                    runs[name] = time_method(name, scene, args.preset, args.iterations, args.warmup, th, args.steps)
            first = next(iter(runs.values()))
            print(markdown(f"{spec} ({first['size']}, {len(scene.train_views)} training views, "
                           f"{first['iterations']}-step schedule, {first['steps']} steps timed), {th} thread(s), "
                           f"load average {load_average()}", runs) + "\n", flush=True)
    print("\n".join(ratio_lines(results, threads)))
    return 0


if __name__ == "__main__":
    from nimbus.cli_util import run_cli

    raise SystemExit(run_cli(main))
