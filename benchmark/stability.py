"""The stability report (``nimbus-bench stability``): extreme inputs through synthesis, training and scoring.

Each :class:`StabilityCase` makes one input dataset from the tiny built-in scene -- by
synthesising weather with extreme (or out-of-range) parameters, by rewriting the
scene (all-black or all-white images, one training view, every sparse point at one
spot), or by leaving it clean and overriding trainer settings so that the Gaussians
degenerate -- and runs each of its methods on it, scored against the clean test views.

Every (case, method) ends in one of three outcomes:

``finished``
    training and scoring completed; PSNR / SSIM / LPIPS are recorded.
``clear error``
    a :class:`~nimbus.errors.NimbusError` stopped it: the message a user would see.
``crash``
    any other exception: a bug (its type and message are recorded, the traceback in the JSON).

Besides the outcome, every row says whether a NaN or inf was seen anywhere: in the
synthesised layers and manifest, in the training log's losses, in ``results.json``, in the
trained parameters (Gaussians, extinction field, airlight), in renders of the test views
(and, for NimbusGS, the medium composition of a training view), or in the metrics.  An
infinite PSNR (a render equal to the ground truth) is a value, not a NaN.

A row fails when it crashed, when it saw a NaN / inf and did not stop with a clear error,
or when it contradicts its case's expectation (e.g. an out-of-range parameter that does not
end in a clear error).  The command exits 1 when any row fails.

Outputs, written atomically into ``--out``: ``stability.csv`` and ``stability.md`` (the
table: :data:`COLUMNS`) and ``stability.json`` (every row with its details and tracebacks).
"""

from __future__ import annotations

import dataclasses
import json
import math
import shutil
import sys
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import numpy as np

from benchmark.cell import SYNTH_PROTOCOL, SYNTH_SEED
from benchmark.report import shorten
from benchmark.tables import writer
from benchmark.tables.model import Block, Column, LongFormat, Row, Table
from nimbus.cli_util import pick_by_name
from nimbus.errors import NimbusError

OUTCOMES = ("finished", "clear error", "crash")
EXPECTATIONS = ("finished", "clear error", "either")
DEFAULT_METHODS = ("nimbus", "3dgs")
DEFAULT_SCENE = "garden"
DEFAULT_SIZE = "tiny"
DEFAULT_PRESET = "tiny"
#: Training iterations of every run (the preset's schedule is rescaled to it): enough to pass
#: densification, pruning, NimbusGS's stage switch and residual refreshes, short enough that the
#: whole report takes a minute or two on a CPU.
DEFAULT_ITERATIONS = 100
#: Names this command in its --out folder's marker: --overwrite replaces only a folder it wrote itself.
OWNER = "nimbus-bench stability"
TRAIN_SEED = 0
COLUMNS = ("case", "method", "expected", "outcome", "stage", "message", "nan_seen", "nan_where", "psnr", "ssim",
           "lpips", "seconds", "verdict")
#: Characters of an error message kept in the Markdown table (the CSV and JSON keep all of it).
MD_MESSAGE_CHARS = 140


# --- cases -----------------------------------------------------------------------------------
@dataclass(frozen=True)
class StabilityCase:
    """One extreme input and the methods run on it.

    Attributes
    ----------
    name : str
        Identifier (file-name safe), e.g. ``opaque_haze``.
    description : str
        What is extreme about it, one line.
    weather : str or None
        Weather setting synthesised from the clean scene (``H``, ``R+S``, ...;
        :mod:`weather_synth.settings`) with the ``onerestore`` protocol; None keeps the clean images.
    synth : tuple of str
        ``key=value`` synthesis overrides (``nimbus-synth degrade --set``), e.g. ``haze.beta=Infinity``.
    fill : float or None
        Replace every input image by this grey value in [0, 1] (0: black, 1: white).
    train_views : int or None
        Keep only the first this-many training views (the test views stay, for scoring).
    collapse_points : bool
        Move every sparse point to their centroid: the Gaussians start at one spot with the
        smallest scale, all at the same depth, inside a box most rays miss.
    train : tuple of (str, str)
        Trainer ``--set`` overrides applied on top of the preset.
    methods : tuple of str
        Registered methods run on the input.
    expect : str
        ``finished``, ``clear error`` or ``either`` (both are acceptable ends).
    """

    name: str
    description: str
    weather: str | None = None
    synth: tuple[str, ...] = ()
    fill: float | None = None
    train_views: int | None = None
    collapse_points: bool = False
    train: tuple[tuple[str, str], ...] = ()
    methods: tuple[str, ...] = DEFAULT_METHODS
    expect: str = "either"

    def __post_init__(self) -> None:
        if self.expect not in EXPECTATIONS:
            raise ValueError(f"expect must be one of {EXPECTATIONS}, got {self.expect!r}")
        if self.fill is not None and not 0.0 <= self.fill <= 1.0:
            raise ValueError(f"fill must be in [0, 1], got {self.fill}")
        if self.train_views is not None and self.train_views < 1:
            raise ValueError(f"train_views must be >= 1, got {self.train_views}")
        if self.synth and self.weather is None:
            raise ValueError(f"case {self.name}: synthesis overrides need a weather setting")

    @property
    def rewrites(self) -> bool:
        """Whether the input scene is rewritten after synthesis."""
        return self.fill is not None or self.train_views is not None or self.collapse_points

    @property
    def input_summary(self) -> str:
        """How the input is made, for the table's legend."""
        parts = [f"synthesised {self.weather}" + (f" ({', '.join(self.synth)})" if self.synth else "")
                 if self.weather else "clean scene"]
        if self.fill is not None:
            parts.append(f"every image set to {self.fill:g}")
        if self.train_views is not None:
            parts.append(f"{self.train_views} training view(s)")
        if self.collapse_points:
            parts.append("sparse points collapsed to one")
        if self.train:
            parts.append("trainer " + ", ".join(f"{k}={v}" for k, v in self.train))
        return "; ".join(parts)


# Methods that exercise every NimbusGS component (auto may switch some off on these inputs).
_ALL_COMPONENTS = ("nimbus", "nimbus-full", "3dgs")

#: The report's cases: the issue's extremes (no haze, opaque haze, black / white inputs, one
#: view, huge particle density, degenerate Gaussians) plus NimbusGS's own (T ~ 0, every
#: Gaussian pruned, rays that miss the box, d_max = d_min, MAD = 0) and out-of-range settings.
CASES: tuple[StabilityCase, ...] = (
    StabilityCase("no_haze", "haze with beta = 0: the input is the clean scene, the medium must vanish",
                  weather="H", synth=("haze.beta=0",), expect="finished"),
    StabilityCase("opaque_haze", "onerestore haze with beta = inf: T = 0 over most pixels, the input is airlight",
                  weather="H", synth=("haze.beta=Infinity",)),
    StabilityCase("opaque_height_fog", "physical height fog of infinite density: T = 0 everywhere",
                  weather="H", synth=("haze.mode=heterogeneous", "haze.beta=Infinity")),
    StabilityCase("particle_storm", "rain and snow 100x denser than the preset: the input is nearly white",
                  weather="R+S", synth=("rain.density_scale=100", "snow.amount=100")),
    StabilityCase("black_inputs", "every input image black: no haze evidence, a flat error for GGS", fill=0.0,
                  methods=_ALL_COMPONENTS),
    StabilityCase("white_inputs", "every input image white: dark channel = 1, a flat error for GGS", fill=1.0,
                  methods=_ALL_COMPONENTS),
    StabilityCase("one_view", "a single training view (no neighbour for the view-consistency check)",
                  weather="H", train_views=1, methods=_ALL_COMPONENTS),
    StabilityCase("collapsed_points", "hazy input, every sparse point at one spot: d_max = d_min, a tiny box "
                  "most rays miss", weather="H", collapse_points=True, methods=_ALL_COMPONENTS),
    StabilityCase("all_pruned", "initial opacity below the pruning threshold: every Gaussian is pruned",
                  train=(("init_opacity", "1e-4"),)),
    StabilityCase("exploding_scales", "scale learning rate 10^4 x the default: Gaussians blow up",
                  train=(("lr_scales", "50"),)),
    StabilityCase("nothing_visible", "near plane beyond the scene: no Gaussian is ever visible",
                  train=(("near_plane", "1e6"),)),
    StabilityCase("negative_haze_beta", "out-of-range synthesis parameter (beta = -1)", weather="H",
                  synth=("haze.beta=-1",), expect="clear error"),
    StabilityCase("bad_trainer_setting", "out-of-range trainer setting (lambda_dssim = 2)",
                  train=(("lambda_dssim", "2"),), expect="clear error"),
)


def get_cases(spec: str | None = None) -> list[StabilityCase]:
    """Cases by comma-separated name (None or ``all``: every case), in :data:`CASES` order."""
    return pick_by_name(CASES, spec, "stability case", "nimbus-bench stability --list")


# --- options and rows --------------------------------------------------------------------------
@dataclass(frozen=True)
class StabilityOptions:
    """How every case is run.

    Attributes
    ----------
    scene, size : str
        Built-in scene and size the inputs are made from.
    preset : str
        Trainer preset of every method.
    iterations : int
        Training iterations (the preset's schedule is rescaled to it).
    methods : tuple of str or None
        Run only these of each case's methods (None: all of them).
    ssim_protocol : str
        :data:`nimbus.metrics.SSIM_PROTOCOLS` name.
    lpips_net : str or None
        ``vgg``, ``alex`` or None (no LPIPS).
    device : str or None
        torch device for training (None: CUDA when available, else CPU).
    """

    scene: str = DEFAULT_SCENE
    size: str = DEFAULT_SIZE
    preset: str = DEFAULT_PRESET
    iterations: int = DEFAULT_ITERATIONS
    methods: tuple[str, ...] | None = None
    ssim_protocol: str = "3dgs"
    lpips_net: str | None = "vgg"
    device: str | None = None


def _row(case: StabilityCase, method: str) -> dict:
    return {"case": case.name, "method": method, "expected": case.expect, "outcome": None, "stage": "",
            "message": "", "nan_seen": False, "nan_where": [], "psnr": None, "ssim": None, "lpips": None,
            "seconds": 0.0, "verdict": None}


def verdict(row: dict) -> str:
    """``ok``, or why the row fails the report."""
    if row["outcome"] == "crash":
        return "FAIL: crash"
    if row["nan_seen"] and row["outcome"] != "clear error":
        return "FAIL: NaN / inf without a clear error"
    if row["expected"] != "either" and row["outcome"] != row["expected"]:
        return f"FAIL: expected {row['expected']}"
    return "ok"


# --- NaN / inf detection ----------------------------------------------------------------------
def _nonfinite_in(obj: Any, allow_inf: frozenset[str] | bool = frozenset(), key: str = "") -> bool:
    """Whether a JSON-like object holds a NaN, or an inf under a key not in ``allow_inf`` (True: any key)."""
    if isinstance(obj, dict):
        return any(_nonfinite_in(v, allow_inf, str(k)) for k, v in obj.items())
    if isinstance(obj, (list, tuple)):
        return any(_nonfinite_in(v, allow_inf, key) for v in obj)
    if isinstance(obj, (float, np.floating)):
        inf_ok = allow_inf is True or (allow_inf is not False and key in allow_inf)
        return math.isnan(obj) or (math.isinf(obj) and not inf_ok)
    return False


# An identical render and ground truth have an infinite PSNR: a value, not a failure.
_PSNR_KEYS = frozenset({"psnr"})


def _read_json(path: Path) -> Any:
    return json.loads(path.read_text())  # Python's json reads NaN / Infinity tokens


def synthesis_nonfinite(data: Path) -> bool:
    """NaN in a synthesised setting folder's manifest, NaN / inf in its layer archives.

    An infinite depth (``depth``, ``rain_depth``, ``snow_depth``: sky, no particle) and an
    infinite parameter in the manifest (``haze.beta=Infinity``) are values, not failures.
    """
    if (data / "manifest.json").is_file() and _nonfinite_in(_read_json(data / "manifest.json"), allow_inf=True):
        return True
    for f in sorted((data / "layers").glob("*.npz")):
        with np.load(f) as z:
            for k in z.files:
                bad = np.isnan(z[k]) if k.endswith("depth") else ~np.isfinite(z[k])
                if bad.any():
                    return True
    return False


def log_nonfinite(run: Path) -> bool:
    """NaN / inf among the numbers of the training log (losses, PSNR, counts)."""
    log = run / "train_log.jsonl"
    if not log.is_file():
        return False
    return any(_nonfinite_in(json.loads(line), _PSNR_KEYS) for line in log.read_text().splitlines() if line.strip())


def model_nonfinite(model) -> list[str]:
    """Where a trained model holds NaN / inf: ``parameters`` (every optimised tensor) and ``renders``
    (the test views and, for a method with a medium, the medium composition of a training view)."""
    import torch

    from benchmark.cell import medium_composition, model_parameters

    where = []
    with torch.no_grad():
        if any(not torch.isfinite(p).all() for p in model_parameters(model)):
            where.append("parameters")
        if model.method.num_gaussians == 0:
            return where
        outputs = []
        views = model.scene.test_views or model.scene.train_views
        for view in views:
            render = model.method.render(view.camera)
            outputs += [render["rgb"], render["depth"], render["alpha"]]
        outputs += list(medium_composition(model).values())
        if any(not torch.isfinite(t).all() for t in outputs):
            where.append("renders")
    return where


# --- inputs ------------------------------------------------------------------------------------
def write_clean_scene(work: Path, options: StabilityOptions) -> Path:
    """The clean built-in scene every case starts from (written once per work folder)."""
    from benchmark.cell import write_clean_scene as write

    clean = work / "clean" / f"{options.scene}-{options.size}"
    write(options.scene, options.size, clean)
    return clean


def synthesize(case: StabilityCase, clean: Path, out: Path) -> Path:
    """The case's weather synthesised from the clean scene into ``out`` (the clean scene when it has none).

    The setting folder has the ``nimbus-synth degrade`` layout: ``images/`` the degraded
    inputs and ``clean/`` the ground truth the renders are scored against.

    Raises
    ------
    NimbusError
        A synthesis parameter is out of range (the synthesizer's own message).
    """
    from benchmark.cell import synthesize as degrade
    from nimbus.config_set import apply_overrides, parse_set_args
    from weather_synth.config import protocol_config
    from weather_synth.settings import parse_setting

    if case.weather is None:
        return clean
    config = apply_overrides(protocol_config(SYNTH_PROTOCOL, SYNTH_SEED), parse_set_args(case.synth))
    setting = parse_setting(case.weather)
    degrade(clean, out, [setting.name], config, progress=False, source=f"stability:{case.name}")
    return out / setting.name


def rewrite_scene(case: StabilityCase, source: Path, out: Path) -> Path:
    """``source`` with the case's image fill, training-view cut and point collapse, written to ``out``
    (with ``clean/`` holding the ground truth, as a synthesised setting folder)."""
    from nimbus.data.io import load_scene, write_scene_into
    from nimbus.data.scene_files import output_image_name
    from nimbus.utils.fs import atomic_dir

    scene = load_scene(source)
    truth = {v.name: (source / "clean" / v.name if (source / "clean" / v.name).is_file() else v.image_path)
             for v in scene.views}
    views = list(scene.views)
    if case.train_views is not None:
        keep = {v.name for v in scene.train_views[:case.train_views]} | set(scene.test_names)
        views = [v for v in views if v.name in keep]
    if case.fill is not None:
        views = [dataclasses.replace(v, image=np.full((v.camera.height, v.camera.width, 3), case.fill, np.float32))
                 for v in views]
    scene = scene.with_views(views)
    if case.collapse_points and len(scene.points):
        scene = dataclasses.replace(scene, points=np.repeat(scene.points.mean(0, keepdims=True), len(scene.points), 0))
    with atomic_dir(out, overwrite=True) as tmp:
        write_scene_into(scene, tmp)
        for v in scene.views:
            dst = tmp / "clean" / output_image_name(dataclasses.replace(v, image=None))
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(truth[v.name], dst)
    return out


# --- one run ---------------------------------------------------------------------------------
def run_method(case: StabilityCase, method_name: str, data: Path, run: Path, options: StabilityOptions,
               lpips=None) -> dict:
    """Train ``method_name`` on the case's input, score it and check for NaN / inf; never raises.

    ``lpips`` is a loaded :class:`nimbus.metrics.LPIPS` (or None) shared by every run.
    """
    from benchmark.cell import make_config, score_run, train_method
    from nimbus.data.io import load_scene
    from nimbus.methods.registry import get_method

    row = _row(case, method_name)
    built: list = []  # the model, once built: checked for NaN / inf even when its training fails
    stage = "set-up"
    t0 = time.perf_counter()
    try:
        config = make_config(get_method(method_name), options.preset,
                             {"iterations": str(options.iterations), **dict(case.train)})
        scene = load_scene(data)
        stage = "training"
        results, _ = train_method(method_name, scene, config, run, seed=TRAIN_SEED, scene_path=str(data),
                                  progress=False, device=options.device, model_ready=built.append)
        stage = "scoring"
        score = score_run(run, data, results, ssim_protocol=options.ssim_protocol, lpips_net=lpips,
                          device=options.device)
        row.update(outcome="finished", message="; ".join(run_notes(run, results)),
                   **_metrics(score, row["nan_where"], lpips is not None))
    except NimbusError as e:
        row.update(outcome="clear error", message=str(e))
    except Exception as e:  # recorded, not raised: the report is there to find these
        row.update(outcome="crash", message=f"{e.__class__.__name__}: {e}", traceback=traceback.format_exc())
    row["stage"] = stage if row["outcome"] != "finished" else ""
    try:
        if log_nonfinite(run):
            row["nan_where"].append("train log")
        if (run / "results.json").is_file() and _nonfinite_in(_read_json(run / "results.json"), _PSNR_KEYS):
            row["nan_where"].append("results.json")
        if built:
            row["nan_where"] += model_nonfinite(built[0])
    except Exception as e:  # a check that cannot run is a crash of the run it checks
        row.update(outcome="crash", stage="checks", message=f"{e.__class__.__name__}: {e}",
                   traceback=traceback.format_exc())
    row["seconds"] = time.perf_counter() - t0
    return row


def run_notes(run: Path, results: dict) -> list[str]:
    """What a finished run's table row should say: NimbusGS's components, iterations with nothing visible."""
    notes = []
    if "components" in results:
        notes.append(f"components: {', '.join(results['components']) or 'none'}")
    log = run / "train_log.jsonl"
    blind = sum('"no_visible_gaussians"' in line for line in log.read_text().splitlines()) if log.is_file() else 0
    if blind:
        notes.append(f"no Gaussian visible in {blind} of {results.get('iterations')} iterations")
    return notes


def _metrics(score: dict, nan_where: list[str], lpips_wanted: bool) -> dict:
    """Mean metrics of a score; a NaN metric (stored as None in JSON) is noted in ``nan_where``."""
    mean = score["mean"]
    infinite_psnr = any("PSNR is infinite" in n for n in score["notes"])
    if (mean["psnr"] is None and not infinite_psnr) or mean["ssim"] is None or \
            (lpips_wanted and mean["lpips"] is None) or any("NaN / inf" in n for n in score["notes"]):
        nan_where.append("metrics")
    psnr = float("inf") if mean["psnr"] is None and infinite_psnr else mean["psnr"]
    return {"psnr": psnr, "ssim": mean["ssim"], "lpips": mean["lpips"]}


# --- the report --------------------------------------------------------------------------------
def run_case(case: StabilityCase, clean: Path, work: Path, options: StabilityOptions, lpips=None) -> list[dict]:
    """Every row of one case: its input is made once, then each method runs on it."""
    methods = [m for m in case.methods if options.methods is None or m in options.methods]
    root = work / "cases" / case.name
    if root.exists():
        shutil.rmtree(root)
    t0 = time.perf_counter()
    stage, failure = "synthesis", None
    try:
        data = synthesize(case, clean, root / "synth")
        stage = "input"
        if case.rewrites:
            data = rewrite_scene(case, data, root / "input")
    except NimbusError as e:
        failure = {"outcome": "clear error", "message": str(e)}
    except Exception as e:
        failure = {"outcome": "crash", "message": f"{e.__class__.__name__}: {e}", "traceback": traceback.format_exc()}
    prep = time.perf_counter() - t0
    if failure is not None:
        return [dict(_row(case, m), stage=stage, seconds=prep, **failure) for m in methods]
    synth_nan = case.weather is not None and synthesis_nonfinite(data)
    rows = []
    for m in methods:
        row = run_method(case, m, data, root / "runs" / m, options, lpips)
        if synth_nan:
            row["nan_where"].insert(0, "synthesis")
        row["seconds"] += prep / len(methods)
        rows.append(row)
    return rows


def finalize(row: dict) -> dict:
    row["nan_seen"] = bool(row["nan_where"])
    row["verdict"] = verdict(row)
    return row


def run_report(cases: Sequence[StabilityCase], work: str | Path, options: StabilityOptions | None = None,
               log: Callable[[str], None] | None = None) -> list[dict]:
    """Run every case (module docstring) with scratch files under ``work``; one finished row per (case, method).

    ``log`` receives one progress line per row (default: stderr).
    """
    from nimbus.metrics import LPIPS, WeightsMissing

    options = options or StabilityOptions()
    say = log or (lambda s: print(s, file=sys.stderr, flush=True))
    work = Path(work)
    lpips = None
    if options.lpips_net is not None:
        try:
            lpips = LPIPS(options.lpips_net, device=options.device)
        except WeightsMissing as e:
            say(f"warning: LPIPS not computed ({e})")
    clean = write_clean_scene(work, options)
    total = sum(len([m for m in c.methods if options.methods is None or m in options.methods]) for c in cases)
    rows: list[dict] = []
    for case in cases:
        for row in run_case(case, clean, work, options, lpips):
            rows.append(finalize(row))
            say(format_progress(row, len(rows), total))
    return rows


def format_progress(row: dict, i: int, n: int) -> str:
    """One line per finished row."""
    head = f"[{i}/{n}] {row['case']} / {row['method']}: {row['outcome']}"
    if row["outcome"] == "finished":
        head += f", PSNR {_fmt(row['psnr'], '.2f')} SSIM {_fmt(row['ssim'], '.3f')} LPIPS {_fmt(row['lpips'], '.3f')}"
    else:
        head += f" ({row['stage']}: {shorten(row['message'], 100)})"
    nan = f", NaN/inf in {', '.join(row['nan_where'])}" if row["nan_seen"] else ""
    return f"{head}{nan}, {row['seconds']:.1f} s -> {row['verdict']}"


def _fmt(v, spec: str) -> str:
    if v is None:
        return "n/a"
    if isinstance(v, float) and math.isinf(v):
        return "inf"
    return format(v, spec)


# --- tables -----------------------------------------------------------------------------------
def _cell(row: dict, col: str) -> str:
    v = row[col]
    if col == "nan_where":
        return ", ".join(v)
    if col == "nan_seen":
        return "yes" if v else "no"
    if col in ("psnr", "ssim", "lpips", "seconds"):
        return _fmt(v, {"psnr": ".2f", "ssim": ".4f", "lpips": ".4f", "seconds": ".1f"}[col])
    return "" if v is None else str(v)


#: What stability.md shows of a row besides its case (the row label): text as the CSV has it, the message
#: shortened and NaN / inf with where it was seen.
MD_COLUMNS = tuple(Column(f"shown_{c}", c, c, align="left" if c not in ("psnr", "ssim", "lpips", "seconds") else "right")
                   for c in COLUMNS if c not in ("case", "nan_where"))
CSV_FORMAT = LongFormat("stability.csv", "the stability report, one line per (case, method)", COLUMNS)
CASE_COLUMNS = tuple(Column(k, text, text, align="left") for k, text in
                     (("input", "input"), ("expected", "expected"), ("description", "what is extreme")))


def stability_table(rows: Sequence[dict], notes: Sequence[str] = ()) -> Table:
    """The runs as a :class:`~benchmark.tables.model.Table` (one row per case x method); its CSV lines are the
    rows' fields as :data:`COLUMNS` (figures at the precision :func:`_cell` gives them)."""
    out = []
    for r in rows:
        shown = {c.key: _cell(r, c.text) for c in MD_COLUMNS}
        shown["shown_message"] = shorten(shown["shown_message"], MD_MESSAGE_CHARS)
        if r["nan_seen"]:
            shown["shown_nan_seen"] = f"yes ({_cell(r, 'nan_where')})"
        out.append(Row(r["case"], {("", k): v for k, v in shown.items()}, fields={c: _cell(r, c) for c in COLUMNS}))
    return Table("stability", "stability", "Runs", MD_COLUMNS, [""], [Block(out, ranked=False)], lead=("case",),
                 notes=list(notes), group_heads=False, csv=CSV_FORMAT)


def cases_table(cases: Sequence[StabilityCase]) -> Table:
    """The legend: each case's input, expectation and what is extreme about it."""
    rows = [Row(c.name, {("", "input"): c.input_summary, ("", "expected"): c.expect,
                         ("", "description"): c.description}) for c in cases]
    return Table("stability_cases", "stability", "Cases", CASE_COLUMNS, [""], [Block(rows, ranked=False)],
                 lead=("case",), group_heads=False)


def to_csv(rows: Iterable[dict]) -> str:
    return writer.to_csv([stability_table(list(rows))])


def to_markdown(rows: Sequence[dict], cases: Sequence[StabilityCase], options: StabilityOptions,
                wall_s: float | None = None) -> str:
    """The table with a header saying how it was made, and a legend of the cases (the table writer's Markdown)."""
    failed = [r for r in rows if r["verdict"] != "ok"]
    lines = ["# Stability report", "",
             f"Scene `{options.scene}` ({options.size}), preset `{options.preset}` rescaled to {options.iterations} "
             f"iterations, seed {TRAIN_SEED}; synthesis protocol `{SYNTH_PROTOCOL}`, seed {SYNTH_SEED}. Metrics "
             f"against the clean test views (SSIM `{options.ssim_protocol}`, LPIPS "
             f"`{options.lpips_net or 'none'}`)." + (f" Wall time {wall_s:.0f} s." if wall_s is not None else ""),
             "",
             f"{len(rows)} run(s): " + ", ".join(f"{sum(r['outcome'] == o for r in rows)} {o}" for o in OUTCOMES)
             + f"; {sum(r['nan_seen'] for r in rows)} saw NaN / inf; "
             + (f"**{len(failed)} failed**." if failed else "all ended in a result or a clear error."), ""]
    return "\n".join(lines) + writer.to_markdown(stability_table(rows)) + writer.to_markdown(cases_table(cases))


def write_report(out: str | Path, rows: Sequence[dict], cases: Sequence[StabilityCase], options: StabilityOptions,
                 overwrite: bool = False, wall_s: float | None = None) -> list[Path]:
    """``stability.csv``, ``stability.md`` and ``stability.json`` into ``out``, atomically (all or nothing)."""
    from benchmark.score import versions
    from nimbus.utils.fs import atomic_dir
    from nimbus.utils.jsonable import jsonable

    doc = {"format": "nimbus-bench-stability/1", "options": dataclasses.asdict(options), "versions": versions(),
           "wall_time_s": wall_s, "cases": [dataclasses.asdict(c) for c in cases],
           "rows": [dict(r, psnr="inf" if isinstance(r["psnr"], float) and math.isinf(r["psnr"]) else r["psnr"])
                    for r in rows]}
    names = ("stability.csv", "stability.md", "stability.json")
    with atomic_dir(out, overwrite=overwrite, owner=OWNER) as tmp:
        (tmp / names[0]).write_text(to_csv(rows))
        (tmp / names[1]).write_text(to_markdown(rows, cases, options, wall_s))
        (tmp / names[2]).write_text(json.dumps(jsonable(doc), indent=2, sort_keys=True) + "\n")
    return [Path(out) / n for n in names]
