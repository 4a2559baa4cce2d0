"""``nimbus-train``: reconstruct a scene with 3DGS (and, as they land, NimbusGS and its variants).

Examples::

    nimbus-train builtin:garden:tiny --method 3dgs --preset tiny --out runs/garden-3dgs
    nimbus-train data/garden/H --method 3dgs --preset fast --out runs/g-h --set sh_degree=1 --seed 1
    nimbus-train data/garden/H+S --method nimbus --components csm,plm,ggs --out runs/g-hs
    nimbus-train --resume runs/garden-3dgs
"""

from __future__ import annotations

import json
import os
import shutil
import sys
from pathlib import Path
from typing import Sequence

from nimbus.cli_util import MAX_SEED, ArgumentParser, HelpFormatter, check_seed, run_cli, seed_arg
from nimbus.errors import NimbusError
from nimbus.config_set import apply_overrides, parse_set_args
from nimbus.train.methods import METHODS, get_method

BUILTIN_PREFIX = "builtin:"
#: What ``scene_load_args`` in a run's config.json may hold (the keyword arguments of :func:`load_scene_arg`).
SCENE_LOAD_ARGS = ("downscale",)


def load_scene_arg(spec: str, downscale: int = 1):
    """A scene from a path, or ``builtin:NAME[:SIZE]`` rendered in memory (default size tiny).

    A built-in scene has no ``images_N`` copies, so ``downscale`` other than 1 is refused for it
    (pick a smaller SIZE, or ``--set train_downscale=N``) rather than silently ignored.
    """
    check_downscale(spec, downscale)
    if spec.startswith(BUILTIN_PREFIX):
        from nimbus.data.builtin import render_builtin

        parts = spec[len(BUILTIN_PREFIX):].split(":")
        name, size = parts[0], (parts[1] if len(parts) > 1 else "tiny")
        return render_builtin(name, size=size, seed=0)
    from nimbus.data.io import load_scene

    return load_scene(spec, downscale=downscale)


def check_downscale(spec: str, downscale: int) -> None:
    """Refuse a ``downscale`` that :func:`load_scene_arg` could not honour for ``spec``."""
    if spec.startswith(BUILTIN_PREFIX) and downscale != 1:
        raise NimbusError(f"--downscale {downscale} reads the images_{downscale}/ copies of a scene folder; "
                          f"built-in scenes have none. Pick a smaller size ({BUILTIN_PREFIX}NAME:tiny) or "
                          "train on shrunk images with --set train_downscale=N")


def scene_input_folder(spec: str) -> Path | None:
    """The folder a scene is read from (None for a built-in scene): what ``--out`` must stay apart from."""
    if spec.startswith(BUILTIN_PREFIX):
        return None
    path = Path(spec)
    return path.parent if path.is_file() else path  # a transforms*.json file reads its folder


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


def read_run_config(run: Path) -> dict:
    """The checked ``config.json`` of run folder ``run``: method, scene, seed, config and scene_load_args.

    Raises NimbusError naming the file for anything that is not what :meth:`GaussianTrainer.write_config` writes.
    """
    cfg_file = run / "config.json"
    fix = "it is not a config.json written by nimbus-train; restore it or start a new run with --out"
    try:
        saved = json.loads(cfg_file.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as e:
        raise NimbusError(f"cannot read {cfg_file} ({e.__class__.__name__}); check its permissions") from None
    except (ValueError, RecursionError) as e:
        raise NimbusError(f"{cfg_file} is not valid JSON ({str(e)[:120]}); {fix}") from None
    if not isinstance(saved, dict):
        raise NimbusError(f"{cfg_file} holds a {type(saved).__name__}, not an object; {fix}")
    for key, kind in (("method", str), ("scene", str), ("seed", int), ("config", dict)):
        if key not in saved:
            raise NimbusError(f"{cfg_file} has no {key!r}; {fix}")
        if not isinstance(saved[key], kind) or isinstance(saved[key], bool):
            raise NimbusError(f"{cfg_file}: {key!r} is {saved[key]!r}, expected a {kind.__name__}; {fix}")
    check_seed(saved["seed"], f"{cfg_file}: 'seed'")
    load_args = saved.get("scene_load_args") or {}
    if (not isinstance(load_args, dict) or not set(load_args) <= set(SCENE_LOAD_ARGS)
            or not all(isinstance(v, int) and not isinstance(v, bool) and v >= 1 for v in load_args.values())):
        raise NimbusError(f"{cfg_file}: 'scene_load_args' is {load_args!r}, expected {{\"downscale\": N}} with "
                          f"N >= 1 (or nothing); {fix}")
    return {**saved, "scene_load_args": load_args}


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
    p.add_argument("--seed", type=seed_arg, default=0, help=f"training seed in [0, {MAX_SEED}]")
    p.add_argument("--downscale", type=int, default=1,
                   help="use images_N of a Mip-NeRF360-style scene folder (not for builtin: scenes)")
    p.add_argument("--overwrite", action="store_true", help="replace a non-empty run directory")
    p.add_argument("--resume", metavar="RUN", help="continue an interrupted run from its checkpoint")
    p.add_argument("--device", default=None, help="torch device: cpu or cuda[:N] (default: cuda if available)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def _resume(args, device):
    from nimbus.train.trainer import CHECKPOINT

    run = Path(args.resume)
    cfg_file, ckpt = run / "config.json", run / CHECKPOINT
    if not cfg_file.is_file() or not ckpt.is_file():
        raise NimbusError(f"{run} is not a resumable run (needs config.json and {CHECKPOINT})")
    if not os.access(run, os.W_OK | os.X_OK):
        raise NimbusError(f"{run} cannot be written (read-only or not ours); a resumed run writes its checkpoint "
                          "and outputs there. Fix its permissions or copy the run folder somewhere writable")
    saved = read_run_config(run)
    method = get_method(saved["method"])
    config_cls = type(method.preset("tiny"))
    try:
        config = config_cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in saved["config"].items()})
    except (TypeError, ValueError, NimbusError) as e:
        raise NimbusError(f"{cfg_file}: its 'config' does not fit method {saved['method']!r} ({e}); restore the "
                          "file or start a new run with --out") from None
    scene = load_scene_arg(saved["scene"], **saved["scene_load_args"])
    trainer = method.trainer()(scene, config, run, seed=saved["seed"], scene_path=saved["scene"],
                               progress=not args.quiet, device=device, scene_load_args=saved["scene_load_args"])
    trainer.load_checkpoint(ckpt)
    print(f"resuming {run} at iteration {trainer.iteration}/{config.iterations}", file=sys.stderr)
    return trainer.train(), trainer


def _new_run(args, device):
    from nimbus.utils.fs import check_output_dir

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
    # Before anything is deleted: --out SCENE --overwrite (or an ancestor of the scene) would remove the input.
    out = check_output_dir(args.out, args.overwrite, inputs=[scene_input_folder(args.scene)])
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
        trainer = method.trainer()(scene, config, out, seed=args.seed, scene_path=args.scene,
                                   progress=not args.quiet, device=device, scene_load_args=load_args)
        return trainer.train(), trainer
    except BaseException:
        _remove_unresumable(out, created)
        raise


def _remove_unresumable(out: Path, created: Path | None) -> None:
    """After a failed new run: remove what it wrote unless a checkpoint was saved (kept for --resume and for
    the last-good state the error names), so a plain retry is not refused as "not empty"."""
    from nimbus.train.trainer import CHECKPOINT, LAST_GOOD

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
    device = parse_device(args.device)
    if args.resume and (args.components is not None or args.set):
        raise NimbusError("--resume continues a run with its saved settings; drop --components / --set, "
                          "or start a new run with --out")
    if args.downscale < 1:
        raise NimbusError(f"--downscale must be a positive integer (1, 2, 4, 8), got {args.downscale}")
    results, trainer = _resume(args, device) if args.resume else _new_run(args, device)
    against = " (against clean/)" if results.get("eval_reference") == "clean" else ""
    print(f"{results['method']}: {results['eval_split']} PSNR{against} {results['psnr']:.2f} dB, "
          f"SSIM {results['ssim']:.4f}, {results['num_gaussians']} Gaussians, "
          f"{results['train_time_s']:.1f} s -> {trainer.out}")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    raise SystemExit(run_cli(_main, argv))


if __name__ == "__main__":
    main()
