"""A posed scene with its sparse points against the same scene without them (issue 36: points for posed captures).

Usage::

    python -m tools.speed.posed_init [--scenes garden,street] [--size small] [--preset fast]
                                     [--inits scene,triangulated,densified,random] [--densify N]
                                     [--work DIR] [--json OUT] [--seed 0]

For each built-in scene it writes the scene as transforms.json twice, with its sparse points
(``sparse_pc.ply``) and without, and trains 3DGS (``--preset``) on

* ``scene``: the exported points (the built-in scenes' points, unprojected from exact depth maps);
* ``triangulated``: the points-less export, so ``nimbus-train`` triangulates its training views with the
  poses fixed (:mod:`nimbus.data.triangulate`; below 500 points it falls back to random points, and the
  table says so), with ``--set init_densify=0``;
* ``densified``: the same with ``--set init_densify=N`` (``--densify N``, default the trainer's default):
  the triangulated points and N pixels of the training views at the depth of nearby points or on the
  backdrop (:mod:`nimbus.data.densify`);
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

INITS = ("scene", "triangulated", "densified", "random")


def _export(name: str, size: str, seed: int, work: Path) -> tuple[Path, Path]:
    """``WORK/NAME/with`` and ``WORK/NAME/without``: the built-in scene as transforms.json, with and without points."""
    from nimbus.data.builtin import render_builtin
    from nimbus.data.io import write_scene

    with_dir, without_dir = work / name / "with", work / name / "without"
    if not (with_dir / "transforms.json").is_file() or not (without_dir / "transforms.json").is_file():
        scene = render_builtin(name, size, seed)
        write_scene(scene, with_dir, format="transforms", overwrite=True)
        bare = dataclasses.replace(scene, points=np.zeros((0, 3)), colors=np.zeros((0, 3), np.uint8))
        write_scene(bare, without_dir, format="transforms", overwrite=True)
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
        print(f"{name} ({args.size}, {args.preset}):", flush=True)
        with_dir, without_dir = _export(name, args.size, args.seed, args.work)
        runs = {"scene": (with_dir, []), "triangulated": (without_dir, ["--set", "init_densify=0"]),
                "densified": (without_dir, ["--set", f"init_densify={args.densify}"]),
                "random": (without_dir, ["--set", "init_triangulate=false"])}
        for init in inits:
            scene, extra = runs[init]
            tag = f"densified{args.densify}" if init == "densified" else init
            out = args.work / name / f"run-{tag}-{args.preset}-s{args.seed}"
            rows.append({"scene": name, "run": init, **_train(scene, out, args, extra)})
    print(f"\n{'scene':<10} {'run':<13} {'init':<13} {'points':>7} {'PSNR':>7} {'SSIM':>7} {'vs scene':>9} {'time':>7}")
    for r in rows:
        ref = next((q["psnr"] for q in rows if q["scene"] == r["scene"] and q["run"] == "scene"), None)
        delta = f"{r['psnr'] - ref:+.2f}" if ref is not None else "-"
        init = r["init"] + (f" ({r['triangulated']} tri.)" if r["init"] != "triangulated" and r["triangulated"] else "")
        print(f"{r['scene']:<10} {r['run']:<13} {init:<13} {r['points']:>7} {r['psnr']:>7.2f} {r['ssim']:>7.4f} "
              f"{delta:>9} {r['train_time_s']:>6.0f}s")
    if args.json:
        args.json.write_text(json.dumps({"size": args.size, "preset": args.preset, "seed": args.seed, "rows": rows},
                                        indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
