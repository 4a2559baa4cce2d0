"""``nimbus-synth sfm``: recover cameras from a folder of photos and write a COLMAP scene."""

from __future__ import annotations

import argparse
import sys

from nimbus.cli_util import MAX_SEED, seed_arg
from nimbus.data.sfm import CAMERA_MODELS, MATCHERS, SfmConfig, list_photos, run_sfm

HELP = "recover cameras and sparse points from photos (COLMAP SfM on the CPU) and write a scene folder"
EXAMPLE = "nimbus-synth sfm my_photos/ --out scenes/garden --fov 65"


def _params_arg(text: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers in COLMAP's order for the camera "
                                         f"model (e.g. 800,400,300,0.01 for SIMPLE_RADIAL f,cx,cy,k), got {text!r}")
    if not values:
        raise argparse.ArgumentTypeError("expected at least one number")
    return values


def add_arguments(parser: argparse.ArgumentParser) -> None:
    default = SfmConfig()
    parser.add_argument("photos", metavar="PHOTOS_DIR", help="folder of photos (searched recursively; only read)")
    parser.add_argument("--out", required=True, metavar="SCENE_DIR", help="scene folder to create")
    parser.add_argument("--overwrite", action="store_true", help="replace a non-empty SCENE_DIR")
    parser.add_argument("--matcher", choices=MATCHERS, default=default.matcher,
                        help="exhaustive: every pair of photos; sequential: neighbours in name order (video)")
    parser.add_argument("--seed", type=seed_arg, default=default.seed,
                        help=f"random seed in [0, {MAX_SEED}] (same seed, same result)")
    parser.add_argument("--max-image-size", type=int, default=default.max_image_size,
                        help="longest side (pixels) photos are reduced to for feature extraction")
    parser.add_argument("--camera-model", choices=CAMERA_MODELS, default=default.camera_model,
                        help="camera model to estimate (auto: SIMPLE_RADIAL, or SIMPLE_PINHOLE for fewer than 8 "
                             "photos); distorted models are undistorted to PINHOLE afterwards")
    sharing = parser.add_mutually_exclusive_group()
    sharing.add_argument("--single-camera", dest="single_camera", action="store_const", const=True, default=None,
                         help="all photos share one camera (the default when they have one size and the same or "
                              "no EXIF focal length)")
    sharing.add_argument("--camera-per-photo", dest="single_camera", action="store_const", const=False,
                         help="fit a camera to each photo (photos from several cameras or zooms)")
    prior = parser.add_mutually_exclusive_group()
    prior.add_argument("--focal", type=float, metavar="PX",
                       help="prior focal length in pixels of the photos (default: EXIF when every photo states it)")
    prior.add_argument("--fov", type=float, metavar="DEG", help="prior horizontal field of view in degrees")
    prior.add_argument("--camera-params", type=_params_arg, metavar="P1,P2,...",
                       help="every parameter of --camera-model in COLMAP's order, in pixels (e.g. SIMPLE_RADIAL: "
                            "f,cx,cy,k)")
    parser.add_argument("--fix-intrinsics", action="store_true",
                        help="keep the prior (focal, distortion) fixed in bundle adjustment instead of refining it")
    parser.add_argument("--no-exif", action="store_true", help="ignore the photos' EXIF focal length")
    parser.add_argument("--threads", type=int, default=default.num_threads,
                        help="CPU threads; 1 gives the same result on every run, -1 uses every core (faster)")


def run(args: argparse.Namespace) -> int:
    from nimbus.utils.fs import check_output_dir

    # The scene is written atomically beside SCENE_DIR; refuse before feature extraction when SCENE_DIR is
    # unusable or overlaps the photos (--overwrite would replace them).
    check_output_dir(args.out, args.overwrite, inputs=[args.photos])
    config = SfmConfig(matcher=args.matcher, seed=args.seed, max_image_size=args.max_image_size,
                       camera_model=args.camera_model, single_camera=args.single_camera,
                       num_threads=args.threads, focal_px=args.focal, fov_deg=args.fov,
                       camera_params=args.camera_params, fix_intrinsics=args.fix_intrinsics,
                       use_exif=not args.no_exif)
    result = run_sfm(args.photos, args.out, overwrite=args.overwrite, config=config,
                     log=lambda msg: print(f"sfm: {msg}", file=sys.stderr, flush=True))
    print(f"registered {result.registered} / {result.total} views")
    unregistered = sorted(set(list_photos(args.photos)) - set(result.scene.names))
    if unregistered:
        print(f"unregistered ({len(unregistered)}): {', '.join(unregistered)}")
    print("\n".join(result.calibration.lines()))
    print(f"wrote {args.out} (the calibration report is in its manifest.json)")
    return 0
