"""``nimbus-bench tradeoff``: the speed / accuracy trade-off sweep (:mod:`benchmark.tradeoff`)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Sequence

from benchmark.cell import DEFAULT_PRESET, DEFAULT_SIZE, Cell
from benchmark.grid import add_run_arguments
from benchmark.tradeoff import (DEFAULT_METHOD, DEFAULT_SCENE, DEFAULT_WEATHER, KNOBS, base_cell, build_sweep,
                                parse_knobs, sweep_cells, to_markdown, tradeoff_rows, write_tradeoff)

HELP = ("sweep the knobs that cost time (iterations, image scale, K, grid, SH degree, components): "
        "table + Pareto plot")
EXAMPLE = "nimbus-bench tradeoff --knob iterations=150,300,600 --knob ray_samples --root tradeoff_runs"
DEFAULT_ROOT = "tradeoff_runs"
OUT_SUBDIR = "tradeoff"


def add_arguments(p: argparse.ArgumentParser) -> None:
    knob_help = "; ".join(f"{k}: {s.doc}" for k, s in KNOBS.items())
    p.add_argument("--knob", action="append", metavar="NAME[=V1,V2,...]",
                   help=f"a knob to sweep, with its values or its defaults (repeatable; default: all of these "
                        f"the method has). Any config setting can be a knob with explicit values. {knob_help}")
    p.add_argument("--scene", default=DEFAULT_SCENE, help="built-in scene of the base cell")
    p.add_argument("--weather", default=DEFAULT_WEATHER, help="weather setting of the base cell (H, R, S, H+R, ...)")
    p.add_argument("--method", default=DEFAULT_METHOD, help="method of the base cell")
    p.add_argument("--preset", default=DEFAULT_PRESET, help="trainer preset of the base cell: tiny, fast, paper")
    p.add_argument("--size", default=DEFAULT_SIZE, help="built-in scene size: tiny, compact, small, standard")
    p.add_argument("--seed", type=int, default=0, help="training seed")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="base config override (repeatable)")
    p.add_argument("--root", default=DEFAULT_ROOT,
                   help="benchmark folder of the sweep's cells (its own: `nimbus-bench tables` would average "
                        "the variations of a shared root as if they were seeds)")
    p.add_argument("--out", default=None, help=f"folder for tradeoff.csv/.md/.png (default: ROOT/{OUT_SUBDIR})")
    add_run_arguments(p, jobs_help="local worker processes (cells side by side share the cores: their times grow)")
    p.add_argument("--dry-run", action="store_true", help="print the sweep's cells and exit")


def run(args: argparse.Namespace) -> int:
    from benchmark.grid import executor_from_args, options_from_args, run_grid, say_failed
    from benchmark.store import ResultsStore
    from nimbus.config_set import parse_set_args
    from nimbus.utils.fs import check_output_dir

    knobs = parse_knobs(args.knob)
    base = base_cell(args.scene, args.weather, args.method, args.preset, args.seed, args.size,
                     parse_set_args(args.set))
    points = build_sweep(base, knobs or None)
    cells = sweep_cells(points)
    out = Path(args.out) if args.out else Path(args.root) / OUT_SUBDIR
    check_output_dir(out, overwrite=True)  # before the sweep trains anything (its files are rewritten in place)
    n_knobs = len(dict.fromkeys(p.knob for p in points))
    print(f"{len(cells)} cell(s) for {len(points)} (knob, value) point(s) of {n_knobs} knob(s) -> {args.root}",
          file=sys.stderr)
    if args.dry_run:
        for p in points:
            print(f"{p.knob}={p.value}{' (base)' if p.base else ''}\t{p.cell.cell_id}\t"
                  f"{','.join(f'{k}={v}' for k, v in p.cell.overrides) or '-'}")
        return 0
    outcome = run_grid(cells, args.root, executor_from_args(args), options_from_args(args), rerun=args.rerun,
                       progress=not args.quiet)
    records = ResultsStore(args.root).latest()
    rows = tradeoff_rows(points, records)
    if not any(r["status"] == "ok" for r in rows):
        print(f"error: no cell of the sweep finished; see the errors in {args.root}/results.jsonl and rerun",
              file=sys.stderr)
        return 1
    title = (f"Speed / accuracy trade-off: {base.method} ({base.preset}) on {base.data_name}, {base.weather}, "
             f"seed {base.seed}")
    written = write_tradeoff(rows, out, title, _header(base, cells, records))
    print(to_markdown(rows))
    for path in written:
        print(path)
    say_failed(outcome, args.root)
    return 1 if outcome.failed else 0


def _header(base: Cell, cells: Sequence[Cell], records: dict[str, dict]) -> list[str]:
    recs = [records[c.cell_id] for c in cells if records.get(c.cell_id, {}).get("status") == "ok"]

    def distinct(key: str) -> str:
        return ", ".join(sorted({str(r.get(key)) for r in recs})) or "n/a"

    overrides = ", ".join(f"{k}={v}" for k, v in base.overrides) or "none"
    lines = [f"Base cell `{base.cell_id}` (base overrides: {overrides}); one knob varied at a time; "
             f"{len(cells)} distinct cell(s), the base listed under every knob.",
             f"PSNR / SSIM / LPIPS against the clean test views (SSIM protocol: {distinct('ssim_protocol')}; "
             f"LPIPS: {distinct('lpips_net')}); device: {distinct('device')}.",
             "train s: the training loop's wall-clock; cell s: the whole cell (training, rendering, scoring); "
             "peak MB: the CUDA allocator's peak on a GPU, the worker process's peak resident memory on a CPU.",
             "A ● marks a cell on that panel's Pareto front: no other cell is at least as cheap and at least as "
             "accurate, one of the two strictly (values compared as printed here)."]
    if len({r.get("lpips_net") for r in recs}) > 1 or len({r.get("ssim_protocol") for r in recs}) > 1:
        lines.append("**Warning:** the cells were scored with different protocols (finished cells are reused); "
                     "rerun with --rerun to score them alike.")
    return lines
