"""The benchmark's HTML report (``nimbus-bench report``): one static page and its thumbnails for a results store.

Written into ``OUT``::

    OUT/index.html      one self-contained page: inline CSS and JavaScript, no network, opens from disk
    OUT/images/         downscaled thumbnails (JPEG, at most :data:`THUMB_WIDTH` px wide) and their
                        difference-to-clean versions; the trade-off plot when the store has one

Sections:

* **Summary**: per weather setting x method, the mean PSNR / SSIM / LPIPS / training time over the
  finished cells (every scene and seed, as ``nimbus-bench run`` prints it), with cell and error
  counts; best and second best marked per setting; sortable by clicking a column head.  Where the
  records carry the degraded input's own score (:mod:`benchmark.tables.inputs`) an ``Input PSNR`` column
  gives each row the PSNR of the degraded test views themselves.  With clean-ceiling cells
  (:mod:`benchmark.tables.ceiling`) the ceiling is the first block and a ``ΔPSNR vs clean`` column gives
  each row's gap to it.
* **Test views**: per scene and setting, a few test views (:attr:`ReportOptions.views`, evenly
  spaced over the split): the degraded input, each cell's render (the clean ceiling's too), the
  clean view, each captioned with its PSNR against the clean view (the record's per-view value where
  it has one, else computed here with the benchmark's protocol,
  :func:`nimbus.metrics.peak_signal_noise_ratio`).  Clicking an image enlarges it; a switch shows
  ``|image - clean| x`` :data:`DIFF_GAIN` instead.
* **NimbusGS**: for every cell whose run folder holds a NimbusGS record, the component decision
  (``auto`` or forced) with its evidence (``results.json``), and the decomposition I_in | clean
  render | T | P | R of a few training views (``decomposition/*.png``, written by
  :meth:`nimbus.methods.nimbusgs.NimbusGS.write_outputs`).
* **Decomposition against the ground truth**: per cell whose run folder holds a ``nimbus-bench decompose``
  record (``RUN/decompose/decompose.json``), its table of learned T, airlight and clean-render bias per depth
  band (:mod:`benchmark.tables.decompose`); the cells of medium-modelling methods on a hazy setting that have
  none are listed with the command that makes it (the report reads records; it loads no model).
* **Trade-off** and **stability**: the files ``nimbus-bench tradeoff`` / ``stability`` wrote, when
  found in ``ROOT/`` or ``ROOT/*/`` (or given): the Pareto plot and the tables.
* **Provenance**: the commands that reproduce the cells (rebuilt from the records: the store keeps
  no command lines), seeds, protocols, software versions, and every cell's record in brief.

The page is rendered from the Jinja2 templates of ``benchmark/templates/`` (``report.html`` and one template per
section, with autoescaping on; :mod:`benchmark.templating`); this module gathers what they show.  The summary is
the one :func:`benchmark.tables.summary.summary_table`, written by the table writer's HTML form.

Full-size images are links into the store (relative to ``OUT``, so the page and the store move
together), or copies with ``copy_full``; the thumbnails keep a 3-scene x 7-setting x 6-method store
to a few MB.  The page is built in a temporary folder and renamed into place
(:func:`nimbus.utils.fs.atomic_dir`).
"""

from __future__ import annotations

import json
import math
import os
import shlex
import shutil
import warnings
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import TYPE_CHECKING, Iterable, Sequence
import numpy as np

from benchmark.cell import CEILING
from benchmark.tables import ceiling
from benchmark.tables.results import ordered
from benchmark.tables.summary import summary_table
from benchmark.tables.writer import from_csv, to_html
from benchmark.templating import render_template
from nimbus.errors import NimbusError

if TYPE_CHECKING:
    from benchmark.score import ImageIndex

PAGE = "index.html"
IMAGES = "images"
#: Names this command in its --out folder's marker: --overwrite replaces only a folder it wrote itself.
OWNER = "nimbus-bench report"
#: Thumbnails are at most this wide (never enlarged), a little more than they are shown (160 px): a 3-scene x
#: 7-setting x 6-method store of 320 x 240 views made a 4.7 MB report (2 views a setting; noisy stand-in renders,
#: the worst case for JPEG).
THUMB_WIDTH = 192
JPEG_QUALITY = 80
#: ``|image - clean|`` (mean over the channels) is multiplied by this in the difference thumbnails, so
#: small errors show; they are grey, at a lower quality (their noise-like detail makes most of the bytes).
DIFF_GAIN = 4.0
DIFF_JPEG_QUALITY = 70
#: Test views shown per scene and setting, by default.
DEFAULT_VIEWS = 2
#: Training views whose decomposition is shown per NimbusGS cell.
DECOMPOSITION_VIEWS = 3
DECOMPOSITION_PANELS = ("input I_in", "clean render", "transmission T", "airlight P", "residual R")
TRADEOFF_FILES = ("tradeoff.csv", "tradeoff.png", "tradeoff.md")
STABILITY_FILES = ("stability.csv", "stability.md", "stability.json")


@dataclass(frozen=True)
class ReportOptions:
    """What the report shows and how.

    Attributes
    ----------
    views : int
        Test views per scene and setting (evenly spaced over the split; all when fewer).
    thumb_width : int
        Largest thumbnail width in pixels.
    copy_full : bool
        Copy the full-size images into ``OUT/images/full/`` (a portable report, larger) instead of
        linking to them in the store.
    tradeoff, stability : path or None
        Folders of ``nimbus-bench tradeoff`` / ``stability`` outputs; None: look in ``ROOT/`` and ``ROOT/*/``.
    method_order : tuple of str
        Methods listed first (rows of the summary, columns of the view grids).
    """

    views: int = DEFAULT_VIEWS
    thumb_width: int = THUMB_WIDTH
    copy_full: bool = False
    tradeoff: Path | None = None
    stability: Path | None = None
    method_order: tuple[str, ...] = ()


# --- the store -------------------------------------------------------------------------------
def found_outputs(root: Path, given: Path | None, files: Sequence[str], flag: str) -> list[Path]:
    """Folders holding ``files[0]``: ``given`` (NimbusError when it has none), else ``ROOT`` and ``ROOT/*``."""
    if given is not None:
        if not (Path(given) / files[0]).is_file():
            raise NimbusError(f"{flag} {given} holds no {files[0]}; give the --out folder of that command")
        return [Path(given)]
    return sorted({p.parent for p in [root / files[0], *root.glob(f"*/{files[0]}")] if p.is_file()})


# --- images ----------------------------------------------------------------------------------
class ImageWriter:
    """Writes thumbnails under ``tmp/images`` and names full-size images as seen from the final ``out``."""

    def __init__(self, tmp: Path, out: Path, width: int, copy_full: bool) -> None:
        self.tmp, self.out, self.width, self.copy_full = tmp, out.resolve(), width, copy_full
        self.written: list[str] = []

    def thumb(self, name: str, img: np.ndarray, quality: int = JPEG_QUALITY) -> str:
        """Write ``img`` (float RGB or grey (H, W), [0, 1]) as ``images/<name>.jpg``, at most :attr:`width` wide;
        its src."""
        import cv2

        from nimbus.data.images import to_uint8

        h, w = img.shape[:2]
        if w > self.width:
            img = cv2.resize(img, (self.width, max(1, round(h * self.width / w))), interpolation=cv2.INTER_AREA)
        pixels = to_uint8(img) if img.ndim == 2 else to_uint8(img)[:, :, ::-1]
        ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(pixels), [cv2.IMWRITE_JPEG_QUALITY, quality])
        if not ok:
            raise RuntimeError(f"JPEG encoding of {name} failed")
        rel = f"{IMAGES}/{name}.jpg"
        dst = self._inside(rel)
        dst.parent.mkdir(parents=True, exist_ok=True)
        dst.write_bytes(buf.tobytes())
        self.written.append(rel)
        return rel

    def _inside(self, rel: str) -> Path:
        """``tmp / rel``, refused unless it stays inside ``tmp/images``: names are made of record fields."""
        from nimbus.utils.fs import confined_path

        return confined_path(self.tmp / IMAGES, Path(rel).relative_to(IMAGES), "report image")

    def full(self, path: Path, name: str) -> str:
        """The href of a full-size image: a path relative to ``out``, or a copy in ``images/full/``."""
        if self.copy_full:
            rel = f"{IMAGES}/full/{name}{path.suffix}"
            dst = self._inside(rel)
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(path, dst)
            return rel
        return os.path.relpath(Path(path).resolve(), self.out)

    def copy(self, path: Path, name: str) -> str:
        """Copy a file (a plot) into ``images/``; its src."""
        rel = f"{IMAGES}/{name}"
        dst = self._inside(rel)
        dst.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(path, dst)
        return rel


def figure(images: ImageWriter, name: str, img: np.ndarray, full: Path, caption: str,
           diff_against: np.ndarray | None = None) -> dict:
    """One captioned, clickable thumbnail (with its difference thumbnail when ``diff_against`` is given), for the
    ``figure`` macro of ``templates/macros.html``."""
    fig = {"src": images.thumb(name, img), "diff": None, "caption": caption, "small": img.shape[1] < images.width // 2,
           "missing": None}
    if diff_against is not None:
        diff = np.abs(img - diff_against).mean(axis=2) * DIFF_GAIN
        fig["diff"] = images.thumb(name + "_diff", diff, DIFF_JPEG_QUALITY)
    fig["href"] = images.full(full, name)
    return fig


def psnr_caption(value: float | None) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "PSNR n/a"
    return "PSNR ∞" if math.isinf(value) else f"{value:.2f} dB"


def evenly_spaced(items: Sequence, n: int) -> list:
    """``n`` items spread over ``items`` (first and last included), or all of them."""
    if len(items) <= n:
        return list(items)
    if n == 1:
        return [items[0]]
    return [items[round(i * (len(items) - 1) / (n - 1))] for i in range(n)]


# --- test views ------------------------------------------------------------------------------
def column_labels(recs: Sequence[dict]) -> list[str]:
    """A distinct label per record of one setting: the method, then preset / seed / overrides where needed."""
    labels = [r["method"] for r in recs]
    for extra in (lambda r: r.get("preset"), lambda r: f"s{r.get('seed')}",
                  lambda r: ",".join(f"{k}={v}" for k, v in sorted((r.get("overrides") or {}).items())) or "-",
                  lambda r: r["cell_id"]):
        dup = {lab for lab in labels if labels.count(lab) > 1}
        if not dup:
            break
        labels = [f"{lab} {extra(r)}" if lab in dup else lab for lab, r in zip(labels, recs)]
    return labels


def view_grids(root: Path, recs: list[dict], images: ImageWriter, options: ReportOptions) -> str:
    """Per scene and setting, the grid of test views (input, each cell's render, clean), with PSNR captions."""
    from benchmark.score import ImageIndex
    from nimbus.data.images import read_image
    from nimbus.metrics import peak_signal_noise_ratio
    from benchmark.cell import family_dir
    from benchmark.store import record_data_name
    from weather_synth.settings import ALL_SETTING_NAMES, parse_family_setting

    scenes = []
    ok = [r for r in recs if r.get("status") == "ok" and r.get("run_dir")]
    for scene in ordered(record_data_name(r) for r in ok):
        grids = []
        scenes.append({"name": scene, "grids": grids})
        here = [r for r in ok if record_data_name(r) == scene]
        # The clean ceiling has no weather of its own: its renders stand beside every setting's, before the clean view.
        ceilings = [r for r in here if r["weather"] == CEILING]
        ceiling_labels = [ceiling.label(lab) for lab in column_labels(ceilings)]
        for w in ordered((r["weather"] for r in here if r["weather"] != CEILING), ALL_SETTING_NAMES):
            cells = [r for r in here if r["weather"] == w]
            order = ordered((r["method"] for r in cells), options.method_order)
            cells.sort(key=lambda r: order.index(r["method"]))
            labels = column_labels(cells) + ceiling_labels
            cells += ceilings
            family = parse_family_setting(w)
            data = family_dir(root, scene, family.protocol) / family.setting.name
            names = ordered(v["name"] for r in cells for v in (r.get("per_view") or []))
            if not names and (data / "test_list.txt").is_file():
                names = in_store(root, data / "test_list.txt", f"test list of {scene}/{w}").read_text().split()
            inputs, cleans = ImageIndex(data / "images"), ImageIndex(data / "clean")
            render_folders = [render_folder(root, r) for r in cells]
            rows = []
            for name in evenly_spaced(names, options.views):
                clean_path = cleans.find(name)
                if clean_path is None:
                    continue
                clean = read_image(in_store(root, clean_path, f"clean view {name} of {scene}/{w}"))
                key = f"views/{scene}/{w}/{Path(name).with_suffix('').as_posix()}"
                figs = []
                in_path = inputs.find(name)
                if in_path is not None:
                    img = read_image(in_store(root, in_path, f"degraded view {name} of {scene}/{w}"))
                    figs.append(figure(images, f"{key}_input", img, in_path,
                                       psnr_caption(float(peak_signal_noise_ratio(img, clean))), clean))
                else:
                    figs.append({"missing": "no input", "inline": False})
                for r, renders in zip(cells, render_folders):
                    figs.append(render_figure(root, r, renders, name, clean, images, f"{key}_{r['cell_id']}"))
                figs.append(figure(images, f"{key}_clean", clean, clean_path, "clean (reference)"))
                rows.append({"name": name, "figures": figs})
            grids.append({"description": family.description, "weather": w, "rows": rows,
                          "heads": ["view", "degraded input", *labels, "clean"]})
    return render_template("views.html", scenes=scenes, diff_gain=f"{DIFF_GAIN:g}")


def render_folder(root: Path, rec: dict) -> tuple[Path, ImageIndex | None]:
    """A cell's folder of evaluation renders (its results.json names the split) and its index (None if missing)."""
    from benchmark.score import ImageIndex
    from benchmark.store import record_run_dir

    run = record_run_dir(root, rec)
    split = read_json(in_store(root, run / "results.json", f"results.json of cell {rec['cell_id']!r}"))
    folder = in_store(root, run / "renders" / str(split.get("eval_split", "test")),
                      f"renders folder of cell {rec['cell_id']!r}")
    return folder, (ImageIndex(folder) if folder.is_dir() else None)


def render_figure(root: Path, rec: dict, renders: tuple[Path, ImageIndex | None], name: str, clean: np.ndarray,
                  images: ImageWriter, key: str) -> dict:
    """One cell's render of view ``name`` (from :func:`render_folder`'s ``renders``) with its PSNR (the record's,
    else computed), or why it is missing."""
    from nimbus.data.images import read_image
    from nimbus.metrics import peak_signal_noise_ratio

    folder, index = renders
    path = index.find(name) if index is not None else None
    if path is None:
        return {"missing": f"no render ({folder.relative_to(root)} missing)", "inline": True}
    img = read_image(in_store(root, path, f"render {name} of cell {rec['cell_id']!r}"))
    psnr = next((v.get("psnr") for v in rec.get("per_view") or [] if v.get("name") == name), None)
    if psnr is None and img.shape == clean.shape:
        psnr = float(peak_signal_noise_ratio(img, clean))
    return figure(images, key, img, path, psnr_caption(psnr), clean if img.shape == clean.shape else None)


def in_store(root: Path, path: Path, what: str) -> Path:
    """``path`` (under ``root`` as written), refused unless it resolves inside the store: a record's field or a
    file in a run folder must not lead the report to read (or, with ``copy_full``, copy) anything else."""
    from nimbus.utils.fs import confined_path

    try:
        confined_path(root, path.relative_to(root), what)
    except NimbusError:
        raise NimbusError(f"{what} ({path}) leads outside the results store {root} (through a link, to "
                          f"{path.resolve()}); copy the file into the store instead of linking to it") from None
    return path


def read_json(path: Path) -> dict:
    """A JSON object file, or {} when it is missing or not one (the report shows what it can)."""
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return d if isinstance(d, dict) else {}


# --- NimbusGS ----------------------------------------------------------------------------------
def decision_pairs(nimbus: dict) -> list[tuple[str, str]]:
    """The component decision and its evidence as (name, value) pairs (nested records flattened)."""
    keys = ("mode", "components", "haze_evidence", "particle_evidence", "estimated_time_saved_s",
            "initial_transmission", "beta_max", "beta_mean")
    pairs = []

    def add(name: str, v) -> None:
        if isinstance(v, dict):
            for k, sub in v.items():
                add(f"{name}.{k}", sub)
            return
        if isinstance(v, float):
            v = f"{v:.4g}"
        elif isinstance(v, list):
            v = ", ".join(map(str, v)) or "none"
        pairs.append((name, v))

    for k in keys:
        if k in nimbus:
            add(k, nimbus[k])
    return pairs


def nimbus_sections(root: Path, recs: list[dict], images: ImageWriter) -> str:
    """Per NimbusGS cell (a run whose results.json has a ``nimbus`` record): decision and decomposition."""
    from benchmark.store import record_run_dir
    from nimbus.data.images import read_image

    cells = []
    for r in recs:
        if r.get("status") != "ok" or not r.get("run_dir"):
            continue
        run = record_run_dir(root, r)
        nimbus = read_json(in_store(root, run / "results.json", f"results.json of cell {r['cell_id']!r}")).get("nimbus")
        strips = sorted((run / "decomposition").glob("*.png")) if (run / "decomposition").is_dir() else []
        if not isinstance(nimbus, dict) and not strips:
            continue
        rows = []
        for strip_path in evenly_spaced(strips, DECOMPOSITION_VIEWS):
            strip = read_image(in_store(root, strip_path, f"decomposition of cell {r['cell_id']!r}"))
            w = strip.shape[1] // len(DECOMPOSITION_PANELS)
            rows.append({"name": strip_path.name, "figures": [
                figure(images, f"nimbus/{r['cell_id']}/{strip_path.stem}_{i}", strip[:, i * w:(i + 1) * w],
                       strip_path, panel) for i, panel in enumerate(DECOMPOSITION_PANELS)]})
        has = isinstance(nimbus, dict)
        cells.append({"cell_id": r["cell_id"], "mode": nimbus.get("mode", "?") if has else None,
                      "decision": decision_pairs(nimbus) if has else None, "strips": rows})
    return render_template("nimbus.html", cells=cells) if cells else ""


# --- decomposition against the ground truth ------------------------------------------------------
def models_medium(results: dict) -> bool:
    """Whether a run's ``results.json`` is a medium-modelling method's: NimbusGS with CSM, or medium-3dgs."""
    nimbus = results.get("nimbus")
    return ((isinstance(nimbus, dict) and "csm" in (nimbus.get("components") or []))
            or isinstance(results.get("medium"), dict))


def decomposition_sections(root: Path, recs: list[dict], images: ImageWriter) -> str:
    """Per cell with a ``nimbus-bench decompose`` record in its run folder (``RUN/decompose/decompose.json``): its
    table (and a link to its ``decompose.md``); per other finished cell of a medium-modelling method on a setting
    with haze: the command that makes one (the report reads records, it re-renders no model)."""
    from dataclasses import replace

    from benchmark.decompose import DEFAULT_DIR, MARKDOWN, RECORD
    from benchmark.tables.decompose import NOTES, decompose_table
    from weather_synth.settings import parse_family_setting

    cells, missing = [], []
    for r in recs:
        if r.get("status") != "ok" or not r.get("run_dir"):
            continue
        run = root / r["run_dir"]
        record = read_json(run / DEFAULT_DIR / RECORD)
        if isinstance(record.get("bands"), dict):
            md = run / DEFAULT_DIR / MARKDOWN
            cells.append({"cell_id": r["cell_id"], "views": record.get("views", "?"),
                          "iteration": record.get("iteration", "?"), "link_name": MARKDOWN,
                          "link": images.full(md, f"decompose-{r['cell_id']}") if md.is_file() else None,
                          "table": to_html(replace(decompose_table(record), notes=[]))})
            continue
        try:
            hazy = parse_family_setting(r.get("weather", "")).setting.haze
        except NimbusError:
            hazy = False
        if hazy and models_medium(read_json(run / "results.json")):
            missing.append(r)
    if not cells and not missing:
        return ""
    return render_template("decompose.html", notes=NOTES, cells=cells, missing=[
        f"nimbus-bench decompose {shlex.quote(str(root / r['run_dir']))}" for r in missing])


# --- trade-off, stability ------------------------------------------------------------------------
def extra_sections(root: Path, images: ImageWriter, options: ReportOptions) -> tuple[str, str]:
    """The trade-off and stability sections' HTML (empty strings when there is nothing to show)."""
    trade, stab = [], []
    for i, folder in enumerate(found_outputs(root, options.tradeoff, TRADEOFF_FILES, "--tradeoff")):
        plot = images.copy(folder / "tradeoff.png", f"tradeoff-{i}.png") if (folder / "tradeoff.png").is_file() else None
        trade.append({"folder": folder, "plot": plot, "table": to_html(from_csv(folder / "tradeoff.csv")), "details": []})
    for folder in found_outputs(root, options.stability, STABILITY_FILES, "--stability"):
        stab.append({"folder": folder, "plot": None, "table": to_html(from_csv(folder / "stability.csv")),
                     "details": [(images.full(folder / n, n), n) for n in STABILITY_FILES[1:] if (folder / n).is_file()]})
    return tuple(render_template("extras.html", items=items) if items else "" for items in (trade, stab))


# --- provenance ---------------------------------------------------------------------------------
def _scene_argument(record: dict, root: str, sources: dict) -> tuple[str, str]:
    """(what ``--scenes`` takes, the size key) for a record: a built-in scene's name and ``size:<size>``; a
    folder scene's path (the root's record of its source, read once per scene into ``sources``) and
    ``downscale:<N>`` (``tree`` for a dataset tree)."""
    from benchmark.scene_sources import BUILTIN, TREE, load_source
    from benchmark.store import record_data_name

    name = record_data_name(record)
    if name not in sources:
        sources[name] = load_source(root, name)
    source = sources[name]
    if source is None or source.kind == BUILTIN:
        return record["scene"], f"size:{record.get('size')}"
    return source.path, "tree" if source.kind == TREE else f"downscale:{source.downscale}"


def _size_arguments(size: str) -> list[str]:
    kind, _, value = size.partition(":")
    if kind == "size":
        return ["--size", value]
    return ["--downscale", value] if kind == "downscale" and value != "1" else []


def reproduce_commands(recs: Iterable[dict], root: str) -> list[str]:
    """``nimbus-bench run`` command lines that run exactly these cells (each one a full product of its lists).

    Cells are grouped by what one command fixes (size, preset, overrides, scoring protocols); within a
    group, (scene, setting) pairs with the same (methods x seeds) are gathered, and scenes sharing their
    settings make one command.  A command runs the clean ceiling of its scenes and seeds unless told
    ``--no-ceiling``, which it is where those ceiling cells are not all in ``recs``; a ceiling cell whose
    scene, preset and seed have no weather cell is not reproduced (no command runs a ceiling alone).  A folder
    scene (a capture, a photo folder, a dataset tree) is named by its path, as ``--scenes`` took it.
    """
    groups: dict[tuple, dict[tuple[str, str], set[tuple[str, int]]]] = {}
    ceilings: set[tuple] = set()
    sources: dict = {}
    for r in recs:
        scene, size = _scene_argument(r, root, sources)
        key = (size, r.get("preset"), tuple(sorted((r.get("overrides") or {}).items())),
               r.get("ssim_protocol") or "3dgs", r.get("lpips_net") or "none", r.get("eval_protocol") or "default")
        if r["weather"] == CEILING:
            ceilings.add((key, scene, int(r["seed"])))
            continue
        groups.setdefault(key, {}).setdefault((scene, r["weather"]), set()).add((r["method"], int(r["seed"])))
    lines = []
    for key, pairs in groups.items():
        size, preset, overrides, ssim, lpips, evaluation = key
        by_signature: dict[tuple, dict[str, list[str]]] = {}
        for (scene, weather), ms in pairs.items():
            methods = sorted({m for m, _ in ms})
            seeds = sorted({s for _, s in ms})
            if len(ms) == len(methods) * len(seeds):
                signatures = [(tuple(methods), tuple(seeds))]
            else:  # not a product: one command per method
                signatures = [((m,), tuple(sorted(s for mm, s in ms if mm == m))) for m in methods]
            for sig in signatures:
                by_signature.setdefault(sig, {}).setdefault(scene, []).append(weather)
        for (methods, seeds), scenes in by_signature.items():
            by_weathers: dict[tuple, list[str]] = {}
            for scene, weathers in scenes.items():
                by_weathers.setdefault(tuple(weathers), []).append(scene)
            for weathers, scene_list in by_weathers.items():
                argv = ["nimbus-bench", "run", "--scenes", ",".join(dict.fromkeys(scene_list)),
                        "--weathers", ",".join(weathers), "--methods", ",".join(methods), "--preset", str(preset), "--seeds",
                        ",".join(map(str, seeds)), *_size_arguments(size)]
                argv += (["--protocol", evaluation] if evaluation != "default" else
                         ["--ssim", ssim, "--lpips", lpips])
                argv += ["--root", root]
                for k, v in overrides:
                    argv += ["--set", f"{k}={v}"]
                if not {(key, scene, seed) for scene in scene_list for seed in seeds} <= ceilings:
                    argv.append("--no-ceiling")
                lines.append(shlex.join(argv))
    return lines


def provenance_html(root: Path, recs: list[dict], command: str | None) -> str:
    """Commands, seeds, protocols, versions and the cells' records in brief."""
    from benchmark.cell import SCENE_SEED, SYNTH_PROTOCOL, SYNTH_SEED
    from benchmark.report import shorten
    from benchmark.store import record_data_name
    from nimbus.versions import software_versions

    synth = []
    for scene in ordered(record_data_name(r) for r in recs):
        index = read_json(root / "data" / scene / "index.json")
        synth.append(f"{scene}: protocol {index.get('protocol', SYNTH_PROTOCOL)}, seed {index.get('seed', SYNTH_SEED)}")
    versions: dict[str, dict[str, int]] = {}
    for r in recs:
        for k, v in (r.get("versions") or {}).items():
            versions.setdefault(k, {}).setdefault(str(v), 0)
            versions[k][str(v)] += 1
    cells = [(r["cell_id"], r.get("status"), r.get("device") or "", r.get("host") or "", r.get("finished_at") or "",
              r.get("wall_time_s") or "", (r.get("config_hash") or "")[:12], (r.get("input_sha256") or "")[:12],
              shorten(r.get("error") or "", 160)) for r in recs]
    return render_template(
        "provenance.html", command=command, generated=datetime.now(timezone.utc).isoformat(timespec="seconds"),
        version=software_versions().get("nimbus", "?"), commands=reproduce_commands(recs, str(root)),
        seeds=sorted({int(r["seed"]) for r in recs}), scene_seed=SCENE_SEED, synthesis=synth,
        versions=[(k, ", ".join(v if len(c) == 1 else f"{v} ({n} cells)" for v, n in c.items()))
                  for k, c in sorted(versions.items())],
        cell_heads=("cell", "status", "device", "host", "finished", "wall s", "config", "input", "error"), cells=cells)


# --- the page --------------------------------------------------------------------------------------
def build_page(root: Path, tmp: Path, out: Path, options: ReportOptions, command: str | None) -> str:
    """The page's HTML (``templates/report.html``); thumbnails are written under ``tmp`` (the final folder will
    be ``out``)."""
    from benchmark.store import ResultsStore, load_results

    with warnings.catch_warnings():  # a truncated last line is the store's business, not the report's
        warnings.simplefilter("ignore", UserWarning)
        df = load_results(root)
        recs = list(ResultsStore(root).latest().values())
    table = summary_table(df, options.method_order)  # raises for an empty store before any image is made
    images = ImageWriter(tmp, out, options.thumb_width, options.copy_full)
    sections = [("summary", "Summary", to_html(table)),
                ("views", "Test views", view_grids(root, recs, images, options))]
    nimbus = nimbus_sections(root, recs, images)
    if nimbus:
        sections.append(("nimbus", "NimbusGS: component decision and decomposition", nimbus))
    decomposition = decomposition_sections(root, recs, images)
    if decomposition:
        sections.append(("decompose", "Decomposition against the ground truth", decomposition))
    trade, stab = extra_sections(root, images, options)
    if trade:
        sections.append(("tradeoff", "Speed / accuracy trade-off", trade))
    if stab:
        sections.append(("stability", "Stability", stab))
    sections.append(("provenance", "Provenance", provenance_html(root, recs, command)))
    return render_template("report.html", root=root, n_cells=len(recs),
                           n_ok=sum(r.get("status") == "ok" for r in recs), sections=sections)


def build_report(root: str | os.PathLike, out: str | os.PathLike, options: ReportOptions = ReportOptions(),
                 command: str | None = None, overwrite: bool = False) -> Path:
    """Write the report of the store under ``root`` into the folder ``out``, atomically; the page's path.

    Raises
    ------
    NimbusError
        No store (or one without a finished cell), an ``out`` that is, holds or lies in the store
        (or in any store or scene), an existing non-empty ``out`` without ``overwrite``, or one
        this command did not write (:func:`nimbus.utils.fs.check_output_dir` with an owner).
    """
    from benchmark.store import require_store
    from nimbus.utils.fs import atomic_dir, check_output_dir, refuse_overlap

    root, out = Path(root), Path(out)
    store = require_store(root)
    if options.views < 1 or options.thumb_width < 16:
        raise NimbusError(f"--views must be at least 1 and --thumb-width at least 16, got {options.views} and "
                          f"{options.thumb_width}")
    # Replacing --out deletes it: it must be none of what the page is made from.
    refuse_overlap(out, [store, root / "runs", root / "data", root / "scenes", options.tradeoff, options.stability])
    check_output_dir(out, overwrite, owner=OWNER)
    with atomic_dir(out, overwrite=overwrite, owner=OWNER) as tmp:
        (tmp / PAGE).write_text(build_page(root, tmp, out, options, command), encoding="utf-8")
    return out / PAGE
