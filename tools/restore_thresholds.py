"""The validation data behind ``restorer=auto``'s thresholds (:mod:`nimbus.restore`), and what it shows.

    python -m tools.restore_thresholds [--root DIR] [--sizes tiny,small]

Renders the built-in scenes with scene seed :data:`VALIDATION_SEED` and degrades them with the
same synthesis seed (the benchmark's cells use 0 for both, so no view scored there is seen
here), all seven settings, the ``onerestore`` protocol; then prints, over the *training* views,
the range of each ``auto`` statistic for views with and without the degradation it detects,
and how many views the current thresholds get wrong.

Last, what the particle step is worth: for every degraded training view, its PSNR
against the clean view restored as ``auto`` would with the particle remover first, minus without it
(``dcp`` or nothing, as the haze test says), and for each cut of the white share the mean of that gain
over all views when the step runs on the views at or above the cut.  ``PARTICLE_SHARE`` is the cut
with the largest mean gain: the step is there to improve the views, not to name what they show.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from nimbus.cli_util import run_cli

#: Scene and synthesis seed of the validation data (the benchmark's is 0).
VALIDATION_SEED = 1
SCENES = ("garden", "street", "tabletop")


def prepare(root: Path, sizes: list[str], seed: int = VALIDATION_SEED) -> list[Path]:
    """The degraded scene folders (``root/data/<scene>-<size>``), rendered and synthesised with scene and
    synthesis ``seed`` where missing.

    An unknown size, or a ``root`` whose scenes were made with another seed, raises NimbusError before anything
    is written."""
    from nimbus.data.builtin import get_size, write_builtin
    from nimbus.data.io import load_scene
    from nimbus.schemas import SceneManifest, read_json_file
    from nimbus.errors import NimbusError
    from weather_synth.config import protocol_config
    from weather_synth.dataset import degrade_scene
    from weather_synth.settings import ALL_SETTING_NAMES, parse_setting

    for size in sizes:
        get_size(size)
    for manifest in sorted((root / "scenes").glob("*/manifest.json")):
        made = read_json_file(manifest, SceneManifest, "delete the scene folder to render it again")["seed"]
        if made != seed:
            raise NimbusError(f"{manifest.parent} was made with seed {made}, not {seed}; give another --root for "
                              f"seed {seed}")
    out = []
    for size in sizes:
        for scene in SCENES:
            clean, data = root / "scenes" / f"{scene}-{size}", root / "data" / f"{scene}-{size}"
            if not (clean / "manifest.json").is_file():
                write_builtin(scene, clean, size, seed=seed, overwrite=True, progress=False)
            if not all((data / s / "manifest.json").is_file() for s in ALL_SETTING_NAMES):
                degrade_scene(load_scene(clean), data, [parse_setting(s) for s in ALL_SETTING_NAMES],
                              protocol_config("onerestore", seed), overwrite=True, progress=False,
                              source=f"builtin:{scene}:{size}")
            out.append(data)
    return out


def evidence_rows(data_dirs: list[Path]) -> list[dict]:
    """One row per training view and setting (``clean`` included): scene, setting, name and the evidence."""
    from nimbus.data.images import read_image
    from nimbus.restore import image_evidence

    rows = []
    for data in data_dirs:
        for setting in sorted(p for p in data.iterdir() if (p / "manifest.json").is_file()):
            names = (setting / "train_list.txt").read_text().split()
            for kind, folder in (("clean", "clean"), (setting.name, "images")):
                for name in names:
                    if kind == "clean" and setting.name != "H":  # the clean views once per scene
                        continue
                    ev = image_evidence(read_image(setting / folder / name))
                    rows.append({"scene": data.name, "setting": kind, "name": name, **ev.to_dict()})
    return rows


def _report(rows: list[dict], stat: str, components: str, threshold: float) -> str:
    """The ranges of ``stat`` over views with any of ``components`` (e.g. ``"RS"``) and without."""
    has = np.array([bool(set(components) & set(r["setting"].split("+"))) for r in rows])
    x = np.array([r[stat] for r in rows])
    pos, neg = x[has], x[~has]
    wrong = int((pos < threshold).sum() + (neg >= threshold).sum())
    cuts = np.unique(x)
    errors = [int((pos < c).sum() + (neg >= c).sum()) for c in cuts]
    best = float(cuts[int(np.argmin(errors))])
    return (f"{stat} ({'/'.join(components)}): with {pos.min():.4f}..{pos.max():.4f} (n={len(pos)}), "
            f"without {neg.min():.4f}..{neg.max():.4f} (n={len(neg)}); threshold {threshold}: {wrong} views wrong "
            f"(fewest, {min(errors)}, from {best:.4f})")


#: The white-share cuts the particle step's gain is tabled for (and ``inf``: never).
SHARE_CUTS = tuple(round(0.70 + 0.02 * i, 2) for i in range(21))


def particle_gain_rows(data_dirs: list[Path]) -> list[dict]:
    """One row per degraded training view of every setting: scene, setting, name, the white share, and ``gain``:
    the view's PSNR (dB, against its clean view) restored as ``auto`` restores it with the particle step, minus
    without it (either way ``dcp`` where the haze test says so).  The clean views are left out: a benchmark
    restores only weather settings' views (and a clean view's PSNR against itself is infinite)."""
    from nimbus.data.images import read_image
    from nimbus.metrics.image import peak_signal_noise_ratio
    from nimbus.restore import Restorer, image_evidence

    # (hazy, with the particle step) -> what auto runs
    restorers = {(False, False): Restorer("none"), (False, True): Restorer("particles"),
                 (True, False): Restorer("dcp"), (True, True): Restorer("dcp+particles")}
    rows = []
    for data in data_dirs:
        for setting in sorted(p for p in data.iterdir() if (p / "manifest.json").is_file()):
            for name in (setting / "train_list.txt").read_text().split():
                image, clean = read_image(setting / "images" / name), read_image(setting / "clean" / name)
                ev = image_evidence(image)
                with_, without = (float(peak_signal_noise_ratio(restorers[ev.haze, parts](image)[0], clean))
                                  for parts in (True, False))
                rows.append({"scene": data.name, "setting": setting.name, "name": name,
                             "white_share": ev.white_share, "gain": with_ - without})
    return rows


def share_gains(rows: list[dict], cuts=SHARE_CUTS) -> list[tuple[float, float]]:
    """``(cut, mean gain)`` for each cut and for ``inf`` (the step never runs): the gain of the views at or above
    the cut, summed and divided by the number of all views (a view below the cut gains 0)."""
    share = np.array([r["white_share"] for r in rows])
    gain = np.array([r["gain"] for r in rows])
    return [(c, float(np.where(share >= c, gain, 0.0).sum() / len(rows))) for c in (*cuts, float("inf"))]


def best_share(gains: list[tuple[float, float]]) -> float:
    """The cut with the largest mean gain; of equal ones the highest (the step runs on fewer views)."""
    return max(gains, key=lambda cg: (round(cg[1], 6), cg[0]))[0]


def main(argv: list[str] | None = None) -> int:
    from nimbus.restore import HAZE_DARK_MEAN, PARTICLE_SHARE

    parser = argparse.ArgumentParser(prog="python -m tools.restore_thresholds", description=__doc__.split("\n")[0])
    parser.add_argument("--root", default="restore-validation", help="where the validation scenes are (made)")
    parser.add_argument("--sizes", default="tiny,small", help="built-in scene sizes, comma-separated")
    args = parser.parse_args(argv)
    data_dirs = prepare(Path(args.root), [s.strip() for s in args.sizes.split(",") if s.strip()])
    rows = evidence_rows(data_dirs)
    for scene in [*sorted({r["scene"] for r in rows}), "all"]:
        sub = [r for r in rows if scene in ("all", r["scene"])]
        print(scene)
        print("  " + _report(sub, "dark_mean", "H", HAZE_DARK_MEAN))
        print("  " + _report(sub, "white_share", "RS", PARTICLE_SHARE))
    gains = share_gains(particle_gain_rows(data_dirs))
    print("particle step, mean PSNR gain per training view (dB) when it runs on views with white share >= cut:")
    print("  " + ", ".join(f"{c:g}: {g:+.3f}" for c, g in gains))
    print(f"  largest from {best_share(gains):g}; PARTICLE_SHARE = {PARTICLE_SHARE:g}: "
          f"{dict(gains).get(PARTICLE_SHARE, float('nan')):+.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(run_cli(main))
