"""``nimbus-synth preview``: a contact sheet (clean + every setting x a few views) of a degraded dataset."""

from __future__ import annotations

import argparse
from pathlib import Path

from nimbus.errors import NimbusError

HELP = "draw a contact sheet (rows: clean and each weather setting, columns: views) of a degraded dataset"
EXAMPLE = "nimbus-synth preview bench/garden --out garden_sheet.png"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", metavar="DATASET", help="a `nimbus-synth degrade` output folder (or one setting folder)")
    parser.add_argument("--out", required=True, metavar="SHEET.png", help="PNG file to write")
    parser.add_argument("--views", type=int, default=6, help="views (columns), spread evenly over the scene")
    parser.add_argument("--view", action="append", default=None, metavar="NAME",
                        help="show this view (repeatable; replaces --views)")
    parser.add_argument("--tile-width", type=int, default=192, help="width of each image on the sheet (pixels)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing SHEET.png")


def run(args: argparse.Namespace) -> int:
    from nimbus.data.images import write_image
    from weather_synth.contact_sheet import dataset_contact_sheet

    out = Path(args.out)
    if out.suffix.lower() != ".png":
        raise NimbusError(f"--out must be a .png file, got {out}")
    if out.exists() and not args.overwrite:
        raise NimbusError(f"{out} exists; pass --overwrite to replace it or choose another --out")
    if args.tile_width < 16:
        raise NimbusError(f"--tile-width must be at least 16 pixels, got {args.tile_width}")
    write_image(out, dataset_contact_sheet(args.dataset, args.views, args.tile_width, args.view))
    print(f"wrote {out}")
    return 0
