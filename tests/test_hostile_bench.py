"""``nimbus-bench`` against hostile use (issue 14): two runs on one root, unusable or overlapping folders.

The cells here never train: ``benchmark.cell._train_cell`` is replaced by a fake that does what
a real cell does to the file system (and ``_score_cell`` by nothing) (clear leftovers, fill ``runs/<id>.partial``, rename it into
place) and can be held in flight, so two runners can be made to overlap without any timing.
"""

from __future__ import annotations

import json
import re
import os
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from benchmark import cell as cell_module
from benchmark import grid
from benchmark.cell import CellOptions, run_dir
from benchmark.cli import TOOL
from benchmark.grid import InlineExecutor, build_cells, run_grid
from benchmark.store import FileLock, ResultsStore, load_results
from nimbus.cli_util import run_cli
from nimbus.data import write_scene
from nimbus.data.images import write_image
from nimbus.errors import NimbusError

OPTIONS = CellOptions(lpips_net=None)
RUN_ARGS = ["run", "--scenes", "garden", "--weathers", "H", "--methods", "3dgs", "--set", "iterations=5",
            "--lpips", "none", "--quiet", "--no-ceiling"]  # one cell: the clean ceiling would be a second
REPO = Path(__file__).resolve().parents[1]


def the_cell():
    return build_cells(["garden"], ["H"], ["3dgs"], ["tiny"], [0], "tiny", {"iterations": "5"})[0]


def fake_cell(root, cell, hold=None) -> dict:
    """What a real cell does to its folders, minus the training; ``hold()`` keeps it in flight."""
    final, partial = cell_module.clear_run_dirs(Path(root), cell)
    partial.mkdir(parents=True)
    (partial / "owner.txt").write_text(f"{os.getpid()} {threading.get_ident()}")
    if hold is not None:
        hold()
    os.replace(partial, final)
    return {"psnr": 25.0, "ssim": 0.9, "lpips": None, "ssim_protocol": "3dgs", "lpips_net": None,
            "train_time_s": 0.1, "num_gaussians": 7}


def dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def wait_for(predicate, what: str, limit_s: float = 120.0) -> None:
    """Poll until ``predicate()``: a guard against a hung test, not a timing assertion."""
    deadline = time.monotonic() + limit_s
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"gave up waiting for {what}")
        time.sleep(0.05)


# --- the lock ------------------------------------------------------------------------------
HOLDER = textwrap.dedent("""
    import sys
    from benchmark.store import FileLock
    lock = FileLock(sys.argv[1])
    assert lock.acquire()
    print("held", flush=True)
    sys.stdin.read()  # hold until the test closes stdin or kills us
""")


def test_lock_is_exclusive_across_processes_and_freed_when_its_holder_dies(tmp_path):
    path = tmp_path / "locks" / "cell.lock"
    holder = subprocess.Popen([sys.executable, "-c", HOLDER, str(path)], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True, cwd=REPO)
    try:
        assert holder.stdout.readline().strip() == "held"
        mine = FileLock(path)
        assert not mine.acquire() and not mine.held
        named = mine.holder()
        assert named.pid == holder.pid and named.host and named.started_at
        assert f"pid {holder.pid}" in named.describe()
    finally:
        holder.kill()  # a killed run: it cannot release anything
        holder.wait()
    assert path.exists()  # its file is left behind, naming a dead process ...
    assert mine.acquire()  # ... and the lock is free: taken over
    assert mine.holder().pid == os.getpid()
    assert not FileLock(path).acquire()  # a second holder in this very process is refused too
    mine.release()
    assert not path.exists()


def test_stale_lock_file_of_a_dead_process_is_taken_over(tmp_path):
    path = tmp_path / "cell.lock"
    path.write_text(json.dumps({"pid": dead_pid(), "host": "elsewhere", "started_at": "2020-01-01T00:00:00+00:00"}))
    with FileLock(path) as lock:
        assert lock.held and lock.holder().pid == os.getpid()
    assert not path.exists()


# --- which record counts ---------------------------------------------------------------------
#: The fields every results record has (nimbus.schemas.ResultRecord): a hand-made record starts from these.
CELL = {"scene": "garden", "size": "tiny", "weather": "H", "method": "3dgs", "preset": "tiny", "seed": 0}


def test_a_later_error_never_hides_an_ok_record(tmp_path):
    store = ResultsStore(tmp_path)
    store.append({**CELL, "cell_id": "a", "status": "ok", "psnr": 20.0})
    store.append({**CELL, "cell_id": "b", "status": "error", "error": "first"})
    store.append({**CELL, "cell_id": "a", "status": "error", "error": "the other run removed my folder"})
    store.append({**CELL, "cell_id": "b", "status": "error", "error": "second"})
    latest = store.latest()
    assert latest["a"]["status"] == "ok" and latest["a"]["psnr"] == 20.0
    assert latest["b"]["error"] == "second"  # never finished: its latest error shows
    assert store.finished() == {"a"}
    store.append({**CELL, "cell_id": "a", "status": "ok", "psnr": 21.0})  # a later ok supersedes (--rerun)
    store.append({**CELL, "cell_id": "a", "status": "error", "error": "again"})
    df = load_results(tmp_path).set_index("cell_id")
    assert df.loc["a", "psnr"] == 21.0 and df.loc["a", "status"] == "ok" and df.loc["b", "status"] == "error"
    assert len(load_results(tmp_path, latest=False)) == 6


APPENDER = textwrap.dedent("""
    import sys
    from benchmark.store import ResultsStore
    store = ResultsStore(sys.argv[1])
    for i in range(int(sys.argv[3])):
        store.append({"cell_id": f"{sys.argv[2]}-{i}", "scene": "garden", "size": "tiny", "weather": "H",
                      "method": "3dgs", "preset": "tiny", "seed": 0, "status": "ok", "pad": "x" * 20000})
""")


def test_concurrent_appends_are_whole_lines(tmp_path):
    # Lines far longer than a pipe buffer, from 3 processes at once: none may be cut or interleaved.
    procs = [subprocess.Popen([sys.executable, "-c", APPENDER, str(tmp_path), f"w{k}", "60"], cwd=REPO)
             for k in range(3)]
    assert [p.wait() for p in procs] == [0, 0, 0]
    recs = ResultsStore(tmp_path).records()
    assert sorted(r["cell_id"] for r in recs) == sorted(f"w{k}-{i}" for k in range(3) for i in range(60))
    assert all(len(r["pad"]) == 20000 for r in recs)


# --- two runs on one root ----------------------------------------------------------------------
def test_second_run_leaves_a_cell_in_flight_alone(tmp_path, monkeypatch):
    cell = the_cell()
    in_flight, go = threading.Event(), threading.Event()
    calls = []

    def cell_fn(c, root, options):
        calls.append(threading.current_thread().name)
        if threading.current_thread().name == "A":
            return fake_cell(root, c, hold=lambda: (in_flight.set(), go.wait(120)))
        return fake_cell(root, c)

    monkeypatch.setattr(cell_module, "_train_cell", cell_fn)
    monkeypatch.setattr(cell_module, "_score_cell", lambda *a: {})
    monkeypatch.setattr(grid, "prepare_data", lambda *a, **k: None)
    outcomes = {}
    a = threading.Thread(name="A", target=lambda: outcomes.setdefault(
        "A", run_grid([cell], tmp_path, InlineExecutor(), OPTIONS, progress=False, log=lambda s: None)))
    a.start()
    try:
        assert in_flight.wait(120)
        partial = run_dir(tmp_path, cell).with_name(cell.cell_id + cell_module.PARTIAL_SUFFIX)
        owner = (partial / "owner.txt").read_text()
        said = []
        b = run_grid([cell], tmp_path, InlineExecutor(), OPTIONS, progress=False, log=said.append)
        assert calls == ["A"]  # B never started the cell, so never cleared A's folder
        assert (partial / "owner.txt").read_text() == owner
        assert b.ran == [] and b.failed == [] and b.skipped == []
        assert list(b.running_elsewhere) == [cell.cell_id] and f"pid {os.getpid()}" in b.running_elsewhere[cell.cell_id]
        assert any("another run" in s and cell.cell_id in s for s in said)
        assert ResultsStore(tmp_path).records() == []  # and wrote no record for it
    finally:
        go.set()
        a.join()
    assert [r["status"] for r in outcomes["A"].ran] == ["ok"]
    assert (run_dir(tmp_path, cell) / "owner.txt").read_text() == owner
    assert not (tmp_path / "locks" / f"{cell.cell_id}.lock").exists()  # released once stored
    again = run_grid([cell], tmp_path, InlineExecutor(), OPTIONS, progress=False, log=lambda s: None)
    assert again.skipped == [cell.cell_id] and again.ran == [] and calls == ["A"]


def test_a_cell_finished_while_waiting_for_its_lock_is_not_rerun(tmp_path, monkeypatch):
    # B read the store before A stored the cell's record, and gets the lock after A released it:
    # B must look again and skip the cell rather than clear A's finished run folder.
    cell = the_cell()
    monkeypatch.setattr(grid, "prepare_data", lambda *a, **k: None)
    store = ResultsStore(tmp_path)
    real_finished = ResultsStore.finished
    looks = []

    def finished(self):
        looks.append(1)
        if len(looks) == 1:  # B's first look: nothing yet; then A finishes the cell
            fake_cell(tmp_path, cell)
            store.append({"cell_id": cell.cell_id, **cell.to_dict(), "status": "ok", "psnr": 25.0})
            return set()
        return real_finished(self)

    monkeypatch.setattr(ResultsStore, "finished", finished)
    monkeypatch.setattr(cell_module, "_train_cell", lambda *a: pytest.fail("the finished cell was run again"))
    outcome = run_grid([cell], tmp_path, InlineExecutor(), OPTIONS, progress=False, log=lambda s: None)
    assert outcome.skipped == [cell.cell_id] and outcome.ran == [] and run_dir(tmp_path, cell).is_dir()


def test_data_preparation_waits_for_another_run_preparing_it(tmp_path):
    from weather_synth.dataset import MANIFEST

    cell = the_cell()
    (tmp_path / "scenes" / cell.data_name).mkdir(parents=True)
    (tmp_path / "scenes" / cell.data_name / "manifest.json").write_text("{}")
    (tmp_path / "data" / cell.data_name / "H").mkdir(parents=True)
    (tmp_path / "data" / cell.data_name / "H" / MANIFEST).write_text("{}")
    other = ResultsStore(tmp_path).data_lock(cell.data_name)
    assert other.acquire()
    said = []
    t = threading.Thread(target=cell_module.prepare_data, args=(tmp_path, [cell]), kwargs={"log": said.append})
    t.start()
    try:
        wait_for(lambda: said, "the waiting message")
        assert "waiting for another run" in said[0] and t.is_alive()  # blocked on our lock
    finally:
        other.release()
        t.join()
    assert said == [said[0]]  # then found the data there: nothing rendered or synthesised


RUNNER_A = textwrap.dedent("""
    import os, sys, time
    from pathlib import Path
    from benchmark import cell, grid
    from benchmark.cli import TOOL
    from nimbus.cli_util import run_cli
    sys.path.insert(0, os.path.join(sys.argv[1], "tests"))
    from test_hostile_bench import fake_cell

    go = Path(sys.argv[2])
    def hold():
        while not go.exists():
            time.sleep(0.05)
    cell._train_cell = lambda c, root, options: fake_cell(root, c, hold=hold)
    cell._score_cell = lambda *a: {}
    grid.prepare_data = lambda *a, **k: None
    grid.make_executor = lambda *a: grid.InlineExecutor()  # the fake cell lives in this process
    sys.exit(run_cli(TOOL.run, sys.argv[3:]))
""")


@pytest.mark.slow
def test_two_cli_runs_on_one_root(tmp_path, monkeypatch, capsys):
    """The issue's scenario with two processes: B skips A's cell, A's record stands, both summaries are right."""
    root, go = tmp_path / "bench", tmp_path / "go"
    cell = the_cell()
    a = subprocess.Popen([sys.executable, "-c", RUNNER_A, str(REPO), str(go), *RUN_ARGS, "--root", str(root)],
                         cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    partial = run_dir(root, cell).with_name(cell.cell_id + cell_module.PARTIAL_SUFFIX)
    try:
        wait_for(lambda: (partial / "owner.txt").exists() or a.poll() is not None, "runner A's cell")
        assert a.poll() is None, a.communicate()
        owner = (partial / "owner.txt").read_text()
        monkeypatch.setattr(cell_module, "_train_cell", lambda *args: pytest.fail("B ran A's cell"))
        monkeypatch.setattr(grid, "prepare_data", lambda *args, **k: None)
        rc = run_cli(TOOL.run, RUN_ARGS + ["--root", str(root)])
        out, err = capsys.readouterr()
        assert rc == 1  # not done here, but not failed either
        assert "running elsewhere, not failed" in err and f"pid {a.pid}" in err and "failed;" not in err
        assert out.strip() == "(no results)"
        assert (partial / "owner.txt").read_text() == owner
    finally:
        go.touch()
        a_out, a_err = a.communicate(timeout=120)
    assert a.returncode == 0, a_err
    row = next(line.split() for line in a_out.splitlines() if line.startswith("H "))
    assert row[1] == "3dgs" and row[-2:] == ["1", "0"]  # one cell, no error
    recs = ResultsStore(root).records()
    assert [r["status"] for r in recs] == ["ok"] and (run_dir(root, cell) / "owner.txt").read_text() == owner
    assert run_cli(TOOL.run, RUN_ARGS + ["--root", str(root)]) == 0  # B again: done
    assert "skipping 1 finished cell(s)" in capsys.readouterr().err


# --- unusable or overlapping folders ---------------------------------------------------------------
def deny_writes_to(monkeypatch, path: Path) -> None:
    """Make ``path`` look read-only to the access check (tests may run as root, who can write anywhere)."""
    real = os.access

    def access(p, mode, *a, **k):
        if Path(p).resolve() == path.resolve() and mode & os.W_OK:
            return False
        return real(p, mode, *a, **k)

    monkeypatch.setattr(os, "access", access)


def one_error_line(capsys, *words) -> str:
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("error:")]
    assert len(lines) == 1 and "Traceback" not in err, err
    assert all(w in lines[0] for w in words), lines[0]
    return lines[0]


@pytest.mark.parametrize("where", ["file", "under-file", "read-only"])
def test_run_refuses_an_unusable_root(where, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(grid, "prepare_data", lambda *a, **k: pytest.fail("work started"))
    afile = tmp_path / "afile"
    afile.write_text("mine")
    root = {"file": afile, "under-file": afile / "sub", "read-only": tmp_path / "ro"}[where]
    if where == "read-only":
        root.mkdir()
        deny_writes_to(monkeypatch, root)
    assert run_cli(TOOL.run, RUN_ARGS + ["--root", str(root)]) == 2
    one_error_line(capsys, "--root", "choose another --root")
    assert afile.read_text() == "mine"
    with pytest.raises(NimbusError, match="--root"):
        run_grid([the_cell()], root, InlineExecutor(), OPTIONS, progress=False)


@pytest.mark.skipif(os.name != "posix" or os.geteuid() == 0, reason="root reads and writes any folder")
def test_run_refuses_a_root_without_permissions(tmp_path, capsys):
    root = tmp_path / "bench"
    root.mkdir()
    root.chmod(0o500)
    try:
        assert run_cli(TOOL.run, RUN_ARGS + ["--root", str(root)]) == 2
        one_error_line(capsys, "--root")
    finally:
        root.chmod(0o700)


@pytest.fixture
def store_root(tmp_path):
    root = tmp_path / "bench"
    store = ResultsStore(root)
    store.append({"cell_id": "garden-tiny_H_3dgs_tiny_s0", "scene": "garden", "size": "tiny", "weather": "H",
                  "method": "3dgs", "preset": "tiny", "seed": 0, "status": "ok", "psnr": 20.0, "ssim": 0.5,
                  "lpips": 0.3, "ssim_protocol": "3dgs", "lpips_net": "vgg"})
    return root


@pytest.mark.parametrize("case, words", [
    ("out-is-root", ["--out", "contains the input"]),
    ("out-contains-root", ["--out", "contains the input"]),
    ("out-is-file", ["--out", "not a directory"]),
    ("out-under-file", ["--out", "not a directory"]),
    ("out-read-only", ["--out", "cannot be written"]),
    ("root-is-file", ["--root", "is a file"]),
    ("root-under-file", ["does not exist"]),
    ("parquet-is-store", ["--parquet", "is the input"]),
])
def test_tables_refuses_unusable_or_overlapping_folders(case, words, store_root, tmp_path, monkeypatch, capsys):
    afile = tmp_path / "afile"
    afile.write_text("mine")
    root, out, extra = store_root, tmp_path / "tables", []
    if case == "out-is-root":
        out = store_root
    elif case == "out-contains-root":
        out = tmp_path
    elif case == "out-is-file":
        out = afile
    elif case == "out-under-file":
        out = afile / "tables"
    elif case == "out-read-only":
        out.mkdir()
        deny_writes_to(monkeypatch, out)
    elif case == "root-is-file":
        root = afile
    elif case == "root-under-file":
        root = afile / "bench"
    elif case == "parquet-is-store":
        extra = ["--parquet", str(store_root / "results.jsonl")]
    before = (store_root / "results.jsonl").read_bytes()
    assert run_cli(TOOL.run, ["tables", "--root", str(root), "--out", str(out), *extra]) == 2
    one_error_line(capsys, *words)
    assert (store_root / "results.jsonl").read_bytes() == before and afile.read_text() == "mine"
    assert sorted(p.name for p in store_root.iterdir()) == ["results.jsonl"]  # no table written there
    # and an --out apart from the store file, even a folder inside the root, works
    assert run_cli(TOOL.run, ["tables", "--root", str(store_root), "--out", str(store_root / "tables")]) == 0


@pytest.fixture
def scored(tmp_path, make_scene, monkeypatch):
    """A scene on disk and renders of every view."""
    monkeypatch.setenv("NIMBUS_CACHE", str(tmp_path / "empty-cache"))
    scene_dir, renders = tmp_path / "scene", tmp_path / "renders"
    scene = make_scene(n_views=3, width=16, height=12, test_names=["000.png"])
    write_scene(scene, scene_dir)
    for v in scene.views:
        write_image(renders / v.name, np.clip(v.image + 0.05, 0, 1))
    return scene_dir, renders


@pytest.mark.parametrize("case, words", [
    ("out-in-gt", ["--out", "lies inside the input"]),
    ("out-replaces-gt-image", ["--out", "lies inside the input"]),
    ("out-in-pred", ["--out", "lies inside the input"]),
    ("out-under-file", ["--out", "not a directory"]),
    ("out-read-only", ["--out", "cannot be written"]),
    ("pred-is-file", ["renders folder", "is a file"]),
    ("gt-is-file", ["is a file"]),
])
def test_score_refuses_unusable_or_overlapping_paths(case, words, scored, tmp_path, monkeypatch, capsys):
    scene_dir, renders = scored
    afile = tmp_path / "afile"
    afile.write_text("mine")
    pred, gt, out = renders, scene_dir, tmp_path / "res" / "r.json"
    if case == "out-in-gt":
        out = scene_dir / "r.json"
    elif case == "out-replaces-gt-image":
        out = scene_dir / "images" / "000.png"
    elif case == "out-in-pred":
        out = renders / "r.json"
    elif case == "out-under-file":
        out = afile / "r.json"
    elif case == "out-read-only":
        out.parent.mkdir()
        deny_writes_to(monkeypatch, out.parent)
    elif case == "pred-is-file":
        pred = afile
    elif case == "gt-is-file":
        gt = afile
    before = {p: p.read_bytes() for p in [*scene_dir.rglob("*"), *renders.rglob("*")] if p.is_file()}
    rc = run_cli(TOOL.run, ["score", "--pred", str(pred), "--gt", str(gt), "--lpips", "none", "--out", str(out),
                            "--overwrite"])
    assert rc == 2
    one_error_line(capsys, *words)
    after = {p: p.read_bytes() for p in [*scene_dir.rglob("*"), *renders.rglob("*")] if p.is_file()}
    assert after == before and afile.read_text() == "mine"


def test_score_reports_an_unreadable_input_as_one_error(scored, tmp_path, monkeypatch, capsys):
    import benchmark.score as score

    scene_dir, renders = scored

    def denied(folder):
        raise PermissionError(13, "Permission denied", str(folder))

    monkeypatch.setattr(score, "list_images", denied)  # as a folder without read permission does
    assert run_cli(TOOL.run, ["score", "--pred", str(renders), "--gt", str(scene_dir), "--lpips", "none"]) == 2
    one_error_line(capsys, str(renders), "permission denied")


# --- confinement: a record's fields never lead the report out of the store (issue 35) -----------------------
CID = "garden-tiny_H_3dgs_tiny_s0"


def _image(path: Path, value: float) -> None:
    write_image(path, np.full((8, 8, 3), value, np.float32))


@pytest.fixture
def report_store(tmp_path):
    """A hand-made store of one finished cell (nothing trains): its data, its run folder and its record; and,
    outside the store, a run folder with a 'secret' render."""
    root = tmp_path / "bench"
    data = root / "data" / "garden-tiny" / "H"
    _image(data / "images" / "000.png", 0.6)
    _image(data / "clean" / "000.png", 0.5)
    (data / "test_list.txt").write_text("000.png\n")
    for run in (root / "runs" / CID, tmp_path / "outside" / "run"):
        (run / "results.json").parent.mkdir(parents=True)
        (run / "results.json").write_text('{"eval_split": "test"}')
        _image(run / "renders" / "test" / "000.png", 0.45)
    record = {"cell_id": CID, "scene": "garden", "size": "tiny", "weather": "H", "method": "3dgs", "preset": "tiny",
              "seed": 0, "overrides": {}, "status": "ok", "psnr": 26.0, "ssim": 0.9, "lpips": None,
              "ssim_protocol": "3dgs", "lpips_net": None, "train_time_s": 1.0, "run_dir": f"runs/{CID}",
              "per_view": [{"name": "000.png", "psnr": 26.0}]}
    return root, record


def _files(top: Path) -> dict[str, bytes]:
    """Every file and link under ``top`` (links not followed), by path relative to it."""
    return {str(p.relative_to(top)): (os.readlink(p).encode() if p.is_symlink() else p.read_bytes())
            for p in sorted(top.rglob("*")) if p.is_symlink() or p.is_file()}


def _escape_by_link(root: Path, record: dict) -> dict:
    run = root / "runs" / CID
    for p in sorted(run.rglob("*"), reverse=True):
        p.rmdir() if p.is_dir() else p.unlink()
    run.rmdir()
    run.symlink_to(root.parent / "outside" / "run")
    return record


def _render_linked_out(root: Path, record: dict) -> dict:
    render = root / "runs" / CID / "renders" / "test" / "000.png"
    render.unlink()
    render.symlink_to(root.parent / "outside" / "run" / "renders" / "test" / "000.png")
    return record


# case -> (how the record or the store is made hostile, words the one error line must hold)
ONE_NAME, OUTSIDE = "not a single file name", "points outside"
REPORT_ESCAPES = {
    # the thumbnails' names are made of the cell id: this one used to write JPEGs beside --out
    "cell_id-climbs-out": (lambda root, r: dict(r, cell_id="x/" + "../" * 6 + "escaped"), ("'cell_id'", ONE_NAME)),
    "cell_id-absolute": (lambda root, r: dict(r, cell_id=str(root.parent / "escaped")), ("'cell_id'", ONE_NAME)),
    # --copy-full used to read and copy this run's images into the report
    "run_dir-absolute": (lambda root, r: dict(r, run_dir=str(root.parent / "outside" / "run")), ("'run_dir'", OUTSIDE)),
    "run_dir-climbs-out": (lambda root, r: dict(r, run_dir="../outside/run"), ("'run_dir'", OUTSIDE)),
    "run_dir-linked-out": (_escape_by_link, ("'run_dir'", OUTSIDE)),
    "scene-climbs-out": (lambda root, r: dict(r, scene="../../outside"), ("'scene'", ONE_NAME)),
    "render-linked-out": (_render_linked_out, ("render 000.png", "leads outside the results store")),
}


def test_the_hand_made_store_reports(report_store, tmp_path, capsys):
    """The sane store the escapes below start from makes a report (so a refusal there is the escape's)."""
    root, record = report_store
    ResultsStore(root).append(record)
    assert run_cli(TOOL.run, ["report", "--root", str(root), "--out", str(tmp_path / "out"), "--copy-full"]) == 0
    assert (tmp_path / "out" / "index.html").is_file() and list((tmp_path / "out" / "images" / "full").rglob("*.png"))


@pytest.mark.parametrize("case", list(REPORT_ESCAPES))
def test_report_refuses_record_fields_that_lead_out_of_the_store(case, report_store, tmp_path, capsys):
    root, record = report_store
    make_hostile, words = REPORT_ESCAPES[case]
    ResultsStore(root).append(make_hostile(root, record))
    before = _files(tmp_path)
    assert run_cli(TOOL.run, ["report", "--root", str(root), "--out", str(tmp_path / "out"), "--copy-full"]) == 2
    one_error_line(capsys, *words)
    assert _files(tmp_path) == before  # nothing written anywhere: not beside --out, not in the store
    assert not (tmp_path / "out").exists()


# --- a malformed record costs its line, not the store (issue 35, item 2) ------------------------------------------
DEEP = "[" * 200_000 + "]" * 200_000
# case -> (the store's second line, words its one warning line must hold); these used to end in tracebacks
MALFORMED_LINES = {
    "list-as-cell_id": ('{"cell_id": ["a"], "scene": "garden"}', "field 'cell_id' must be a string"),
    "string-as-psnr": ("PSNR-ABC", "field 'psnr' must be a number or null, got 'abc'"),
    "missing-scene": ("NO-SCENE", "field 'scene' is missing"),
    "nested-200k-deep": (DEEP, "is not valid JSON (nested too deeply)"),
    "non-object": ('["garden", 20.0]', "holds a list, not an object"),
    "nan-psnr": ("PSNR-NAN", "field 'psnr' must be a finite number, got nan"),
    "unknown-status": ("STATUS-DONE", "field 'status' must be 'ok' or 'error', got 'done'"),
}


def _malformed(record: dict, line: str) -> str:
    other = dict(record, cell_id=record["cell_id"].replace("3dgs", "nimbus"), method="nimbus")
    edits = {"PSNR-ABC": dict(other, psnr="abc"), "NO-SCENE": {k: v for k, v in other.items() if k != "scene"},
             "PSNR-NAN": dict(other, psnr=float("nan")), "STATUS-DONE": dict(other, status="done")}
    return json.dumps(edits[line]) if line in edits else line


@pytest.mark.parametrize("case", list(MALFORMED_LINES))
def test_tables_and_report_skip_a_malformed_record_with_one_warning_line(case, report_store, tmp_path, capsys):
    root, record = report_store
    line, words = MALFORMED_LINES[case]
    ResultsStore(root).append(record)
    with open(root / "results.jsonl", "a") as f:
        f.write(_malformed(record, line) + "\n")
    for command in (["tables", "--out", str(tmp_path / "tables")], ["report", "--out", str(tmp_path / "report")]):
        assert run_cli(TOOL.run, [*command[:1], "--root", str(root), *command[1:]]) == 0, command
        err = capsys.readouterr().err
        warned = [w for w in err.splitlines() if w.startswith("warning:")]
        assert "Traceback" not in err and len(warned) == 1, err
        assert f"results.jsonl line 2: {words}" in warned[0] and len(warned[0]) < 400, warned[0]
    # the good record is still there, in the tables and in the report, and the skipped one is not
    table = (tmp_path / "tables" / "weather_H.md").read_text()
    assert "| 3dgs | 26.00 |" in table and "| nimbus |" not in table
    assert CID in (tmp_path / "report" / "index.html").read_text()


# --- --overwrite replaces only the command's own earlier output (issue 35) ------------------------------------
def _scene_folder(tmp_path: Path) -> Path:
    scene = tmp_path / "scene"
    (scene / "sparse" / "0").mkdir(parents=True)
    (scene / "sparse" / "0" / "cameras.txt").write_text("# a COLMAP model\n")
    return scene


MARKER = ".nimbus-output"  # what a command writes into its output folder, naming itself (an on-disk name)


# case -> (the --out folder, made in the report store's tmp_path; words the one error line must hold)
REPORT_OUT_REFUSALS = {
    # these two used to be deleted by `report --out ... --overwrite`
    "stability-results-in-the-store": (lambda root: root / "stability", ("results store",)),
    "the-stores-locks": (lambda root: root / "locks", ("results store",)),
    "a-new-folder-in-the-store": (lambda root: root / "report", ("results store",)),
    "a-new-folder-in-a-scene": (lambda root: _scene_folder(root.parent) / "report", ("scene",)),
    "a-folder-of-the-users": (lambda root: root.parent / "mine", ("not written by nimbus-bench report",)),
    "another-commands-output": (lambda root: root.parent / "stab", ("not written by 'nimbus-bench stability'",)),
}


@pytest.mark.parametrize("case", list(REPORT_OUT_REFUSALS))
def test_report_overwrite_refuses_what_it_did_not_write(case, report_store, tmp_path, capsys):
    root, record = report_store
    ResultsStore(root).append(record)
    (root / "stability").mkdir()
    (root / "stability" / "stability.csv").write_text("case,method,verdict\nno_haze,3dgs,ok\n")
    (root / "locks").mkdir()
    (root / "locks" / f"{CID}.lock").write_text('{"pid": 1}\n')
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "thesis.tex").write_text("mine")
    (tmp_path / "stab").mkdir()
    (tmp_path / "stab" / MARKER).write_text("nimbus-bench stability\n")
    out, words = REPORT_OUT_REFUSALS[case]
    out = out(root)
    before = _files(tmp_path)
    assert run_cli(TOOL.run, ["report", "--root", str(root), "--out", str(out), "--overwrite"]) == 2
    one_error_line(capsys, "--out", *words, "nothing was written or deleted")
    assert _files(tmp_path) == before


def test_report_overwrite_replaces_its_own_earlier_report(report_store, tmp_path):
    root, record = report_store
    ResultsStore(root).append(record)
    out = tmp_path / "out"
    assert run_cli(TOOL.run, ["report", "--root", str(root), "--out", str(out)]) == 0
    (out / "stale.txt").write_text("from the earlier report")
    assert run_cli(TOOL.run, ["report", "--root", str(root), "--out", str(out), "--overwrite"]) == 0
    assert (out / "index.html").is_file() and not (out / "stale.txt").exists()


@pytest.mark.parametrize("command", [["stability", "--cases", "no_haze", "--methods", "3dgs", "--iterations", "2",
                                      "--lpips", "none"]])
def test_case_reports_overwrite_only_their_own_output(command, tmp_path, capsys):
    """Checked before any case runs: a foreign folder is refused, and so is one inside a results store."""
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "thesis.tex").write_text("mine")
    ResultsStore(tmp_path / "bench").append({**CELL, "cell_id": "a", "status": "ok"})
    before = _files(tmp_path)
    for out, words in ((tmp_path / "mine", "not written by"), (tmp_path / "bench" / command[0], "results store")):
        argv = [*command, "--out", str(out), "--work", str(tmp_path / "w"), "--overwrite"]
        assert run_cli(TOOL.run, argv) == 2
        one_error_line(capsys, words)
        assert _files(tmp_path) == before


def test_the_store_file_is_what_marks_a_store():
    from benchmark.store import STORE_FILE
    from nimbus.utils.fs import OUTPUT_MARKER, STORE_OR_SCENE_FILES

    assert STORE_OR_SCENE_FILES[0] == STORE_FILE  # nimbus cannot import benchmark: the name is repeated
    assert OUTPUT_MARKER == MARKER


# --- issue 35, round 2: a full disk and non-finite values in records ----------------------------------------------
def test_a_cell_that_meets_a_full_disk_is_recorded_as_failed_in_one_line(tmp_path, monkeypatch, disk_full):
    from nimbus.utils.fs import atomic_write_bytes

    def cell_fn(c, root, options):  # a cell whose run writes its checkpoint when the disk is full
        final, partial = cell_module.clear_run_dirs(Path(root), c)
        atomic_write_bytes(partial / "checkpoint.pt", bytes(4096))
        return fake_cell(root, c)

    monkeypatch.setattr(cell_module, "_train_cell", cell_fn)
    monkeypatch.setattr(cell_module, "_score_cell", lambda record, root, options: {})
    disk_full(".checkpoint.pt.tmp-")
    record = cell_module.run_cell(the_cell(), str(tmp_path), OPTIONS)
    assert record["status"] == "error" and "traceback" not in record, (record.get("error"), record.get("traceback"))
    assert record["error"].startswith("no space left on the device of ") and "checkpoint.pt needs 4,096 bytes" in \
        record["error"]
    assert not list(tmp_path.rglob(".checkpoint.pt.tmp-*"))


@pytest.mark.parametrize("field, value, where", [
    ("psnr", float("nan"), "psnr"),
    ("per_view", [{"name": "a", "ssim": float("inf")}], "per_view[0].ssim"),
])
def test_a_record_with_a_non_finite_value_is_refused_naming_the_field(tmp_path, field, value, where):
    store = ResultsStore(tmp_path)
    cell = {"status": "ok", "scene": "garden", "size": "tiny", "weather": "H", "method": "3dgs", "preset": "tiny",
            "seed": 0}
    store.append({**cell, "cell_id": "ok", "psnr": 20.0})
    before = store.path.read_bytes()
    with pytest.raises(NimbusError, match=rf"refusing to write a record of cell 'bad' .*: its field "
                                          rf"{re.escape(where)} is not a finite number"):
        store.append({**cell, "cell_id": "bad", field: value})
    assert store.path.read_bytes() == before
