"""``benchmark.cell``: the one call into a trainer and the questions the benchmark asks a trained model.

The grid's end-to-end cells are in test_grid, the stability report's in test_stability.
"""

from __future__ import annotations

import torch

from benchmark.cell import make_config, medium_composition, model_parameters, train_method
from nimbus.methods.gs3d import GaussianSplatting
from nimbus.methods.registry import METHODS, MethodSpec


def _train(method_name, scene, tmp_path, **kwargs):
    from nimbus.methods.registry import get_method

    config = make_config(get_method(method_name), "tiny", {"iterations": "2"})
    return train_method(method_name, scene, config, tmp_path / method_name, seed=0, scene_path="in-memory",
                        progress=False, device="cpu", **kwargs)


def test_train_method_returns_results_and_the_model_it_announced(make_scene, tmp_path):
    announced = []
    results, model = _train("3dgs", make_scene(n_views=3), tmp_path, model_ready=announced.append)
    assert announced == [model] and results["iterations"] == 2
    assert (tmp_path / "3dgs" / "results.json").is_file()
    params = model_parameters(model)
    assert params and all(isinstance(p, torch.Tensor) for p in params)
    assert sum(p.numel() for p in params) >= results["num_gaussians"] * 11


def test_medium_composition_of_nimbusgs_only(make_scene, tmp_path):
    _, model = _train("nimbus-full", make_scene(n_views=3), tmp_path)
    parts = medium_composition(model)
    assert set(parts) == {"transmission", "airlight", "residual", "degraded"}
    h, w = model.method.train_views[0].camera.height, model.method.train_views[0].camera.width
    assert parts["degraded"].shape == (h, w, 3) and parts["transmission"].shape == (h, w, 1)
    _, gs = _train("3dgs", make_scene(n_views=3), tmp_path)
    assert medium_composition(gs) == {}


class _HasCompose(GaussianSplatting):
    def compose(self, vi, render):  # a 3DGS-like method with a method of that name: not a medium
        raise AssertionError("asked for a medium it does not model")


def test_medium_composition_asks_the_method_not_the_attribute(make_scene, tmp_path, monkeypatch):
    monkeypatch.setitem(METHODS, "has-compose", MethodSpec("has-compose", "test double", f"{__name__}:_HasCompose"))
    _, model = _train("has-compose", make_scene(n_views=3), tmp_path)
    assert medium_composition(model) == {}
