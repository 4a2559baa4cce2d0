"""Grid runner, results store, executors (local processes, Dask) and resumption, on a tiny grid.

Every cell is 3DGS with 5 iterations on the tiny built-in garden (16 views of 64x48),
so a cell costs well under a second plus its process start-up.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest

from benchmark import cell, grid
from benchmark.cell import CEILING, CellOptions, data_dir, run_dir, scene_dir
from benchmark.cli import TOOL
from benchmark.grid import DaskExecutor, InlineExecutor, LocalExecutor, build_cells, run_grid
from benchmark.store import ResultsStore, load_results
from nimbus.cli_util import run_cli
from nimbus.data.images import read_image, write_image
from nimbus.errors import NimbusError, SkippedRecordWarning
from nimbus.metrics import peak_signal_noise_ratio as psnr
from nimbus.utils.fs import sha256_file

OVERRIDES = {"iterations": "5"}
OPTIONS = CellOptions(lpips_net=None)  # LPIPS is tested in test_lpips / test_score; keep cells fast


def cells(weathers=("H", "R")):
    return build_cells(["garden"], list(weathers), ["3dgs"], ["tiny"], [0], "tiny", OVERRIDES)


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """A root where the default local executor ran two cells (one worker process: the second reuses it)."""
    root = tmp_path_factory.mktemp("bench")
    outcome = run_grid(cells(), root, LocalExecutor(jobs=1), OPTIONS, progress=False, log=lambda s: None)
    return root, outcome


def _original_step():
    from nimbus.methods.gs3d import GaussianSplatting

    return GaussianSplatting.train_iteration


_ORIGINAL_STEP = _original_step()


def copy_data(src, dst):
    """A new root sharing the prepared scenes and degraded data (skips re-synthesis)."""
    for sub in ("scenes", "data"):
        shutil.copytree(src / sub, dst / sub)
    return dst


# --- store -----------------------------------------------------------------------------------
#: The fields every results record has (nimbus.schemas.ResultRecord): a hand-made record starts from these.
CELL = {"scene": "garden", "size": "tiny", "weather": "H", "method": "3dgs", "preset": "tiny", "seed": 0}


def test_store_ignores_and_repairs_a_truncated_last_line(tmp_path):
    store = ResultsStore(tmp_path)
    store.append({**CELL, "cell_id": "a", "status": "ok", "psnr": 20.0})
    store.append({**CELL, "cell_id": "b", "status": "error", "error": "boom"})
    with open(store.path, "ab") as f:  # a crash in the middle of writing a record
        f.write(b'{"cell_id": "c", "status": "o')
    with pytest.warns(UserWarning, match="truncated"):
        assert [r["cell_id"] for r in store.records()] == ["a", "b"]
        assert store.finished() == {"a"}
    with pytest.warns(UserWarning, match="truncated"):
        store.append({**CELL, "cell_id": "c", "status": "ok"})
    lines = store.path.read_text().splitlines()
    assert [json.loads(line)["cell_id"] for line in lines] == ["a", "b", "c"]
    store.append({**CELL, "cell_id": "b", "status": "ok", "psnr": 21.0})  # a retry supersedes the error
    df = load_results(tmp_path)
    assert sorted(df["cell_id"]) == ["a", "b", "c"]
    assert df.set_index("cell_id").loc["b", "psnr"] == 21.0
    assert len(load_results(tmp_path, latest=False)) == 4


def test_store_skips_a_corrupt_middle_line_and_reads_the_rest(tmp_path):
    store = ResultsStore(tmp_path)
    store.append({**CELL, "cell_id": "a", "status": "ok"})
    with open(store.path, "ab") as f:
        f.write(b"not json\n")
    store.append({**CELL, "cell_id": "b", "status": "ok"})
    with pytest.warns(SkippedRecordWarning, match=r"results.jsonl line 2: is not valid JSON .*skipped"):
        assert [r["cell_id"] for r in store.records()] == ["a", "b"]


# --- cells -----------------------------------------------------------------------------------
def test_build_cells_order_ids_and_validation():
    cs = build_cells(["garden", "street"], ["h", "R+H"], ["3dgs"], ["tiny"], [0, 1])
    assert len(cs) == 8
    assert cs[0].cell_id == "garden-tiny_H_3dgs_tiny_s0"
    assert cs[2].weather == "H+R"  # canonical setting names
    assert len({c.cell_id for c in cs}) == 8
    assert build_cells(["garden"], ["H"], ["3dgs"], ["tiny"], [0], overrides={"iterations": "5"})[0].cell_id \
        != cs[0].cell_id
    for bad in (dict(scenes=["nowhere"]), dict(weathers=["fog+X"]), dict(methods=["nope"]),
                dict(presets=["huge"]), dict(seeds=[-1]), dict(overrides={"no_such_field": "1"})):
        args = dict(scenes=["garden"], weathers=["H"], methods=["3dgs"], presets=["tiny"], seeds=[0]) | bad
        overrides = args.pop("overrides", None)
        with pytest.raises(NimbusError):
            build_cells(**args, overrides=overrides)


def test_a_cell_named_twice_is_one_cell(tmp_path, capsys):
    """Repeated names and seeds made copies of one cell, which trained at once into one run folder."""
    cs = build_cells(["garden", "garden"], ["H", "h"], ["3dgs"], ["tiny", "tiny"], [0, 0])
    assert [c.cell_id for c in cs] == ["garden-tiny_H_3dgs_tiny_s0"]
    for flag in ("--preset", "--scenes"):
        assert run_cli(TOOL.run, ["run", flag, ",", "--root", str(tmp_path / "r")]) == 2
        assert f"{flag} is empty" in capsys.readouterr().err
    assert not (tmp_path / "r").exists()


def test_the_clean_ceiling_is_one_cell_per_scene_preset_and_seed():
    cs = build_cells(["garden", "street"], ["H", "R"], ["3dgs", "nimbus"], ["tiny"], [0, 1], ceiling=True)
    ceilings = [c for c in cs if c.is_ceiling]
    # per scene x preset x seed, not per weather or method; 3dgs among the methods is a cell of its own
    assert [c.cell_id for c in ceilings] == ["garden-tiny_clean_3dgs_tiny_s0", "garden-tiny_clean_3dgs_tiny_s1",
                                             "street-tiny_clean_3dgs_tiny_s0", "street-tiny_clean_3dgs_tiny_s1"]
    assert len(cs) == 2 * 2 * 2 * 2 + 4 and len({c.cell_id for c in cs}) == len(cs)
    assert cs[:2] == ceilings[:2]  # each scene's reference first
    assert not any(c.is_ceiling for c in build_cells(["garden"], ["H"], ["3dgs"], ["tiny"], [0]))  # only when asked
    assert data_dir("r", ceilings[0]) == scene_dir("r", ceilings[0])  # the clean scene, not a weather setting
    # the ceiling trains 3dgs with the grid's --set: one 3dgs lacks is refused, naming the way out
    with pytest.raises(NimbusError, match="--no-ceiling"):
        build_cells(["garden"], ["H"], ["nimbus"], ["tiny"], [0], overrides={"lambda_dcp": "0.1"}, ceiling=True)
    assert build_cells(["garden"], ["H"], ["nimbus"], ["tiny"], [0], overrides={"lambda_dcp": "0.1"})


def test_default_methods_skip_unregistered(monkeypatch):
    monkeypatch.setattr(grid, "DEFAULT_METHODS", ("not-a-method", "3dgs"))
    names, skipped = grid.resolve_methods(None)
    assert names == ["3dgs"] and skipped == ["not-a-method"]
    with pytest.raises(NimbusError, match="unknown method"):
        grid.resolve_methods("3dgs,not-a-method")


# --- end to end ----------------------------------------------------------------------------
def test_local_run_records_and_scores_against_clean_views(finished):
    root, outcome = finished
    assert [r["status"] for r in outcome.ran] == ["ok", "ok"], [r.get("error") for r in outcome.ran]
    df = load_results(root)
    assert sorted(df["weather"]) == ["H", "R"]
    for rec in df["record"]:
        c = next(c for c in cells() if c.cell_id == rec["cell_id"])
        data, run = data_dir(root, c), run_dir(root, c)
        assert rec["input_sha256"] == sha256_file(data / "manifest.json")
        assert [v["name"] for v in rec["per_view"]] == ["000.png", "008.png"]  # the LLFF test views
        for v in rec["per_view"]:
            render = run / "renders" / "test" / v["name"]
            assert rec["output_sha256"][v["name"]] == sha256_file(render)
            # scored against clean/, not against the degraded images the trainer saw
            assert v["psnr"] == pytest.approx(psnr(read_image(render), read_image(data / "clean" / v["name"])))
            assert v["psnr"] != pytest.approx(psnr(read_image(render), read_image(data / "images" / v["name"])))
        assert rec["psnr"] == pytest.approx(np.mean([v["psnr"] for v in rec["per_view"]]))
        assert rec["lpips"] is None and rec["ssim_protocol"] == "3dgs"
        assert rec["psnr_vs_input"] is None  # the trainer scored against clean/ too: no figure against the input
        assert rec["iterations"] == 5 and rec["num_gaussians"] > 0
        assert rec["num_params"] >= rec["num_gaussians"] * 11
        assert len(rec["config_hash"]) == 64 and rec["config"]["iterations"] == 5
        assert {"nimbus", "torch", "numpy", "pycolmap", "cpu_isa"} <= rec["versions"].keys()
        assert rec["peak_memory_mb"] > 0 and rec["render_fps"] > 0 and rec["started_at"] <= rec["finished_at"]
        assert isinstance(rec["threads"], int) and rec["threads"] >= 1  # what trained it (results move with it)
        assert not list((root / "runs").glob("*.partial"))


def _input_score(data, names, lpips_net=None) -> dict:
    """The degraded test views against the clean ones, scored here with benchmark.metrics on the files."""
    from benchmark.metrics import score_images

    return score_images([read_image(data / "images" / n) for n in names],
                        [read_image(data / "clean" / n) for n in names], ssim_protocol="3dgs",
                        lpips_net=lpips_net, names=names)["mean"]


def test_a_weather_cell_records_its_degraded_inputs_own_score(finished):
    """input_psnr / input_ssim / input_lpips: the cell's degraded test views themselves, scored as its renders are."""
    root, _ = finished
    for rec in load_results(root)["record"]:
        c = next(c for c in cells() if c.cell_id == rec["cell_id"])
        data = data_dir(root, c)
        names = [v["name"] for v in rec["per_view"]]  # the cell's test views, no training view
        expected = _input_score(data, names)
        assert rec["input_psnr"] == pytest.approx(expected["psnr"], rel=1e-6)
        assert rec["input_ssim"] == pytest.approx(expected["ssim"], rel=1e-6)
        assert rec["input_lpips"] is None  # the grid was run without LPIPS, like the renders
        # The weather is in the input (below a perfect score), and it is no render's score.
        assert 0 < rec["input_psnr"] < 60 and rec["input_ssim"] < 1
        assert rec["input_psnr"] != pytest.approx(rec["psnr"])
    h = next(r for r in load_results(root)["record"] if r["weather"] == "H")
    r = next(r for r in load_results(root)["record"] if r["weather"] == "R")
    assert h["input_psnr"] != pytest.approx(r["input_psnr"])  # each setting its own input


def test_the_input_score_takes_the_cells_lpips_network(finished):
    """Rescored with LPIPS, a cell's input gets the same network's value as the one computed here on the files."""
    from nimbus.metrics.lpips_weights import weights_path

    if not weights_path("alex").is_file():
        pytest.skip("LPIPS alex weights not set up; run `nimbus-bench setup-weights`")
    root, _ = finished
    rec = next(r for r in ResultsStore(root).records() if r["weather"] == "H")
    scored = cell.score_cell({**rec, "status": cell.TRAINED}, str(root), CellOptions(lpips_net="alex"))
    assert scored["status"] == "ok", scored.get("error")
    expected = _input_score(data_dir(root, cell.Cell.from_dict(rec)), [v["name"] for v in rec["per_view"]], "alex")
    assert scored["input_lpips"] == pytest.approx(expected["lpips"], rel=1e-5) and scored["input_lpips"] > 0
    assert scored["input_psnr"] == pytest.approx(rec["input_psnr"])  # the rest as before


def test_a_settings_input_is_scored_once_per_process_and_again_when_its_data_changes(finished, tmp_path,
                                                                                      monkeypatch):
    """Every method of a setting has the same degraded input: scoring it again for each gave the same numbers."""
    root, _ = finished
    rec = next(r for r in ResultsStore(root).records() if r["weather"] == "H")
    calls = []
    real = cell.score_input
    monkeypatch.setattr(cell, "score_input", lambda *a, **k: calls.append(a[0]) or real(*a, **k))
    cell._input_score.cache_clear()
    options = CellOptions(lpips_net=None)
    first = cell.score_cell({**rec, "status": cell.TRAINED}, str(root), options)
    again = cell.score_cell({**rec, "status": cell.TRAINED}, str(root), options)
    assert len(calls) == 1 and first["input_psnr"] == again["input_psnr"] == pytest.approx(rec["input_psnr"])
    # The same setting synthesised again (another manifest) is scored again, from its own images.
    copy = copy_data(root, tmp_path)
    shutil.copytree(root / "runs", copy / "runs")
    data = data_dir(copy, cell.Cell.from_dict(rec))
    names = [v["name"] for v in rec["per_view"]]
    image = read_image(data / "images" / names[0])
    image[:8] = 1.0 - image[:8]
    write_image(data / "images" / names[0], image)
    manifest = data / "manifest.json"
    manifest.write_text(manifest.read_text() + "\n")
    changed = cell.score_cell({**rec, "status": cell.TRAINED}, str(copy), options)
    assert len(calls) == 2 and changed["input_psnr"] == pytest.approx(_input_score(data, names)["psnr"], rel=1e-6)
    assert changed["input_psnr"] < first["input_psnr"]


def test_the_workers_start_while_the_data_is_prepared_and_then_train_the_cells(finished, tmp_path, monkeypatch):
    """Their start-up (a fresh checkout: the kernels' build) runs beside the data's preparation, not after it."""
    import multiprocessing

    from benchmark import workers

    root, outcome = finished
    spawned, alive_at_prep = [], []

    class Counted(workers._Worker):
        def __init__(self, *args, **kwargs):
            spawned.append(args[1:] + tuple(kwargs.values()))
            super().__init__(*args, **kwargs)

    def prepare(*args, **kwargs):
        alive_at_prep.extend(p.name for p in multiprocessing.active_children())
        return real(*args, **kwargs)

    real = grid.prepare_data
    monkeypatch.setattr(workers, "_Worker", Counted)
    monkeypatch.setattr(grid, "prepare_data", prepare)
    again = run_grid(cells(), copy_data(root, tmp_path), LocalExecutor(jobs=1), OPTIONS, progress=False,
                     log=lambda s: None).ran
    assert alive_at_prep == ["nimbus-bench-worker"]
    assert len(spawned) == 1 and spawned[0][1] is not None  # one worker, started with the options to warm up
    assert [r["status"] for r in again] == ["ok", "ok"] and {r["cell_id"] for r in again} == {
        r["cell_id"] for r in outcome.ran}
    assert not [p for p in multiprocessing.active_children() if p.name == "nimbus-bench-worker"]


def test_an_executor_used_again_sizes_its_workers_for_the_new_cells(monkeypatch):
    """Workers are sized for the cells they are started for: a second imap does not inherit the first one's count."""
    from benchmark import workers

    sizes = []
    monkeypatch.setattr(workers.CellWorkers, "imap", lambda self, cells, root, options: iter(sizes.append(self.jobs)
                                                                                          or ()))
    monkeypatch.setattr(grid, "usable_cpus", lambda: 8)
    executor = LocalExecutor("auto")
    for n in (1, 5):
        list(executor.imap(cells()[:1] * n, "root", OPTIONS))
    assert sizes == [1, 5]


def test_workers_started_for_data_that_fails_to_prepare_are_stopped(tmp_path, monkeypatch):
    import multiprocessing

    def broken(*args, **kwargs):
        raise NimbusError("no data")

    monkeypatch.setattr(grid, "prepare_data", broken)
    with pytest.raises(NimbusError, match="no data"):
        run_grid(cells(), tmp_path / "root", LocalExecutor(jobs=1), OPTIONS, progress=False, log=lambda s: None)
    # Told to stop: it exits once warmed up (here in seconds; a fresh checkout's build takes longer).
    for worker in [p for p in multiprocessing.active_children() if p.name == "nimbus-bench-worker"]:
        worker.join(60)
        assert not worker.is_alive(), "the worker started for the run did not exit"


def test_a_reused_worker_gives_a_cell_the_figures_of_a_fresh_one(finished, tmp_path):
    """Nothing leaks from one cell to the next in a worker: the same renders and scores as a first cell."""
    root, outcome = finished
    second = outcome.ran[1]
    fresh = run_grid([c for c in cells() if c.cell_id == second["cell_id"]], copy_data(root, tmp_path),
                     LocalExecutor(jobs=1), OPTIONS, progress=False, log=lambda s: None).ran[0]
    assert fresh["status"] == "ok", fresh.get("error")
    assert fresh["output_sha256"] == second["output_sha256"]
    assert fresh["per_view"] == second["per_view"] and fresh["num_gaussians"] == second["num_gaussians"]


def test_a_dead_worker_fails_its_cell_only(finished, tmp_path, monkeypatch):
    """A worker killed mid-cell (out of memory, a signal) costs that cell; a new worker runs the rest."""
    import os
    import signal

    from benchmark import workers

    root = copy_data(finished[0], tmp_path)
    victim = cells(["H", "R", "S"])[1]
    original = workers._Worker.send

    def send(self, c, *args):
        taken = original(self, c, *args)
        if taken and c.cell_id == victim.cell_id:
            os.kill(self.process.pid, signal.SIGKILL)
        return taken

    monkeypatch.setattr(workers._Worker, "send", send)
    outcome = run_grid(cells(["H", "R", "S"]), root, LocalExecutor(jobs=1), OPTIONS, progress=False,
                       log=lambda s: None)
    by_id = {r["cell_id"]: r for r in outcome.ran}
    assert len(by_id) == 3 and [r["cell_id"] for r in outcome.failed] == [victim.cell_id]
    assert "killed by signal 9" in by_id[victim.cell_id]["error"]
    assert ResultsStore(root).finished() == {c.cell_id for c in cells(["H", "R", "S"])} - {victim.cell_id}
    monkeypatch.undo()
    again = run_grid(cells(["H", "R", "S"]), root, LocalExecutor(jobs=1), OPTIONS, progress=False,
                     log=lambda s: None)  # resumable: only the lost cell runs again
    assert [r["cell_id"] for r in again.ran] == [victim.cell_id] and not again.failed


_PEAK_PROBE = """
import numpy as np
from nimbus.utils.memory import peak_rss_mb, reset_peak_rss, status_kb
if not reset_peak_rss():
    print("no-reset")
    raise SystemExit
before = peak_rss_mb()
big = np.ones(2**25)  # 256 MiB, every page touched
grown = peak_rss_mb()
del big
reset = reset_peak_rss()
print(before, grown, reset, peak_rss_mb(), status_kb("VmRSS") / 1024)
"""


def test_peak_memory_resets_between_jobs():
    """In a fresh process (as a worker starts): a long-lived test process may hand the 256 MiB back from memory it
    already holds, which raises no peak."""
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", _PEAK_PROBE], capture_output=True, text=True, check=True).stdout
    if out.strip() == "no-reset":
        pytest.skip("this kernel does not let a process reset its resident-set high-water mark")
    before, grown, reset, after, rss = out.split()
    assert float(grown) > float(before) + 200
    assert reset == "True"
    assert float(after) < float(before) + 100 and float(after) <= float(rss) + 1


def test_a_worker_that_cannot_reset_the_peak_runs_one_cell(monkeypatch):
    """Where the peak cannot be reset, each cell gets a fresh process (its figure is its own there too)."""
    import multiprocessing
    import threading

    from benchmark import workers

    monkeypatch.setattr(workers, "warm_up", lambda options, reverse=False: None)
    monkeypatch.setattr(workers, "reset_peak_memory", lambda: False)
    monkeypatch.setattr(workers, "train_cell", lambda c, root, options: {"cell_id": c["scene"]})
    parent, child = multiprocessing.Pipe()
    t = threading.Thread(target=workers.serve, args=(child,))
    t.start()
    parent.send((cells()[0].to_dict(), "root", OPTIONS))
    parent.send((cells()[1].to_dict(), "root", OPTIONS))  # never taken
    assert parent.recv() == ({"cell_id": "garden"}, False)
    t.join(timeout=10)
    assert not t.is_alive() and not parent.poll()


def test_rerun_skips_finished_cells(finished):
    root, _ = finished
    before = (root / "results.jsonl").read_bytes()
    outcome = run_grid(cells(), root, InlineExecutor(), OPTIONS, progress=False, log=lambda s: None)
    assert outcome.ran == [] and len(outcome.skipped) == 2
    assert (root / "results.jsonl").read_bytes() == before


def test_crash_mid_cell_resumes_without_corrupt_records(finished, tmp_path, monkeypatch):
    root = copy_data(finished[0], tmp_path)
    from nimbus.methods.gs3d import GaussianSplatting
    from nimbus.train.runner import Runner

    first = cells()[0]
    original, original_train = GaussianSplatting.after_step, Runner.train
    running = {}

    def train(self):  # which run folder the method below trains into
        running["out"] = self.out
        return original_train(self)

    def crash(self, it):  # the process is killed during the second cell's training
        if running["out"].name.startswith(cells()[1].cell_id) and it == 3:
            raise KeyboardInterrupt
        return original(self, it)

    monkeypatch.setattr(Runner, "train", train)
    monkeypatch.setattr(GaussianSplatting, "after_step", crash)
    with pytest.raises(KeyboardInterrupt):
        run_grid(cells(), root, InlineExecutor(), OPTIONS, progress=False, log=lambda s: None)
    store = ResultsStore(root)
    assert [r["cell_id"] for r in store.records()] == [first.cell_id]
    assert (root / "runs" / (cells()[1].cell_id + cell.PARTIAL_SUFFIX)).is_dir()
    assert not run_dir(root, cells()[1]).exists()
    with open(store.path, "ab") as f:  # and a torn record from a crash while writing
        f.write(b'{"cell_id": "' + cells()[1].cell_id.encode() + b'", "sta')

    monkeypatch.setattr(GaussianSplatting, "after_step", original)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        outcome = run_grid(cells(), root, InlineExecutor(), OPTIONS, progress=False, log=lambda s: None)
    assert [r["cell_id"] for r in outcome.ran] == [cells()[1].cell_id] and outcome.skipped == [first.cell_id]
    recs = store.records()  # no warning now: the torn line was cut off before the append
    assert [r["status"] for r in recs] == ["ok", "ok"]
    # Ctrl-C inside a step saved a half-done step: the cell was trained again from the start, not resumed
    assert "resumed_from_iteration" not in recs[1]
    assert run_dir(root, cells()[1]).is_dir() and not list((root / "runs").glob("*.partial"))


def test_ctrl_c_gives_one_line_saying_how_to_continue(tmp_path, monkeypatch, capsys):
    """Ctrl-C reaches the parent and every worker: one line from the parent, no worker traceback or nimbus-train
    hint (the grid resumes its own cells), and the interrupt's exit status."""
    from benchmark import workers
    from benchmark.commands import run as run_command

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(run_command, "run_grid", interrupted)
    rc = run_cli(TOOL.run, ["run", "--scenes", "garden", "--weathers", "H", "--methods", "3dgs", "--root",
                            str(tmp_path / "r")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 130 and err[-1].startswith("error: interrupted; run the same command again to continue")
    assert str(tmp_path / "r") in err[-1] and not any("Traceback" in line for line in err)

    class Conn:  # a worker waiting for its next cell when Ctrl-C comes
        def recv(self):
            raise KeyboardInterrupt

    assert workers.serve(Conn()) is None
    assert capsys.readouterr().err == ""


def test_a_cell_cut_short_by_ctrl_c_does_not_print_nimbus_trains_resume_hint(finished, tmp_path, monkeypatch,
                                                                             capsys):
    from nimbus.methods.gs3d import GaussianSplatting

    original = GaussianSplatting.after_step

    def stop(self, it):
        if it == 3:
            raise KeyboardInterrupt
        return original(self, it)

    monkeypatch.setattr(GaussianSplatting, "after_step", stop)
    with pytest.raises(KeyboardInterrupt):
        cell.train_cell(cells()[0], str(copy_data(finished[0], tmp_path)), OPTIONS)
    assert "nimbus-train --resume" not in capsys.readouterr().err


class _Killed(BaseException):
    """A process killed between two steps (SIGKILL, a machine going away): nothing is saved on the way out."""


def _kill_second_cell_at(monkeypatch, step: int, cell_id: str | None = None):
    """Make the second cell's (or ``cell_id``'s) training die before its step ``step``."""
    from nimbus.methods.gs3d import GaussianSplatting
    from nimbus.train.runner import Runner

    original, original_train = GaussianSplatting.train_iteration, Runner.train
    running = {}

    def train(self):
        running["out"] = self.out
        return original_train(self)

    def killed(self, it):
        if running["out"].name.startswith(cell_id or cells()[1].cell_id) and it == step:
            raise _Killed
        return original(self, it)

    monkeypatch.setattr(Runner, "train", train)
    monkeypatch.setattr(GaussianSplatting, "train_iteration", killed)


def _killed_grid(finished, tmp_path, monkeypatch):
    """A grid of two cells checkpointing every 2 steps whose second cell died before its step 4 (after the
    checkpoint of step 2): ``(root, cells, its .partial folder)``."""
    root = copy_data(finished[0], tmp_path)
    grid_cells = build_cells(["garden"], ["H", "R"], ["3dgs"], ["tiny"], [0], "tiny", OVERRIDES)
    monkeypatch.setattr(cell, "make_config", _with_checkpoints_every(2))
    _kill_second_cell_at(monkeypatch, 4)
    with pytest.raises(_Killed):
        run_grid(grid_cells, root, InlineExecutor(), OPTIONS, progress=False, log=lambda s: None)
    partial = root / "runs" / (grid_cells[1].cell_id + cell.PARTIAL_SUFFIX)
    assert (partial / "checkpoint.pt").is_file()
    return root, grid_cells, partial


def test_a_killed_cell_continues_from_its_last_checkpoint(finished, tmp_path, monkeypatch):
    root, grid_cells, partial = _killed_grid(finished, tmp_path, monkeypatch)
    from nimbus.methods.gs3d import GaussianSplatting
    monkeypatch.setattr(GaussianSplatting, "train_iteration", _ORIGINAL_STEP)  # the kill undone, the config kept
    outcome = run_grid(grid_cells, root, InlineExecutor(), OPTIONS, progress=False, log=lambda s: None)
    [rec] = outcome.ran
    assert rec["status"] == "ok" and rec["resumed_from_iteration"] == 2 and rec["iterations"] == 5
    # the same figures as the cell trained without interruption (checkpointing does not change training)
    uninterrupted = load_results(finished[0]).set_index("cell_id").loc[grid_cells[1].cell_id]
    assert rec["psnr"] == pytest.approx(uninterrupted["psnr"], abs=1e-4)
    assert rec["num_gaussians"] == uninterrupted["num_gaussians"]
    assert run_dir(root, grid_cells[1]).is_dir() and not partial.exists()


def test_a_killed_clean_ceiling_cell_continues_from_its_last_checkpoint(finished, tmp_path, monkeypatch):
    """The ceiling is resumed by the cells' one path: its partial run is recognised as its own (the clean scene)."""
    root = copy_data(finished[0], tmp_path)
    [ceiling] = [c for c in build_cells(["garden"], ["H"], ["3dgs"], ["tiny"], [0], "tiny", OVERRIDES, ceiling=True)
                 if c.is_ceiling]
    monkeypatch.setattr(cell, "make_config", _with_checkpoints_every(2))
    _kill_second_cell_at(monkeypatch, 4, ceiling.cell_id)
    with pytest.raises(_Killed):
        run_grid([ceiling], root, InlineExecutor(), OPTIONS, progress=False, log=lambda s: None)
    partial = root / "runs" / (ceiling.cell_id + cell.PARTIAL_SUFFIX)
    assert (partial / "checkpoint.pt").is_file() and ResultsStore(root).records() == []
    from nimbus.methods.gs3d import GaussianSplatting
    monkeypatch.setattr(GaussianSplatting, "train_iteration", _ORIGINAL_STEP)
    [rec] = run_grid([ceiling], root, InlineExecutor(), OPTIONS, progress=False, log=lambda s: None).ran
    assert rec["status"] == "ok" and rec["resumed_from_iteration"] == 2 and rec["iterations"] == 5
    assert rec["weather"] == CEILING and not partial.exists()


def test_a_partial_run_of_other_settings_is_not_resumed(finished, tmp_path, monkeypatch):
    root, grid_cells, partial = _killed_grid(finished, tmp_path, monkeypatch)
    saved = json.loads((partial / "config.json").read_text())
    saved["config"]["lr_opacity"] *= 2  # e.g. a Nimbus whose preset changed since the interrupted attempt
    (partial / "config.json").write_text(json.dumps(saved))

    from nimbus.methods.gs3d import GaussianSplatting
    monkeypatch.setattr(GaussianSplatting, "train_iteration", _ORIGINAL_STEP)
    outcome = run_grid(grid_cells, root, InlineExecutor(), OPTIONS, progress=False, log=lambda s: None)
    [rec] = outcome.ran
    assert rec["status"] == "ok" and "resumed_from_iteration" not in rec
    run = run_dir(root, grid_cells[1])
    assert json.loads((run / "config.json").read_text())["config"]["lr_opacity"] != saved["config"]["lr_opacity"]


def _with_checkpoints_every(n: int):
    original = cell.make_config

    def make_config(method, preset, overrides):
        return dataclasses.replace(original(method, preset, overrides), checkpoint_interval=n)
    return make_config


def test_failed_cell_is_recorded_and_retried(finished, tmp_path, monkeypatch):
    root = copy_data(finished[0], tmp_path)
    from nimbus.train.runner import Runner

    def fail(self):
        raise NimbusError("every Gaussian was pruned")

    monkeypatch.setattr(Runner, "train", fail)
    outcome = run_grid(cells(["H"]), root, InlineExecutor(), OPTIONS, progress=False, log=lambda s: None)
    assert outcome.failed and outcome.failed[0]["error"] == "every Gaussian was pruned"
    assert ResultsStore(root).finished() == set()
    monkeypatch.undo()
    outcome = run_grid(cells(["H"]), root, InlineExecutor(), OPTIONS, progress=False, log=lambda s: None)
    assert [r["status"] for r in outcome.ran] == ["ok"]


def test_dask_executor_on_a_local_cluster(finished, tmp_path):
    # dask is in the test extra; an install without it (pip install -e .) skips rather than fails
    pytest.importorskip("distributed", reason="dask is not installed (pip install -e '.[test]' brings it)")
    from distributed import Client, LocalCluster

    root = copy_data(finished[0], tmp_path)
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as cluster, \
            Client(cluster) as client:
        outcome = run_grid(cells(["H"]), root, DaskExecutor(client), OPTIONS, progress=False, log=lambda s: None)
    assert [r["status"] for r in outcome.ran] == ["ok"], outcome.ran[0].get("error")
    df = load_results(root)
    assert list(df["cell_id"]) == [cells(["H"])[0].cell_id]
    # same data, config and seed as the local run: the same figures
    local = load_results(finished[0]).set_index("cell_id")
    assert df["psnr"].iloc[0] == pytest.approx(local.loc[df["cell_id"].iloc[0], "psnr"], abs=1e-6)
    with pytest.raises(NimbusError, match="--scheduler"):
        DaskExecutor(None)


# --- command line ------------------------------------------------------------------------
GRID_ARGV = ["run", "--scenes", "garden", "--weathers", "H,R", "--methods", "3dgs", "--set", "iterations=5",
             "--lpips", "none", "--quiet"]


def test_cli_resumes_and_prints_the_table(finished, capsys):
    root, _ = finished
    before = (root / "results.jsonl").read_bytes()
    rc = run_cli(TOOL.run, GRID_ARGV + ["--no-ceiling", "--root", str(root)])
    out, err = capsys.readouterr()
    assert rc == 0, err
    assert "skipping 2 finished cell(s)" in err and "clean-ceiling" not in err
    assert (root / "results.jsonl").read_bytes() == before  # --no-ceiling: nothing left to train
    lines = out.splitlines()
    assert lines[0].split() == ["Weather", "Method", "PSNR↑", "SSIM↑", "LPIPS↓", "Train", "s↓", "Cells", "Errors",
                                "Input", "PSNR"]
    assert lines[1].split()[:2] == ["H", "3dgs"] and lines[2].split()[:2] == ["R", "3dgs"]
    assert lines[1].split()[-3:-1] == lines[2].split()[-3:-1] == ["1", "0"]  # one cell each, no error
    # Each setting's degraded input, scored alike: what the line's cells have to beat.
    records = {r["weather"]: r for r in ResultsStore(root).records()}
    assert [line.split()[-1] for line in lines[1:3]] == [f"{records[w]['input_psnr']:.2f}" for w in "HR"]
    assert "Input PSNR = the degraded test views' own PSNR" in out
    assert "SSIM protocol: 3dgs" in out and "ceiling" not in out and "ΔPSNR" not in out
    assert not any(line.startswith(CEILING) for line in lines)


def test_cli_trains_the_clean_ceiling_once_on_the_clean_views(finished, tmp_path, capsys):
    """By default a grid of two weathers gains one clean-ceiling cell (3dgs on the clean scene), resumable alike."""
    src = finished[0]
    root = copy_data(src, tmp_path / "root")
    shutil.copytree(src / "runs", root / "runs")
    shutil.copyfile(src / "results.jsonl", root / "results.jsonl")  # the two weather cells, finished
    assert run_cli(TOOL.run, GRID_ARGV + ["--root", str(root)]) == 0
    out, err = capsys.readouterr()
    assert "skipping 2 finished cell(s)" in err and "+ 1 clean-ceiling cell(s)" in err
    recs = ResultsStore(root).records()
    assert len(recs) == 3
    ceiling = recs[-1]
    assert ceiling["status"] == "ok", ceiling.get("error")
    assert (ceiling["weather"], ceiling["method"], ceiling["preset"], ceiling["seed"], ceiling["size"]) == \
        (CEILING, "3dgs", "tiny", 0, "tiny")
    assert ceiling["cell_id"] == cells()[0].cell_id.replace("_H_", "_clean_")
    assert ceiling["config"]["iterations"] == 5  # the grid's --set
    assert not {"input_psnr", "input_ssim", "input_lpips"} & ceiling.keys()  # no degraded input of its own
    # It trained on the clean scene: its input is the clean scene's manifest, its run read that folder.
    clean = root / "scenes" / "garden-tiny"
    assert ceiling["input_sha256"] == sha256_file(clean / "manifest.json")
    config = json.loads((root / ceiling["run_dir"] / "config.json").read_text())
    assert config["scene"] == str(clean.resolve())
    # The same test views and ground truth as the weather cells (the synthesiser's clean/ is the scene's images).
    weather = [r for r in recs if r["weather"] != CEILING]
    assert all([v["name"] for v in r["per_view"]] == [v["name"] for v in ceiling["per_view"]] for r in weather)
    for v in ceiling["per_view"]:
        assert sha256_file(clean / "images" / v["name"]) == sha256_file(root / "data" / "garden-tiny" / "H" / "clean"
                                                                         / v["name"])
        render = root / ceiling["run_dir"] / "renders" / "test" / v["name"]
        assert v["psnr"] == pytest.approx(psnr(read_image(render), read_image(clean / "images" / v["name"])))
    # The summary: the ceiling first, then each line's gap to it (its PSNR minus the ceiling's).
    lines = out.splitlines()
    assert lines[0].split()[-3:] == ["ΔPSNR", "vs", "clean"]
    first = lines[1].split()
    assert first[:5] == [CEILING, "3DGS", "(clean", "views)", f"{ceiling['psnr']:.2f}"]
    assert first[-4:] == ["1", "0", "n/a", "n/a"]  # neither an input nor a gap of its own
    for line, rec in zip(lines[2:4], weather):
        assert line.split()[0] == rec["weather"]
        assert float(line.split()[-1]) == pytest.approx(rec["psnr"] - ceiling["psnr"], abs=0.005)
    # Rerun: every cell finished, the ceiling too; nothing trains again.
    before = (root / "results.jsonl").read_bytes()
    assert run_cli(TOOL.run, GRID_ARGV + ["--root", str(root)]) == 0
    assert "skipping 3 finished cell(s)" in capsys.readouterr().err
    assert (root / "results.jsonl").read_bytes() == before


@pytest.mark.parametrize("argv, message", [
    (["run", "--weathers", "fog,X"], "weather"),
    (["run", "--methods", "nope"], "unknown method"),
    (["run", "--seeds", "a"], "--seeds"),
    (["run", "--seeds", "0,1,0"], "names a seed twice"),
    (["run", "--seeds", "-1"], "--seeds"),
    (["run", "--executor", "dask"], "--scheduler"),
    (["run", "--jobs", "0"], "--jobs"),
    (["run", "--set", "nofield=1", "--methods", "3dgs"], "unknown setting"),
])
def test_cli_bad_input_is_one_clear_error(argv, message, tmp_path, capsys):
    assert run_cli(TOOL.run, argv + ["--root", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err
    assert "error:" in err and message in err and "Traceback" not in err
    assert not (tmp_path / "r").exists()


def test_worker_threads_count_the_cores_this_process_may_use(monkeypatch):
    # Under taskset / a scheduler's CPU set the machine's core count oversubscribes: two runs pinned to one
    # core each would both take every core's worth of threads.
    monkeypatch.setattr(os, "cpu_count", lambda: 64)
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {3}, raising=False)
    assert LocalExecutor(jobs=1).threads() == 1
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(8)), raising=False)
    assert LocalExecutor(jobs=2).threads() == 4 and LocalExecutor(jobs=16).threads() == 1
    monkeypatch.delattr(os, "sched_getaffinity", raising=False)  # no affinity query (macOS): the machine's count
    assert LocalExecutor(jobs=2).threads() == 32
    # auto: one worker per core, one thread each; fewer cells than cores share the cores out.
    assert LocalExecutor("auto").workers(200) == 64 and LocalExecutor("auto").threads(200) == 1
    assert LocalExecutor("auto").workers(3) == 3 and LocalExecutor("auto").threads(3) == 21
    assert LocalExecutor("auto").workers(1) == 1 and LocalExecutor("auto").threads(1) == 64


def test_auto_jobs_give_each_worker_one_thread_and_refuse_nonsense():
    # One thread a cell (as many cells as cores): its figures do not depend on how many cores the machine has.
    assert LocalExecutor("auto").threads() == 1 and LocalExecutor("auto").jobs is None
    for bad in (0, -1, "two", 1.5, True):
        with pytest.raises(NimbusError, match="--jobs"):
            LocalExecutor(bad)
    assert grid.jobs_arg("AUTO") == "auto" and grid.jobs_arg("3") == 3


def test_auto_workers_start_two_then_as_many_as_the_memory_holds_at_the_cells_peak():
    from benchmark.workers import FIRST_WAVE, MEMORY_SHARE, CellWorkers

    mib = 2 ** 20
    assert CellWorkers(8).allowed() == 8  # no budget: --jobs N runs N
    w = CellWorkers(8, memory=100_000 * mib)
    assert w.allowed() == FIRST_WAVE  # no cell has said what it takes yet
    w._note_peak({"peak_memory_mb": 1000.0})
    assert w.allowed() == 8  # 80 of them would fit: the cores bound it
    w._note_peak({"peak_memory_mb": float("nan")})  # a record without a usable peak changes nothing
    w._note_peak({"status": "error"})
    assert w.allowed() == 8
    w._note_peak({"peak_memory_mb": 100_000 * MEMORY_SHARE / 3 + 1})
    assert w.allowed() == 2  # the largest peak so far counts
    w._note_peak({"peak_memory_mb": 10 ** 9})
    assert w.allowed() == 1  # never none
    assert CellWorkers(1, memory=100_000 * mib).allowed() == 1


def test_auto_budget_is_memavailable_within_the_memory_limit(tmp_path, monkeypatch):
    from nimbus.utils import memory

    info = tmp_path / "meminfo"
    info.write_text("MemTotal:       8000000 kB\nMemAvailable:      1024 kB\n")
    monkeypatch.setattr(memory, "MEMINFO", info)
    monkeypatch.setenv(memory.MEMORY_LIMIT_ENV, "1")
    assert memory.available_memory() == 2 ** 20  # MemAvailable, below the 1 GiB limit
    info.write_text("MemAvailable:   99999999 kB\n")
    assert memory.available_memory() == 2 ** 30  # the limit, below MemAvailable
    monkeypatch.setattr(memory, "MEMINFO", tmp_path / "absent")
    assert memory.available_memory() == 2 ** 30  # no /proc: the limit alone


def test_auto_workers_retire_when_a_peak_says_fewer_fit(tmp_path, finished):
    """Three cells and a budget that holds none: the first two run at once (no peak known yet), the third alone."""
    from benchmark.workers import CellWorkers

    root = copy_data(finished[0], tmp_path)
    workers = CellWorkers(2, memory=1)
    todo = build_cells(["garden"], ["H", "R"], ["3dgs"], ["tiny"], [0, 1], "tiny", OVERRIDES)[:3]  # data made
    records = list(workers.imap(todo, str(root), dataclasses.replace(OPTIONS, threads=1)))
    assert [r["status"] for r in records] == ["ok"] * 3
    assert workers.peak_mb > 0 and workers.allowed() == 1
    assert [r["cells_at_once"] for r in records] == [2, 2, 1]
    assert all(r["threads"] == 1 for r in records)


PARENT_WITH_A_BUSY_CHILD = """
import multiprocessing, os, sys, time
from benchmark.workers import exit_with_parent

def busy(parent, ready):
    exit_with_parent(parent, poll_s=0.1)
    open(ready, "w").close()
    while True:  # a cell that would train for an hour
        time.sleep(0.01)

if __name__ == "__main__":
    ready = sys.argv[1]
    child = multiprocessing.get_context("spawn").Process(target=busy, args=(os.getpid(), ready))
    child.start()
    while not os.path.exists(ready):
        time.sleep(0.01)
    print(child.pid, flush=True)
    time.sleep(60)
"""


def test_a_worker_exits_soon_after_its_parent_is_killed(tmp_path):
    import signal
    import subprocess
    import sys
    import time

    script = tmp_path / "parent.py"
    script.write_text(PARENT_WITH_A_BUSY_CHILD)
    parent = subprocess.Popen([sys.executable, str(script), str(tmp_path / "ready")], stdout=subprocess.PIPE, text=True,
                              cwd=Path(__file__).resolve().parents[1])
    child = int(parent.stdout.readline())
    try:
        os.kill(parent.pid, signal.SIGKILL)  # no cleanup runs in the parent
        parent.wait(timeout=30)
        deadline = time.monotonic() + 30  # a guard; it takes about the poll interval
        while time.monotonic() < deadline and Path(f"/proc/{child}").exists() and \
                Path(f"/proc/{child}/stat").read_text().split()[2] != "Z":
            time.sleep(0.05)
        assert not Path(f"/proc/{child}").exists() or Path(f"/proc/{child}/stat").read_text().split()[2] == "Z"
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.kill(child, signal.SIGKILL)
