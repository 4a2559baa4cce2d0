"""The stability report (``nimbus-bench stability``): its cases, outcomes, NaN detection and tables,
plus regression tests of the bugs it found."""

from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest
import torch

from benchmark import stability
from benchmark.cli import TOOL
from benchmark.cell import make_config
from benchmark.stability import CASES, COLUMNS, StabilityCase, get_cases
from nimbus.cli_util import run_cli
from nimbus.errors import NimbusError
from nimbus.methods.gs3d import GaussianSplatting
from nimbus.methods.registry import METHODS, MethodSpec, get_method

FAST = ["--iterations", "12", "--lpips", "none"]


def _read_csv(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


# --- the case list -------------------------------------------------------------------------------
def test_cases_cover_the_issues_extremes():
    by = {c.name: c for c in CASES}
    assert len(by) == len(CASES)
    synth = {c.name: dict(s.split("=", 1) for s in c.synth) for c in CASES}
    assert any(c.weather == "H" and synth[c.name].get("haze.beta") == "0" for c in CASES)          # no haze
    assert any(c.weather == "H" and synth[c.name].get("haze.beta") == "Infinity" for c in CASES)   # opaque haze
    assert {0.0, 1.0} <= {c.fill for c in CASES}                                                   # black / white
    assert any(c.train_views == 1 for c in CASES)                                                  # one view
    assert any(c.weather and "R" in c.weather and "S" in c.weather
               and float(synth[c.name]["rain.density_scale"]) >= 10 for c in CASES)                # particle density
    assert any(c.collapse_points for c in CASES)                                                   # d_max = d_min
    trained = {k for c in CASES for k, _ in c.train}
    assert {"init_opacity", "lr_scales", "near_plane"} <= trained                                  # degenerate
    errors = [c for c in CASES if c.expect == "clear error"]
    assert any(c.synth for c in errors) and any(c.train for c in errors)                           # out of range
    for c in CASES:
        assert {"3dgs"} <= set(c.methods) and any(m.startswith("nimbus") for m in c.methods)


def test_case_settings_are_valid_unless_they_must_fail():
    for case in CASES:
        for m in case.methods:
            overrides = {"iterations": "20", **dict(case.train)}
            if case.expect == "clear error" and case.train:
                with pytest.raises(NimbusError):
                    make_config(get_method(m), "tiny", overrides)
            else:
                make_config(get_method(m), "tiny", overrides)


def test_case_selection_and_validation():
    assert [c.name for c in get_cases("white_inputs,no_haze")] == ["no_haze", "white_inputs"]  # CASES order
    assert get_cases("all") == list(CASES)
    with pytest.raises(NimbusError, match="unknown stability case"):
        get_cases("no_haze,nope")
    with pytest.raises(ValueError):
        StabilityCase("x", "bad", expect="sometimes")


# --- NaN detection -------------------------------------------------------------------------------
def test_nonfinite_detection_allows_an_infinite_psnr_only():
    assert not stability._nonfinite_in({"psnr": math.inf, "per_view": [{"psnr": math.inf}]}, frozenset({"psnr"}))
    assert stability._nonfinite_in({"psnr": math.nan}, frozenset({"psnr"}))
    assert stability._nonfinite_in({"loss": math.inf}, frozenset({"psnr"}))
    assert stability._nonfinite_in([1.0, {"a": [np.float32("nan")]}])


def test_synthesis_scan_flags_nan_layers_but_not_sky_depth(tmp_path):
    (tmp_path / "layers").mkdir()
    np.savez(tmp_path / "layers" / "000.npz", transmission=np.ones((2, 2), np.float32),
             snow_depth=np.full((2, 2), np.inf, np.float32))
    assert not stability.synthesis_nonfinite(tmp_path)
    np.savez(tmp_path / "layers" / "001.npz", transmission=np.array([[np.nan]], np.float32))
    assert stability.synthesis_nonfinite(tmp_path)


# --- end to end -------------------------------------------------------------------------------
def test_report_runs_cases_and_writes_the_table(tmp_path, capsys):
    out = tmp_path / "report"
    argv = ["stability", "--out", str(out), "--work", str(tmp_path / "work"),
            "--cases", "no_haze,white_inputs,negative_haze_beta,bad_trainer_setting",
            "--methods", "3dgs,nimbus-full"] + FAST
    assert run_cli(TOOL.run, argv) == 0, capsys.readouterr().err
    err = capsys.readouterr().err
    assert err.count("-> ok") == 5 and "[5/5]" in err  # one progress line per row
    rows = _read_csv(out / "stability.csv")
    assert tuple(rows[0]) == COLUMNS
    got = {(r["case"], r["method"]): r for r in rows}  # --methods keeps the cases' methods among those
    assert list(got) == [("no_haze", "3dgs"), ("white_inputs", "nimbus-full"), ("white_inputs", "3dgs"),
                         ("negative_haze_beta", "3dgs"), ("bad_trainer_setting", "3dgs")]
    for key in [("no_haze", "3dgs"), ("white_inputs", "3dgs"), ("white_inputs", "nimbus-full")]:
        r = got[key]
        assert r["outcome"] == "finished" and r["nan_seen"] == "no" and r["verdict"] == "ok"
        assert 0 < float(r["psnr"]) < 60 and -1 <= float(r["ssim"]) <= 1 and r["lpips"] == "n/a"
        assert float(r["seconds"]) > 0
    assert "components: csm, plm, ggs" in got[("white_inputs", "nimbus-full")]["message"]
    bad = got[("negative_haze_beta", "3dgs")]
    assert (bad["outcome"], bad["stage"], bad["verdict"]) == ("clear error", "synthesis", "ok")
    assert "haze.beta=-1: must be a number >= 0" in bad["message"] and bad["psnr"] == "n/a"
    assert got[("bad_trainer_setting", "3dgs")]["outcome"] == "clear error"
    assert got[("bad_trainer_setting", "3dgs")]["stage"] == "set-up"
    md = (out / "stability.md").read_text()
    assert md.count("\n| ") >= len(rows) + 1 and "| negative_haze_beta | 3dgs | clear error | clear error |" in md
    doc = json.loads((out / "stability.json").read_text())
    assert len(doc["rows"]) == len(rows) and doc["options"]["iterations"] == 12


def _register(monkeypatch, name, method_cls):
    monkeypatch.setitem(METHODS, name, MethodSpec(name, "test double", f"{__name__}:{method_cls.__name__}"))


class _Crashing(GaussianSplatting):
    def train_iteration(self, step):
        raise ZeroDivisionError("a bug")


class _NaNParams(GaussianSplatting):
    def get_info(self):  # the last thing a run asks of its method: after every check, the results are written
        with torch.no_grad():
            self.params.tensors["opacity_logits"][0] = float("nan")
        return super().get_info()


def test_crash_and_unflagged_nan_fail_the_report(tmp_path, monkeypatch, capsys):
    _register(monkeypatch, "crashing", _Crashing)
    _register(monkeypatch, "nan-params", _NaNParams)
    case = StabilityCase("clean", "the clean scene", methods=("crashing", "nan-params"))
    monkeypatch.setattr(stability, "CASES", (case,))
    out = tmp_path / "report"
    rc = run_cli(TOOL.run, ["stability", "--out", str(out), "--work", str(tmp_path / "work")] + FAST)
    assert rc == 1
    assert "2 run(s) failed the report" in capsys.readouterr().err
    got = {r["method"]: r for r in _read_csv(out / "stability.csv")}
    crash = got["crashing"]
    assert (crash["outcome"], crash["stage"], crash["verdict"]) == ("crash", "training", "FAIL: crash")
    assert crash["message"] == "ZeroDivisionError: a bug"
    nan = got["nan-params"]
    assert nan["outcome"] == "finished" and nan["nan_seen"] == "yes" and "parameters" in nan["nan_where"]
    assert nan["verdict"] == "FAIL: NaN / inf without a clear error"
    assert "Traceback" in json.loads((out / "stability.json").read_text())["rows"][0]["traceback"]


class _NaNThenClearError(GaussianSplatting):
    def train_iteration(self, step):
        with torch.no_grad():
            self.params.tensors["opacity_logits"][0] = float("nan")
        raise NimbusError("the loss became NaN")


def test_a_model_whose_training_failed_is_still_checked(tmp_path, monkeypatch, capsys):
    _register(monkeypatch, "nan-then-error", _NaNThenClearError)
    monkeypatch.setattr(stability, "CASES", (StabilityCase("clean", "the clean scene", methods=("nan-then-error",)),))
    out = tmp_path / "report"
    assert run_cli(TOOL.run, ["stability", "--out", str(out), "--work", str(tmp_path / "work")] + FAST) == 0, \
        capsys.readouterr().err
    row = _read_csv(out / "stability.csv")[0]
    assert (row["outcome"], row["stage"], row["message"]) == ("clear error", "training", "the loss became NaN")
    assert row["nan_seen"] == "yes" and "parameters" in row["nan_where"] and row["verdict"] == "ok"


@pytest.mark.parametrize("argv, message", [
    (["--cases", "nope"], "unknown stability case"),
    (["--methods", "nope"], "unknown method"),
    (["--iterations", "1"], "--iterations"),
    (["--preset", "huge"], "unknown preset"),
])
def test_bad_arguments_are_one_clear_error_before_any_work(argv, message, tmp_path, capsys):
    assert run_cli(TOOL.run, ["stability", "--out", str(tmp_path / "o"), "--work", str(tmp_path / "w")] + argv) == 2
    err = capsys.readouterr().err
    assert "error:" in err and message in err and "Traceback" not in err
    assert not (tmp_path / "o").exists() and not (tmp_path / "w").exists()


def test_existing_output_is_refused_before_any_work(tmp_path, capsys):
    (tmp_path / "o").mkdir()
    (tmp_path / "o" / "keep.txt").write_text("x")
    assert run_cli(TOOL.run, ["stability", "--out", str(tmp_path / "o"), "--work", str(tmp_path / "w")]) == 2
    assert "--overwrite" in capsys.readouterr().err and not (tmp_path / "w").exists()


# --- regressions found by the report -------------------------------------------------------------
def test_opaque_height_fog_is_pure_airlight_without_nan():
    """A height fog of infinite density gave NaN transmission (inf * (2 N - 1) mixed +inf and -inf in
    the noise part's quadrature), found by the ``opaque_height_fog`` case."""
    from nimbus.data.camera import Camera
    from weather_synth.haze import HazeConfig, HazeModel
    from weather_synth.medium import HeightFogMedium

    fog = HeightFogMedium(density=math.inf, falloff=0.5, noise_amplitude=0.8, seed=1)
    o, d = np.zeros((4, 3)), np.tile([1.0, 0.0, 0.0], (4, 1))
    tau = fog.optical_depth(o, d, np.array([0.5, 2.0, 30.0, np.inf]))
    assert np.all(tau == np.inf)
    cam = Camera.look_at((0, -6, 1.5), (0, 0, 0.5), (0, 0, 1), 24, 16, 70)
    model = HazeModel(HazeConfig(mode="heterogeneous", beta=math.inf, airlight=(0.7, 0.7, 0.7)), seed=0,
                      depth_scale=4.0)
    vh = model.view("a", cam, np.full((16, 24), 5.0, np.float32))
    assert not np.isnan(vh.transmission).any() and np.all(vh.transmission == 0)
    assert not np.isnan(vh.particle_transmission(3.0)).any()
