"""Run the benchmark grid (``nimbus-bench run``): synthesise, train, render and score every cell.

With no arguments this is the default benchmark: every built-in scene (garden, street,
tabletop) at the tiny size, all seven weather settings (onerestore protocol), NimbusGS, 3DGS and
restore-3dgs (those registered) with the tiny preset, seed 0, into ``bench_runs/``, and per scene, preset and
seed the clean ceiling: 3DGS trained on the clean views, which the tables measure each method against
(``--no-ceiling``: not run).  Rerunning skips finished cells (see :mod:`benchmark.grid`).

Two runs may share a root: each leaves the cells the other is running to it and lists them
as running elsewhere (not failed).  Exit status: 0 when every cell has a result, 1 when a
cell failed or was left to another run that has not finished it yet, 2 for bad input.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
import warnings

from benchmark.cell import CEILING_METHOD, DEFAULT_PRESET, DEFAULT_SIZE
from benchmark.grid import (AUTO_JOBS, add_run_arguments, build_cells, executor_from_args, options_from_args,
                            resolve_methods, run_grid, say_failed, split_names)
from nimbus.cli_util import check_seed
from nimbus.errors import NimbusError

HELP = "run the benchmark grid (scenes x weathers x methods x presets x seeds), resumable, locally or on Dask"
EXAMPLE = "nimbus-bench run --scenes garden --weathers H,R --methods 3dgs --preset tiny --jobs 2"
DEFAULT_ROOT = "bench_runs"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scenes", default=None,
                   help="comma list of built-in scenes (default: all of them) and folders: a scene folder (COLMAP "
                        "images/ + sparse/0, or transforms.json: degraded with the run's weathers, --depth auto), a "
                        "photo folder (posed by SfM first, cached under ROOT/sfm), or a degraded dataset tree (ours, "
                        "or the NimbusGS authors' layout: one folder per setting such as haze_rain/, one per scene "
                        "inside, scored against its clean/); a folder's scene is named after the folder")
    p.add_argument("--downscale", type=int, default=1,
                   help="scene folders: train and score on images_<N>/ (Mip-NeRF360 layout) instead of images/")
    p.add_argument("--weathers", default="all",
                   help="comma list of settings (H, R, S, H+R, ...) or all, in the default (onerestore: beta and "
                        "airlight drawn per view) protocol; SETTING@physical (e.g. H@physical, all@physical) for "
                        "the physical protocol's family (one medium per scene), tabled apart")
    p.add_argument("--methods", default="default",
                   help="comma list of registered methods; default: nimbus, 3dgs and restore-3dgs (those registered)")
    p.add_argument("--preset", default=DEFAULT_PRESET, help="trainer preset(s), comma list: tiny, fast, paper")
    p.add_argument("--seeds", default="0", help="comma list of training seeds")
    p.add_argument("--size", default=DEFAULT_SIZE, help="built-in scene size: tiny, compact, small, standard (built-in scenes only)")
    p.add_argument("--no-ceiling", action="store_true",
                   help="do not train the clean ceiling (3dgs on each scene's clean training views, one cell per scene "
                        "x preset x seed) that the tables give every method's gap to")
    p.add_argument("--root", default=DEFAULT_ROOT, help="benchmark folder (data, runs, results.jsonl)")
    add_run_arguments(p, jobs_help="local worker processes: auto (default) runs one cell per core with one torch "
                                   "thread each, as many as memory holds; N runs N with cores/N threads each",
                      jobs_default=AUTO_JOBS)
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="trainer config override (repeatable)")


def _seeds(spec: str) -> list[int]:
    try:
        seeds = [int(s) for s in spec.split(",") if s.strip()]
    except ValueError:
        raise NimbusError(f"--seeds expects comma-separated integers, got {spec!r}") from None
    if not seeds:
        raise NimbusError("--seeds is empty; give e.g. --seeds 0,1,2")
    if len(set(seeds)) != len(seeds):
        raise NimbusError(f"--seeds {spec!r} names a seed twice; give each once, e.g. --seeds 0,1,2")
    return [check_seed(s, "each of --seeds") for s in seeds]


def _check_protocol(root: str, cells, protocol: str) -> None:
    """Refuse a run whose cells the root already scored with another evaluation protocol (they would be skipped
    and the table would mix the two)."""
    from benchmark.store import ResultsStore

    ids = {c.cell_id for c in cells}
    other = {rec.get("eval_protocol", "default") for cid, rec in ResultsStore(root).latest().items()
             if cid in ids and rec.get("status") == "ok"} - {protocol}
    if other:
        raise NimbusError(f"{root} already holds cells of this grid scored with --protocol {sorted(other)[0]}; "
                          f"a root keeps one protocol: give --protocol {sorted(other)[0]} or another --root")


def run(args: argparse.Namespace) -> int:
    from benchmark.scene_sources import register_sources, resolve_scenes
    from nimbus.utils.fs import check_output_dir
    from benchmark.store import load_results
    from benchmark.tables.summary import summary_text
    from nimbus.data.builtin import list_scenes
    from nimbus.config_set import parse_set_args
    from weather_synth.settings import parse_family_weather

    items = split_names(args.scenes, "--scenes") if args.scenes else list_scenes()
    if args.downscale < 1:
        raise NimbusError(f"--downscale must be a positive integer (1, 2, 4, 8), got {args.downscale}")
    scenes = resolve_scenes(items, args.size, args.downscale, log=lambda m: print(m, file=sys.stderr))
    weathers = [w.name for w in parse_family_weather(args.weathers)]
    methods, skipped = resolve_methods(args.methods)
    if skipped:
        print(f"note: method(s) {', '.join(skipped)} not registered (yet); skipped", file=sys.stderr)
    if not methods:
        raise NimbusError("no method to run; pass --methods (e.g. --methods 3dgs)")
    presets = split_names(args.preset, "--preset")
    seeds = _seeds(args.seeds)
    executor = executor_from_args(args)
    options = options_from_args(args)
    cells = build_cells(scenes, weathers, methods, presets, seeds, args.size, parse_set_args(args.set),
                        ceiling=not args.no_ceiling)
    ceilings = sum(c.is_ceiling for c in cells)
    check_output_dir(Path(args.root), overwrite=True, flag="--root")  # before sources/ is written into it
    _check_protocol(args.root, cells, options.eval_protocol)
    register_sources(args.root, scenes)
    n_weathers = len({c.weather for c in cells if not c.is_ceiling})
    print(f"{len(cells)} cell(s): {len(scenes)} scene(s) x {n_weathers} weather(s) x {len(methods)} method(s) "
          f"x {len(presets)} preset(s) x {len(seeds)} seed(s)"
          + (f" + {ceilings} clean-ceiling cell(s) ({CEILING_METHOD} on the clean views)" if ceilings else "")
          + f" -> {args.root}", file=sys.stderr)
    try:
        outcome = run_grid(cells, args.root, executor, options, rerun=args.rerun, progress=not args.quiet)
    except KeyboardInterrupt:
        print(f"error: interrupted; run the same command again to continue (the finished cells are kept in "
              f"{args.root}; a cell cut short goes on from its checkpoint where that is exact, else starts again)",
              file=sys.stderr)
        return 130
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        df = load_results(args.root)
    # A cell another run is working on is not this run's to report: an old error record of it
    # would count as a failure here while it may well be finishing there.
    ids = {c.cell_id for c in cells} - set(outcome.running_elsewhere)
    df = df[df["cell_id"].isin(ids)]
    print(summary_text(df, methods), end="")
    say_failed(outcome, args.root)
    if outcome.running_elsewhere:
        print(f"{len(outcome.running_elsewhere)} cell(s) not in this table: another run on {args.root} is running "
              "them (running elsewhere, not failed); rerun the same command after it ends to see them here",
              file=sys.stderr)
    return 1 if outcome.failed or outcome.running_elsewhere else 0
