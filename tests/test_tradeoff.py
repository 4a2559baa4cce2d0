"""``nimbus-bench tradeoff``: knob parsing, sweep cells, Pareto fronts, the command end to end, train_downscale.

The end-to-end sweep is 3DGS with 4 iterations on the tiny built-in garden under haze
(3 cells, run in this process), without LPIPS, so it costs a few seconds.
"""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import torch

from benchmark import grid
from benchmark.cli import TOOL
from benchmark.cell import Cell
from benchmark.grid import InlineExecutor
from benchmark.store import ResultsStore
from benchmark.tradeoff import (CSV_COLUMNS, PARETO_COLUMNS, SweepPoint, base_cell, build_sweep, pareto_front,
                                parse_knobs, sweep_cells, tradeoff_rows)
from nimbus.cli_util import run_cli
from nimbus.data.images import read_image
from nimbus.errors import NimbusError
from nimbus.train.config import PRESETS
from nimbus.train.runner import Runner

SWEEP = ["tradeoff", "--method", "3dgs", "--weather", "H", "--set", "iterations=4", "--knob", "iterations=2,4",
         "--knob", "train_downscale=1,2", "--lpips", "none", "--quiet"]


# --- Pareto fronts ---------------------------------------------------------------------------------
def test_pareto_front_hand_made_case():
    cost = [1.0, 2.0, 3.0, 4.0, 2.0, None]
    psnr = [10.0, 12.0, 11.0, 15.0, 12.0, 20.0]
    # p2 is beaten by p1 (cheaper and better); p1 and p4 are identical, so neither beats the other;
    # p5 has no cost and is on no front.
    assert pareto_front(cost, psnr).tolist() == [True, True, False, True, True, False]
    lpips = [0.5, 0.3, 0.4, 0.1, 0.35, float("nan")]
    # lower is better: p4 costs as much as p1 for a worse LPIPS.
    assert pareto_front(cost, lpips, higher_is_better=False).tolist() == [True, True, False, True, False, False]


def test_pareto_front_properties_on_random_points_with_ties():
    rng = np.random.default_rng(0)
    for _ in range(20):
        c, q = rng.integers(0, 6, 25).astype(float), rng.integers(0, 6, 25).astype(float)
        front = pareto_front(c, q)

        def dominates(j, i):
            return c[j] <= c[i] and q[j] >= q[i] and (c[j] < c[i] or q[j] > q[i])

        for i in range(len(c)):
            beaten = any(dominates(j, i) for j in range(len(c)))
            assert front[i] == (not beaten)
            if not front[i]:  # every point off the front is beaten by a point on it
                assert any(front[j] and dominates(j, i) for j in range(len(c)))


def test_rows_list_the_base_under_every_knob_and_compare_values_as_printed():
    base = Cell("garden", "H", "3dgs")
    a = Cell("garden", "H", "3dgs", overrides=(("sh_degree", "2"),))
    b = Cell("garden", "H", "3dgs", overrides=(("sh_degree", "3"),))
    points = [SweepPoint("iterations", "300", base, True), SweepPoint("sh_degree", "1", base, True),
              SweepPoint("sh_degree", "2", a, False), SweepPoint("sh_degree", "3", b, False)]

    def rec(psnr, lpips, t, mb):
        return {"status": "ok", "psnr": psnr, "lpips": lpips, "train_time_s": t, "peak_memory_mb": mb}

    records = {base.cell_id: rec(16.0, 0.440, 10.0, 400.0), a.cell_id: rec(16.5, 0.43804, 20.0, 400.0),
               b.cell_id: rec(16.5, 0.43800, 25.0, 400.0)}  # b: better LPIPS than a only below 0.001
    rows = tradeoff_rows(points, records)
    assert [r["on_pareto_lpips_time"] for r in rows] == [True, True, True, False]
    assert [r["on_pareto_psnr_memory"] for r in rows] == [False, False, True, True]  # a and b tie
    rows = tradeoff_rows(points, {**records, base.cell_id: {"status": "error"}})
    assert rows[0]["status"] == "error" and rows[0]["psnr"] is None and not rows[0]["on_pareto_psnr_time"]


# --- knobs and sweeps ------------------------------------------------------------------------------
@pytest.mark.parametrize("tokens, match", [
    (["iterations="], "lists no values"),
    (["Bad-Name=1"], "expected NAME"),
    (["lambda_dssim"], "no default values"),
    (["iterations=2", "iterations=4"], "given twice"),
])
def test_parse_knobs_rejects_bad_tokens(tokens, match):
    with pytest.raises(NimbusError, match=match):
        parse_knobs(tokens)


def test_parse_knobs():
    assert parse_knobs(["iterations=150, 300,150", "sh_degree"]) == [("iterations", ("150", "300")),
                                                                     ("sh_degree", None)]


def test_default_sweep_shares_the_base_cell_and_switches_method_for_3dgs():
    base = base_cell(overrides={"log_interval": "5", "ray_samples": "16"})  # nimbus, tiny preset
    points = build_sweep(base)
    assert list(dict.fromkeys(p.knob for p in points)) == ["iterations", "train_downscale", "ray_samples",
                                                           "grid_resolution", "sh_degree", "components"]
    by = {(p.knob, p.value): p for p in points}
    tiny_iterations = PRESETS["tiny"].iterations
    assert [p.value for p in points if p.knob == "iterations"] == [str(tiny_iterations // 2), str(tiny_iterations),
                                                                   str(2 * tiny_iterations)]
    assert [p.value for p in points if p.knob == "ray_samples"] == ["8", "16", "32"]  # around the base override
    for key in [("iterations", str(tiny_iterations)), ("ray_samples", "16"), ("components", "auto"),
                ("train_downscale", "1")]:
        assert by[key].base and by[key].cell == base
    gs = by[("components", "3dgs")].cell
    assert gs.method == "3dgs" and dict(gs.overrides) == {"log_interval": "5"}  # ray_samples is not a 3DGS setting
    assert dict(by[("components", "csm+plm")].cell.overrides)["components"] == "csm,plm"
    cells = sweep_cells(points)
    assert len({c.cell_id for c in cells}) == len(cells) == len(points) - 5  # the base listed under 6 knobs


@pytest.mark.parametrize("knob, match", [
    ("iterations=0", r"^--knob iterations=0: must be an integer >= 2"),
    ("components=csm+fog", "unknown fog"),
    ("not_a_setting=1", "no setting 'not_a_setting'"),
])
def test_build_sweep_rejects_values_the_config_rejects(knob, match):
    with pytest.raises(NimbusError, match=match):
        build_sweep(base_cell(), parse_knobs([knob]))


def test_nimbus_knob_on_3dgs_names_the_method():
    with pytest.raises(NimbusError, match="use --method nimbus"):
        build_sweep(base_cell(method="3dgs"), parse_knobs(["ray_samples=8"]))
    assert {p.knob for p in build_sweep(base_cell(method="3dgs"))} == {"iterations", "train_downscale", "sh_degree"}


# --- the command -----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def swept(tmp_path_factory):
    """The sweep run once through the CLI (cells in this process), and the store's size after it."""
    root = tmp_path_factory.mktemp("tradeoff")
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(grid, "make_executor", lambda *a, **k: InlineExecutor())
        assert run_cli(TOOL.run, SWEEP + ["--root", str(root)]) == 0
    return root


def _rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_tradeoff_writes_table_and_plot(swept):
    out = swept / "tradeoff"
    rows = _rows(out / "tradeoff.csv")
    assert list(rows[0]) == list(CSV_COLUMNS)
    assert [(r["knob"], r["value"], r["base"]) for r in rows] == [
        ("iterations", "2", "False"), ("iterations", "4", "True"),
        ("train_downscale", "1", "True"), ("train_downscale", "2", "False")]
    assert len({r["cell_id"] for r in rows}) == 3
    assert all(r["status"] == "ok" and float(r["psnr"]) > 0 and float(r["train_time_s"]) >= 0 for r in rows)
    assert all(r["lpips"] == "" for r in rows)  # --lpips none
    assert [r["iterations"] for r in rows] == ["2", "4", "4", "4"]
    for col in PARETO_COLUMNS:  # a panel without values has no front; one with values has one
        flags = [r[col] == "True" for r in rows]
        assert any(flags) == col.startswith("on_pareto_psnr")
    base_rows = [r for r in rows if r["base"] == "True"]
    assert base_rows[0]["on_pareto_psnr_time"] == base_rows[1]["on_pareto_psnr_time"]
    png = read_image(out / "tradeoff.png")
    assert png.shape == (990, 1320, 3) and png.std() > 0
    md = (out / "tradeoff.md").read_text()
    assert "| train_downscale | 2 |" in md and "(base)" in md


def test_train_downscale_cell_trains_small_and_renders_full_size(swept):
    rec = next(r for r in ResultsStore(swept).latest().values() if ("train_downscale", "2") in
               [tuple(kv) for kv in r["overrides"].items()])
    run = swept / rec["run_dir"]
    assert json.loads((run / "config.json").read_text())["config"]["train_downscale"] == 2
    renders = sorted((run / "renders" / "test").glob("*.png"))
    assert renders and all(read_image(p).shape == (48, 64, 3) for p in renders)  # the tiny scene's full size


def test_tradeoff_rerun_skips_finished_cells(swept, capsys):
    before = len(ResultsStore(swept).records())
    (swept / "tradeoff" / "tradeoff.csv").unlink()
    capsys.readouterr()
    assert run_cli(TOOL.run, SWEEP + ["--root", str(swept)]) == 0  # the local executor would start processes
    assert "skipping 3 finished cell(s)" in capsys.readouterr().err
    assert len(ResultsStore(swept).records()) == before
    assert len(_rows(swept / "tradeoff" / "tradeoff.csv")) == 4


@pytest.mark.parametrize("knob", ["iterations=", "ray_samples=8", "iterations=0", "nosuch"])
def test_bad_knob_exits_2_with_one_error_line_and_no_output(tmp_path, capsys, knob):
    root = tmp_path / "r"
    assert run_cli(TOOL.run, SWEEP[:7] + ["--knob", knob, "--root", str(root)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: --knob")
    assert not root.exists()


# --- train_downscale --------------------------------------------------------------------------------
def test_train_downscale_area_averages_training_views_and_keeps_test_views(make_scene, tmp_path):
    scene = make_scene(n_views=4, width=32, height=24)
    config = PRESETS["tiny"].with_overrides({"train_downscale": "2"})
    t = Runner("3dgs", scene, config, tmp_path / "run", progress=False, device=torch.device("cpu"))
    src, cam = scene.train_views[0], scene.train_views[0].camera
    small = t.method.train_views[0]
    assert small.camera.width == 16 and small.camera.height == 12
    np.testing.assert_allclose([small.camera.fx, small.camera.cx], [cam.fx / 2, cam.cx / 2])
    blocks = src.load_image().reshape(12, 2, 16, 2, 3).mean(axis=(1, 3))  # 2x2 box average
    np.testing.assert_allclose(t.method.train_images[0].numpy(), blocks, atol=1e-6)
    assert t.scene.test_views[0].camera.width == 32
    with pytest.raises(NimbusError, match="train_downscale"):
        PRESETS["tiny"].with_overrides({"train_downscale": "0"})
