"""Train one method on validation setting folders and score it, with the medium's error against the true layers.

    python -m tools.validation_cells --tag NAME --method nimbus --preset tiny FOLDER [FOLDER ...] \
        [--set KEY=VALUE ...] [--seed N] [--out records.jsonl]
    python -m tools.validation_cells --summary records.jsonl --tags A,B[,...]

A FOLDER is a synthesised setting folder of a validation scene (scene and synthesis seed >= 1, never the
benchmark's 0), e.g. ``VAL/data/garden-tiny/H`` after ``python -m tools.restore_thresholds --root VAL
--sizes tiny`` (seed 1; ``tools.restore_thresholds.prepare(root, sizes, seed)`` for other seeds).  Each
folder's run is trained in a temporary folder, its test views scored against ``clean/`` (PSNR on 8-bit renders,
SSIM of the 3DGS protocol, no LPIPS), and one JSON record appended to ``--out``: tag, method, folder, the
``--set`` overrides, seed, PSNR, SSIM, seconds and, for a method with a medium on a hazy folder, the learned
transmission's mean error against the synthesiser's (``T_err_mean``, ``T_abs``) and the effective airlight
``P / (1 - T)`` beside the true one.  This is how ``lambda_dehaze`` and ``nimbus-paper``'s departures were
measured (``tables/validation_tiny``).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path


def medium_errors(method, folder: Path) -> dict | None:
    """Mean error of the learned T against the true t over the training views, and the airlights; None without."""
    import numpy as np
    import torch

    if getattr(method, "medium", None) is None:
        return None
    learned, true, a_hat, a_true = [], [], [], []
    with torch.no_grad():
        for vi, view in enumerate(method.train_views):
            layers = np.load(folder / "layers" / (Path(view.name).stem + ".npz"))
            if "transmission" not in layers.files:
                return None
            parts = method.render(view.camera, view_index=vi)
            T = parts["transmission"][..., 0].float().cpu().numpy()
            P = parts["airlight"].float().cpu().numpy()
            learned.append(T.ravel())
            true.append(layers["transmission"].ravel())
            a_hat.append((P.reshape(-1, 3).sum(0) / max(float((1 - T).sum()), 1e-6)))
            a_true.append(layers["airlight"])
    err = np.concatenate(learned) - np.concatenate(true)
    return {"T_err_mean": float(err.mean()), "T_abs": float(np.abs(err).mean()),
            "A_hat": np.mean(a_hat, 0).round(3).tolist(), "A_true": np.mean(a_true, 0).round(3).tolist()}


def cell_name(folder: str) -> str:
    """``.../seed-1/data/garden-tiny/H`` -> ``seed-1 garden-tiny H``."""
    parts = Path(folder).parts
    return " ".join((parts[-4], parts[-2], parts[-1]))


def summary(records: Path, tags: list[str]) -> str:
    """A Markdown table: PSNR / SSIM of each tag per cell (the last record of a tag and cell), the tags' means over
    the cells all of them have, and each later tag's wins over the first."""
    if not tags:
        raise ValueError("give --tags: the comma list of tags to table")
    recs: dict[str, dict[str, tuple[float, float]]] = {t: {} for t in tags}
    for line in records.read_text().splitlines():
        r = json.loads(line)
        if r["tag"] in recs:
            recs[r["tag"]][cell_name(r["folder"])] = (r["psnr"], r["ssim"])
    cells = sorted(set.intersection(*(set(v) for v in recs.values())))
    if not cells:
        have = "; ".join(f"{t}: {len(v)} cell(s)" for t, v in recs.items())
        raise ValueError(f"no cell has a record of every tag in {records} ({have}); table tags that share cells")
    rows = ["| cell | " + " | ".join(tags) + " |", "| --- |" + " --- |" * len(tags)]
    for c in cells:
        rows.append(f"| {c} | " + " | ".join(f"{recs[t][c][0]:.2f} / {recs[t][c][1]:.3f}" for t in tags) + " |")
    means = [(sum(recs[t][c][0] for c in cells) / len(cells), sum(recs[t][c][1] for c in cells) / len(cells))
             for t in tags]
    rows.append(f"| mean of {len(cells)} | " + " | ".join(f"{m[0]:.2f} / {m[1]:.3f}" for m in means) + " |")
    wins = [sum(recs[t][c][0] >= recs[tags[0]][c][0] for c in cells) for t in tags[1:]]
    rows.append(f"| PSNR >= {tags[0]} | - | " + " | ".join(f"{w} of {len(cells)}" for w in wins) + " |")
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m tools.validation_cells", description=__doc__.split("\n")[0])
    p.add_argument("folders", nargs="*", type=Path)
    p.add_argument("--summary", type=Path, help="print a table of these records instead of training")
    p.add_argument("--tags", default="", help="with --summary: the comma list of tags to table, the first compared")
    p.add_argument("--tag", help="a name for this variant in the records")
    p.add_argument("--method", default="nimbus")
    p.add_argument("--preset", default="tiny")
    p.add_argument("--seed", type=int, default=0, help="training seed")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--out", type=Path, default=Path("validation_cells.jsonl"))
    args = p.parse_args(argv)
    if args.summary:
        try:
            print(summary(args.summary, [t for t in args.tags.split(",") if t]))
        except (OSError, ValueError) as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        return 0
    if not args.tag or not args.folders:
        p.error("give --tag and at least one FOLDER (or --summary RECORDS)")

    from benchmark.cell import make_config, score_run, train_method
    from nimbus.config_set import parse_set_args
    from nimbus.data.io import load_scene
    from nimbus.methods.registry import get_method

    overrides = parse_set_args(args.set)
    for folder in args.folders:
        config = make_config(get_method(args.method), args.preset, overrides)
        t0 = time.time()
        with tempfile.TemporaryDirectory(prefix="validation_cells_") as tmp:
            run = Path(tmp) / "run"
            results, runner = train_method(args.method, load_scene(folder), config, run, seed=args.seed,
                                           scene_path=str(folder), progress=False)
            score = score_run(run, folder, results, ssim_protocol="3dgs", lpips_net=None, device=None)
            medium = medium_errors(runner.method, folder)
        rec = {"tag": args.tag, "method": args.method, "preset": args.preset, "folder": str(folder),
               "overrides": overrides, "seed": args.seed, "psnr": score["mean"]["psnr"],
               "ssim": score["mean"]["ssim"], "time": round(time.time() - t0, 1), "dec": medium}
        with args.out.open("a") as fh:
            fh.write(json.dumps(rec) + "\n")
        print(f"{args.tag} {args.method} {folder.parent.name}/{folder.name}: {rec['psnr']:.2f} dB "
              f"SSIM {rec['ssim']:.3f} ({rec['time']} s)", file=sys.stderr, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
