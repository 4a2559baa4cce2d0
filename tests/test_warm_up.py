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


def test_a_cpu_worker_loads_the_cpu_kernels(calls):
    warm_up(CellOptions(device="cpu"))
    assert calls == ["raster"]


@pytest.mark.parametrize("loaded,expected", [(None, False), (object(), True)])
def test_gsplat_whose_extension_does_not_load_is_not_available(monkeypatch, loaded, expected):
    fake = types.ModuleType("gsplat")
    cuda = types.ModuleType("gsplat.cuda")
    backend = types.ModuleType("gsplat.cuda._backend")
    backend._C = loaded
    fake.cuda, cuda._backend = cuda, backend
    monkeypatch.setitem(sys.modules, "gsplat", fake)
    monkeypatch.setitem(sys.modules, "gsplat.cuda", cuda)
    monkeypatch.setitem(sys.modules, "gsplat.cuda._backend", backend)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    gsplat_backend.package_available.cache_clear()
    try:
        assert gsplat_backend.package_available() is expected
    finally:
        gsplat_backend.package_available.cache_clear()
