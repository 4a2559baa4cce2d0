"""``nimbus-bench score``: score any method's renders against a scene's ground truth (:mod:`benchmark.score`)."""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

from benchmark.score import SPLITS, format_table, score_renders
from nimbus.errors import NimbusError
from nimbus.metrics import LPIPS_NETS, SSIM_PROTOCOLS
from nimbus.utils.fs import atomic_write_json, check_output_dir, refuse_overlap

HELP = "score any method's renders (PSNR / SSIM / LPIPS) against a scene's ground truth, matched by view name"
EXAMPLE = "nimbus-bench score --pred renders/ --gt data/garden_H --ssim 3dgs --lpips vgg --out results.json"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--pred", required=True, metavar="DIR", help="folder of renders named after the views")
    p.add_argument("--gt", required=True, metavar="SCENE",
                   help="scene folder (COLMAP / transforms.json); a degraded setting folder is scored against "
                        "its clean/ images")
    p.add_argument("--gt-dir", metavar="DIR", default=None,
                   help="folder of ground-truth images to use instead of SCENE/clean or the scene's images")
    p.add_argument("--split", choices=SPLITS, default="test", help="which views to score")
    p.add_argument("--ssim", choices=tuple(SSIM_PROTOCOLS), default="3dgs",
                   help="SSIM protocol: 3dgs (paper), skimage, dmpix (nerfbaselines)")
    p.add_argument("--lpips", choices=LPIPS_NETS + ("none",), default="vgg", help="LPIPS network (vgg: paper)")
    p.add_argument("--downscale", type=int, default=1, help="use the scene's images_<d> folder")
    p.add_argument("--device", default=None,
                   help="LPIPS device, e.g. cpu or cuda (unset: cuda when available, else cpu)")
    p.add_argument("--out", metavar="FILE", default=None, help="write the results as JSON")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out file")


def _check_out_file(out: Path, overwrite: bool, inputs: list) -> None:
    """Refuse a results file that cannot be written, or that would land in (or replace) an input."""
    # Nothing is written inside what is scored: a results file in the scene or the renders
    # folder would become one of their files (and --out SCENE/images/x.png would replace one).
    refuse_overlap(out, inputs, "--out")
    check_output_dir(out.parent, overwrite=True, flag="--out")  # under a file, read-only, unreadable
    if out.is_dir():
        raise NimbusError(f"--out {out} is a folder; give a file name such as results.json")
    if out.exists() and not overwrite:
        raise NimbusError(f"--out {out} exists; pass --overwrite to replace it or choose another file")


def run(args: argparse.Namespace) -> int:
    out = Path(args.out) if args.out else None
    if out is not None:  # before any work: a bad --out should not cost a scoring run
        _check_out_file(out, args.overwrite, [args.pred, args.gt, args.gt_dir])
    t0 = time.perf_counter()

    def progress(done: int, total: int) -> None:
        print(f"\rscored {done}/{total} views", end="" if done < total else "\n", file=sys.stderr, flush=True)

    with warnings.catch_warnings():  # a missing LPIPS is reported below, in the table and in the file
        warnings.simplefilter("ignore", UserWarning)
        try:
            result = score_renders(args.pred, args.gt, split=args.split, ssim_protocol=args.ssim,
                                   lpips_net=None if args.lpips == "none" else args.lpips, gt_dir=args.gt_dir,
                                   downscale=args.downscale, device=args.device, progress=progress)
        except PermissionError as e:  # an unreadable --pred / --gt folder or image
            raise NimbusError(f"{e.filename or 'an input'} cannot be read (permission denied); give read access "
                              "to the renders and the scene") from None
    print(format_table(result))
    if result["lpips_missing"]:
        print(f"warning: LPIPS is missing; run `{result['setup_command']}` and score again", file=sys.stderr)
    if out is not None:
        atomic_write_json(out, result)
        print(f"wrote {out}")
    print(f"{result['views']} views in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    return 0
