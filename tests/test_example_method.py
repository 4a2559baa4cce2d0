"""Adding a method is one file plus one registry line (issue 16): the example method trains, renders, resumes
and runs through ``nimbus-train`` with nothing else touched."""

from __future__ import annotations

import json

import pytest
import torch

from nimbus.cli.train import _main as train_main
from nimbus.data.builtin import render_builtin
from nimbus.methods import registry
from nimbus.methods.base import Method
from nimbus.methods.registry import MethodSpec
from nimbus.train.checkpoint import CHECKPOINT
from nimbus.train.config import TrainConfig
from nimbus.train.runner import Runner
from tests.example_method import ExampleMethod


@pytest.fixture(autouse=True)
def example_registered(monkeypatch):
    """The one registry line (added for the test only)."""
    monkeypatch.setitem(registry.METHODS, "example",
                        MethodSpec("example", "fixed Gaussians, learned colours", "tests.example_method:ExampleMethod"))


@pytest.fixture(scope="module")
def scene():
    s = render_builtin("garden", size="tiny", seed=0)
    return s.with_views(s.train_views[:4] + s.test_views[:2])


def _cfg(**kw):
    return TrainConfig(**{"iterations": 8, "checkpoint_interval": 4, "log_interval": 2, "lr_sh_dc": 0.05, **kw})


def test_the_example_implements_the_protocol_and_trains_renders_and_writes_outputs(scene, tmp_path):
    runner = Runner("example", scene, _cfg(), tmp_path / "run", seed=0, progress=False)
    assert isinstance(runner.method, ExampleMethod) and isinstance(runner.method, Method)
    camera = runner.method.train_views[0].camera
    with torch.no_grad():
        before = runner.method.render(camera)
    assert {"rgb", "depth", "alpha"} <= before.keys() and before["rgb"].shape == (camera.height, camera.width, 3)
    with torch.no_grad():
        assert torch.equal(runner.method.render(camera, view_index=0)["rgb"], before["rgb"])
    res = runner.run()
    assert res["method"] == "example" and res["iterations"] == 8 and res["example"]["points"] == len(scene.points)
    for name in ("config.json", CHECKPOINT, "train_log.jsonl", "results.json", "point_cloud.ply"):
        assert (tmp_path / "run" / name).is_file(), name
    assert sorted(p.stem for p in (tmp_path / "run" / "renders" / "test").iterdir()) == \
        sorted(v.stem for v in scene.test_views)
    with torch.no_grad():
        after = runner.method.render(camera)
    assert not torch.equal(after["rgb"], before["rgb"])  # the colours were learned


def test_the_example_resumes_to_the_same_result(scene, tmp_path, interrupt_and_resume):
    full = Runner("example", scene, _cfg(), tmp_path / "full", seed=2, progress=False).run()
    # Ctrl-C after step 5, between checkpoints: the interrupt saves the state
    resumed = interrupt_and_resume(lambda: Runner("example", scene, _cfg(), tmp_path / "half", seed=2,
                                                  progress=False), 5)
    assert resumed.iteration == 5
    out = resumed.run()
    assert out["psnr"] == full["psnr"] and out["ssim"] == full["ssim"]


def test_the_example_is_a_method_of_nimbus_train(tmp_path, monkeypatch):
    out = tmp_path / "cli"
    args = ["--set", "iterations=4", "--set", "checkpoint_interval=2", "--quiet"]
    assert train_main(["builtin:garden:tiny", "--method", "example", "--preset", "tiny", *args,
                       "--out", str(out)]) == 0
    assert json.loads((out / "results.json").read_text())["method"] == "example"
    assert json.loads((out / "config.json").read_text())["method"] == "example"
    assert train_main(["--resume", str(out), "--quiet"]) == 0  # finished run: resumes to the same end
