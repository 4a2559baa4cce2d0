"""How SfM calibration and poses degrade with fewer photos: a view-count sweep on a built-in scene.

Usage::

    python -m tools.speed.sfm [--scene garden] [--views 200,80,40,20] [--size 240x180]
                              [--cases self,prior] [--threads 1] [--train [--preset fast]] [--json OUT]

For each view count N, renders N views of the scene's camera rig (the orbit for
``garden``: exact intrinsics and poses), writes the images only, and runs
:func:`nimbus.data.sfm.run_sfm` once per case:

``self``       the defaults: no prior, the focal length is self-calibrated (what a user without EXIF
               gets), one camera shared by the photos (all the same size)
``prior``      ``focal_px`` = the true focal length, refined by bundle adjustment
``fixed``      the true focal length kept fixed (``fix_intrinsics``)
``per-photo``  no prior, a camera per photo (``single_camera=False``, COLMAP's default without EXIF)

and prints, per N and case: registered photos, the focal error (%), the pose error
after a similarity (Umeyama) fit of the camera centres (mean rotation error in degrees,
RMS centre error relative to the rig's extent), the mean reprojection error, the
focal-probe rise and which warnings the calibration report raised.  ``--train`` also
trains 3DGS on every SfM scene and on the exact-pose scene of the same views
(the scene's LLFF test split) and prints the test-view PSNR of both (slow: minutes per
case on a CPU).  ``--json OUT`` writes every row.  A case whose SfM fails is a row with
its error.  The photos are rendered with 2 x 2 supersampling, not timed.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

from nimbus.data.align import pose_error
from nimbus.data.builtin import get_scene
from nimbus.data.builtin.points import PointCloudConfig, sample_points
from nimbus.data.builtin.raycast import RenderSettings, render_view
from nimbus.data.images import write_image
from nimbus.data.scene import Scene, View, llff_test_names
from nimbus.data.sfm import SfmConfig, run_sfm
from nimbus.errors import NimbusError
from nimbus.utils.fs import atomic_write_json

CASES = ("self", "prior", "fixed", "per-photo")


def render_photos(scene: str, n_views: int, width: int, height: int, seed: int, out: Path) -> Scene:
    """Render ``n_views`` of the built-in ``scene``'s rig at ``width`` x ``height``, write ``out/NNN.png``.

    Returns the exact scene (in-memory images, exact cameras, LLFF test split, sparse points
    unprojected from the exact depth) for pose comparison and the exact-pose training run.
    """
    config = get_scene(scene).config
    world = config.world(seed)
    views = []
    for i, cam in enumerate(config.cameras(n_views, width, height, seed)):
        r = render_view(world, cam, RenderSettings(samples_per_axis=2))
        write_image(out / f"{i:03d}.png", r.image)
        views.append(View(f"{i:03d}.png", cam, image=r.image, depth=r.depth, sky=r.sky))
    test = llff_test_names([v.name for v in views])
    train = [v for v in views if v.name not in set(test)]
    points, colors = sample_points([v.camera for v in train], [v.image for v in train], [v.depth for v in train],
                                   [v.sky for v in train], PointCloudConfig(), seed)
    return Scene(tuple(views), frozenset(test), points, colors, None, "builtin", {"scene": scene})


def case_config(case: str, true_focal: float, threads: int, seed: int) -> SfmConfig:
    base = SfmConfig(seed=seed, num_threads=threads)
    return {"self": base, "prior": replace(base, focal_px=true_focal),
            "fixed": replace(base, focal_px=true_focal, fix_intrinsics=True),
            "per-photo": replace(base, single_camera=False)}[case]


def train_psnr(scene: Scene, preset: str, out: Path, seed: int) -> float:
    """Test-view PSNR of 3DGS (``preset``) trained on ``scene``."""
    from nimbus.methods.registry import get_method
    from nimbus.train.runner import Runner

    runner = Runner("3dgs", scene, get_method("3dgs").preset(preset), out, seed=seed, progress=False)
    return float(runner.run()["psnr"])


def run_case(exact: Scene, photos: Path, work: Path, case: str, args) -> dict:
    true_focal = exact.views[0].camera.fx
    row = {"views": len(exact), "case": case}
    t0 = time.perf_counter()
    try:
        result = run_sfm(photos, work / f"sfm_{case}", config=case_config(case, true_focal, args.threads, args.seed))
    except NimbusError as e:
        return {**row, "error": str(e)}
    cal = result.calibration
    # Undistortion crops the photos, so compare focal lengths of the estimated model (before it).
    by_name = {v.name: v.camera for v in exact.views}
    err = pose_error([v.camera for v in result.scene.views], [by_name[v.name] for v in result.scene.views])
    row.update(registered=result.registered, sfm_s=round(time.perf_counter() - t0, 1),
               focal_err_pct=100.0 * (cal.focal_px / true_focal - 1.0), rot_deg=err.rotation_deg,
               center_rel=err.center, reproj_px=cal.reprojection_error_px, track=cal.mean_track_length,
               probe_rise=cal.focal_probe_rise, distortion=cal.to_dict()["distortion"], flags=list(cal.flags))
    if args.train:
        row["psnr_sfm"] = train_psnr(result.scene, args.preset, work / f"train_{case}", args.seed)
    return row


def format_table(rows: list[dict]) -> str:
    head = (f"{'views':>5} {'case':<9} {'reg':>7} {'focal err':>9} {'rot deg':>8} {'centre':>7} {'reproj':>6} "
            f"{'track':>5} {'probe':>6} {'dist':>5}")
    train = any("psnr_sfm" in r for r in rows)
    if train:
        head += f" {'PSNR sfm':>8} {'exact':>6}"
    lines = [head + "  flags", "-" * (len(head) + 7)]
    for r in rows:
        if "error" in r:
            lines.append(f"{r['views']:>5} {r['case']:<9} failed: {r['error'][:90]}")
            continue
        probe = "-" if r["probe_rise"] is None else f"{100 * r['probe_rise']:.0f}%"
        dist = "inf" if r["distortion"] is None else f"{100 * r['distortion']:.1f}%"
        line = (f"{r['views']:>5} {r['case']:<9} {r['registered']:>3}/{r['views']:<3} {r['focal_err_pct']:>+8.1f}% "
                f"{r['rot_deg']:>8.2f} {100 * r['center_rel']:>6.2f}% {r['reproj_px']:>6.2f} {r['track']:>5.2f} "
                f"{probe:>6} {dist:>5}")
        if train:
            line += f" {r.get('psnr_sfm', float('nan')):>8.2f} {r.get('psnr_exact', float('nan')):>6.2f}"
        lines.append(line + "  " + (",".join(r["flags"]) or "-"))
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", default="garden", help="built-in scene whose camera rig is rendered")
    p.add_argument("--views", default="200,80,40,20", help="comma-separated view counts")
    p.add_argument("--size", default="240x180", help="photo size WIDTHxHEIGHT")
    p.add_argument("--cases", default="self,prior", help=f"comma-separated, from {','.join(CASES)}")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=1, help="SfM threads (-1: every core)")
    p.add_argument("--train", action="store_true", help="also train 3DGS on each SfM and exact scene (slow)")
    p.add_argument("--preset", default="fast", help="3DGS preset for --train")
    p.add_argument("--json", metavar="OUT", help="write the rows as JSON")
    p.add_argument("--keep", metavar="DIR", help="keep photos and scenes in DIR (default: a temporary folder)")
    args = p.parse_args(argv)
    views = [int(v) for v in args.views.split(",")]
    cases = args.cases.split(",")
    width, height = (int(v) for v in args.size.lower().split("x"))
    if unknown := set(cases) - set(CASES):
        p.error(f"unknown case(s) {sorted(unknown)}; choose from {CASES}")
    root = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="bench-sfm-"))
    rows = []
    try:
        for n in views:
            work = root / f"n{n}"
            shutil.rmtree(work, ignore_errors=True)
            exact = render_photos(args.scene, n, width, height, args.seed, work / "photos")
            psnr_exact = train_psnr(exact, args.preset, work / "train_exact", args.seed) if args.train else None
            for case in cases:
                row = run_case(exact, work / "photos", work, case, args)
                if psnr_exact is not None:
                    row["psnr_exact"] = psnr_exact
                rows.append(row)
                print(f"[{n} views, {case}] done", file=sys.stderr, flush=True)
    finally:
        if not args.keep:
            shutil.rmtree(root, ignore_errors=True)
    true_focal = get_scene(args.scene).config.cameras(1, width, height, 0)[0].fx
    print(f"{args.scene} {width}x{height}, true focal {true_focal:.1f} px; "
          "focal err vs truth, pose error after a similarity fit (centre: RMS / rig extent), probe: reprojection "
          "rise with the focal 20% off")
    print(format_table(rows))
    if args.json:
        atomic_write_json(args.json, {"scene": args.scene, "size": [width, height], "seed": args.seed, "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
