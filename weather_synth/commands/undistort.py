"""``nimbus-synth undistort``: write a scene with distorted cameras as a pinhole COLMAP scene."""

from __future__ import annotations

import argparse
import shutil

HELP = "write a scene whose cameras have lens distortion (COLMAP or transforms.json) as a pinhole COLMAP scene"
EXAMPLE = "nimbus-synth undistort phone_capture/ --out scenes/phone_pinhole"

# Private undistortion cache inside the output's temporary folder: the command writes nothing outside --out.
_WORK_CACHE = ".undistort-cache"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scene", metavar="SCENE", help="scene folder (COLMAP images/ + sparse/0, or transforms.json; "
                                                       "only read)")
    parser.add_argument("--out", required=True, metavar="DIR", help="scene folder to create (COLMAP, PINHOLE cameras)")
    parser.add_argument("--overwrite", action="store_true", help="replace a non-empty DIR")
    parser.add_argument("--downscale", type=int, default=1, metavar="D",
                        help="undistort the images_D copies (Mip-NeRF360 / nerfstudio layout) instead of images/")
    parser.add_argument("--text", action="store_true", help="write the COLMAP model as .txt instead of .bin")


def run(args: argparse.Namespace) -> int:
    from nimbus.data.io import load_scene, write_scene_into
    from nimbus.utils.fs import atomic_dir, check_output_dir

    # Before anything is read or written: DIR must be usable and apart from the scene (--overwrite
    # would otherwise replace the input).
    check_output_dir(args.out, args.overwrite, inputs=[args.scene])
    with atomic_dir(args.out, overwrite=args.overwrite) as tmp:
        scene = load_scene(args.scene, downscale=args.downscale, cache_dir=tmp / _WORK_CACHE)
        write_scene_into(scene, tmp, text=args.text)
        shutil.rmtree(tmp / _WORK_CACHE, ignore_errors=True)
    info = scene.metadata.get("undistorted")
    sizes = sorted({f"{v.camera.width}x{v.camera.height}" for v in scene.views})
    if info is None:
        print(f"{args.scene} has no lens distortion: copied {len(scene)} views as they are")
    else:
        print(f"undistorted {info['views']} of {len(scene)} views ({'; '.join(info['lenses'])}) to pinhole "
              f"{', '.join(sizes)}")
    print(f"wrote {args.out}")
    return 0
