"""``nimbus-bench decompose`` (benchmark/decompose.py): a NimbusGS run's learned layers against the synthesised truth.

One tiny garden, degraded with haze (H) and with rain only (R) by ``nimbus-synth``; nimbus-full trained on H for a
few iterations.  The figures are checked against the same quantities computed here from the files the synthesiser
wrote, with nothing but numpy; the refusals (a method without a medium, a scene without haze layers) against the
CLI's one-line error.
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from benchmark.cell import synthesize, write_clean_scene
from benchmark.cli import TOOL
from benchmark.decompose import ALL, BANDS, DEFAULT_DIR, MARKDOWN, RECORD
from benchmark.tables.decompose import decompose_table
from benchmark.tables.writer import to_markdown
from nimbus.cli.train import _main as train
from nimbus.cli_util import run_cli
from nimbus.data.images import read_image

TRAIN = ["--preset", "tiny", "--set", "iterations=6", "--quiet", "--device", "cpu"]
NIMBUS = ["--set", "m_init=3", "--set", "write_decomposition=false"]


def bench(argv) -> int:
    return run_cli(TOOL.run, argv)


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("decompose")
    write_clean_scene("garden", "tiny", root / "clean")
    synthesize(root / "clean", root / "data", ["H", "R"], progress=False, source="builtin:garden:tiny")
    return root


@pytest.fixture(scope="module")
def run(data) -> Path:
    out = data / "run"
    assert train([str(data / "data" / "H"), "--method", "nimbus-full", *TRAIN, *NIMBUS, "--out", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def record(run) -> dict:
    assert bench(["decompose", str(run), "--device", "cpu"]) == 0
    return json.loads((run / DEFAULT_DIR / RECORD).read_text())


def truth_of(folder: Path, method, vi: int) -> dict:
    """Training view ``vi``'s true t, airlight, clean view, ray distance and sky mask, read straight from the files."""
    view = method.train_views[vi]
    stem = Path(view.name).stem
    layers = np.load(folder / "layers" / f"{stem}.npz")
    z = np.load(folder / "depths" / f"{stem}.npy")
    sky = cv2.imread(str(folder / "sky" / f"{stem}.png"), cv2.IMREAD_GRAYSCALE) > 0
    return {"t": layers["transmission"].astype(np.float64), "A": layers["airlight"].astype(np.float64),
            "clean": read_image(folder / "clean" / view.name).astype(np.float64), "sky": sky,
            # z-depth to ray distance: intrinsics only, the same in the world and the training frame.
            "r": view.camera.ray_distance_from_z(z).astype(np.float64)}


def test_every_band_is_there_with_finite_figures(record, run):
    bands = record["bands"]
    assert set(bands) == {*BANDS, ALL}  # (the JSON is written key-sorted)
    w, h = record["size"]
    assert bands[ALL]["pixels"] == record["views"] * w * h == sum(bands[b]["pixels"] for b in BANDS)
    for name, band in bands.items():
        assert band["pixels"] > 0, name  # the garden has sky and surfaces across the whole depth range
        for key in ("t_bias", "t_mae", "airlight_bias", "psnr", "psnr_offset_removed", "veil_gain_db", "mse_share"):
            assert math.isfinite(band[key]), (name, key)
        for key in ("airlight_error", "clean_bias"):
            assert len(band[key]) == 3 and all(math.isfinite(v) for v in band[key]), (name, key)
        assert 0 <= band["t_mae"] <= 1 and abs(band["t_bias"]) <= band["t_mae"] + 1e-12
        assert band["veil_gain_db"] >= 0  # removing the mean never raises the squared error
    assert sum(bands[b]["mse_share"] for b in BANDS) == pytest.approx(1.0)
    assert record["method"] == "nimbus-full" and record["setting"] == "H"
    # The table is the record's, through the one writer, and names every band.
    md = (run / DEFAULT_DIR / MARKDOWN).read_text()
    assert md == to_markdown(decompose_table(record))
    for name in (*BANDS, ALL):
        assert f"| {name}" in md


def test_figures_equal_an_independent_computation(record, run, data):
    from nimbus.train.runner import Runner

    method = Runner.open(run, progress=False, device=torch.device("cpu")).method
    folder = data / "data" / "H"
    views = []
    for vi, view in enumerate(method.train_views):
        with torch.no_grad():
            out = method.render(view.camera, view_index=vi)
        views.append((truth_of(folder, method, vi), out["transmission"][..., 0].double().numpy(),
                      out["airlight"].double().numpy(), out["rgb"].clamp(0, 1).double().numpy()))
    surface = np.concatenate([t["r"][~t["sky"]] for t, *_ in views])
    lo, hi = surface.min(), surface.max()
    assert record["depth"]["edges"] == pytest.approx([lo, lo + (hi - lo) / 3, lo + 2 * (hi - lo) / 3, hi])
    far_from = lo + 2 * (hi - lo) / 3

    # The model is rendered again here, in float32 on as many threads as torch takes: a render may differ from
    # decompose's in the last bits, hence the tolerances (a wrong band or formula moves a figure by far more).
    # T bias and T MAE of the far band, and of the sky.
    for band, pick in (("far", lambda t: ~t["sky"] & (t["r"] >= far_from)), ("sky", lambda t: t["sky"])):
        diff = np.concatenate([(T - t["t"])[pick(t)] for t, T, _, _ in views])
        assert record["bands"][band]["t_bias"] == pytest.approx(diff.mean(), rel=1e-6, abs=1e-9)
        assert record["bands"][band]["t_mae"] == pytest.approx(np.abs(diff).mean(), rel=1e-6, abs=1e-9)
    # Over every pixel: the clean render's per-channel bias, the veil figure and the effective airlight.
    err = np.concatenate([(rgb - t["clean"]).reshape(-1, 3) for t, _, _, rgb in views])
    bias = err.mean(0)
    psnr = 10 * np.log10(1 / (err ** 2).mean())
    psnr_after = 10 * np.log10(1 / ((err - bias) ** 2).mean())
    every = record["bands"][ALL]
    assert every["clean_bias"] == pytest.approx(bias, rel=1e-6, abs=1e-9)
    assert every["psnr"] == pytest.approx(psnr, rel=1e-6)
    assert every["veil_gain_db"] == pytest.approx(psnr_after - psnr, rel=1e-4, abs=1e-6)
    veil = sum((1 - T).sum() for _, T, _, _ in views)
    learned = sum(P.reshape(-1, 3).sum(0) for _, _, P, _ in views) / veil
    true = sum((1 - T).sum() * t["A"] for t, T, _, _ in views) / veil
    assert every["airlight_error"] == pytest.approx(learned - true, rel=1e-6, abs=1e-9)


def test_a_run_without_a_medium_is_refused(data, capsys):
    out = data / "run_3dgs"
    assert train([str(data / "data" / "H"), "--method", "3dgs", *TRAIN, "--out", str(out)]) == 0
    capsys.readouterr()
    assert bench(["decompose", str(out), "--device", "cpu"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "3dgs" in err[0] and "medium" in err[0]
    assert not (out / DEFAULT_DIR).exists()


def _run_on(run: Path, scene: str, out: Path) -> Path:
    """A copy of ``run`` whose config.json says it was trained on ``scene``."""
    shutil.copytree(run, out, ignore=shutil.ignore_patterns(DEFAULT_DIR))
    cfg = json.loads((out / "config.json").read_text())
    cfg["scene"] = scene
    (out / "config.json").write_text(json.dumps(cfg))
    return out


@pytest.mark.parametrize("case, message", [
    ("clean", "has no layers/"),  # a scene folder nimbus-synth did not write
    ("rain", "holds no transmission"),  # a setting without haze: layers, but no t or A
    ("builtin", "built-in scene"),
])
def test_a_scene_without_haze_layers_is_refused(case, message, run, data, tmp_path, capsys):
    scene = {"clean": str(data / "clean"), "rain": str(data / "data" / "R"), "builtin": "builtin:garden:tiny"}[case]
    moved = _run_on(run, scene, tmp_path / case)
    capsys.readouterr()
    assert bench(["decompose", str(moved), "--device", "cpu"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and message in err[0], err
    assert not (moved / DEFAULT_DIR).exists()


def test_the_report_shows_the_record_and_asks_for_the_missing_ones(record, run, tmp_path):
    """The report's section: a cell with a record gets its table; a NimbusGS cell on haze without one gets the
    command; a 3DGS cell neither."""
    from benchmark.html_report import ImageWriter, decomposition_sections

    root = tmp_path / "store"
    shutil.copytree(run, root / "runs" / "with")
    shutil.copytree(run, root / "runs" / "without", ignore=shutil.ignore_patterns(DEFAULT_DIR))
    plain = root / "runs" / "plain"
    plain.mkdir()
    (plain / "results.json").write_text(json.dumps({"method": "3dgs"}))
    recs = [{"status": "ok", "run_dir": f"runs/{name}", "cell_id": f"cell-{name}", "weather": "H"}
            for name in ("with", "without", "plain")]
    html = decomposition_sections(root, recs, ImageWriter(tmp_path / "tmp", tmp_path / "out", 64, False))
    assert "<h3>cell-with</h3>" in html and "decompose.md</a>" in html
    assert f"{record['bands']['far']['t_bias']:.3f}" in html
    assert "nimbus-bench decompose" in html and "runs/without" in html
    assert "cell-without</h3>" not in html and "plain" not in html
