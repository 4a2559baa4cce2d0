"""Haze depth without depth maps: multi-view consistency and accuracy of the depth sources on the built-in scenes.

Each built-in scene is rendered, then its depth maps are dropped (as a real
capture has none; the sky masks stay, so every source puts the sky at infinity
alike) and each source gives every view a depth map:

- ``scene``: the exact maps (the reference; consistency below 1 only at depth edges),
- ``sparse``: the sparse points densified view by view,
- ``recon N``: a 3DGS fit of N iterations to all views, rendered per view (the time is the fit's).

Columns: ``consistency`` (:func:`weather_synth.depth_consistency.depth_consistency`:
share of pixels whose depth agrees within 5 % with the nearest other view's),
``within 5 % of exact`` (share of the exact map's surface pixels whose depth is
within 5 % of it), ``median rel. error`` against the exact map, and seconds.

Run (the table in the README and the issue's closing note)::

    python -m tools.speed.depth --scenes garden,street,tabletop --sizes tiny --iterations 300,600,1000
    python -m tools.speed.depth --scenes garden,street,tabletop --sizes small --iterations 600

Timings depend on the machine and its load (the development machine is shared); the fit runs on
CUDA when torch sees a GPU.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time

import numpy as np
import torch

from benchmark.tables.model import Block, Column, Row, Table
from benchmark.tables.writer import to_markdown
from nimbus.data.builtin import list_scenes, render_builtin
from weather_synth.depth import DepthConfig, DepthSource
from weather_synth.depth_consistency import depth_consistency

SOURCES = ("scene", "sparse", "recon")


def source_row(scene, exact: dict, config: DepthConfig, label: str) -> dict:
    """One table row: the source's depth for every view of ``scene``, scored against ``exact``."""
    start = time.perf_counter()
    src = DepthSource(scene, config, log=None)
    depths = {v.name: src(v)[0] for v in scene.views}
    seconds = time.perf_counter() - start
    views = scene.views
    cons = depth_consistency([v.camera for v in views], lambda i: depths[views[i].name], [v.name for v in views])
    within, rel = [], []
    for v in views:
        e, z = exact[v.name], depths[v.name]
        ok = np.isfinite(e)
        err = np.abs(z[ok].astype(np.float64) - e[ok]) / e[ok]
        within.append(float(np.mean(err <= 0.05)))
        rel.append(err)
    return {"source": label, "consistency": cons["mean"], "within_5pct_of_exact": float(np.mean(within)),
            "median_rel_error": float(np.median(np.concatenate(rel))), "seconds": seconds}


def bench_scene(name: str, size: str, iterations: list[int], sources=SOURCES) -> list[dict]:
    """Rows for one built-in scene and size (module docstring)."""
    scene = render_builtin(name, size)
    exact_src = DepthSource(scene, DepthConfig("scene"), log=None)
    exact = {v.name: exact_src(v)[0] for v in scene.views}
    bare = scene.with_views([dataclasses.replace(v, depth=None, depth_path=None) for v in scene.views])
    rows = []
    if "scene" in sources:
        rows.append(source_row(scene, exact, DepthConfig("scene"), "scene (exact)"))
    if "sparse" in sources:
        rows.append(source_row(bare, exact, DepthConfig("sparse"), "sparse"))
    for it in iterations if "recon" in sources else ():
        rows.append(source_row(bare, exact, DepthConfig("recon", recon_iterations=it, recon_cache="none"),
                               f"recon {it}"))
    for r in rows:
        r.update(scene=name, size=size, views=len(scene.views))
    return rows


#: The table's columns after the scene (the row label).
COLUMNS = (Column("size", "size", "size", align="left"), Column("views", "views", "views"),
           Column("source", "source", "source", align="left"), Column("consistency", "consistency", "consistency", 3),
           Column("within_5pct_of_exact", "within 5 % of exact", "within 5 % of exact", 3),
           Column("median_rel_error", "median rel. error", "median rel. error", 3),
           Column("seconds", "seconds", "seconds", 1))


def format_table(rows: list[dict]) -> str:
    """Markdown table of :func:`bench_scene` rows (through the benchmark's table writer)."""
    table = Table("depth", "depth", "Depth sources", COLUMNS, [""],
                  [Block([Row(r["scene"], {("", c.key): r[c.key] if c.key != "views" else float(r["views"])
                                           for c in COLUMNS}) for r in rows], ranked=False)],
                  lead=("scene",), group_heads=False)
    return to_markdown(table)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", default="garden,street", help=f"comma-separated, of {', '.join(list_scenes())}")
    parser.add_argument("--sizes", default="tiny", help="comma-separated: tiny, compact, small, standard")
    parser.add_argument("--iterations", default="300,600", help="recon fit lengths to compare, comma-separated")
    parser.add_argument("--sources", default=",".join(SOURCES), help="comma-separated, of scene, sparse, recon")
    parser.add_argument("--threads", type=int, default=2, help="torch threads")
    parser.add_argument("--json", default=None, help="also write the rows to this JSON file")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    iterations = [int(x) for x in args.iterations.split(",") if x]
    rows = []
    for size in args.sizes.split(","):
        for name in args.scenes.split(","):
            new = bench_scene(name, size, iterations, args.sources.split(","))
            rows += new
            print("\n".join(format_table(new).splitlines()[4:-2]), file=sys.stderr, flush=True)  # progress: the rows
    print(format_table(rows))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
