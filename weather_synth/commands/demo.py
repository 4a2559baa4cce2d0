"""``nimbus-synth demo``: render a built-in scene, degrade it in every setting and draw a contact sheet."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from weather_synth.commands.degrade import add_synth_arguments, config_from_args

HELP = "render a built-in scene, degrade it in all seven settings and write a contact sheet to look at"
EXAMPLE = "nimbus-synth demo --out /tmp/nimbus_demo"
SHEET = "contact_sheet.png"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from nimbus.data.builtin import SIZES, list_scenes

    parser.add_argument("--out", required=True, metavar="DIR",
                        help=f"folder to create: the degraded dataset plus {SHEET}")
    parser.add_argument("--scene", choices=list_scenes(), default="garden", help="built-in scene")
    parser.add_argument("--size", choices=list(SIZES), default="small", help="built-in scene size")
    parser.add_argument("--views", type=int, default=6, help="views (columns) on the contact sheet")
    parser.add_argument("--tile-width", type=int, default=192, help="width of each image on the sheet (pixels)")
    parser.add_argument("--overwrite", action="store_true", help="replace a non-empty DIR")
    add_synth_arguments(parser)


def run(args: argparse.Namespace) -> int:
    from nimbus.data.builtin import render_builtin
    from nimbus.data.images import write_image
    from nimbus.utils.fs import atomic_dir, check_output_dir
    from weather_synth.contact_sheet import check_sheet_options, dataset_contact_sheet
    from weather_synth.dataset import degrade_scene, format_summary
    from weather_synth.settings import parse_weather

    settings = parse_weather(args.weather)
    check_sheet_options(args.views, args.tile_width)
    check_output_dir(args.out, args.overwrite)  # the demo reads no files, so no input to overlap
    scene = render_builtin(args.scene, args.size, seed=args.seed, progress=not args.quiet)
    config = config_from_args(args, scene)
    # The whole folder (dataset and sheet) is built beside DIR and renamed into place, so a failed or killed
    # demo leaves no partial DIR (atomic_dir removes a killed run's temporary folder on the next run).
    with atomic_dir(args.out, args.overwrite) as tmp:
        summaries = degrade_scene(scene, tmp, settings, config, overwrite=True,  # tmp holds only atomic_dir's .owner
                                  progress=not args.quiet, source=f"builtin:{args.scene}:{args.size}")
        write_image(tmp / SHEET, dataset_contact_sheet(tmp, args.views, args.tile_width))
    print(format_summary(summaries))
    print(f"wrote {args.out}; look at {Path(args.out) / SHEET}", file=sys.stdout)
    return 0
