"""tools.speed.training times a run without changing it; nimbus-bench setup-kernels builds the kernels."""

from __future__ import annotations

import shutil

import pytest
import torch

from benchmark.cli import TOOL
from tools.speed import training
from nimbus.cli_util import run_cli
from nimbus.methods.registry import get_method
from nimbus.train.run_folder import load_scene_arg
from nimbus.train.runner import Runner


def _train(method_name: str, scene, steps: int, probe: bool, out):
    config = get_method(method_name).preset("tiny").with_changes({"iterations": steps})
    method = Runner(method_name, scene, config, out, seed=0, progress=False,
                    checkpoints=False).method
    timer = training.Probe(method.device)
    if probe:
        with training.instrumented(method, timer):
            for step in range(1, steps + 1):
                timer.step(lambda: method.train_iteration(step))
    else:
        for step in range(1, steps + 1):
            method.train_iteration(step)
    return method, timer


@pytest.mark.parametrize("method_name", ["3dgs", "nimbus-full"])
def test_instrumented_training_is_bit_identical_and_times_every_part(method_name, tmp_path):
    from nimbus.kernels import raster

    scene = load_scene_arg("builtin:garden:tiny")
    backward, composite = torch.Tensor.backward, raster.composite
    plain, _ = _train(method_name, scene, 16, probe=False, out=tmp_path / "plain")
    timed, probe = _train(method_name, scene, 16, probe=True, out=tmp_path / "timed")
    for key, value in plain.params.tensors.items():
        assert torch.equal(value, timed.params.tensors[key]), key
    # The wrappers are gone afterwards: the method and the kernels' modules are as before.
    assert "loss" not in vars(timed) and "step_post_backward" not in vars(timed.strategy)
    assert torch.Tensor.backward is backward and raster.composite is composite
    summary = training.summarise(probe.steps)
    parts = summary["parts"]
    must = ["project", "bin", "composite", "raster_bwd", "rest_bwd", "loss", "optimizer", "densify"]
    if method_name == "nimbus-full":
        must += ["march", "airlight", "ggs", "refresh"]
    for key in must:
        assert parts[key][2] > 0, key  # called in some step
    for step in probe.steps:  # the exclusive parts add up to the whole step
        assert sum(v for k, v in step.items() if k != "whole") == pytest.approx(step["whole"])
    assert 0 < summary["raster"] < summary["whole"]
    table = training.markdown("t", {method_name: summary | {"gaussians": 1, "components": "-"}})
    assert "| whole / rasterizer |" in table and "| projection + SH |" in table


def test_setup_kernels_builds_or_says_why(monkeypatch, capsys):
    monkeypatch.setenv("NIMBUS_DISABLE_CPP", "1")
    assert run_cli(TOOL.run, ["setup-kernels"]) == 0
    assert "NIMBUS_DISABLE_CPP is set" in capsys.readouterr().out
    monkeypatch.delenv("NIMBUS_DISABLE_CPP")
    if shutil.which("c++") is None and shutil.which("g++") is None:
        pytest.skip("no C++ compiler")
    assert run_cli(TOOL.run, ["setup-kernels"]) == 0
    out = capsys.readouterr().out
    assert "compositing kernel: " in out and "ray-march kernel: " in out and "cached in " in out
    assert "training-step kernels (loss, gradient check): " in out


def test_a_method_can_be_timed_with_overrides():
    """``NAME:key=value,...`` times a variant beside its method in one run; a bad override is the trainer's error."""
    from nimbus.errors import NimbusError

    scene = load_scene_arg("builtin:garden:tiny")
    r = training.time_method("3dgs:iterations=7,sh_degree=0", scene, "tiny", None, 0, 1, steps=2)
    assert r["iterations"] == 7 and r["steps"] == 2 and r["whole"] > 0
    with pytest.raises(NimbusError, match="refresh_mode"):
        training.time_method("nimbus:refresh_mode=sometimes", scene, "tiny", None, 0, 1, steps=2)
    with pytest.raises(NimbusError, match="key=value"):
        training.time_method("nimbus:lazy", scene, "tiny", None, 0, 1, steps=2)
    with pytest.raises(NimbusError, match="ggs_clip"):  # a value with a comma stays one value (then checked)
        training.time_method("nimbus:ggs_clip=2,3,refresh_mode=all", scene, "tiny", None, 0, 1, steps=2)


def test_runs_taking_turns_train_as_they_would_alone():
    """--interleave: runs that take turns, switching the thread count between them, end with the same model as
    each run trained alone, and every step of each is timed once."""
    scene = load_scene_arg("builtin:garden:tiny")
    runs = (("3dgs", 2, None), ("nimbus-full", 1, 7))  # name, threads, steps (of a 9-step schedule)
    alone = []
    for name, threads, steps in runs:
        with training.TimedRun(name, scene, "tiny", 9, threads, steps) as run:
            run.advance(100)
            alone.append({k: v.clone() for k, v in run.method.params.tensors.items()})
    (name_a, threads_a, steps_a), (name_b, threads_b, steps_b) = runs
    with training.TimedRun(name_a, scene, "tiny", 9, threads_a, steps_a) as a, \
            training.TimedRun(name_b, scene, "tiny", 9, threads_b, steps_b) as b:
        while not (a.finished and b.finished):
            a.advance(4)
            b.advance(3)
        assert (a.done, len(a.probe.steps), b.done, len(b.probe.steps)) == (9, 9, 7, 7)
        assert a.result(warmup=2)["steps"] == 7 and b.result(warmup=2)["iterations"] == 9
        for run, params in zip((a, b), alone):
            for key, value in run.method.params.tensors.items():
                assert torch.equal(value, params[key]), key


def test_interleaved_tool_prints_every_thread_count(capsys):
    """The command, interleaved: a table per thread count and the ratios between them."""
    argv = ["--sizes", "tiny", "--methods", "3dgs", "3dgs:sh_degree=0", "--preset", "tiny", "--steps", "3",
            "--warmup", "1", "--threads", "1,2", "--interleave", "2"]
    assert training.main(argv) == 0
    out = capsys.readouterr().out
    assert "interleaved 2 steps at a time" in out
    assert "1 thread(s)" in out and "2 thread(s)" in out and "2 steps timed" in out
    assert "3dgs:sh_degree=0 / 3dgs" in out and "3dgs: 1 thr / 2 thr" in out
    with pytest.raises(SystemExit):
        training.main(argv[:-1] + ["-1"])
