"""``nimbus-synth scene``: render a built-in procedural scene to a COLMAP scene folder."""

from __future__ import annotations

import argparse
import json
import time

from nimbus.cli_util import MAX_SEED, seed_arg
from nimbus.data.builtin import SCENES, SIZES, get_scene, get_size, list_scenes, write_builtin
from nimbus.errors import NimbusError

HELP = "render a built-in outdoor scene (exact depth and sky mask) as a COLMAP scene folder"
EXAMPLE = "nimbus-synth scene garden --size small --out scenes/garden"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("name", nargs="?", metavar="NAME", help=f"scene to render: {', '.join(list_scenes())}")
    parser.add_argument("--size", default="small", choices=list(SIZES),
                        help="image size and view count (see --list)")
    parser.add_argument("--out", metavar="DIR", help="scene folder to create (must be empty unless --overwrite)")
    parser.add_argument("--seed", type=seed_arg, default=0,
                        help=f"0 to {MAX_SEED}; shifts textures and jitters objects and cameras slightly")
    parser.add_argument("--overwrite", action="store_true", help="replace a non-empty --out")
    parser.add_argument("--list", action="store_true", help="list the scenes and sizes, then exit")


def format_listing() -> str:
    """The text of ``--list``: scenes with descriptions, then sizes."""
    lines = ["scenes:"]
    lines += [f"  {name:<10} {SCENES[name].description}" for name in list_scenes()]
    lines.append("sizes:")
    for name, p in SIZES.items():
        lines.append(f"  {name:<10} {p.width}x{p.height} px, {p.n_views} views, "
                     f"{p.samples_per_axis}x{p.samples_per_axis} samples per pixel")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    if args.list:
        print(format_listing())
        return 0
    if not args.name:
        raise NimbusError(f"name a scene to render ({', '.join(list_scenes())}) or pass --list")
    get_scene(args.name)
    preset = get_size(args.size)
    if not args.out:
        raise NimbusError("pass --out DIR, the scene folder to create")
    start = time.perf_counter()
    out = write_builtin(args.name, args.out, size=args.size, seed=args.seed, overwrite=args.overwrite, progress=True)
    seconds = time.perf_counter() - start
    info = json.loads((out / "manifest.json").read_text())
    lo, hi = info["depth_range"]
    print(f"{args.name} ({args.size}): {info['image_count']} views {preset.width}x{preset.height}, "
          f"depth {lo:.2f}-{hi:.1f} m, {info['sparse_points']} sparse points, seed {args.seed}, "
          f"{seconds:.1f} s -> {out}")
    return 0
