"""CI regression on tiny scenes: the regression grid against the committed reference figures, and the check itself.

The first test runs :data:`benchmark.reference.REGRESSION_GRID` (tiny built-in scenes, a few
weathers, NimbusGS and 3DGS, tiny preset, seed 0) and fails when a figure got worse than
``tables/reference/regression_tiny.json`` by more than its tolerance or when the synthesised
data changed.  A deliberate change is recorded with ``nimbus-bench reference update
--regression`` (the diff of the reference file shows in review).  The other tests check the
comparison on synthetic records.
"""

from __future__ import annotations

import json

import pytest

from benchmark.cli import TOOL
from benchmark.reference import (REGRESSION_GRID, REGRESSION_REFERENCE, Tolerance, compare, diff_table,
                                 load_reference, make_reference, notes, run_regression)
from benchmark.store import ResultsStore, load_results
from benchmark.weights import weights_path
from nimbus.cli_util import run_cli
from nimbus.errors import NimbusError
from nimbus.render.rasterize import cpp_available

UPDATE = "nimbus-bench reference update --regression"


@pytest.mark.slow
def test_tiny_benchmark_matches_the_committed_references(tmp_path):
    if not weights_path(REGRESSION_GRID.lpips_net).is_file():
        pytest.skip("LPIPS weights not set up; run `nimbus-bench setup-weights` (CI does)")
    reference = load_reference(REGRESSION_REFERENCE)
    assert set(reference["cells"]) == {c.cell_id for c in REGRESSION_GRID.cells()}, (
        f"{REGRESSION_REFERENCE} does not hold the cells of REGRESSION_GRID; run `{UPDATE}`")
    df = run_regression(tmp_path / "bench")
    problems = compare(df, reference)
    if problems and not cpp_available():
        problems.append("the C++ kernels could not be built here; the references were recorded with them")
    assert not problems, ("\n" + diff_table(df, reference) + "\n" + "\n".join(problems)
                          + f"\nIf the change is deliberate, run `{UPDATE}` and commit the reference file's diff.")


# --- the comparison, on synthetic records -----------------------------------------------------
def record(cell_id: str, psnr: float = 20.0, ssim: float = 0.7, lpips: float = 0.3, status: str = "ok",
           input_sha256: str = "a" * 64, config_hash: str = "c" * 64) -> dict:
    return {"cell_id": cell_id, "status": status, "psnr": psnr, "ssim": ssim, "lpips": lpips,
            "input_sha256": input_sha256, "config_hash": config_hash, "ssim_protocol": "3dgs", "lpips_net": "vgg",
            "error": None if status == "ok" else "boom"}


def store(tmp_path, *records):
    root = tmp_path / f"store{len(list(tmp_path.iterdir()))}"
    s = ResultsStore(root)
    for r in records:
        s.append(r)
    return root, load_results(root)


def test_check_fails_beyond_tolerance_and_on_changed_input(tmp_path):
    tol = Tolerance(psnr_db=0.3, ssim=0.01, lpips=0.01)
    _, base = store(tmp_path, record("a"), record("b"))
    reference = make_reference(base, tol)
    assert compare(base, reference) == [] and notes(base, reference) == []

    _, within = store(tmp_path, record("a", psnr=19.75, ssim=0.695, lpips=0.309), record("b"))
    assert compare(within, reference) == []

    _, worse = store(tmp_path, record("a", psnr=19.6), record("b", lpips=0.32))
    problems = compare(worse, reference)
    assert len(problems) == 2
    assert problems[0].startswith("a: psnr 19.6000 is worse than the reference 20.0000")
    assert problems[1].startswith("b: lpips 0.3200 is worse")
    table = diff_table(worse, reference)
    assert "-0.4000!" in table and "+0.0200!" in table

    _, changed = store(tmp_path, record("a", input_sha256="b" * 64), record("b"))
    assert compare(changed, reference) == ["a: the synthesised input changed (manifest sha256 bbbbbbbbbbbb "
                                           "!= aaaaaaaaaaaa)"]
    assert "CHANGED!" in diff_table(changed, reference)

    _, broken = store(tmp_path, record("a", status="error"))
    assert compare(broken, reference) == ["a: failed (boom)", "b: not run"]


def test_improvements_and_config_changes_pass_with_a_note(tmp_path):
    _, base = store(tmp_path, record("a"))
    reference = make_reference(base)
    _, better = store(tmp_path, record("a", psnr=21.0, config_hash="d" * 64))
    assert compare(better, reference) == []
    assert notes(better, reference) == ["a: better than the reference (psnr)",
                                        "a: the trainer config changed since the reference was written"]


def test_regression_update_refuses_a_failed_cell(tmp_path):
    cells = REGRESSION_GRID.cells()
    _, df = store(tmp_path, *[record(c.cell_id) for c in cells[1:]], record(cells[0].cell_id, status="error"))
    with pytest.raises(NimbusError, match=f"1 regression cell.*{cells[0].cell_id}"):
        make_reference(df, grid=REGRESSION_GRID)
    _, df = store(tmp_path, *[record(c.cell_id) for c in cells])
    ref = make_reference(df, grid=REGRESSION_GRID)
    assert set(ref["cells"]) == {c.cell_id for c in cells} and ref["grid"]["methods"] == ("nimbus", "3dgs")


def test_reference_cli_update_then_check(tmp_path, capsys):
    root, _ = store(tmp_path, record("a"), record("b"))
    ref = tmp_path / "ref.json"
    assert run_cli(TOOL.run, ["reference", "update", "--root", str(root), "--reference", str(ref)]) == 0
    assert set(json.loads(ref.read_text())["cells"]) == {"a", "b"}
    assert run_cli(TOOL.run, ["reference", "check", "--root", str(root), "--reference", str(ref)]) == 0
    assert "2 reference cell(s) checked: ok" in capsys.readouterr().out
    worse, _ = store(tmp_path, record("a", ssim=0.6), record("b"))
    assert run_cli(TOOL.run, ["reference", "check", "--root", str(worse), "--reference", str(ref)]) == 1
    out = capsys.readouterr().out
    assert "REGRESSION a: ssim 0.6000 is worse" in out and "1 problem(s)" in out
    assert run_cli(TOOL.run, ["reference", "check", "--root", str(root)]) == 2
    assert "--regression" in capsys.readouterr().err
    assert run_cli(TOOL.run, ["reference", "check", "--root", str(root), "--reference",
                              str(tmp_path / "none.json")]) == 2
    assert "does not exist" in capsys.readouterr().err
