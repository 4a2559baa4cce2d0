"""CI regression on tiny scenes: the regression grid against the committed reference figures, and the check itself.

The first test runs :data:`benchmark.reference.REGRESSION_GRID` (tiny built-in scenes, a few
weathers, NimbusGS and 3DGS, tiny preset, seed 0) and fails when a figure got worse than
``benchmark/data/regression_tiny.json`` by more than its tolerance or when the synthesised
data changed by content (more than one 8-bit level).  A deliberate change is recorded with
``nimbus-bench reference update --regression`` (the diff of the reference file shows in
review).  ``NIMBUS_CPU_ISA=generic|avx2|avx512`` runs it with the compositing kernel forced to
one instruction-set clone.  The other tests check the comparison on synthetic records and
small data folders built here.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from benchmark.cli import TOOL
from benchmark.reference import (CONTENT_GRID, CROSS_CPU_TOLERANCE, REGRESSION_GRID, REGRESSION_REFERENCE, Tolerance,
                                 attach_input_content, compare, decode_fingerprint, diff_table, image_fingerprint,
                                 load_reference, make_reference, notes, run_regression)
from nimbus.data.images import write_image
from benchmark.store import ResultsStore, load_results
from nimbus.cli_util import run_cli
from nimbus.errors import NimbusError
from nimbus.metrics import weights_path
from nimbus.render import backends

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
    if problems and not backends.available("cpp"):
        problems.append("the C++ kernels could not be built here; the references were recorded with them")
    assert not problems, ("\n" + diff_table(df, reference) + "\n" + "\n".join(problems)
                          + f"\nIf the change is deliberate, run `{UPDATE}` and commit the reference file's diff.")


def test_the_committed_reference_checks_inputs_by_content_within_the_cross_cpu_spread():
    reference = load_reference(REGRESSION_REFERENCE)
    tol = Tolerance(**reference["tolerance"])
    # Tighter than the spread measured between CPUs, the check would fail on a machine unlike the recorder's.
    assert all(getattr(tol, f) >= getattr(CROSS_CPU_TOLERANCE, f) for f in ("psnr_db", "ssim", "lpips"))
    assert tol.input_levels == 1.0
    keys = {ref.get("input") for ref in reference["cells"].values()}
    assert keys == set(reference["inputs"]) == {f"{s}-{REGRESSION_GRID.size}/{w}" for s in REGRESSION_GRID.scenes
                                                for w in REGRESSION_GRID.weathers}
    for views in reference["inputs"].values():
        assert len(views) >= 8 and all(len(decode_fingerprint(v["image"])) == 3 * CONTENT_GRID[0] * CONTENT_GRID[1]
                                       for v in views.values())


# --- the comparison, on synthetic records -----------------------------------------------------
def record(cell_id: str, psnr: float = 20.0, ssim: float = 0.7, lpips: float = 0.3, status: str = "ok",
           input_sha256: str = "a" * 64, config_hash: str = "c" * 64) -> dict:
    return {"cell_id": cell_id, "scene": "garden", "size": "tiny", "weather": "H", "method": "3dgs", "preset": "tiny",
            "seed": 0, "status": status, "psnr": psnr, "ssim": ssim, "lpips": lpips,
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

    # A reference without recorded input content cannot judge other bytes: they are shown, never fail.
    _, other_bytes = store(tmp_path, record("a", input_sha256="b" * 64), record("b"))
    assert compare(other_bytes, reference) == []
    assert "bytes differ" in diff_table(other_bytes, reference)

    _, broken = store(tmp_path, record("a", status="error"))
    assert compare(broken, reference) == ["a: failed (boom)", "b: not run"]


# --- the synthesised input, compared by content ------------------------------------------------
SCENE_FIELDS = {"scene": "garden", "size": "tiny", "method": "nimbus", "preset": "tiny", "seed": 0}


def cell_record(weather: str, **kw) -> dict:
    """A record naming a real cell (so its data folder can be found); the cell id as the grid writes it."""
    from benchmark.cell import Cell

    cell = Cell("garden", weather, "nimbus", "tiny", 0, "tiny")
    return {**record(cell.cell_id, **kw), **cell.to_dict()}


def data_folder(root, weather: str, images: dict) -> None:
    """ROOT/data/garden-tiny/WEATHER as synthesis writes it, as far as the fingerprint reads it."""
    folder = root / "data" / "garden-tiny" / weather
    views = []
    for name, (img, clean) in images.items():
        write_image(folder / "images" / name, img)
        write_image(folder / "clean" / name, clean)
        views.append({"name": name, "image": f"images/{name}", "clean": f"clean/{name}"})
    (folder / "manifest.json").write_text(json.dumps({"views": views}))


def levels(rng, h=24, w=32):
    return rng.integers(2, 253, (h, w, 3)).astype(np.float32)


def test_fingerprint_is_block_means_in_8bit_levels(tmp_path):
    img = np.zeros((24, 32, 3), np.float32)
    img[:6, :8, 0] = 1.0  # the top-left block of the 4 x 4 grid, red
    img[12:, :, 2] = 100 / 255
    write_image(tmp_path / "a.png", img)
    means = decode_fingerprint(image_fingerprint(tmp_path / "a.png")).reshape(*CONTENT_GRID, 3)
    assert means[0, 0, 0] == 255 and means[0, 1, 0] == 0 and means[:, :, 1].max() == 0
    assert (means[2:, :, 2] == 100).all() and (means[:2, :, 2] == 0).all()


def test_input_is_compared_by_content_within_one_level(tmp_path):
    rng = np.random.default_rng(0)
    base = {f"{i:03d}.png": (levels(rng), levels(rng)) for i in range(3)}
    root, df = store(tmp_path, cell_record("R+S"))
    data_folder(root, "R+S", {k: (a / 255, b / 255) for k, (a, b) in base.items()})
    df = attach_input_content(df, root)
    reference = make_reference(df)
    cid = df["cell_id"].iloc[0]
    assert reference["cells"][cid]["input"] == "garden-tiny/R+S"
    assert set(reference["inputs"]["garden-tiny/R+S"]) == set(base)
    assert compare(df, reference) == []

    def check(images, sha="b" * 64):
        root, df = store(tmp_path, cell_record("R+S", input_sha256=sha))
        data_folder(root, "R+S", {k: (a / 255, b / 255) for k, (a, b) in images.items()})
        df = attach_input_content(df, root)
        row = next(line for line in diff_table(df, reference).splitlines() if line.startswith(cid))
        return compare(df, reference), row.split()[-1]

    # Other bytes (another CPU), every pixel one level off: passes, and the table says so.
    off_by_one = {k: (a + rng.choice([-1.0, 1.0], a.shape), b) for k, (a, b) in base.items()}
    problems, word = check(off_by_one)
    assert problems == [] and word.startswith("~") and 0 < float(word[1:]) <= 1
    # A moved streak (bright pixels in another block) fails, naming the view.
    moved = dict(base)
    a, b = base["001.png"]
    a = a.copy()
    a[2:5, 3, :] = 255.0
    moved["001.png"] = (a, b)
    problems, word = check(moved)
    assert len(problems) == 1 and "the synthesised input changed: 001.png (image)" in problems[0]
    assert word == "CHANGED!"
    # Two levels off everywhere is beyond the tolerance, in the clean images too.
    problems, _ = check({k: (a, np.minimum(b + 2, 255)) for k, (a, b) in base.items()})
    assert len(problems) == 1 and "(clean) differs by 2.00" in problems[0]
    # A missing view, or a missing data folder, fails.
    problems, _ = check({k: v for k, v in base.items() if k != "002.png"})
    assert "views differ" in problems[0]
    root, df = store(tmp_path, cell_record("R+S"))
    problems = compare(attach_input_content(df, root), reference)
    assert len(problems) == 1 and "could not be read" in problems[0]


def test_a_clean_ceiling_cell_is_checked_by_its_input_bytes(tmp_path):
    """Its data folder is the clean scene, whose manifest lists no views: no content to read, and no crash."""
    root, df = store(tmp_path, cell_record("clean"))
    (root / "scenes" / "garden-tiny").mkdir(parents=True)
    (root / "scenes" / "garden-tiny" / "manifest.json").write_text(json.dumps({"generator": "builtin", "seed": 0}))
    df = attach_input_content(df, root)
    assert df["input_content"].iloc[0] is None
    reference = make_reference(df)
    assert "input" not in reference["cells"][df["cell_id"].iloc[0]] and compare(df, reference) == []
    _, other = store(tmp_path, cell_record("clean", input_sha256="b" * 64))
    assert compare(other, reference) == [] and "bytes differ" in diff_table(other, reference)


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


def test_emulate_cpu_reruns_the_grid_in_a_child_with_the_cpus_switches(tmp_path, capsys, monkeypatch):
    import subprocess

    from benchmark.reference import EMULATED_CPUS

    root, _ = store(tmp_path, record("a"))
    assert run_cli(TOOL.run, ["reference", "check", "--root", str(root), "--reference", str(tmp_path / "r.json"),
                              "--emulate-cpu", "avx2"]) == 2
    assert "add --regression" in capsys.readouterr().err
    calls = []

    def fake_run(cmd, env, check):
        calls.append((cmd, env))
        return subprocess.CompletedProcess(cmd, 1)

    monkeypatch.setattr(subprocess, "run", fake_run)
    assert run_cli(TOOL.run, ["reference", "check", "--regression", "--emulate-cpu", "generic"]) == 1
    (cmd, env), = calls
    assert cmd[-5:] == ["reference", "check", "--regression", "--emulate-cpu", "generic"]
    assert all(env[k] == v for k, v in EMULATED_CPUS["generic"].items())
    assert env["NIMBUS_CPU_ISA"] == "generic" and env["NIMBUS_EMULATED_CPU"] == "generic"
