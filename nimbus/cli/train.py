"""``nimbus-train``: reconstruct a scene with 3DGS (and, as they land, NimbusGS and its variants).

Examples::

    nimbus-train builtin:garden:tiny --method 3dgs --preset tiny --out runs/garden-3dgs
    nimbus-train data/garden/H --method 3dgs --preset fast --out runs/g-h --set sh_degree=1 --seed 1
    nimbus-train data/garden/H+S --method nimbus --components csm,plm,ggs --out runs/g-hs
    nimbus-train --resume runs/garden-3dgs
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Sequence

from nimbus.cli_util import ArgumentParser, HelpFormatter, run_cli
from nimbus.errors import NimbusError
from nimbus.train.config import parse_set_args
from nimbus.train.methods import METHODS, get_method

BUILTIN_PREFIX = "builtin:"


def load_scene_arg(spec: str, downscale: int = 1):
    """A scene from a path, or ``builtin:NAME[:SIZE]`` rendered in memory (default size tiny)."""
    if spec.startswith(BUILTIN_PREFIX):
        from nimbus.data.builtin import render_builtin

        parts = spec[len(BUILTIN_PREFIX):].split(":")
        name, size = parts[0], (parts[1] if len(parts) > 1 else "tiny")
        return render_builtin(name, size=size, seed=0)
    from nimbus.data.io import load_scene

    return load_scene(spec, downscale=downscale)


def build_parser() -> ArgumentParser:
    p = ArgumentParser(prog="nimbus-train", description=__doc__, formatter_class=HelpFormatter)
    p.add_argument("scene", nargs="?", help="scene folder (COLMAP or transforms.json), or builtin:NAME[:SIZE]")
    p.add_argument("--method", default="3dgs", help=f"one of: {', '.join(sorted(METHODS))}")
    p.add_argument("--preset", default="fast", help="tiny (CI, seconds), fast (minutes on a CPU), paper (30k its)")
    p.add_argument("--out", help="run directory to create")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a config field (repeatable)")
    p.add_argument("--components", metavar="LIST",
                   help="NimbusGS components: auto (default), none, or a comma list of csm, plm, ggs "
                        "(same as --set components=LIST)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--downscale", type=int, default=1, help="use images_N of a Mip-NeRF360-style scene")
    p.add_argument("--overwrite", action="store_true", help="replace a non-empty run directory")
    p.add_argument("--resume", metavar="RUN", help="continue an interrupted run from its checkpoint")
    p.add_argument("--device", default=None, help="torch device (default: cuda if available, else cpu)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def _main(argv: Sequence[str] | None) -> int:
    import torch

    from nimbus.train.trainer import CHECKPOINT
    from nimbus.utils.fs import check_output_dir

    args = build_parser().parse_args(argv)
    device = torch.device(args.device) if args.device else None
    if args.resume and (args.components is not None or args.set):
        raise NimbusError("--resume continues a run with its saved settings; drop --components / --set, "
                          "or start a new run with --out")
    if args.resume:
        run = Path(args.resume)
        cfg_file, ckpt = run / "config.json", run / CHECKPOINT
        if not cfg_file.is_file() or not ckpt.is_file():
            raise NimbusError(f"{run} is not a resumable run (needs config.json and {CHECKPOINT})")
        saved = json.loads(cfg_file.read_text())
        method = get_method(saved["method"])
        config_cls = type(method.preset("tiny"))
        config = config_cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in saved["config"].items()})
        scene = load_scene_arg(saved["scene"], **saved.get("scene_load_args", {}))
        trainer = method.trainer()(scene, config, run, seed=saved["seed"], scene_path=saved["scene"],
                                   progress=not args.quiet, device=device,
                                   scene_load_args=saved.get("scene_load_args", {}))
        trainer.load_checkpoint(ckpt)
        print(f"resuming {run} at iteration {trainer.iteration}/{config.iterations}", file=sys.stderr)
    else:
        if not args.scene or not args.out:
            raise NimbusError("give a SCENE and --out RUN (or --resume RUN); see nimbus-train --help")
        method = get_method(args.method)
        base = method.preset(args.preset)
        overrides = parse_set_args(args.set)
        if args.components is not None:
            if not hasattr(base, "components"):
                raise NimbusError(f"--components applies to NimbusGS methods, not {args.method!r}; "
                                  f"use --method nimbus (or a nimbus-* variant)")
            if "components" in overrides:
                raise NimbusError("give the components once: --components LIST or --set components=LIST, not both")
            overrides["components"] = args.components
        config = base.with_overrides(overrides)
        check_output_dir(args.out, args.overwrite)
        scene = load_scene_arg(args.scene, args.downscale)
        out = Path(args.out)
        if out.exists() and args.overwrite:
            import shutil

            shutil.rmtree(out)
        load_args = {"downscale": args.downscale} if args.downscale != 1 else {}
        trainer = method.trainer()(scene, config, out, seed=args.seed, scene_path=args.scene,
                                   progress=not args.quiet, device=device, scene_load_args=load_args)
    results = trainer.train()
    against = " (against clean/)" if results.get("eval_reference") == "clean" else ""
    print(f"{results['method']}: {results['eval_split']} PSNR{against} {results['psnr']:.2f} dB, "
          f"SSIM {results['ssim']:.4f}, {results['num_gaussians']} Gaussians, "
          f"{results['train_time_s']:.1f} s -> {trainer.out}")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    raise SystemExit(run_cli(_main, argv))


if __name__ == "__main__":
    main()
