"""``nimbus-bench export``: a trained run's Gaussians in a format other viewers open (:mod:`nimbus.train.splat`).

The run folder is only read: the file goes where ``--out`` says, never into the run unless asked.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from nimbus.errors import NimbusError

FORMATS = ("splat",)
HELP = "export a run's Gaussians (its point_cloud.ply) for web viewers: .splat (antimatter15/splat layout)"
EXAMPLE = "nimbus-bench export bench_runs/runs/garden-tiny_H_nimbus_tiny_s0 --format splat --out garden_H.splat"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run", metavar="RUN", help="a run folder (holding point_cloud.ply) or a 3DGS .ply file")
    p.add_argument("--format", choices=FORMATS, default="splat",
                   help="splat: 32 bytes per Gaussian (position, linear scale, RGBA, rotation), DC colour only")
    p.add_argument("--out", required=True, metavar="FILE", help="the file to write")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out file")


def run(args: argparse.Namespace) -> int:
    from nimbus.train.ply import read_gaussian_ply
    from nimbus.train.splat import write_splat

    src = Path(args.run)
    ply = src / "point_cloud.ply" if src.is_dir() else src
    if not ply.is_file():
        raise NimbusError(f"{ply} does not exist; give a finished run folder (nimbus-train writes point_cloud.ply "
                          "at the end) or a .ply file")
    out = Path(args.out)
    if out.is_dir():
        raise NimbusError(f"--out {out} is a folder; give a file name such as scene.splat")
    if out.exists() and not args.overwrite:
        raise NimbusError(f"--out {out} exists; pass --overwrite to replace it or choose another --out")
    if out.resolve() == ply.resolve():
        raise NimbusError(f"--out {out} is the input {ply}; choose another file name")
    g = read_gaussian_ply(ply)
    path = write_splat(out, g["means"], g["sh"], g["opacity_logits"], g["log_scales"], g["quats_wxyz"])
    dropped = " (higher SH bands dropped: .splat holds the DC colour only)" if g["sh"].shape[1] > 1 else ""
    print(f"{path}: {len(g['means'])} Gaussians, {path.stat().st_size} bytes{dropped}")
    return 0
