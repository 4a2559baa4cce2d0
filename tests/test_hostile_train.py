"""Hostile and faulty input to training (issue 14): checkpoints that would run code, --out over the scene,
garbage models, bad arguments and run folders, leftovers after a failure, resumed logs, corrupt PLY headers.

Every hostile file is built here in tmp_path.  A CLI failure must be one ``error:`` line and exit code 2.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from nimbus.cli.train import main as train_main
from nimbus.cli_util import MAX_SEED, seed_arg
from nimbus.data.builtin import render_builtin
from nimbus.errors import NimbusError
from nimbus.train.config import TrainConfig
from nimbus.train.ply import read_gaussian_ply, write_gaussian_ply
from nimbus.methods.gs3d import GaussianSplatting
from nimbus.train.checkpoint import CHECKPOINT, LAST_GOOD, check_plain
from nimbus.train.runner import Runner

REPO = Path(__file__).resolve().parents[1]
# A few iterations: every CLI run here takes about a second.
FAST = ["--preset", "tiny", "--set", "iterations=4", "--set", "checkpoint_interval=2", "--quiet"]


def cli(argv, capsys) -> tuple[int, str]:
    """Run nimbus-train in-process; (exit code, stderr)."""
    capsys.readouterr()
    with pytest.raises(SystemExit) as info:
        train_main([str(a) for a in argv])
    return info.value.code, capsys.readouterr().err


def assert_one_error(code: int, err: str, *needles: str) -> None:
    lines = [line for line in err.splitlines() if line.strip()]
    errors = [line for line in lines if line.startswith("error: ")]
    assert code == 2, err
    assert len(errors) == 1 and "Traceback" not in err, err
    for needle in needles:
        assert needle.lower() in errors[0].lower(), errors[0]


def snapshot(root: Path) -> dict[str, bytes]:
    """Every file under ``root`` by relative path, with its bytes."""
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def scene():
    s = render_builtin("garden", size="tiny", seed=0)
    return s.with_views(s.train_views[:4] + s.test_views[:2])


def _cfg(**kw) -> TrainConfig:
    base = dict(iterations=6, sh_degree=0, densify_from=100, densify_until=100, checkpoint_interval=3,
                log_interval=1, opacity_reset_interval=1000)
    base.update(kw)
    return TrainConfig(**base)


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    """A finished nimbus-train run folder (config.json, checkpoint.pt, ...) trained with the largest seed."""
    out = tmp_path_factory.mktemp("runs") / "run"
    with pytest.raises(SystemExit) as info:
        train_main(["builtin:garden:tiny", *FAST, "--seed", str(MAX_SEED), "--out", str(out)])
    assert info.value.code == 0
    assert json.loads((out / "config.json").read_text())["seed"] == MAX_SEED
    return out


@pytest.fixture
def run(finished_run, tmp_path):
    """A private copy of the finished run, for a test to spoil."""
    dst = tmp_path / "run"
    shutil.copytree(finished_run, dst)
    return dst


# --- 1. checkpoints never unpickle arbitrary objects ---------------------------------------------------------
class _RunsCode:
    """Unpickling this runs a shell command (what a hostile checkpoint does)."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {shlex.quote(str(self.marker))}",)


def _hostile_checkpoint(path: Path, marker: Path, legacy: bool) -> None:
    state = {"iteration": _RunsCode(marker), "params": {}}
    # torch.save pickles it as any object; legacy: the pre-1.6 format that torch.load still reads
    torch.save(state, path, _use_new_zipfile_serialization=not legacy)


@pytest.mark.parametrize("legacy", [False, True], ids=["zip", "legacy-pickle"])
def test_resume_refuses_a_checkpoint_that_would_run_code(run, tmp_path, capsys, legacy):
    marker = tmp_path / "pwned"
    _hostile_checkpoint(run / CHECKPOINT, marker, legacy)
    # The file is live: a plain unpickling would have run the command.
    control = tmp_path / "control"
    _hostile_checkpoint(tmp_path / "control.pt", control, legacy)
    torch.load(tmp_path / "control.pt", weights_only=False)
    assert control.exists()

    code, err = cli(["--resume", run], capsys)
    assert_one_error(code, err, "start a new run", "can run code")
    assert not marker.exists()


def test_last_good_checkpoint_is_refused_the_same_way(scene, tmp_path):
    marker = tmp_path / "pwned"
    t = Runner("3dgs", scene, _cfg(), tmp_path / "r", seed=0, progress=False)
    (tmp_path / "r").mkdir()
    _hostile_checkpoint(tmp_path / "r" / LAST_GOOD, marker, legacy=False)
    with pytest.raises(NimbusError, match="can run code"):
        t.load_checkpoint(tmp_path / "r" / LAST_GOOD)
    assert not marker.exists()


def test_checkpoint_of_pickled_objects_is_refused_with_start_a_new_run(scene, tmp_path):
    """What an older Nimbus could have written (numpy values pickled as objects) is not loaded."""
    t = Runner("3dgs", scene, _cfg(), tmp_path / "r", seed=0, progress=False)
    state = t.state_dict()
    state["order"] = np.array(state["order"])
    (tmp_path / "r").mkdir()
    torch.save(state, tmp_path / "r" / CHECKPOINT)
    with pytest.raises(NimbusError, match="(?i)start a new run"):
        t.load_checkpoint(tmp_path / "r" / CHECKPOINT)


@pytest.mark.parametrize("content, message", [
    (b"", "cannot read checkpoint"),
    (b"PK\x03\x04 truncated zip", "cannot read checkpoint"),
    (None, "does not fit this run"),  # a valid file with the wrong structure
])
def test_corrupt_or_foreign_checkpoint_is_a_clear_error(run, capsys, content, message):
    if content is None:
        torch.save({"iteration": 1, "params": {"tensors": {}}}, run / CHECKPOINT)
    else:
        (run / CHECKPOINT).write_bytes(content)
    code, err = cli(["--resume", run], capsys)
    assert_one_error(code, err, message, "--out")


def test_every_checkpoint_loads_with_weights_only(scene, tmp_path):
    from nimbus.methods.nimbusgs.config import NimbusConfig

    cfg = NimbusConfig(**{**dataclasses_fields(_cfg()), "m_init": 2, "refresh_interval": 2, "grid_resolution": 4,
                          "ray_samples": 4, "components": "csm,plm,ggs", "write_decomposition": False,
                          "airlight_hidden": 4})
    Runner("nimbus", scene, cfg, tmp_path / "n", seed=0, progress=False).run()
    state = torch.load(tmp_path / "n" / CHECKPOINT, weights_only=True)
    assert state["extra"]["medium"] is not None and state["extra"]["store"] is not None
    assert state["iteration"] == 6 and state["visible_steps"] > 0


def dataclasses_fields(cfg) -> dict:
    import dataclasses

    return {f.name: getattr(cfg, f.name) for f in dataclasses.fields(cfg)}


def test_a_method_that_checkpoints_an_object_fails_at_save_time(scene, tmp_path):
    t = Runner("3dgs", scene, _cfg(), tmp_path / "s", seed=0, progress=False)
    state_dict = t.method.state_dict
    t.method.state_dict = lambda: {**state_dict(), "extra": {"score": np.float64(1.0)}}
    with pytest.raises(TypeError, match=r"state\['extra'\]\['score'\] is a numpy.float64"):
        t.save_checkpoint()
    check_plain({"a": [1, 2.0, "x", None, True, (torch.zeros(1),)]})


def test_no_package_unpickles_untrusted_data():
    """Every torch.load in the packages passes weights_only=True; no pickle.load(s), no allow_pickle=True."""
    offences = []
    for pkg in ("nimbus", "weather_synth", "benchmark"):
        for path in (REPO / pkg).rglob("*.py"):
            text = path.read_text()
            for m in re.finditer(r"torch\.load\(([^)]*)\)", text):
                if "weights_only=True" not in m.group(1):
                    offences.append(f"{path}: {m.group(0)}")
            offences += [f"{path}: {m.group(0)}" for m in
                         re.finditer(r"pickle\.loads?\(|allow_pickle\s*=\s*True|weights_only\s*=\s*False", text)]
    assert not offences, offences


# --- 2. --out never deletes or writes into the scene ---------------------------------------------------------
@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    from nimbus.data.io import write_scene

    root = tmp_path_factory.mktemp("data") / "parent" / "garden"
    s = render_builtin("garden", size="tiny", seed=0)
    write_scene(s.with_views(s.train_views[:3] + s.test_views[:1]), root)
    return root


@pytest.mark.parametrize("where", ["scene", "ancestor", "inside", "images-folder"])
def test_out_over_the_scene_is_refused_and_the_scene_is_intact(scene_dir, capsys, where):
    before = snapshot(scene_dir.parent)
    out = {"scene": scene_dir, "ancestor": scene_dir.parent, "inside": scene_dir / "run",
           "images-folder": scene_dir / "images"}[where]
    code, err = cli([scene_dir, *FAST, "--out", out, "--overwrite"], capsys)
    assert_one_error(code, err, "input")
    assert snapshot(scene_dir.parent) == before


# --- confinement: a resumed run never writes into its scene, and a refusal changes nothing (issue 35) --------
def _disk_run(scene_dir: Path, scene_copy: Path, out: Path) -> Path:
    """A 4-step run (checkpoints at 2 and 4, a log line per step) of a copy of the scene on disk, in ``out``."""
    from nimbus.train.run_folder import load_scene_arg

    shutil.copytree(scene_dir, scene_copy)
    Runner("3dgs", load_scene_arg(str(scene_copy)), _cfg(iterations=4, checkpoint_interval=2), out, seed=0,
           scene_path=str(scene_copy), progress=False).train()
    return out


@pytest.mark.parametrize("where", ["inside", "contains"])
def test_resume_refuses_a_run_folder_overlapping_its_scene(scene_dir, tmp_path, capsys, where):
    """A run folder inside the scene (left there by a library call or moved there) used to resume, training
    and writing its renders, checkpoints and log into the input."""
    if where == "inside":
        scene, run = tmp_path / "scene", tmp_path / "scene" / "run"
    else:  # the scene inside the run folder
        scene, run = tmp_path / "run" / "scene", tmp_path / "run"
    _disk_run(scene_dir, scene, run)
    before = snapshot(tmp_path)
    code, err = cli(["--resume", run], capsys)
    assert_one_error(code, err, "--resume", "overlaps the scene", "move the run folder")
    assert snapshot(tmp_path) == before


@pytest.mark.parametrize("field, value", [("iteration", -3), ("iteration", 2.5), ("visible_steps", -1),
                                          ("visible_steps", 99), ("train_time", float("nan"))])
def test_a_refused_checkpoint_leaves_the_run_folder_untouched(scene_dir, tmp_path, capsys, field, value):
    """A checkpoint with an impossible count is refused before the log is opened: a negative iteration used to
    cut train_log.jsonl to 0 bytes (every line was 'after' it) before the run failed."""
    from nimbus.train.checkpoint import read_checkpoint, write_checkpoint

    run = _disk_run(scene_dir, tmp_path / "scene", tmp_path / "run")
    state = read_checkpoint(run / CHECKPOINT)
    write_checkpoint(run / CHECKPOINT, {**state, field: value})
    assert (run / "train_log.jsonl").stat().st_size > 0
    before = snapshot(tmp_path)
    code, err = cli(["--resume", run], capsys)
    assert snapshot(tmp_path) == before
    assert_one_error(code, err, "does not fit this run", field)


@pytest.mark.parametrize("where, words", [
    ("a-folder-of-the-users", "not written by nimbus-train"),  # used to be emptied, then trained into
    ("a-results-store", "not written by nimbus-train"),
    ("inside-another-scene", "lies inside the scene"),
    ("inside-a-results-store", "lies inside the results store"),
])
def test_out_overwrite_replaces_only_a_run_folder_of_nimbus_train(scene_dir, tmp_path, capsys, where, words):
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "thesis.tex").write_text("mine")
    (tmp_path / "bench").mkdir()
    (tmp_path / "bench" / "results.jsonl").write_text('{"cell_id": "a", "status": "ok"}\n')
    (tmp_path / "other" / "sparse" / "0").mkdir(parents=True)
    (tmp_path / "other" / "sparse" / "0" / "cameras.txt").write_text("# a COLMAP model\n")
    out = {"a-folder-of-the-users": tmp_path / "mine", "a-results-store": tmp_path / "bench",
           "inside-another-scene": tmp_path / "other" / "run", "inside-a-results-store": tmp_path / "bench" / "run"}[where]
    before = snapshot(tmp_path)
    code, err = cli([scene_dir, *FAST, "--out", out, "--overwrite"], capsys)
    assert_one_error(code, err, "--out", words, "nothing was written or deleted")
    assert snapshot(tmp_path) == before and out.exists() == where.startswith("a-")  # no folder made either


# --- 3. a garbage model writes no results ------------------------------------------------------------------
def _poisoned(after_step):
    """``after_step`` that then, after the last step, turns one Gaussian's opacity NaN (the loss guard has
    nothing to see)."""
    def step(self, it):
        events = after_step(self, it)
        if it == self.cfg.iterations:
            with torch.no_grad():
                self.params["opacity_logits"][0] = float("nan")
        return events
    return step


def _gone(after_step):
    """``after_step`` that moves every Gaussian out of every view after the last step: evaluation sees nothing."""
    def step(self, it):
        events = after_step(self, it)
        if it == self.cfg.iterations:
            with torch.no_grad():
                self.params["means"].add_(1e6)
        return events
    return step


@pytest.mark.parametrize("wrap, message", [(_poisoned, "non-finite parameters \\(opacity_logits\\)"),
                                           (_gone, "no Gaussian is visible in any test view")])
def test_garbage_model_raises_and_writes_no_results(scene, tmp_path, monkeypatch, wrap, message):
    out = tmp_path / "g"
    monkeypatch.setattr(GaussianSplatting, "after_step", wrap(GaussianSplatting.after_step))
    with pytest.raises(NimbusError, match=message):
        Runner("3dgs", scene, _cfg(), out, seed=0, progress=False).run()
    for name in ("results.json", "point_cloud.ply", "renders/test"):
        assert not (out / name).exists(), name


def test_never_visible_run_raises_and_writes_no_results(scene, tmp_path):
    t = Runner("3dgs", scene, _cfg(iterations=3), tmp_path / "far", seed=0, progress=False)
    with torch.no_grad():
        t.method.params["means"].fill_(float("nan"))  # what --set lr_means_init=inf did after one step
    with pytest.raises(NimbusError, match="non-finite parameters"):
        t.run()
    assert not (tmp_path / "far" / "point_cloud.ply").exists()


def test_cli_reports_a_garbage_model_as_one_error_line(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(GaussianSplatting, "after_step", _poisoned(GaussianSplatting.after_step))
    out = tmp_path / "bad"
    code, err = cli(["builtin:garden:tiny", *FAST, "--out", out], capsys)
    assert_one_error(code, err, "non-finite parameters")
    assert not (out / "results.json").exists() and not (out / "point_cloud.ply").exists()


# --- 4. bad arguments and run folders -----------------------------------------------------------------------
@pytest.mark.parametrize("seed", ["-1", str(10**20), str(MAX_SEED + 1), "1.5"])
def test_out_of_range_seed_is_refused(tmp_path, capsys, seed):
    code, err = cli(["builtin:garden:tiny", *FAST, "--seed", seed, "--out", tmp_path / "o"], capsys)
    assert_one_error(code, err, "seed", str(MAX_SEED))
    assert not (tmp_path / "o").exists()
    assert seed_arg(str(MAX_SEED)) == MAX_SEED and seed_arg("0") == 0


@pytest.mark.parametrize("device", ["tpu", "cuda", "cuda:99", "meta", "not a device"])
def test_unusable_device_is_refused(tmp_path, capsys, device):
    if device == "cuda" and torch.cuda.is_available():
        pytest.skip("CUDA is available here")
    code, err = cli(["builtin:garden:tiny", *FAST, "--device", device, "--out", tmp_path / "o"], capsys)
    assert_one_error(code, err, "--device")
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("text, needle", [
    ("{not json", "not valid JSON"),
    ("[" * 100_000 + "]" * 100_000, "not valid JSON (nested too deeply)"),
    ("[" * 200_000 + "]" * 200_000, "not valid JSON (nested too deeply)"),
    ("[]", "holds a list, not an object"),
    ('"config"', "holds a string, not an object"),
    (b"\xff\xfe{}", "not a UTF-8 text file"),
    (None, "field 'method' is missing"),
    ({"seed": "x"}, "field 'seed' must be an integer, got 'x'"),
    ({"seed": -1}, "field 'seed' must be >= 0, got -1"),
    ({"seed": True}, "field 'seed' must be an integer, got True"),
    ({"seed": float("nan")}, "field 'seed' must be an integer, got nan"),
    ({"config": [1]}, "field 'config' must be an object, got [1]"),
    ({"config": {"no_such_field": 1}}, "does not fit"),
    ({"config": {"iterations": "many"}}, "config"),
    ({"method": 3}, "field 'method' must be a string, got 3"),
    ({"method": ["3dgs"]}, "field 'method' must be a string, got ['3dgs']"),
    ({"method": ""}, "field 'method' must not be empty"),
    ({"method": "nope"}, "unknown method"),
    ({"scene": None}, "field 'scene' must be a string, got None"),
    ({"scene_load_args": {"shell": "rm -rf /"}}, "field 'scene_load_args.shell' is not a known key"),
    ({"scene_load_args": {"downscale": "2"}}, "field 'scene_load_args.downscale' must be an integer, got '2'"),
    ({"scene_load_args": {"downscale": 0}}, "field 'scene_load_args.downscale' must be >= 1, got 0"),
])
def test_broken_config_json_on_resume_is_a_clear_error(run, capsys, text, needle):
    saved = json.loads((run / "config.json").read_text())
    if text is None:
        del saved["method"]
        text = json.dumps(saved)
    elif isinstance(text, dict):
        patch = text
        if isinstance(patch.get("config"), dict):
            patch = {"config": {**saved["config"], **patch["config"]}}
        text = json.dumps({**saved, **patch})
    (run / "config.json").write_bytes(text if isinstance(text, bytes) else text.encode())
    before = snapshot(run)
    code, err = cli(["--resume", run], capsys)
    assert_one_error(code, err, "config.json", needle)
    assert snapshot(run) == before


@pytest.mark.parametrize("patch, needle", [
    ({"seed": "x"}, "field 'seed' must be an integer, got 'x'"),
    ({"scene": ["builtin:garden"]}, "field 'scene' must be a string"),
    ({"scene_load_args": {"downscale": float("nan")}}, "field 'scene_load_args.downscale' must be an integer"),
])
def test_nimbus_view_of_a_run_whose_config_json_does_not_fit_is_one_error(run, capsys, patch, needle):
    """nimbus-view opens a run through the same schema-checked reader as --resume."""
    from nimbus.cli.view import main as view_main

    (run / "config.json").write_text(json.dumps({**json.loads((run / "config.json").read_text()), **patch}))
    capsys.readouterr()
    with pytest.raises(SystemExit) as info:
        view_main([str(run), "--port", "0"])
    assert_one_error(info.value.code, capsys.readouterr().err, "config.json", needle)


def test_unusable_out_is_a_clear_error(tmp_path, capsys):
    a_file = tmp_path / "file"
    a_file.write_text("x")
    for out in (a_file, a_file / "sub"):
        code, err = cli(["builtin:garden:tiny", *FAST, "--out", out], capsys)
        assert_one_error(code, err, "--out")
    assert a_file.read_text() == "x"


def test_read_only_out_and_run_are_clear_errors(run, tmp_path, capsys, monkeypatch):
    ro = tmp_path / "ro"
    ro.mkdir()
    if os.geteuid() == 0:  # root writes anyway: make the permission check see what a user would
        real = os.access
        monkeypatch.setattr(os, "access", lambda p, mode, **kw: False if Path(p).resolve() in (ro, run.resolve())
                            else real(p, mode, **kw))
    ro.chmod(0o555)
    run.chmod(0o555)
    try:
        code, err = cli(["builtin:garden:tiny", *FAST, "--out", ro / "run"], capsys)
        assert_one_error(code, err, "cannot be written")
        code, err = cli(["--resume", run], capsys)
        assert_one_error(code, err, "cannot be written")
    finally:
        ro.chmod(0o755)
        run.chmod(0o755)
    assert not any(ro.iterdir())


def test_downscale_with_a_builtin_scene_is_refused(tmp_path, capsys):
    code, err = cli(["builtin:garden:tiny", *FAST, "--downscale", "2", "--out", tmp_path / "o"], capsys)
    assert_one_error(code, err, "built-in scenes", "train_downscale")
    assert not (tmp_path / "o").exists()
    code, err = cli(["builtin:garden:tiny", *FAST, "--downscale", "0", "--out", tmp_path / "o"], capsys)
    assert_one_error(code, err, "--downscale")


# --- 5. leftovers and resumed logs --------------------------------------------------------------------------
def test_a_run_that_fails_before_its_first_checkpoint_leaves_nothing(tmp_path, capsys, monkeypatch):
    def fail(self, step, vi, render, gt):
        raise NimbusError("the input is unusable")

    with monkeypatch.context() as m:
        m.setattr(GaussianSplatting, "loss", fail)
        code, err = cli(["builtin:garden:tiny", *FAST, "--out", tmp_path / "new" / "deep" / "run"], capsys)
        assert_one_error(code, err, "unusable")
        assert not (tmp_path / "new").exists()  # every folder this run created is gone
        empty = tmp_path / "empty"
        empty.mkdir()
        code, err = cli(["builtin:garden:tiny", *FAST, "--out", empty], capsys)
        assert_one_error(code, err, "unusable")
        assert empty.is_dir() and not any(empty.iterdir())  # an empty --out stays, and stays empty
    code, err = cli(["builtin:garden:tiny", *FAST, "--out", empty], capsys)  # a plain retry works
    assert code == 0, err
    assert (empty / "results.json").is_file()


def test_overwrite_replaces_an_old_run_in_place(run, capsys):
    (run / "old.txt").write_text("stale")
    (run / "renders" / "test" / "stale.png").write_bytes(b"x")
    mode = run.stat().st_mode
    code, err = cli(["builtin:garden:tiny", *FAST, "--out", run, "--overwrite"], capsys)
    assert code == 0, err
    assert not (run / "old.txt").exists() and not (run / "renders" / "test" / "stale.png").exists()
    assert (run / "results.json").is_file() and run.stat().st_mode == mode


class _Killed(BaseException):
    """A kill between checkpoints: nothing is saved (unlike Ctrl-C)."""


def test_resume_does_not_duplicate_log_lines(scene, tmp_path):
    def killed_at_5(self, it):
        if it == 5:
            raise _Killed
        return []

    out = tmp_path / "r"
    with pytest.MonkeyPatch.context() as m, pytest.raises(_Killed):
        m.setattr(GaussianSplatting, "after_step", killed_at_5)
        Runner("3dgs", scene, _cfg(), out, seed=0, progress=False).run()
    log = out / "train_log.jsonl"
    assert max(json.loads(line)["iteration"] for line in log.read_text().splitlines()) == 4
    with log.open("a") as f:
        f.write('{"iteration": 5, "loss": 0.1')  # a line cut short by the kill
    resumed = Runner("3dgs", scene, _cfg(), out, seed=0, progress=False)
    resumed.load_checkpoint(out / CHECKPOINT)
    assert resumed.iteration == 3
    resumed.run()
    steps = [json.loads(line)["iteration"] for line in log.read_text().splitlines()
             if "loss" in json.loads(line)]
    assert steps == [1, 2, 3, 4, 5, 6]


# --- 6. PLY headers -------------------------------------------------------------------------------------------
def _ply_bytes(tmp_path) -> bytes:
    n = 2
    write_gaussian_ply(tmp_path / "ok.ply", np.zeros((n, 3)), np.zeros((n, 1, 3)), np.zeros(n), np.zeros((n, 3)),
                       np.tile([1.0, 0, 0, 0], (n, 1)))
    return (tmp_path / "ok.ply").read_bytes()


@pytest.mark.parametrize("edit, message", [
    (lambda b: b.replace(b"element vertex 2\n", b""), "element vertex"),
    (lambda b: b.replace(b"element vertex 2", b"element vertex -3"), "negative vertex count"),
    (lambda b: b.replace(b"element vertex 2", b"element vertex two"), "integer count"),
    (lambda b: b.replace(b"element vertex 2", b"element vertex 99999999999"), "truncated"),
    (lambda b: b.replace(b"end_header", b"end_headr"), "not a PLY"),
    (lambda b: b.replace(b"property float opacity\n", b""), "opacity"),
    (lambda b: b.replace(b"property float x", b"property double x"), "property float"),
    (lambda b: b.replace(b"format binary", b"format \xff\xfe"), "not ASCII"),
    (lambda b: b[:-5], "truncated"),
])
def test_corrupt_ply_header_is_a_clear_error(tmp_path, edit, message):
    raw = _ply_bytes(tmp_path)
    assert read_gaussian_ply(tmp_path / "ok.ply")["means"].shape == (2, 3)
    (tmp_path / "bad.ply").write_bytes(edit(raw))
    with pytest.raises(NimbusError, match=message):
        read_gaussian_ply(tmp_path / "bad.ply")


# --- issue 35, round 2: faults that ended in a traceback, a full disk, non-finite exports --------------------
# Each ends in one error line with exit 2 and leaves nothing partial: a dangling --out link, a checkpoint tensor
# of another shape (--resume and nimbus-view), a disk that fills up while a run writes, NaN in a PLY export.
def test_out_given_as_a_dangling_link_is_one_error_line(tmp_path, capsys):
    link = tmp_path / "out"
    link.symlink_to(tmp_path / "missing" / "run")
    code, err = cli(["builtin:garden:tiny", *FAST, "--out", link], capsys)
    assert_one_error(code, err, "is a link to", "does not exist")
    assert link.is_symlink() and not (tmp_path / "missing").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def _reshaped_checkpoint(run: Path, name: str, shape: tuple) -> None:
    state = torch.load(run / CHECKPOINT, weights_only=True)
    state["params"]["tensors"][name] = torch.zeros(shape)
    torch.save(state, run / CHECKPOINT)


@pytest.mark.parametrize("name, shape, needle", [
    ("means", (5, 3), "'log_scales' has shape"),  # fewer Gaussians than the other tensors
    ("sh_rest", None, "'sh_rest' has shape"),  # another SH degree's coefficients
    ("quats", None, "'quats' has shape"),  # 3 numbers per rotation instead of 4
])
def test_resume_refuses_a_checkpoint_tensor_of_the_wrong_shape_and_keeps_the_run(run, capsys, name, shape, needle):
    n = torch.load(run / CHECKPOINT, weights_only=True)["params"]["tensors"]["means"].shape[0]
    shape = shape or {"sh_rest": (n, 3, 7), "quats": (n, 3)}[name]
    _reshaped_checkpoint(run, name, shape)
    before = snapshot(run)
    code, err = cli(["--resume", run, "--quiet"], capsys)
    assert_one_error(code, err, "does not fit this run", needle)
    assert snapshot(run) == before  # the log is not cut back, nothing is written


def test_viewer_refuses_a_checkpoint_tensor_of_the_wrong_shape(run, capsys):
    from nimbus.cli.view import main as view_main

    _reshaped_checkpoint(run, "means", (5, 3))
    with pytest.raises(SystemExit) as info:
        view_main([str(run), "--port", "0"])
    assert_one_error(info.value.code, capsys.readouterr().err, "does not fit this run", "'log_scales' has shape")


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_a_ply_export_with_non_finite_values_is_refused_naming_the_property(tmp_path, bad):
    n = 4
    scales = np.zeros((n, 3))
    scales[2, 1] = bad
    with pytest.raises(NimbusError, match=r"point_cloud.ply: 1 of 4 Gaussians have NaN or infinite values "
                                          r"\(in scale_1\)"):
        write_gaussian_ply(tmp_path / "point_cloud.ply", np.zeros((n, 3)), np.zeros((n, 1, 3)), np.zeros(n), scales,
                           np.tile([1.0, 0, 0, 0], (n, 1)))
    assert list(tmp_path.iterdir()) == []


def test_a_full_disk_at_the_first_checkpoint_leaves_no_run_folder(tmp_path, capsys, disk_full):
    failed = disk_full(".checkpoint.pt.tmp-", after_bytes=100)
    out = tmp_path / "new" / "run"
    code, err = cli(["builtin:garden:tiny", *FAST, "--out", out], capsys)
    assert failed, "the checkpoint was never written"
    assert_one_error(code, err, f"no space left on the device of {out}", "checkpoint.pt needs", "bytes free")
    assert list(tmp_path.iterdir()) == []  # no run folder, no temporary file, no parent made for it


def test_a_full_disk_after_a_checkpoint_leaves_a_run_that_resumes(tmp_path, capsys):
    from conftest import _fill_disk_for

    out = tmp_path / "run"
    with pytest.MonkeyPatch.context() as m:
        real = Runner.finish

        def finish(self):  # the disk fills up once training is done, as the renders are written
            _fill_disk_for(m, ".png.tmp-")
            return real(self)

        m.setattr(Runner, "finish", finish)
        code, err = cli(["builtin:garden:tiny", *FAST, "--out", out], capsys)
    assert_one_error(code, err, "no space left on the device of", "renders")
    assert (out / CHECKPOINT).is_file() and not (out / "results.json").exists()
    assert not list(out.rglob(".*tmp-*"))  # no temporary file left behind
    code, err = cli(["--resume", out, "--quiet"], capsys)  # space freed: the run finishes
    assert code == 0, err
    assert (out / "results.json").is_file()


@pytest.mark.parametrize("edited", ["robust-3dgs", "restore-3dgs"])
def test_resume_refuses_a_run_whose_config_names_another_method(run, capsys, edited):
    # A config.json whose method was edited loaded the checkpoint into another method's class: restore-3dgs took
    # the 3dgs state whole and "resumed" (exit 0, a silent wrong run); robust-3dgs failed on a missing key.  The
    # checkpoint now names its method, and a mismatch is one error line naming both.
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["method"] == "3dgs"
    cfg["method"] = edited
    (run / "config.json").write_text(json.dumps(cfg))
    before = snapshot(run)
    code, err = cli(["--resume", run, "--quiet"], capsys)
    assert_one_error(code, err, "was written by method '3dgs'", f"config.json says '{edited}'")
    assert snapshot(run) == before
