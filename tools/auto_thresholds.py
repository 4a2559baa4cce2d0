"""The validation runs behind ``components=auto``'s thresholds (:mod:`nimbus.methods.nimbusgs.auto`), and what they show.

    python -m tools.auto_thresholds [--root DIR] [--scene-seeds 1,2] [--sizes tiny] [--cache DIR] [--jobs N]
                                    [--quick] [--checks]
    python -m tools.auto_thresholds --report [--root DIR] [--cache DIR]
    python -m tools.auto_thresholds --store ROOT

On the validation scenes (the built-in scenes rendered and degraded with each of ``--scene-seeds``,
1 to 4 unless given, as :mod:`tools.restore_thresholds` makes them; the benchmark's cells use
seed 0, and only their held-out test views are ever reported), each scene's
seven settings and its clean views, trains ``nimbus`` (tiny preset) four times: CSM on or off
crossed with PLM on or off (GGS on when either is, as ``auto`` does), with the first of
``--seeds``; the PLM pair at the current haze decision again with every further seed (default
0 and 1: one seed's PLM gain moves by a few tenths of a dB with nothing but the code's float
rounding), and the PLM gains and evidence are the means over the seeds.  Each
decision is made one way through ``auto`` itself, by thresholds it cannot fail or cannot meet,
so every run records the same evidence an ``auto`` run would (the stage-1 model, and with it
the particle evidence, does not depend on PLM).  It prints, per cell, the evidence and the
forced-on minus forced-off PSNR on the test views, then derives:

* the haze rule (``auto_dark_threshold``, ``auto_depth_corr``): a cell needs CSM when the
  best run with CSM beats the best without by >= :data:`MIN_GAIN_DB`;
* the particle thresholds, one pair for the cells the haze rule declares hazy and one for
  the rest: a cell needs PLM when, with CSM as the haze rule decides, PLM on beats PLM off
  by >= :data:`MIN_GAIN_DB`.

Rule (each decision): every cell that needs the component is declared; among the rules that
do, the one that gives away the fewest dB over all the cells (a cell declared that loses from the
component gives away its loss, a cell left out that gains gives away its gain, however small);
among those, the one with the widest margin (how far every threshold can move, in spreads of the
evidence, before a validation cell is decided otherwise).  Each threshold sits half-way between
two values seen (or below all), rounded to the fewest digits that decide the same.  The current
defaults are kept when they give away no more and have at least half that margin.  A cell
"needs" a component by what it gains, whatever the synthesizer put in it (PLM may gain on a hazy
scene without particles).  The cells of every scene seed count alike (seed 0, the benchmark's own
data, is refused).

``--checks`` also trains, with CSM as the current haze rule decides and PLM on, without the
top-hat cap (``residual_tophat=0``), with the outlier test everywhere
(``residual_outlier_scope=all``) and, on the hazy cells, with the airlight evaluated per 2 x 2
block (``airlight_stride=2``), and prints what each default is worth on the validation cells.  ``--report`` trains the same four variants on the benchmark's own cells (seed 0,
tiny, seven settings), applies the current defaults to their evidence and prints where
``auto``'s choice is >= :data:`MIN_GAIN_DB` below the best variant: a report, never an
input to the thresholds.

``--store ROOT`` trains nothing: it reads a benchmark store (``nimbus-bench run --root ROOT``) that holds
``nimbus`` and ``nimbus-no-plm`` runs of the same cells (scene, setting, preset, training seed) on validation
scenes (scene seed >= 1, e.g. ``ROOT/scenes`` and ``ROOT/data`` made by this tool for ``--sizes small``), takes each
pair as a hazy cell's PLM on / off with CSM on (``auto``'s stage-1 evidence from the ``nimbus`` run's
``results.json``) and prints the same per-cell table and hazy particle pair.  It is how the pair is derived at a
size where this tool's four variants per cell cost too much CPU (the small scenes: about half an hour a run).

Each run's figures are kept as JSON under ``--cache`` (a rerun trains only what is missing).
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import multiprocessing
import sys
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Sequence

import numpy as np

from tools.restore_thresholds import SCENES, VALIDATION_SEED, prepare
from nimbus.cli_util import run_cli

#: A component is needed where forcing it on gains at least this much test PSNR (dB).
MIN_GAIN_DB = 0.3
METHOD = "nimbus"
#: Training seeds of the PLM pair (``--seeds``): one seed's gain moves by a few tenths of a dB with the float
#: rounding of the code, enough to flip a cell across :data:`MIN_GAIN_DB`.
TRAIN_SEEDS = (0, 1)
#: A run name's suffix for a training seed other than the first (``csm+plm@s1``).
SEED_MARK = "@s"
#: Scene and synthesis seeds of the validation scenes (``--scene-seeds``; the benchmark's data use 0).
SCENE_SEEDS = tuple(range(VALIDATION_SEED, VALIDATION_SEED + 4))
#: The setting name of a scene's clean views (``ROOT/scenes/<scene>-<size>``).
CLEAN = "clean"

# Decisions forced through auto's own thresholds: met by any evidence, or by none.
_HAZE = {True: {"auto_dark_threshold": "0"}, False: {"auto_dark_threshold": "1", "auto_depth_corr": "1"}}
_PARTICLES = {
    True: {"auto_particle_threshold": "-1", "auto_particle_energy": "0",
           "auto_particle_threshold_haze": "-1", "auto_particle_energy_haze": "0",
           "auto_particle_threshold_haze_large": "-1", "auto_particle_energy_haze_large": "0"},
    False: {"auto_particle_threshold": "1", "auto_particle_energy": "1e9",
            "auto_particle_threshold_haze": "1", "auto_particle_energy_haze": "1e9",
            "auto_particle_threshold_haze_large": "1", "auto_particle_energy_haze_large": "1e9"},
}
#: The four variants, by which components they force on: name -> (csm, plm).
VARIANTS = {"csm+plm": (True, True), "csm": (True, False), "plm": (False, True), "none": (False, False)}
#: The ``--checks`` runs (PLM on, CSM by the current haze rule): name -> extra overrides.
CHECKS = {"tophat-off": {"residual_tophat": "0"}, "scope-all": {"residual_outlier_scope": "all"},
          "airlight-stride-2": {"airlight_stride": "2"}}
#: Checks of the medium alone: trained on the cells the haze rule calls hazy only (elsewhere CSM is off).
HAZE_ONLY_CHECKS = {"airlight-stride-2"}


def variant_overrides(csm: bool, plm: bool, extra: dict | None = None) -> dict[str, str]:
    """``--set`` overrides that make ``auto`` decide CSM and PLM as given (and skip the decomposition strips)."""
    return {**_HAZE[csm], **_PARTICLES[plm], "write_decomposition": "false", **(extra or {})}


def cell_folders(root: Path, sizes: list[str], seeds: Sequence[int] = SCENE_SEEDS) -> list[tuple[str, str, Path]]:
    """``(scene-size@seed, setting, folder)`` of every validation cell: for each scene seed (its scenes under
    ``root/seed-N``), each scene's clean views and seven settings."""
    out = []
    for seed in seeds:
        seed_root = root / f"seed-{seed}"
        for data in prepare(seed_root, sizes, seed):
            label = f"{data.name}@{seed}"
            out.append((label, CLEAN, seed_root / "scenes" / data.name))
            out += [(label, s.name, s) for s in sorted(data.iterdir()) if (s / "manifest.json").is_file()]
    return out


def run_one(job: dict) -> dict:
    """Train and score one variant of one cell (``job``: folder, overrides, preset, threads, out); cached JSON."""
    import torch

    from benchmark.cell import make_config, score_run, train_method
    from nimbus.data.io import load_scene
    from nimbus.methods.registry import get_method
    from nimbus.utils.fs import atomic_write_json

    out = Path(job["out"])
    if out.is_file():
        return json.loads(out.read_text())
    if job["threads"]:
        torch.set_num_threads(job["threads"])
    folder = Path(job["folder"])
    config = make_config(get_method(METHOD), job["preset"], job["overrides"])
    with tempfile.TemporaryDirectory(prefix="auto_thresholds_") as tmp:
        run = Path(tmp) / "run"
        results, _ = train_method(METHOD, load_scene(folder), config, run, seed=job.get("seed", 0),
                                  scene_path=str(folder), progress=False)
        score = score_run(run, folder, results, ssim_protocol="3dgs", lpips_net=None, device=None)
    nim = results["nimbus"]
    rec = {"folder": str(folder), "overrides": job["overrides"], "psnr": score["mean"]["psnr"],
           "ssim": score["mean"]["ssim"], "components": results["components"], "haze": nim["haze_evidence"],
           "particles": nim["particle_evidence"], "train_time_s": results.get("train_time_s")}
    atomic_write_json(out, rec)
    print(f"{out.stem}: {rec['psnr']:.2f} dB, {sorted(rec['components'])}", file=sys.stderr, flush=True)
    return rec


def _digest(preset: str, overrides: dict[str, str]) -> str:
    """A run's cache key: its config, but for the ``auto_*`` defaults (each run forces its decisions)."""
    from benchmark.cell import make_config
    from nimbus.methods.registry import get_method

    config = dataclasses.asdict(make_config(get_method(METHOD), preset, overrides))
    fields = {k: v for k, v in config.items() if not k.startswith("auto_")}
    return hashlib.sha256(json.dumps([fields, overrides], sort_keys=True, default=str).encode()).hexdigest()[:8]


def train_all(jobs: list[tuple[tuple[str, str, Path], str, dict[str, str]]], cache: Path, preset: str,
              workers: int, threads: int | None) -> dict[tuple[str, str, str], dict]:
    """``{(scene-size, setting, run name): record}``; ``jobs``: ``((scene-size, setting, folder), name, overrides)``."""
    keys, todo = [], []
    for (data, setting, folder), name, overrides in jobs:
        keys.append((data, setting, name))
        seed = split_seed(name)[1]
        todo.append({"folder": str(folder), "overrides": overrides, "preset": preset, "threads": threads,
                     "seed": seed,
                     "out": str(cache / f"{data}_{setting}_{name}_{preset}_{_digest(preset, overrides)}.json")})
    if workers > 1:  # spawned: the parent has torch's thread pools up (it rendered the scenes)
        with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
            recs = list(pool.map(run_one, todo))
    else:
        recs = [run_one(job) for job in todo]
    for key, job, rec in zip(keys, todo, recs):
        csm, plm = VARIANTS.get(split_seed(key[2])[0], (None, None))
        comps = set(rec["components"])
        if csm is not None and ("csm" in comps, "plm" in comps) != (csm, plm):
            raise RuntimeError(f"{job['out']}: ran with {sorted(comps)}, not the forced variant {key[2]}")
    return dict(zip(keys, recs))


@dataclasses.dataclass
class Cell:
    """One scene and setting's evidence and gains."""

    data: str
    setting: str
    psnr: dict[str, float]
    dark_median: float
    dark_depth_corr: float
    #: Particle evidence (asymmetry, energy) with CSM on / off.
    particles: dict[bool, tuple[float, float]]

    @property
    def complete(self) -> bool:
        """All four variants ran (``--quick`` runs only the PLM pair at the current haze decision)."""
        return len(self.psnr) == len(VARIANTS)

    @property
    def csm_gain(self) -> float:
        p = self.psnr
        return max(p["csm+plm"], p["csm"]) - max(p["plm"], p["none"])

    def plm_gain(self, hazy: bool) -> float:
        p = self.psnr
        return p["csm+plm"] - p["csm"] if hazy else p["plm"] - p["none"]

    def best(self) -> tuple[str, float]:
        name = max(self.psnr, key=self.psnr.get)
        return name, self.psnr[name]


def gather(cells: list[tuple[str, str, Path]], recs: dict, seeds: Sequence[int] = TRAIN_SEEDS) -> list[Cell]:
    """The :class:`Cell` of each scene and setting from the variants that ran: each variant's PSNR and particle
    evidence the mean over the training seeds it ran with."""
    out = []
    for data, setting, _ in cells:
        runs = {v: [recs[(data, setting, seed_name(v, s))] for s in seeds
                    if (data, setting, seed_name(v, s)) in recs] for v in VARIANTS}
        runs = {v: rs for v, rs in runs.items() if rs}
        ev = {csm: (float(np.mean([x["particles"]["asymmetry"] for x in runs[name]])),
                    float(np.mean([x["particles"]["energy"] for x in runs[name]])))
              for csm, name in ((True, "csm+plm"), (False, "plm")) if name in runs}
        haze = next(iter(runs.values()))[0]["haze"]
        out.append(Cell(data, setting, {v: float(np.mean([x["psnr"] for x in rs])) for v, rs in runs.items()},
                        haze["dark_median"], haze["dark_depth_corr"], ev))
    return out


def current_haze(folder: Path, preset: str) -> bool:
    """The haze decision of the current defaults for a scene folder (as the ``nimbus`` run will make it)."""
    import torch

    from benchmark.cell import make_config
    from nimbus.data.io import load_scene
    from nimbus.methods.registry import get_method
    from nimbus.methods.nimbusgs.auto import haze_evidence

    cfg = make_config(get_method(METHOD), preset, {})
    scene = load_scene(folder)
    views = scene.train_views
    # Depth ranks and dark channels do not change with the training frame's similarity transform.
    return haze_evidence([torch.from_numpy(v.load_image()) for v in views], [v.camera for v in views],
                         scene.points, cfg.dcp_patch, cfg.auto_dark_threshold, cfg.auto_depth_corr).present


def seed_name(variant: str, seed: int) -> str:
    """The run name of ``variant`` trained with ``seed``: seed 0 unmarked (``csm+plm``), any other marked
    (``csm+plm@s1``); :func:`train_all` trains it with that seed."""
    return variant if seed == 0 else f"{variant}{SEED_MARK}{seed}"


def split_seed(name: str) -> tuple[str, int]:
    """``(variant, seed)`` of a run name made by :func:`seed_name` (``csm+plm@s1`` -> ``("csm+plm", 1)``)."""
    variant, _, seed = name.partition(SEED_MARK)
    return variant, int(seed or 0)


def variant_jobs(cells: list[tuple[str, str, Path]], preset: str, quick: bool,
                 seeds: Sequence[int] = TRAIN_SEEDS) -> list:
    """The four variants of each cell (``quick``: only the PLM pair at the current haze decision), the PLM pairs
    first, so a run cut short has the particle decision's evidence and gains for every cell.  The PLM pair is
    trained with every one of ``seeds``; CSM's other state with the first only (its gains are several dB)."""
    pairs, rest = [], []
    for cell in cells:
        hazy = current_haze(cell[2], preset)
        for seed in seeds:
            for name, (csm, plm) in VARIANTS.items():
                if csm == hazy:
                    pairs.append((cell, seed_name(name, seed), variant_overrides(csm, plm)))
                elif seed == seeds[0]:
                    rest.append((cell, seed_name(name, seed), variant_overrides(csm, plm)))
    return pairs if quick else pairs + rest


def _cuts(values, lo: float, hi: float) -> list[float]:
    """Candidate thresholds in [lo, hi], highest first: below every value, half-way between neighbours, above all."""
    v = np.unique(np.asarray(values, np.float64))
    cuts = np.clip([v[0] - 1, *((v[:-1] + v[1:]) / 2), v[-1] + 1], lo, hi)
    return sorted({float(x) for x in cuts}, reverse=True)


def _round(x: float, keep) -> float:
    """``x`` to the fewest significant digits (2 to 6) for which ``keep(rounded)`` still holds."""
    for digits in range(2, 7):
        r = float(f"{x:.{digits}g}")
        if keep(r):
            return r
    return x


@dataclasses.dataclass(frozen=True)
class Choice:
    """A derived rule: its ``thresholds``, the validation dB it gives away (``shortfall``: the summed PSNR of the
    better state not taken), its declarations on cells that gain less than :data:`MIN_GAIN_DB` (``false``), its
    ``margin`` (how far, in spreads of the evidence, every threshold can move before a cell's decision changes)
    and whether the ``current`` defaults were ``kept``."""

    thresholds: tuple
    shortfall: float
    false: int
    margin: float
    kept: bool


def spread(values: np.ndarray) -> float:
    """A threshold's unit for :func:`margin`: the standard deviation of its evidence (its magnitude when all
    cells show the same value, 1 when that is 0)."""
    v = np.asarray(values, np.float64)
    return float(v.std()) or float(np.abs(v).max(initial=0.0)) or 1.0


def margin(declare, t: tuple, scale: np.ndarray, top: float = 10.0) -> float:
    """How far (in units of ``scale`` per threshold) every threshold of ``t`` can move, all at once and either
    way, before ``declare`` decides a cell differently.  ``declare`` is monotone (a higher threshold never declares
    more), so moving all down and all up are the extremes."""
    same = declare(t)
    t0 = np.asarray(t, np.float64)

    def holds(d):
        return (declare(tuple(t0 - d * scale)) == same).all() and (declare(tuple(t0 + d * scale)) == same).all()

    if holds(top):
        return top
    lo, hi = 0.0, top
    for _ in range(40):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if holds(mid) else (lo, mid)
    return lo


def shortfall(gains: np.ndarray, declared: np.ndarray) -> float:
    """The dB a set of decisions gives away against the better state of each cell (summed over the cells)."""
    return float(np.where(declared, np.maximum(-gains, 0), np.maximum(gains, 0)).sum())


def choose(gains: np.ndarray, declare, candidates: list[tuple], current: tuple, scale: np.ndarray) -> Choice:
    """The rule of the module docstring.

    ``gains``: per cell, forced on minus forced off (dB); ``declare(thresholds)`` gives the declared cells (bool
    array; monotone); ``candidates`` are tried in order of preference (the first of equally good ones wins);
    ``scale``: each threshold's unit for :func:`margin` (the spread of its evidence).
    """
    needed = gains >= MIN_GAIN_DB

    def score(t):
        d = declare(t)
        if (needed & ~d).any():
            return None
        return shortfall(gains, d), int((d & ~needed).sum())

    scored = [(score(t), t) for t in candidates]
    feasible = [(s, t) for s, t in scored if s is not None]
    least = min(s[0] for s, _ in feasible)
    tied = [(s, t) for s, t in feasible if s[0] <= least + 1e-9]
    widest = [(s, t, margin(declare, t, scale)) for s, t in tied]
    s, t, m = max(widest, key=lambda x: x[2])  # max() keeps the first of equal margins
    cur = score(current)
    if cur is not None and cur[0] <= least + 1e-9:
        m_cur = margin(declare, current, scale)
        if m_cur >= m / 2:  # as good, and not on the edge of a decision: no churn
            return Choice(tuple(current), cur[0], cur[1], m_cur, True)
    same = declare(t)
    rounded = tuple(_round(x, lambda r, i=i: (declare(t[:i] + (r,) + t[i + 1:]) == same).all())
                    for i, x in enumerate(t))
    t = rounded if (declare(rounded) == same).all() else t
    return Choice(t, s[0], s[1], margin(declare, t, scale), False)


def derive_haze(cells: list[Cell], current: tuple[float, float]) -> Choice:
    from nimbus.methods.nimbusgs.auto import haze_present

    if not all(c.complete for c in cells):  # no CSM gains without both CSM states
        return Choice(tuple(current), float("nan"), -1, float("nan"), True)

    gains = np.array([c.csm_gain for c in cells])
    dm = np.array([c.dark_median for c in cells])
    corr = np.array([c.dark_depth_corr for c in cells])

    def declare(t):
        return np.array([haze_present(a, b, *t) for a, b in zip(dm, corr)])

    # Highest thresholds first: of equally good rules, the one declaring haze least readily.  The dark
    # threshold's half also counts (thin veil with a depth correlation).
    dark_cuts = sorted({*_cuts(dm, 0, 1), *(min(2 * x, 1.0) for x in _cuts(dm, 0, 1))}, reverse=True)
    return choose(gains, declare, [(d, c) for d in dark_cuts for c in _cuts(corr, -1, 1)], current,
                  np.array([spread(dm), spread(corr)]))


def particle_rule(cells: list[Cell], hazy: np.ndarray, group: bool):
    """``(gains, declare, scale, (asymmetry, energy))`` of the particle pair over the cells in ``group`` (hazy or
    not): PLM's gains, the cells a pair of thresholds declares, the :func:`spread` of each kind of evidence, and
    the evidence."""
    sub = [c for c, h in zip(cells, hazy) if h == group]
    gains = np.array([c.plm_gain(group) for c in sub])
    asym = np.array([c.particles[group][0] for c in sub])
    energy = np.array([c.particles[group][1] for c in sub])

    def declare(t):
        return (asym >= t[0]) & (energy >= t[1])

    return gains, declare, np.array([spread(asym), spread(energy)]), (asym, energy)


def derive_particles(cells: list[Cell], hazy: np.ndarray, group: bool,
                     current: tuple[float, float]) -> tuple[Choice, np.ndarray]:
    """The particle pair of the cells in ``group`` (hazy or not) and the cells it declares."""
    gains, declare, scale, (asym, energy) = particle_rule(cells, hazy, group)
    cands = [(a, e) for a in _cuts(asym, -1, 1) for e in _cuts(energy, 0, np.inf)]
    choice = choose(gains, declare, cands, current, scale)
    return choice, declare(choice.thresholds)


def _cell_table(cells: list[Cell], hazy: np.ndarray) -> list[str]:
    lines = [f"{'cell':<24} {'dark':>6} {'corr':>6} {'csm dB':>7} {'asym':>6} {'energy':>8} {'plm dB':>7}  "
             "PSNR csm+plm / csm / plm / none"]
    for c, h in zip(cells, hazy):
        a, e = c.particles[bool(h)]
        p = " / ".join(f"{c.psnr[v]:.2f}" if v in c.psnr else "-" for v in VARIANTS)
        csm = f"{c.csm_gain:+7.2f}" if c.complete else f"{'-':>7}"
        lines.append(f"{c.data + ' ' + c.setting:<24} {c.dark_median:6.3f} {c.dark_depth_corr:6.2f} "
                     f"{csm} {a:6.3f} {e:8.5f} {c.plm_gain(bool(h)):+7.2f}  {p}")
    return lines


def report_derivation(cells: list[Cell], large: bool = False) -> None:
    """Derive and print the haze rule and the particle pairs; ``large``: the cells' views hold at least
    ``auto_large_view_pixels`` pixels, so the hazy pair derived is the ``_large`` one."""
    from nimbus.methods.nimbusgs.auto import haze_present
    from nimbus.methods.nimbusgs.config import NimbusConfig as C

    haze = derive_haze(cells, (C.auto_dark_threshold, C.auto_depth_corr))
    dark, corr = haze.thresholds
    hazy = np.array([haze_present(c.dark_median, c.dark_depth_corr, dark, corr) for c in cells])
    note = (f"{haze.false} cells declared hazy that gain < {MIN_GAIN_DB} dB from CSM, {haze.shortfall:.2f} dB "
            f"given away, margin {haze.margin:.2f}" if haze.false >= 0
            else "not derived: one CSM state per cell (--quick, --store)")
    print(f"haze rule: auto_dark_threshold={dark} auto_depth_corr={corr} "
          f"({'current kept; ' if haze.kept else ''}{note})")
    print("\n".join(_cell_table(cells, hazy)))
    hazy_suffix = "_haze_large" if large else "_haze"
    for group, fields in ((False, ("auto_particle_threshold", "auto_particle_energy")),
                          (True, ("auto_particle_threshold" + hazy_suffix, "auto_particle_energy" + hazy_suffix))):
        sub = [c for c, h in zip(cells, hazy) if h == group]
        name = "hazy" if group else "haze-free"
        if not sub:
            print(f"{name} cells: none")
            continue
        current = (getattr(C, fields[0]), getattr(C, fields[1]))
        choice, declared = derive_particles(cells, hazy, group, current)
        (a, e), (gains, declare, scale, _) = choice.thresholds, particle_rule(cells, hazy, group)
        needed = [c for c in sub if c.plm_gain(group) >= MIN_GAIN_DB]
        without = [f"{c.data} {c.setting}" for c in needed if not {"R", "S"} & set(c.setting.split("+"))]
        print(f"{name} cells ({len(sub)}): {len(needed)} gain >= {MIN_GAIN_DB} dB from PLM ({len(without)} without "
              f"particles{': ' + ', '.join(without) if without else ''}); {fields[0]}={a} {fields[1]}={e} "
              f"({'current kept; ' if choice.kept else ''}{int(declared.sum())} declared, {choice.false} of them gain "
              f"less; {choice.shortfall:.2f} dB given away over the {len(sub)}, margin {choice.margin:.2f})")
        if not choice.kept:
            now = declare(current)
            print(f"  the current {current[0]} / {current[1]} here: {int(now.sum())} declared, "
                  f"{int(((gains >= MIN_GAIN_DB) & ~now).sum())} needed cells missed, {shortfall(gains, now):.2f} dB "
                  f"given away, margin {margin(declare, current, scale):.2f}")


def report_checks(cells: list[Cell], recs: dict, base: dict, seed: int = 0) -> None:
    """What each default is worth (default minus the ``--checks`` run), per cell the check ran on; ``base``: the
    derivation's runs, whose run with training ``seed`` (the checks') is the default."""
    for name in CHECKS:
        rows = []
        for c in cells:
            rec = recs.get((c.data, c.setting, seed_name(name, seed)))
            if rec is None:  # a haze-only check on a haze-free cell
                continue
            variant = "csm+plm" if "csm" in rec["components"] else "plm"
            base_psnr = base[(c.data, c.setting, seed_name(variant, seed))]["psnr"]
            rows.append((f"{c.data} {c.setting}", base_psnr - rec["psnr"]))
        d = np.array([x for _, x in rows])
        print(f"default minus {name}: mean {d.mean():+.3f} dB, min {d.min():+.3f}, max {d.max():+.3f}, "
              f"{int((d > 0).sum())} of {len(d)} cells better with the default")
        print("  " + ", ".join(f"{n} {x:+.2f}" for n, x in rows))


def report_auto(cells: list[Cell]) -> None:
    """``auto``'s choice under the current defaults against the best forced variant, per cell."""
    from nimbus.methods.nimbusgs.auto import haze_present, particle_thresholds
    from nimbus.methods.nimbusgs.config import NimbusConfig

    cfg = NimbusConfig()
    short = 0
    for c in cells:
        hazy = haze_present(c.dark_median, c.dark_depth_corr, cfg.auto_dark_threshold, cfg.auto_depth_corr)
        if hazy not in c.particles:
            print(f"{c.data + ' ' + c.setting:<24} auto's CSM state ({hazy}) not run")
            continue
        a, e = c.particles[hazy]
        ta, te = particle_thresholds(cfg, hazy)
        choice = {on: name for name, on in VARIANTS.items()}[(hazy, bool(a >= ta and e >= te))]
        best, top = c.best()
        gap = top - c.psnr[choice]
        short += gap >= MIN_GAIN_DB
        flag = "  <-- auto >= %.1f dB below the best" % MIN_GAIN_DB if gap >= MIN_GAIN_DB else ""
        print(f"{c.data + ' ' + c.setting:<24} auto {choice:<8} {c.psnr[choice]:6.2f}  best {best:<8} {top:6.2f}"
              f"  gap {gap:.2f}{flag}")
    print(f"{short} of {len(cells)} cells with auto >= {MIN_GAIN_DB} dB below the best variant"
          + ("" if all(c.complete for c in cells) else " that ran (--quick: the PLM pair only)"))


def report_cells(root: Path, sizes: list[str]) -> list[tuple[str, str, Path]]:
    """The benchmark's own cells (seed 0 data under ``root``, prepared as the grid does), seven settings."""
    from benchmark.cell import Cell as GridCell
    from benchmark.cell import data_dir, prepare_data
    from weather_synth.settings import ALL_SETTING_NAMES

    grid = [GridCell(s, w, METHOD, "tiny", 0, size) for size in sizes for s in SCENES for w in ALL_SETTING_NAMES]
    prepare_data(root, grid, progress=False)
    return [(c.data_name, c.weather, data_dir(root, c)) for c in grid]


def store_cells(root: Path) -> list[Cell]:
    """The hazy cells of a benchmark store holding ``nimbus`` and ``nimbus-no-plm`` runs of the same cells
    (``--store``): each pair's PSNR as PLM on (``csm+plm``) and off (``csm``), and the ``nimbus`` run's stage-1
    evidence.  Raises NimbusError when the store is missing, holds the benchmark's own scenes (seed 0), or has no
    pair whose ``nimbus`` run built CSM."""
    import json

    from benchmark.store import ResultsStore, record_data_name, require_store
    from nimbus.errors import NimbusError
    from nimbus.schemas import SceneManifest, read_json_file

    require_store(root)
    for manifest in sorted((root / "scenes").glob("*/manifest.json")):
        if read_json_file(manifest, SceneManifest, "delete the scene folder to render it again")["seed"] == 0:
            raise NimbusError(f"{manifest.parent} is the benchmark's own scene (seed 0), reported and never tuned "
                              "on; give a store of validation scenes (seed >= 1)")
    ok = [r for r in ResultsStore(root).latest().values() if r.get("status") == "ok"]
    key = ("scene", "size", "weather", "preset", "seed")
    runs = {((*(r[k] for k in key), json.dumps(r.get("overrides") or {}, sort_keys=True)), r["method"]): r
            for r in ok}
    cells = []
    for (cell, method), on in sorted(runs.items()):
        off = runs.get((cell, "nimbus-no-plm"))
        if method != "nimbus" or off is None:
            continue
        name = record_data_name(on)  # a folder name: refused unless scene and size are single names
        if not (root / "scenes" / name / "manifest.json").is_file():
            raise NimbusError(f"{root}/scenes/{name} is missing: the store's scene seed cannot be "
                              "checked (the benchmark's own scenes, seed 0, are never tuned on)")
        if "csm" not in on.get("components", []):
            continue  # auto left the cell haze-free: PLM's gain there is not the hazy pair's
        results = root / "runs" / on["cell_id"] / "results.json"  # the store refuses an id that is not one name
        try:
            ev = json.loads(results.read_text())["nimbus"]
        except (OSError, ValueError, KeyError) as exc:
            raise NimbusError(f"{results}: no NimbusGS evidence to read ({exc})") from None
        haze, part = ev["haze_evidence"], ev["particle_evidence"]
        cells.append(Cell(name, cell[2], {"csm+plm": float(on["psnr"]), "csm": float(off["psnr"])},
                          float(haze["dark_median"]), float(haze["dark_depth_corr"]),
                          {True: (float(part["asymmetry"]), float(part["energy"]))}))
    if not cells:
        raise NimbusError(f"{root} holds no hazy cell with both a nimbus and a nimbus-no-plm run; make them with "
                          "nimbus-bench run --root ROOT --methods nimbus,nimbus-no-plm --weathers H,H+R,H+S ...")
    return cells


def parse_seeds(text: str, flag: str = "--seeds", least: int = 0) -> list[int]:
    """``--seeds`` (training) or ``--scene-seeds``: distinct integers >= ``least`` (CSM's other state trains with
    the first training seed)."""
    from nimbus.errors import NimbusError

    try:
        seeds = [int(s) for s in text.split(",") if s.strip()]
    except ValueError:
        seeds = []
    if not seeds or len(set(seeds)) != len(seeds) or min(seeds) < least:
        extra = (" (0 is the benchmark's own data, reported and never tuned on; --report shows auto on it)"
                 if least else "")
        raise NimbusError(f"{flag} {text!r}: give distinct integers >= {least}, e.g. {flag} {least},{least + 1}"
                          f"{extra}")
    return seeds


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.auto_thresholds", description=__doc__.split("\n")[0])
    parser.add_argument("--root", default=None, help="where the scenes are (made): default auto-validation, or "
                        "auto-report with --report")
    parser.add_argument("--sizes", default="tiny", help="built-in scene sizes, comma-separated")
    parser.add_argument("--preset", default="tiny", help="training preset")
    parser.add_argument("--cache", default=None, help="per-run JSON figures (default ROOT/runs)")
    parser.add_argument("--jobs", type=int, default=1, help="runs trained at once")
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads per run")
    parser.add_argument("--checks", action="store_true",
                        help="also what the top-hat cap, the outlier scope and the per-pixel airlight are worth")
    parser.add_argument("--quick", action="store_true", help="only the PLM pair at the current haze decision "
                        "(no CSM gains: the haze rule is not derived)")
    parser.add_argument("--seeds", default=",".join(map(str, TRAIN_SEEDS)),
                        help="training seeds of the PLM pair, comma-separated (gains and evidence averaged)")
    parser.add_argument("--scene-seeds", default=",".join(map(str, SCENE_SEEDS)),
                        help="scene and synthesis seeds of the validation scenes, comma-separated, each's scenes "
                        "under ROOT/seed-N (the benchmark's data use 0)")
    parser.add_argument("--report", action="store_true", help="auto on the benchmark's seed-0 cells (report only)")
    parser.add_argument("--store", default=None, metavar="ROOT",
                        help="derive the hazy particle pair from a benchmark store's nimbus / nimbus-no-plm runs "
                        "(trains nothing)")
    args = parser.parse_args(argv)
    if args.store:
        from nimbus.data.builtin import get_size
        from nimbus.methods.nimbusgs.config import NimbusConfig

        cells = store_cells(Path(args.store))
        pixels = [get_size(c.data.rsplit("-", 1)[1]) for c in cells]
        large = {p.width * p.height >= NimbusConfig.auto_large_view_pixels for p in pixels}
        if len(large) > 1:
            from nimbus.errors import NimbusError

            raise NimbusError(f"{args.store} mixes views below and above auto_large_view_pixels "
                              f"({NimbusConfig.auto_large_view_pixels}); give one store per side")
        report_derivation(cells, large=large.pop())
        return 0
    root = Path(args.root or ("auto-report" if args.report else "auto-validation"))
    sizes = [s.strip() for s in args.sizes.split(",") if s.strip()]
    from nimbus.data.builtin import get_size

    for size in sizes:  # an unknown size is one error line, before anything is written
        get_size(size)
    seeds = parse_seeds(args.seeds)
    scene_seeds = parse_seeds(args.scene_seeds, "--scene-seeds", least=1)
    cells = report_cells(root, sizes) if args.report else cell_folders(root, sizes, scene_seeds)
    cache = Path(args.cache) if args.cache else root / "runs"
    cache.mkdir(parents=True, exist_ok=True)
    recs = train_all(variant_jobs(cells, args.preset, args.quick, seeds), cache, args.preset, args.jobs,
                     args.threads)
    gathered = gather(cells, recs, seeds)
    if args.report:
        report_auto(gathered)
        return 0
    report_derivation(gathered)
    if args.checks:
        jobs = []
        for cell in cells:  # PLM on, CSM as the current haze rule decides
            if cell[1] == CLEAN:
                continue
            hazy = current_haze(cell[2], args.preset)
            jobs += [(cell, seed_name(name, seeds[0]), variant_overrides(hazy, True, extra))
                     for name, extra in CHECKS.items() if hazy or name not in HAZE_ONLY_CHECKS]
        checks = train_all(jobs, cache, args.preset, args.jobs, args.threads)
        report_checks([c for c in gathered if c.setting != CLEAN], checks, recs, seeds[0])
    return 0

if __name__ == "__main__":
    raise SystemExit(run_cli(main))
