"""A worker warms up what its cells' device renders with; gsplat counts as available only once its
CUDA extension loads (nimbus.render.backends.gsplat.package_available)."""

import sys
import types

import pytest
import torch

from benchmark.cell import CellOptions, warm_up
from nimbus.kernels import raster
from nimbus.render.backends import gsplat as gsplat_backend


@pytest.fixture
def calls(monkeypatch):
    seen = []
    monkeypatch.setattr(gsplat_backend, "package_available", lambda: seen.append("gsplat") or True)
    monkeypatch.setattr(raster, "available", lambda warn=True: seen.append("raster") or True)
    return seen


def test_a_cuda_worker_loads_gsplat_not_the_cpu_kernels(calls):
    warm_up(CellOptions(device="cuda"))
    assert calls == ["gsplat"]


def test_a_cpu_worker_loads_the_cpu_kernels(calls, monkeypatch):
    from nimbus.kernels import march, train_step

    monkeypatch.setattr(march.EXTENSION, "available", lambda warn=True: calls.append("march") or True)
    monkeypatch.setattr(train_step.EXTENSION, "available", lambda warn=True: calls.append("train_step") or True)
    warm_up(CellOptions(device="cpu"))
    assert calls == ["raster", "march", "train_step"]
    calls.clear()
    warm_up(CellOptions(device="cpu"), reverse=True)  # a second worker builds another library meanwhile
    assert calls == ["train_step", "march", "raster"]


@pytest.fixture
def fake_gsplat(monkeypatch):
    """An installed ``gsplat`` package with an empty ``gsplat.cuda``, and CUDA available; the cached answer cleared."""
    fake = types.ModuleType("gsplat")
    cuda = types.ModuleType("gsplat.cuda")
    cuda.__path__ = []
    fake.cuda = cuda
    monkeypatch.setitem(sys.modules, "gsplat", fake)
    monkeypatch.setitem(sys.modules, "gsplat.cuda", cuda)
    monkeypatch.delitem(sys.modules, "gsplat.cuda._backend", raising=False)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    gsplat_backend.package_available.cache_clear()
    yield cuda
    gsplat_backend.package_available.cache_clear()


@pytest.mark.parametrize("loaded,expected", [(None, False), (object(), True)])
def test_gsplat_whose_extension_does_not_load_is_not_available(fake_gsplat, monkeypatch, loaded, expected):
    backend = types.ModuleType("gsplat.cuda._backend")
    backend._C = loaded
    fake_gsplat._backend = backend
    monkeypatch.setitem(sys.modules, "gsplat.cuda._backend", backend)
    assert gsplat_backend.package_available() is expected

class _Finder:
    """A meta-path finder for ``gsplat.cuda._backend`` whose import raises ``error`` (None: no such module)."""

    def __init__(self, error):
        self.error = error

    def find_spec(self, name, path=None, target=None):
        if name != "gsplat.cuda._backend" or self.error is None:
            return None
        import importlib.util

        return importlib.util.spec_from_loader(name, self)

    def create_module(self, spec):
        return None

    def exec_module(self, module):
        raise self.error


@pytest.mark.parametrize("error,expected", [
    # what gsplat 1.5.3 raised on an H200 when twelve workers built its extension at once
    (ImportError("/root/.cache/torch_extensions/gsplat_cuda/gsplat_cuda.so: cannot open shared object file"), False),
    (ModuleNotFoundError("No module named 'jaxtyping'", name="jaxtyping"), False),  # the module's own import
    (RuntimeError("Error building extension 'gsplat_cuda'"), False),
    (None, True),  # no gsplat.cuda._backend at all: another layout, loaded at the first rasterization
])
def test_gsplat_whose_backend_module_fails_to_import_is_not_available(fake_gsplat, monkeypatch, error, expected):
    monkeypatch.setattr(sys, "meta_path", [_Finder(error), *sys.meta_path])
    assert gsplat_backend.package_available() is expected

class _Stop(Exception):
    pass


@pytest.mark.parametrize("device,jobs,n_cells,expected", [
    ("cuda", 12, 12, ["prebuild", "worker"]),   # one process builds gsplat's extension before the workers start
    ("cuda", 1, 12, ["worker"]),                 # one worker builds it alone anyway
    ("cuda", 12, 1, ["worker"]),                 # so does the one worker of a one-cell run
    ("cpu", 12, 12, ["worker"]),                 # the CPU kernels' build takes a lock of its own (nimbus.kernels)
])
def test_a_cuda_run_of_several_workers_builds_the_extension_once_first(monkeypatch, device, jobs, n_cells, expected):
    from benchmark import workers

    seen = []
    monkeypatch.setattr(workers, "prebuild_extensions", lambda ctx, options: seen.append("prebuild"))

    def worker(ctx, index=0, options=None):
        seen.append("worker")
        raise _Stop  # the order is all this test needs: no process starts

    monkeypatch.setattr(workers, "_Worker", worker)
    with pytest.raises(_Stop):
        next(workers.CellWorkers(jobs).imap([object()] * n_cells, "root", CellOptions(device=device)))
    assert seen == expected
