"""``nimbus-synth preview``: a contact sheet (clean + every setting x a few views) of a degraded dataset."""

from __future__ import annotations

import argparse
from pathlib import Path

from nimbus.errors import NimbusError

HELP = ("draw a contact sheet (rows: clean and each weather setting, columns: views) of a degraded dataset; "
        "haze rows and the printout show the depth source and its multi-view consistency")
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
    from nimbus.utils.fs import check_output_dir, refuse_overlap
    from weather_synth.contact_sheet import check_sheet_options, dataset_contact_sheet, depth_lines

    out = Path(args.out)
    if out.suffix.lower() != ".png":
        raise NimbusError(f"--out must be a .png file, got {out}")
    # A sheet written into the dataset would change what it shows (and what trainers read).
    refuse_overlap(out, [args.dataset])
    if out.is_dir():
        raise NimbusError(f"--out {out} is a folder; choose another --out, the .png file to write "
                          f"(e.g. {out / 'sheet.png'})")
    if out.exists() and not args.overwrite:
        raise NimbusError(f"{out} exists; pass --overwrite to replace it or choose another --out")
    # Its folder must be a writable directory (created if missing; nothing is written yet).
    check_output_dir(out.parent, overwrite=True, flag="--out's folder")
    check_sheet_options(args.views, args.tile_width)
    write_image(out, dataset_contact_sheet(args.dataset, args.views, args.tile_width, args.view))
    for line in depth_lines(args.dataset):
        print(line)
    print(f"wrote {out}")
    return 0
