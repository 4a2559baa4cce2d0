"""``nimbus-train``: reconstruct a scene with 3DGS (and, as they land, NimbusGS and its variants).

Examples::

    nimbus-train builtin:garden:tiny --method 3dgs --preset tiny --out runs/garden-3dgs
    nimbus-train data/garden/H --method 3dgs --preset fast --out runs/g-h --set sh_degree=1 --seed 1
    nimbus-train data/garden/H+S --method nimbus --components csm,plm,ggs --out runs/g-hs
    nimbus-train --resume runs/garden-3dgs
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path
from typing import Sequence

from nimbus.cli_util import MAX_SEED, ArgumentParser, HelpFormatter, run_cli, seed_arg
from nimbus.errors import NimbusError
from nimbus.config_set import apply_overrides, parse_set_args
from nimbus.methods.registry import ENTRIES, get_method, method_help
from nimbus.train.run_folder import check_downscale, load_scene_arg, scene_input_folder

#: Names this command in its run folder's marker: --overwrite empties only a run folder it made itself.
OWNER = "nimbus-train"

def parse_device(spec: str | None):
    """``--device`` as a torch device Nimbus can train on (None: the default), else NimbusError."""
    import torch

    if spec is None:
        return None
    try:
        device = torch.device(spec)
    except (RuntimeError, ValueError, TypeError):
        raise NimbusError(f"--device {spec!r} is not a torch device; use cpu or cuda[:N] (or leave --device out "
                          "to use CUDA when available)") from None
    if device.type == "cpu":
        return device
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise NimbusError(f"--device {spec}: CUDA is not available here (no GPU, or torch was built without "
                              "CUDA); use --device cpu or leave --device out")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise NimbusError(f"--device {spec}: this machine has {torch.cuda.device_count()} CUDA device(s) "
                              f"(cuda:0..cuda:{torch.cuda.device_count() - 1}); pick one of them")
        return device
    raise NimbusError(f"--device {spec}: Nimbus trains on cpu or cuda[:N], not {device.type}")


def build_parser() -> ArgumentParser:
    p = ArgumentParser(prog="nimbus-train", description=__doc__, formatter_class=HelpFormatter)
    p.add_argument("scene", nargs="?", help="scene folder (COLMAP or transforms.json), or builtin:NAME[:SIZE]")
    p.add_argument("--method", default="3dgs",
                   help=f"one of: {', '.join(e.name for e in ENTRIES)}, or a variant NAME-SUFFIX "
                        "(--method help lists them all)")
    p.add_argument("--preset", default="fast", help="tiny (CI, seconds), fast (minutes on a CPU), paper (30k its)")
    p.add_argument("--out", help="run directory to create")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a config field (repeatable)")
    p.add_argument("--components", metavar="LIST",
                   help="NimbusGS components: auto (default), none, or a comma list of csm, plm, ggs "
                        "(same as --set components=LIST)")
    p.add_argument("--seed", type=seed_arg, default=0, help=f"training seed in [0, {MAX_SEED}]")
    p.add_argument("--downscale", type=int, default=1,
                   help="use images_N of a Mip-NeRF360-style scene folder (not for builtin: scenes)")
    p.add_argument("--overwrite", action="store_true", help="replace a run directory an earlier nimbus-train made (any other folder is refused)")
    p.add_argument("--resume", metavar="RUN", help="continue an interrupted run from its checkpoint")
    p.add_argument("--device", default=None, help="torch device: cpu or cuda[:N] (default: cuda if available)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def _resume(args, device):
    from nimbus.train.runner import Runner

    runner = Runner.resume(args.resume, progress=not args.quiet, device=device)
    print(f"resuming {runner.out} at iteration {runner.iteration}/{runner.cfg.iterations}", file=sys.stderr)
    return runner.run(), runner


def _new_run(args, device):
    from nimbus.train.runner import Runner
    from nimbus.utils.fs import check_output_dir, mark_output

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
    config = apply_overrides(base, overrides)
    check_downscale(args.scene, args.downscale)
    # Before anything is deleted: --out SCENE --overwrite (or an ancestor of the scene) would remove the input,
    # and --overwrite of a folder this command did not make (a store, a home folder) would empty it.
    out = check_output_dir(args.out, args.overwrite, inputs=[scene_input_folder(args.scene)], owner=OWNER)
    scene = load_scene_arg(args.scene, args.downscale)
    if args.overwrite and out.is_dir():
        # Emptied rather than removed: that needs no write access to its parent, and keeps the folder's mode.
        try:
            _empty_folder(out)
        except OSError as e:
            raise NimbusError(f"--overwrite could not remove the old contents of {out} ({e.strerror}: "
                              f"{e.filename}); fix the permissions or choose another --out") from None
    # What this run creates, to remove again if it fails before there is anything to resume:
    # the topmost missing folder on the way to --out, or the contents of an empty --out.
    created = next((p for p in reversed([out, *out.parents]) if not p.exists()), None)
    load_args = {"downscale": args.downscale} if args.downscale != 1 else {}
    try:
        out.mkdir(parents=True, exist_ok=True)
        mark_output(out, OWNER)  # before training: a killed run's folder is this command's to replace
        runner = Runner(args.method, scene, config, out, seed=args.seed, scene_path=args.scene,
                        scene_load_args=load_args, progress=not args.quiet, device=device)
        return runner.run(), runner
    except BaseException:
        _remove_unresumable(out, created)
        raise


def _remove_unresumable(out: Path, created: Path | None) -> None:
    """After a failed new run: remove what it wrote unless a checkpoint was saved (kept for --resume and for
    the last-good state the error names), so a plain retry is not refused as "not empty"."""
    from nimbus.train.checkpoint import CHECKPOINT, LAST_GOOD

    if (out / CHECKPOINT).exists() or (out / LAST_GOOD).exists():
        return
    if created is not None:
        shutil.rmtree(created, ignore_errors=True)
    elif out.is_dir():  # --out existed, and was empty or emptied by --overwrite
        try:
            _empty_folder(out)
        except OSError:
            pass  # the run's own error is the one to report


def _empty_folder(folder: Path) -> None:
    """Remove everything inside ``folder`` (links themselves, never what they point to)."""
    for p in folder.iterdir():
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        else:
            p.unlink()


def _main(argv: Sequence[str] | None) -> int:
    args = build_parser().parse_args(argv)
    if args.method == "help":
        print(method_help())
        return 0
    device = parse_device(args.device)
    if args.resume and (args.components is not None or args.set):
        raise NimbusError("--resume continues a run with its saved settings; drop --components / --set, "
                          "or start a new run with --out")
    if args.downscale < 1:
        raise NimbusError(f"--downscale must be a positive integer (1, 2, 4, 8), got {args.downscale}")
    results, runner = _resume(args, device) if args.resume else _new_run(args, device)
    against = " (against clean/)" if results.get("eval_reference") == "clean" else ""
    print(f"{results['method']}: {results['eval_split']} PSNR{against} {results['psnr']:.2f} dB, "
          f"SSIM {results['ssim']:.4f}, {results['num_gaussians']} Gaussians, "
          f"{results['train_time_s']:.1f} s -> {runner.out}")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    raise SystemExit(run_cli(_main, argv))


if __name__ == "__main__":
    main()
