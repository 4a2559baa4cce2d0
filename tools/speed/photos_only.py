"""Exact poses against SfM poses, end to end through the command-line tools, and weather on a photos-only scene.

Usage::

    python -m tools.speed.photos_only [--scenes garden,street,tabletop] [--size small] [--preset fast]
                                      [--weather-scene tabletop] [--weathers H,R,S] [--methods 3dgs,nimbus]
                                      [--jobs 2] [--device cpu|cuda] [--work DIR] [--json OUT] [--seed 0]

For each built-in scene it runs what a user with photos runs, one subprocess per step:

1. ``nimbus-synth scene NAME --size SIZE --out WORK/NAME/exact`` (exact cameras and depth: the reference);
2. ``nimbus-synth sfm WORK/NAME/exact/images --out WORK/NAME/sfm`` (the photos only);
3. ``nimbus-train`` 3DGS (``--preset``) on both, each scored on its own test views (the LLFF split of the
   same image names).

and prints, per scene: registered photos, the SfM focal error and pose error after a similarity fit
(:func:`nimbus.data.align.pose_error`), the calibration warnings, and the test-view PSNR / SSIM of the
exact-pose and SfM runs side by side.  For ``--weather-scene`` it also degrades the SfM scene
(``nimbus-synth degrade --depth auto``: a photos-only scene has no depth maps) in each of ``--weathers`` and
trains each of ``--methods`` on it, scored against the clean images of the SfM scene; it prints PSNR / SSIM
per setting and method and NimbusGS's margin over 3DGS.

Steps whose output exists are not rerun (delete WORK to start over).  ``--jobs`` trainings run at once, each
with ``cores / jobs`` threads.  Every figure comes from a command and a seed; ``--json`` writes them all.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from nimbus.data import load_scene
from nimbus.data.align import pose_error
from nimbus.utils.cpus import usable_cpus


def _run(argv: list[str], log: Path, threads: int) -> None:
    """Run one CLI step, its output into ``log``; a failure raises with the log's tail."""
    env = dict(os.environ, OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads))
    log.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    with open(log, "w") as f:
        done = subprocess.run(argv, stdout=f, stderr=subprocess.STDOUT, env=env)
    tail = log.read_text()[-800:]
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(argv)} exited {done.returncode}:\n{tail}")
    print(f"  done in {time.perf_counter() - t0:6.1f} s: {' '.join(argv[:3])} ... {argv[-1] if argv else ''}",
          flush=True)


def _train(scene: Path, method: str, out: Path, args, threads: int) -> dict:
    if not (out / "results.json").is_file():
        _run(["nimbus-train", str(scene), "--method", method, "--preset", args.preset, "--out", str(out),
              "--seed", str(args.seed), "--device", args.device, "--quiet", "--overwrite"],
             out.parent / f"{out.name}.log", threads)
    res = json.loads((out / "results.json").read_text())
    return {"psnr": res["psnr"], "ssim": res["ssim"], "train_time_s": res["train_time_s"],
            "eval_reference": res.get("eval_reference"), "components": res.get("components")}


def _sfm_figures(exact_dir: Path, sfm_dir: Path) -> dict:
    exact, sfm = load_scene(exact_dir), load_scene(sfm_dir)
    by_name = {v.name: v.camera for v in exact.views}
    views = [v for v in sfm.views if v.name in by_name]
    err = pose_error([v.camera for v in views], [by_name[v.name] for v in views])
    manifest = json.loads((sfm_dir / "manifest.json").read_text())
    cal = manifest.get("calibration", {})
    true_f = exact.views[0].camera.fx
    focal = cal.get("focal_px")
    return {"registered": len(sfm), "photos": len(exact),
            "focal_err_pct": None if focal is None else 100.0 * (focal / true_f - 1.0),
            "rot_deg": err.rotation_deg, "center_rel": err.center, "flags": cal.get("flags", []),
            "test_views_sfm": len(sfm.test_views), "test_views_exact": len(exact.test_views)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenes", default="garden,street,tabletop")
    p.add_argument("--size", default="small")
    p.add_argument("--preset", default="fast")
    p.add_argument("--weather-scene", default="tabletop", help="scene whose SfM version is degraded ('' : none)")
    p.add_argument("--weathers", default="H,R,S")
    p.add_argument("--methods", default="3dgs,nimbus")
    p.add_argument("--jobs", type=int, default=2, help="trainings at once")
    p.add_argument("--device", default="cpu")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--work", default="photos_only_runs")
    p.add_argument("--json", metavar="OUT")
    args = p.parse_args(argv)
    work = Path(args.work)
    scenes = [s for s in args.scenes.split(",") if s]
    threads = max(1, usable_cpus() // max(1, args.jobs))

    def prepare(name: str) -> str:
        d = work / name
        if not (d / "exact" / "sparse").is_dir():
            _run(["nimbus-synth", "scene", name, "--size", args.size, "--seed", str(args.seed), "--out",
                  str(d / "exact"), "--overwrite"], d / "scene.log", threads)
        if not (d / "sfm" / "sparse").is_dir():
            _run(["nimbus-synth", "sfm", str(d / "exact" / "images"), "--out", str(d / "sfm"), "--seed",
                  str(args.seed), "--threads", str(threads), "--overwrite"], d / "sfm.log", threads)
        if name == args.weather_scene and not (d / "weather" / "index.json").is_file():
            _run(["nimbus-synth", "degrade", str(d / "sfm"), "--out", str(d / "weather"), "--weather",
                  args.weathers, "--depth", "auto", "--seed", str(args.seed), "--quiet", "--overwrite"],
                 d / "degrade.log", threads)
        return name

    rows: dict[str, dict] = {}
    with concurrent.futures.ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        for name in pool.map(prepare, scenes):
            rows[name] = _sfm_figures(work / name / "exact", work / name / "sfm")
        jobs = {}
        for name in scenes:
            for kind in ("exact", "sfm"):
                jobs[(name, kind, "clean", "3dgs")] = pool.submit(
                    _train, work / name / kind, "3dgs", work / name / f"run_{kind}_3dgs", args, threads)
            if name == args.weather_scene:
                for w in args.weathers.split(","):
                    for m in args.methods.split(","):
                        jobs[(name, "sfm", w, m)] = pool.submit(
                            _train, work / name / "weather" / w, m, work / name / f"run_{w}_{m}", args, threads)
        results = {k: f.result() for k, f in jobs.items()}

    print(f"\nExact poses vs SfM poses ({args.size}, 3DGS {args.preset}, seed {args.seed}, device {args.device})")
    print(f"{'scene':<9} {'reg':>7} {'focal err':>9} {'rot deg':>7} {'centre':>7} {'PSNR exact':>10} "
          f"{'PSNR sfm':>9} {'diff':>6} {'SSIM exact':>10} {'SSIM sfm':>8}  flags")
    for name in scenes:
        r, ex, sf = rows[name], results[(name, "exact", "clean", "3dgs")], results[(name, "sfm", "clean", "3dgs")]
        fe = "n/a" if r["focal_err_pct"] is None else f"{r['focal_err_pct']:+.2f}%"
        print(f"{name:<9} {r['registered']:>3}/{r['photos']:<3} {fe:>9} {r['rot_deg']:>7.3f} "
              f"{100 * r['center_rel']:>6.2f}% {ex['psnr']:>10.2f} {sf['psnr']:>9.2f} {sf['psnr'] - ex['psnr']:>+6.2f} "
              f"{ex['ssim']:>10.3f} {sf['ssim']:>8.3f}  {','.join(r['flags']) or '-'}")
    if args.weather_scene in scenes:
        name = args.weather_scene
        depth = json.loads((work / name / "weather" / args.weathers.split(",")[0] / "manifest.json").read_text())
        depth = depth["scene"]["depth"]
        rows["_weather_depth"] = {"source": depth["source"], "reason": depth.get("reason"),
                                  "consistency": (depth.get("consistency") or {}).get("mean")}
        print(f"\n{name} photos-only (SfM poses; haze depth: {depth['source']}, picked by auto, consistency "
              f"{rows['_weather_depth']['consistency']}), scored against the clean images")
        print(f"{'setting':<8} " + " ".join(f"{m + ' PSNR / SSIM':>22}" for m in args.methods.split(","))
              + "   margin (dB)")
        for w in args.weathers.split(","):
            cells = [results[(name, "sfm", w, m)] for m in args.methods.split(",")]
            line = f"{w:<8} " + " ".join(f"{c['psnr']:>13.2f} / {c['ssim']:.3f}" for c in cells)
            if len(cells) == 2:
                line += f"   {cells[1]['psnr'] - cells[0]['psnr']:+.2f}"
            print(line)
    if args.json:
        out = {"args": vars(args), "scenes": rows,
               "runs": {"/".join(k): v for k, v in results.items()}}
        Path(args.json).write_text(json.dumps(out, indent=1, default=lambda o: None if o is np.nan else str(o)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
