"""``nimbus-synth sfm``: recover cameras from a folder of photos and write a COLMAP scene; or, with
``--known-poses SCENE``, triangulate sparse points for a posed scene that has none (poses held fixed)."""

from __future__ import annotations

import argparse
import sys

from nimbus.cli_util import MAX_SEED, seed_arg
from nimbus.data.sfm import CAMERA_MODELS, MATCHERS, SfmConfig, list_photos, run_sfm

HELP = ("recover cameras and sparse points from photos (COLMAP SfM on the CPU) and write a scene folder; with "
        "--known-poses SCENE, triangulate points for a posed scene that has none (transforms.json, empty points3D)")
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
    parser.add_argument("photos", metavar="PHOTOS_DIR", nargs="?",
                        help="folder of photos (searched recursively; only read)")
    parser.add_argument("--out", metavar="SCENE_DIR",
                        help="scene folder to create (with --known-poses: optional, the scene with the points, "
                             "as a COLMAP scene)")
    parser.add_argument("--known-poses", metavar="SCENE",
                        help="instead of SfM: triangulate the training views of this posed scene (COLMAP or "
                             "transforms.json; only read) with its poses and intrinsics fixed, into the user cache "
                             "($NIMBUS_CACHE/triangulated) that nimbus-train reads for a scene without points")
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
    from nimbus.errors import NimbusError
    from nimbus.utils.fs import check_output_dir

    if args.known_poses is not None:
        if args.photos is not None:
            raise NimbusError(f"give either PHOTOS_DIR (SfM) or --known-poses SCENE (triangulation), not both "
                              f"({args.photos!r} and {args.known_poses!r})")
        return _run_known_poses(args)
    if args.photos is None or args.out is None:
        raise NimbusError("give PHOTOS_DIR and --out SCENE_DIR (or --known-poses SCENE); see nimbus-synth sfm --help")

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


#: Options of the photo mode that mean nothing with --known-poses (the cameras are known).
_SFM_ONLY = (("matcher", "--matcher"), ("camera_model", "--camera-model"), ("single_camera", "--single-camera"),
             ("focal", "--focal"), ("fov", "--fov"), ("camera_params", "--camera-params"),
             ("fix_intrinsics", "--fix-intrinsics"), ("no_exif", "--no-exif"))


def _run_known_poses(args: argparse.Namespace) -> int:
    """Triangulate the scene's training views into the cache (and write the scene with them to --out)."""
    from nimbus.data.io import load_scene, write_scene
    from nimbus.data.triangulate import (MIN_TRIANGULATED_POINTS, TriangulationConfig, triangulate_posed,
                                         triangulation_skip_reason)
    from nimbus.errors import NimbusError
    from nimbus.utils.fs import check_output_dir

    default = SfmConfig()
    given = [flag for name, flag in _SFM_ONLY if getattr(args, name) not in (None, False, getattr(default, name, None))]
    if given:
        raise NimbusError(f"{', '.join(given)} describe(s) unknown cameras; --known-poses keeps the scene's cameras, "
                          "so drop them")
    if args.out is not None:
        check_output_dir(args.out, args.overwrite, inputs=[args.known_poses])
    scene = load_scene(args.known_poses)
    views = scene.train_views or list(scene.views)
    if len(scene.points):
        print(f"note: {args.known_poses} already has {len(scene.points)} sparse points (nimbus-train uses them); "
              "triangulating anyway", file=sys.stderr)
    why = triangulation_skip_reason(views)
    if why is not None:
        raise NimbusError(f"{args.known_poses}: {why}")
    config = TriangulationConfig(max_image_size=args.max_image_size, num_threads=args.threads, seed=args.seed)
    tri = triangulate_posed(views, config, log=lambda msg: print(f"sfm: {msg}", file=sys.stderr, flush=True))
    info = tri.info
    done = "reused the cached triangulation" if info["reused"] else "cached"
    print(f"{done} {info['cache']} (the scene folder is not written)", file=sys.stderr)
    stats = (f"{info['verified_pairs']} of {info['pairs']} view pairs verified" +
             (f", mean reprojection error {info['mean_reprojection_error_px']:.2f} px, mean track length "
              f"{info['mean_track_length']:.2f} views" if len(tri.points) else ""))
    print(f"triangulated {len(tri.points)} points from {len(views)} posed training views with the poses fixed "
          f"({stats})")
    if len(tri.points) < MIN_TRIANGULATED_POINTS:
        print(f"WARNING: fewer than {MIN_TRIANGULATED_POINTS} points: nimbus-train will start from random points "
              "about the cameras' focus instead; more overlap between views, or larger images, give more")
    if args.out is not None:
        import dataclasses

        write_scene(dataclasses.replace(scene, points=tri.points, colors=tri.colors), args.out,
                    overwrite=args.overwrite)
        print(f"wrote {args.out} (COLMAP, with the triangulated points)")
    return 0
