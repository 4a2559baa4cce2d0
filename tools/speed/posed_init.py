"""A posed scene with its sparse points against the same scene without them (issue 36: points for posed captures).

Usage::

    python -m tools.speed.posed_init [--scenes garden,street] [--size small] [--preset fast]
                                     [--inits scene,triangulated,densified,random] [--densify N]
                                     [--lens none|opencv] [--work DIR] [--json OUT] [--seed 0]

For each built-in scene it writes the scene as transforms.json twice, with its sparse points
(``sparse_pc.ply``) and without, and trains 3DGS (``--preset``) on

* ``scene``: the exported points (the built-in scenes' points, unprojected from exact depth maps);
* ``triangulated``: the points-less export, so ``nimbus-train`` triangulates its training views with the
  poses fixed (:mod:`nimbus.data.triangulate`; below 500 points it falls back to random points, and the
  table says so), with ``--set init_densify=0``;
* ``densified``: the same with ``--set init_densify=N`` (``--densify N``, default the trainer's default):
  the triangulated points and N pixels of the training views at the depth of nearby points or on the
  backdrop (:mod:`nimbus.data.densify`), each pixel's depth measured by a plane sweep first where it can be
  (:mod:`nimbus.data.sweep`);
* ``densified-nosweep``: the same without the plane sweep (``--set init_sweep=false``);
* ``random``: the points-less export with ``--set init_triangulate=false``: random points about the
  cameras' focus, or in their frusta for a forward-facing capture (:mod:`nimbus.data.camera_focus`).

and prints per run the initialisation ``nimbus-train`` recorded (``init_points`` in results.json), its
point count, test-view PSNR / SSIM, the PSNR against the ``scene`` run of the same scene, and the training
time.  The triangulation cache is ``WORK/cache`` (``NIMBUS_CACHE``), so a rerun reuses it and the user's
cache is untouched.  Runs whose results exist are not rerun (delete WORK to start over).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from nimbus.train.config import TrainConfig

INITS = ("scene", "triangulated", "densified", "densified-nosweep", "random")


# A phone-like barrel distortion (OPENCV: k1, k2, p1, p2) for --lens opencv.
OPENCV_LENS = {"k1": -0.12, "k2": 0.03, "p1": 0.001, "p2": -0.0005}


def _through_lens(name: str, size: str, seed: int, scene):
    """The scene's views as photographed through :data:`OPENCV_LENS`: each image is a pinhole render of the built-in
    world, wide enough to cover the lens's field, resampled at the undistorted position of every pixel centre.
    Depth and sky maps are dropped (they would be the pinhole's)."""
    import cv2

    from nimbus.data.builtin import get_scene, get_size
    from nimbus.data.builtin.raycast import render_view
    from nimbus.data.camera import Camera
    from nimbus.data.undistort import Lens, undistort_points

    lens = Lens("OPENCV", False, tuple(OPENCV_LENS[k] for k in ("k1", "k2", "p1", "p2")))
    world, settings = get_scene(name).config.world(seed), get_size(size).render_settings
    views = []
    for v in scene.views:
        cam = v.camera
        u, w = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
        xy = undistort_points(np.stack([u.ravel(), w.ravel()], 1), cam, lens)
        px = xy[:, 0] * cam.fx + cam.cx
        py = xy[:, 1] * cam.fy + cam.cy
        pad_x = int(np.ceil(max(0.0, -px.min(), px.max() - cam.width))) + 2
        pad_y = int(np.ceil(max(0.0, -py.min(), py.max() - cam.height))) + 2
        wide = Camera(cam.width + 2 * pad_x, cam.height + 2 * pad_y, cam.fx, cam.fy, cam.cx + pad_x, cam.cy + pad_y,
                      cam.R, cam.t)
        pinhole = render_view(world, wide, settings).image.astype(np.float32)
        mx = (px + pad_x - 0.5).reshape(cam.height, cam.width).astype(np.float32)
        my = (py + pad_y - 0.5).reshape(cam.height, cam.width).astype(np.float32)
        image = cv2.remap(pinhole, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        views.append(dataclasses.replace(v, image=np.clip(image, 0, 1), depth=None, depth_path=None, sky=None,
                                         sky_path=None))
    return dataclasses.replace(scene, views=tuple(views))


def _export(name: str, size: str, seed: int, work: Path, lens: str = "none") -> tuple[Path, Path]:
    """``WORK/NAME[-opencv]/with`` and ``.../without``: the built-in scene as transforms.json, with and without
    points (``lens="opencv"``: the photos taken through :data:`OPENCV_LENS`, declared in the file)."""
    from nimbus.data.builtin import render_builtin
    from nimbus.data.io import write_scene

    folder = work / (name if lens == "none" else f"{name}-{lens}")
    with_dir, without_dir = folder / "with", folder / "without"
    if not (with_dir / "transforms.json").is_file() or not (without_dir / "transforms.json").is_file():
        scene = render_builtin(name, size, seed)
        if lens == "opencv":
            scene = _through_lens(name, size, seed, scene)
        bare = dataclasses.replace(scene, points=np.zeros((0, 3)), colors=np.zeros((0, 3), np.uint8))
        for sc, out in ((scene, with_dir), (bare, without_dir)):
            write_scene(sc, out, format="transforms", overwrite=True)
            if lens == "opencv":
                meta = json.loads((out / "transforms.json").read_text())
                meta.update(camera_model="OPENCV", **OPENCV_LENS)
                (out / "transforms.json").write_text(json.dumps(meta))
    return with_dir, without_dir


def _train(scene: Path, out: Path, args, extra: list[str]) -> dict:
    if not (out / "results.json").is_file():
        argv = [sys.executable, "-m", "nimbus.cli.train", str(scene), "--method", "3dgs", "--preset", args.preset,
                "--out", str(out), "--seed", str(args.seed), "--quiet", "--overwrite", *extra]
        env = dict(os.environ, NIMBUS_CACHE=str(args.work / "cache"))
        t0 = time.perf_counter()
        with open(out.parent / f"{out.name}.log", "w") as f:
            done = subprocess.run(argv, stdout=f, stderr=subprocess.STDOUT, env=env)
        if done.returncode != 0:
            raise RuntimeError(f"{' '.join(argv)} exited {done.returncode}; see {out.parent / f'{out.name}.log'}")
        print(f"  {out.name}: {time.perf_counter() - t0:.0f} s", flush=True)
    res = json.loads((out / "results.json").read_text())
    init = res["init_points"]
    return {"psnr": res["psnr"], "ssim": res["ssim"], "train_time_s": res["train_time_s"],
            "init": init["source"], "points": init["points"],
            "triangulated": (init.get("triangulation") or {}).get("points")}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", default="garden,street")
    p.add_argument("--size", default="small")
    p.add_argument("--preset", default="fast")
    p.add_argument("--inits", default=",".join(INITS), help=f"comma list of {', '.join(INITS)}")
    p.add_argument("--densify", type=int, default=TrainConfig.init_densify,
                   help="pixels added to the triangulated points by the densified runs (init_densify)")
    p.add_argument("--lens", choices=("none", "opencv"), default="none",
                   help="opencv: photograph the scenes through a phone-like OPENCV lens (k1=-0.12, k2=0.03, "
                        "p1=0.001, p2=-0.0005), declared in transforms.json, so nimbus-train undistorts them on load")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--work", type=Path, default=Path("runs/posed_init"))
    p.add_argument("--json", type=Path)
    args = p.parse_args(argv)
    inits = [s.strip() for s in args.inits.split(",") if s.strip()]
    unknown = set(inits) - set(INITS)
    if unknown:
        p.error(f"unknown --inits {sorted(unknown)}; choose from {', '.join(INITS)}")
    rows = []
    for name in [s.strip() for s in args.scenes.split(",") if s.strip()]:
        print(f"{name} ({args.size}, {args.preset}{', OPENCV lens' if args.lens == 'opencv' else ''}):", flush=True)
        with_dir, without_dir = _export(name, args.size, args.seed, args.work, args.lens)
        runs = {"scene": (with_dir, []), "triangulated": (without_dir, ["--set", "init_densify=0"]),
                "densified": (without_dir, ["--set", f"init_densify={args.densify}"]),
                "densified-nosweep": (without_dir, ["--set", f"init_densify={args.densify}", "--set", "init_sweep=false"]),
                "random": (without_dir, ["--set", "init_triangulate=false"])}
        for init in inits:
            scene, extra = runs[init]
            tag = init.replace("densified", f"densified{args.densify}") if init.startswith("densified") else init
            out = with_dir.parent / f"run-{tag}-{args.preset}-s{args.seed}"
            rows.append({"scene": name, "run": init, **_train(scene, out, args, extra)})
    print(f"\n{'scene':<10} {'run':<18} {'init':<13} {'points':>7} {'PSNR':>7} {'SSIM':>7} {'vs scene':>9} {'time':>7}")
    for r in rows:
        ref = next((q["psnr"] for q in rows if q["scene"] == r["scene"] and q["run"] == "scene"), None)
        delta = f"{r['psnr'] - ref:+.2f}" if ref is not None else "-"
        init = r["init"] + (f" ({r['triangulated']} tri.)" if r["init"] != "triangulated" and r["triangulated"] else "")
        print(f"{r['scene']:<10} {r['run']:<18} {init:<13} {r['points']:>7} {r['psnr']:>7.2f} {r['ssim']:>7.4f} "
              f"{delta:>9} {r['train_time_s']:>6.0f}s")
    if args.json:
        args.json.write_text(json.dumps({"size": args.size, "preset": args.preset, "seed": args.seed, "lens": args.lens,
                                         "rows": rows},
                                        indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
