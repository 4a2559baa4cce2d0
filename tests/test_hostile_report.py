"""The hostile-input report (``nimbus-bench hostile``): its checkers catch what they claim to, and a few
cheap cases run end to end through the real tools."""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

import pytest

from benchmark import hostile
from benchmark.cli import TOOL
from benchmark.hostile import CASES, Baseline, Child, HostileCase, Sandbox, classify_outcome, compare, snapshot
from nimbus.cli_util import run_cli
from nimbus.errors import NimbusError

# A stand-in "tool": argv[1] names what it does wrong, then it ends with a clear error (or crashes).
FAKE_TOOL = r"""
import os, sys, time
what = sys.argv[1]
if what == "outside":
    open("stray.txt", "w").write("x")
    open("../outside/canary.txt", "a").write("touched")
elif what == "modify_input":
    open("scene/a.txt", "a").write("changed")
elif what == "delete_input":
    os.remove("scene/a.txt")
elif what == "partial":
    os.makedirs("out/half")
elif what == "marker":
    open("../outside/PWNED", "w").write("")
elif what == "crash":
    raise ValueError("boom")
elif what == "allocate":
    block = b"x" * (160 << 20)
    time.sleep(0.3)
elif what == "sleep":
    time.sleep(60)
elif what == "finish":
    os.makedirs("out")
    open("out/result.txt", "w").write("done")
    sys.exit(0)
print("error: what is wrong; how to fix it", file=sys.stderr)
sys.exit(2)
"""


def _child(code: int, stderr: str = "", killed: str = "") -> Child:
    return Child(code, stderr, 0.1, 0.1, 10.0, killed)


def _prepare(sb: Sandbox) -> None:
    (sb.box / "scene").mkdir()
    (sb.box / "scene" / "a.txt").write_text("input")


@pytest.fixture
def fake_tool(monkeypatch, tmp_path):
    script = tmp_path / "fake_tool.py"
    script.write_text(FAKE_TOOL)
    monkeypatch.setattr(hostile, "tool_argv", lambda tool: [sys.executable, str(script)])
    base = hostile.Base(tmp_path / "base", tmp_path / "base", tmp_path / "base", tmp_path / "base")

    def run(what: str, expect: str = "clear error", baseline: Baseline | None = None, **kw) -> dict:
        case = HostileCase(f"fake_{what}", "a fake tool", "nimbus-train", (what,), expect, _prepare, **kw)
        return hostile.run_case(case, tmp_path / "work", base, baseline)
    return run


# --- outcome classification -------------------------------------------------------------------
def test_outcomes_follow_the_definitions():
    assert classify_outcome(_child(0))[0] == "finished"
    assert classify_outcome(_child(2, "usage: x\nerror: bad value; use 3\n")) == ("clear error",
                                                                                    "error: bad value; use 3")
    assert classify_outcome(_child(2, "Traceback (most recent call last):\nerror: x\n"))[0] == "crash"
    assert classify_outcome(_child(0, "Traceback (most recent call last):\n  ValueError\n"))[0] == "crash"
    assert classify_outcome(_child(1, "error: x\n"))[0] == "crash"
    assert classify_outcome(_child(-9))[0] == "crash"
    assert classify_outcome(_child(2, "error: one\nerror: two\n"))[0] == "unclear error"
    assert classify_outcome(_child(2, "something went wrong\n"))[0] == "unclear error"
    assert classify_outcome(_child(2, "error: x\n", killed="ran past 1 s"))[0] == "crash"


def test_a_grid_run_that_skipped_locked_cells_finished_but_one_with_failures_did_not():
    skipped = "1 cell(s) not in this table: another run on out is running them (running elsewhere, not failed)\n"
    assert hostile.classify_grid_run(_child(1, skipped))[0] == "finished"
    assert hostile.classify_grid_run(_child(1, "1 cell(s) failed; rerun\n" + skipped))[0] == "crash"
    assert hostile.classify_grid_run(_child(1, "Traceback (most recent call last):\n" + skipped))[0] == "crash"


def test_a_bad_value_error_must_name_the_value():
    check = hostile._names("haze.beta=abc")
    assert check(None, [_child(2, "error: --set haze.beta=abc: must be a number >= 0\n")]) == []
    assert check(None, [_child(2, "error: 'haze.beta': ufunc 'isnan' not supported for the input types\n")])
    assert check(None, [_child(0, "")]) == []  # no error line: the outcome check already fails it


# --- snapshots ------------------------------------------------------------------------------
def test_compare_separates_inputs_outside_and_out(tmp_path):
    (tmp_path / "sandbox" / "scene").mkdir(parents=True)
    (tmp_path / "sandbox" / "scene" / "a.txt").write_text("a")
    (tmp_path / "outside").mkdir()
    before = snapshot(tmp_path)
    (tmp_path / "sandbox" / "scene" / "a.txt").write_text("b")
    (tmp_path / "outside" / "new.txt").write_text("n")
    (tmp_path / "sandbox" / "out").mkdir()
    diff = compare(before, snapshot(tmp_path), ["sandbox/scene"], "sandbox/out")
    assert diff["inputs_modified"] == ["sandbox/scene/a.txt"]
    assert diff["outside_writes"] == ["outside/new.txt", "sandbox/scene/a.txt"]
    assert diff["out_changed"] == ["sandbox/out"]


def test_snapshot_sees_links_and_modes_without_following_links(tmp_path):
    (tmp_path / "f").write_text("x")
    (tmp_path / "link").symlink_to("/")
    snap = snapshot(tmp_path)
    assert snap["link"][0] == "link" and not any(k.startswith("link/") for k in snap)
    (tmp_path / "f").chmod(0o600)
    assert snapshot(tmp_path)["f"] != snap["f"]


def test_an_input_deleted_through_an_out_equal_to_it_is_caught(tmp_path):
    (tmp_path / "sandbox" / "scene").mkdir(parents=True)
    (tmp_path / "sandbox" / "scene" / "a.txt").write_text("a")
    before = snapshot(tmp_path)
    (tmp_path / "sandbox" / "scene" / "a.txt").unlink()
    diff = compare(before, snapshot(tmp_path), ["sandbox/scene"], "sandbox/scene")
    assert diff["inputs_modified"] == ["sandbox/scene/a.txt"] and diff["outside_writes"] == []


# --- the checkers on a fake tool ------------------------------------------------------------
def test_a_clean_error_passes(fake_tool):
    row = fake_tool("nothing")
    assert (row["outcome"], row["verdict"]) == ("clear error", "ok")
    assert row["exit"] == "2" and row["peak_mb"] > 0 and row["seconds"] > 0


def test_writing_outside_out_fails(fake_tool):
    row = fake_tool("outside")
    assert row["outcome"] == "clear error"
    assert row["outside_writes"] == ["outside/canary.txt", "sandbox/stray.txt"]
    assert row["verdict"].startswith("FAIL") and "wrote outside --out" in row["verdict"]


@pytest.mark.parametrize("what", ["modify_input", "delete_input"])
def test_a_modified_or_deleted_input_fails(fake_tool, what):
    row = fake_tool(what)
    assert row["inputs_modified"] == ["sandbox/scene/a.txt"] and "input modified" in row["verdict"]


def test_partial_output_after_an_error_fails_but_output_after_finishing_does_not(fake_tool):
    row = fake_tool("partial")
    assert row["partial_output"] == ["sandbox/out", "sandbox/out/half"] and "partial output" in row["verdict"]
    row = fake_tool("finish", expect="finished")
    assert row["verdict"] == "ok" and row["outside_writes"] == []
    assert "expected clear error" in fake_tool("finish")["verdict"]


def test_a_marker_file_means_code_ran(fake_tool):
    assert "code ran" in fake_tool("marker", marker="outside/PWNED")["verdict"]


def test_a_crash_fails(fake_tool):
    row = fake_tool("crash")
    assert row["outcome"] == "crash" and "ValueError: boom" in row["message"]
    assert row["verdict"] == "FAIL: expected clear error"


def test_the_budget_counts_memory_over_the_baseline(fake_tool):
    ok = fake_tool("nothing", budget=True, baseline=Baseline(cpu_s=0.0, peak_mb=0.0))
    assert ok["budget"].endswith(": ok") and ok["verdict"] == "ok"
    over = fake_tool("allocate", budget=True, baseline=Baseline(cpu_s=0.0, peak_mb=0.0))
    assert over["budget"].endswith(": over") and "over budget" in over["verdict"]


def test_the_watchdog_kills_a_child_past_its_limits(tmp_path):
    slow = hostile.start_children([sys.executable, "-c", "import time; time.sleep(60)"], tmp_path, tmp_path / "l",
                                  timeout_s=0.5)[0]
    assert slow.killed.startswith("ran past") and classify_outcome(slow)[0] == "crash"
    fat = hostile.start_children([sys.executable, "-c", "import time; b = b'x' * (300 << 20); time.sleep(60)"],
                                 tmp_path, tmp_path / "l", timeout_s=30, memory_mb=150)[0]
    assert fat.killed.startswith("resident memory")


def test_a_childs_peak_memory_is_its_own_not_the_harnesss(tmp_path):
    """A child forked from a big process inherits its resident size into ru_maxrss at exec."""
    ballast = b"x" * (250 << 20)  # noqa: F841 - the harness's own resident memory
    child = hostile.start_children([sys.executable, "-c", "pass"], tmp_path, tmp_path / "l")[0]
    assert 0 < child.peak_mb < 100 and child.exit_code == 0
    del ballast


def test_a_harness_failure_is_not_blamed_on_the_tool(fake_tool, tmp_path):
    def broken(sb):
        raise OSError("disk full")
    row = hostile.run_case(HostileCase("fake", "x", "nimbus-train", (), "clear error", broken), tmp_path / "w",
                           hostile.Base(tmp_path, tmp_path, tmp_path, tmp_path))
    assert row["outcome"] == "harness error" and row["verdict"] == "FAIL: input not built"


# --- the case list ----------------------------------------------------------------------------
def test_cases_cover_issue_14():
    names = {c.name for c in CASES}
    assert len(names) == len(CASES)
    for needed in ("pickle_resume", "train_out_is_scene", "degrade_out_ancestor", "train_colmap_abs_name",
                   "degrade_colmap_dotdot_name", "train_symlink_out", "points3d_count_2e60", "points3d_truncated",
                   "json_nested_100k", "ply_negative_vertex_count", "seed_huge", "device_tpu", "resume_broken_config",
                   "train_out_read_only", "train_out_under_file", "nan_depth", "corrupt_image", "two_grid_runs",
                   "killed_degrade_leftover"):
        assert needed in names
    assert {c.tool for c in CASES} == set(hostile.TOOLS)
    assert {c.name for c in CASES if c.budget} >= {"points3d_count_2e60", "images_bin_truncated",
                                                     "cameras_bin_truncated"}
    for c in CASES:  # training cases stay short even where a defect lets them train
        if c.tool == "nimbus-train" and "--resume" not in c.args:
            assert "iterations=20" in c.args


def test_case_selection():
    assert [c.name for c in hostile.get_cases("seed_huge,pickle_resume")] == ["pickle_resume", "seed_huge"]
    with pytest.raises(NimbusError, match="unknown hostile case"):
        hostile.get_cases("pickle_resume,nope")
    with pytest.raises(ValueError):
        HostileCase("x", "y", "nimbus-train", (), "maybe", _prepare)


def test_a_renamed_view_is_renamed_in_the_split_lists_too(tmp_path):
    """Otherwise the loader stops at a split mismatch and never meets the hostile name (a false pass)."""
    sparse = tmp_path / "sparse" / "0"
    sparse.mkdir(parents=True)
    (sparse / "images.txt").write_text("# header\n1 1 0 0 0 0 0 0 1 002.png\n\n2 1 0 0 0 0 0 0 1 003.png\n\n")
    (tmp_path / "train_list.txt").write_text("002.png\n003.png\n")
    (tmp_path / "test_list.txt").write_text("001.png\n")
    hostile._rename_view(tmp_path, "003.png", "../../x.png")
    assert (sparse / "images.txt").read_text().splitlines()[3] == "2 1 0 0 0 0 0 0 1 ../../x.png"
    assert (tmp_path / "train_list.txt").read_text() == "002.png\n../../x.png\n"
    assert (tmp_path / "test_list.txt").read_text() == "001.png\n"
    with pytest.raises(RuntimeError):
        hostile._rename_view(tmp_path, "009.png", "y.png")


# --- end to end -------------------------------------------------------------------------------
def _read_csv(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_cheap_cases_end_to_end_through_the_cli(tmp_path, capsys):
    cases = "seed_negative,train_out_is_file,unknown_weather"
    code = run_cli(TOOL.run, ["hostile", "--cases", cases, "--out", str(tmp_path / "rep"), "--work",
                              str(tmp_path / "work")])
    rows = _read_csv(tmp_path / "rep" / "hostile.csv")
    assert [r["case"] for r in rows] == cases.split(",")
    assert all(r["outcome"] == "clear error" and r["message"].startswith("error:") for r in rows)
    assert code == (0 if all(r["verdict"] == "ok" for r in rows) else 1)
    md = (tmp_path / "rep" / "hostile.md").read_text()
    assert "| seed_negative | nimbus-train |" in md and "--seed=-1" in md
    assert "# Hostile-input report" in capsys.readouterr().out


def test_a_failing_case_makes_the_command_exit_1(tmp_path, monkeypatch, capsys):
    script = tmp_path / "fake_tool.py"
    script.write_text(FAKE_TOOL)
    bad = HostileCase("writes_outside", "x", "nimbus-train", ("outside",), "clear error", _prepare)
    monkeypatch.setattr(hostile, "CASES", (bad,))
    monkeypatch.setattr(hostile, "build_base", lambda work: hostile.Base(work, work, work, work))
    monkeypatch.setattr(hostile, "tool_argv", lambda tool: [sys.executable, str(script)])
    assert run_cli(TOOL.run, ["hostile", "--out", str(tmp_path / "rep"), "--work", str(tmp_path / "w")]) == 1
    assert _read_csv(tmp_path / "rep" / "hostile.csv")[0]["verdict"] == "FAIL: wrote outside --out"
    assert "1 case(s) failed the report: writes_outside" in capsys.readouterr().err


def test_list_and_a_bad_out(tmp_path, capsys):
    assert run_cli(TOOL.run, ["hostile", "--list"]) == 0
    assert "pickle_resume" in capsys.readouterr().out
    (tmp_path / "f").write_text("x")
    assert run_cli(TOOL.run, ["hostile", "--cases", "seed_huge", "--out", str(tmp_path / "f")]) == 2


@pytest.mark.slow
def test_the_hostile_inputs_are_really_hostile(tmp_path):
    """A pass means something only if the input is what it claims: the checkpoint runs code when
    unpickled the unsafe way, and the model file is really cut in half."""
    rows = hostile.run_report(hostile.get_cases("pickle_resume,points3d_truncated"), tmp_path, log=lambda s: None)
    by = {r["case"]: r for r in rows}
    case = tmp_path / "cases" / "pickle_resume"
    marker = case / "outside" / "PWNED"
    assert marker.exists() == ("code ran" in by["pickle_resume"]["verdict"])
    marker.unlink(missing_ok=True)
    subprocess.run([sys.executable, "-c", "import torch, sys; torch.load(sys.argv[1], weights_only=False)",
                    str(case / "sandbox" / "run" / "checkpoint.pt")], capture_output=True)
    assert marker.exists()
    cut = tmp_path / "cases" / "points3d_truncated" / "sandbox" / "scene" / "sparse" / "0" / "points3D.bin"
    assert cut.stat().st_size == (tmp_path / "base" / "scene" / "sparse" / "0" / "points3D.bin").stat().st_size // 2
    assert by["points3d_truncated"]["budget"].endswith((": ok", ": over"))
