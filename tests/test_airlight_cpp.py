"""The compiled network airlight (nimbus.kernels.airlight) against the torch layers it replaces."""

from __future__ import annotations

import shutil

import pytest
import torch

from nimbus.kernels import airlight as airlight_kernel
from nimbus.kernels import march as march_kernel
from nimbus.methods.nimbusgs.airlight import NetworkAirlight


@pytest.fixture(scope="module")
def kernel():
    if shutil.which("c++") is None and shutil.which("g++") is None:
        pytest.skip("no C++ compiler: the compiled kernel cannot be built here")
    assert march_kernel.available(), "compiled library unavailable"  # with a compiler, a failed build is a bug


def _inputs(n, inputs="view", dtype=torch.float32, seed=0):
    gen = torch.Generator().manual_seed(seed)
    dirs = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen, dtype=dtype), dim=1)
    t = torch.rand(n, generator=gen, dtype=dtype)
    desc = torch.rand(6, generator=gen, dtype=dtype)
    pixels = torch.rand(n, 3, generator=gen, dtype=dtype)
    return dirs, t, desc, pixels if inputs == "pixel" else None


def _net(hidden, inputs="view", dtype=torch.float32, seed=0):
    torch.manual_seed(seed)
    net = NetworkAirlight(hidden, inputs).to(dtype)
    for p in net.parameters():  # the last layer starts at zero: no gradient would reach the hidden layers
        torch.nn.init.normal_(p, std=0.5)
    return net


def _values_and_grads(net, args, target, compiled):
    net.compiled = compiled
    net.zero_grad(set_to_none=True)
    a = net(*args)
    (a - target).square().mean().backward()
    return a.detach(), [p.grad.clone() for p in net.parameters()]


# Hidden widths: the default (whole register tiles), one with partial tiles, and a single unit.
@pytest.mark.parametrize("hidden,inputs,n", [(64, "view", 1000), (20, "view", 130), (1, "pixel", 70),
                                             (24, "pixel", 3000)])
@pytest.mark.parametrize("dtype,rtol,atol", [(torch.float64, 1e-12, 1e-14), (torch.float32, 1e-5, 1e-6)])
def test_compiled_airlight_matches_the_torch_layers(kernel, hidden, inputs, n, dtype, rtol, atol):
    net = _net(hidden, inputs, dtype)
    args = _inputs(n, inputs, dtype)
    target = torch.rand(n, 3, generator=torch.Generator().manual_seed(5), dtype=dtype)
    a_ref, g_ref = _values_and_grads(net, args, target, compiled=False)
    a_out, g_out = _values_and_grads(net, args, target, compiled=True)
    assert float((a_ref - a_ref.mean(0)).abs().max()) > 1e-4  # the rows differ: the network is not flat
    torch.testing.assert_close(a_out, a_ref, rtol=rtol, atol=atol)
    for g, r in zip(g_out, g_ref):
        assert float(r.abs().max()) > 0
        torch.testing.assert_close(g, r, rtol=rtol * 10, atol=atol * float(r.abs().max()) * 10)


def test_compiled_airlight_gradcheck(kernel):
    gen = torch.Generator().manual_seed(1)
    x = torch.randn(37, 4, generator=gen, dtype=torch.float64)
    base = torch.randn(3, generator=gen, dtype=torch.float64)
    shapes = [(5, 4), (5,), (5, 5), (5,), (3, 5), (3,)]
    weights = [torch.randn(s, generator=gen, dtype=torch.float64).requires_grad_() for s in shapes]
    torch.autograd.gradcheck(lambda *w: airlight_kernel.network_airlight(x, base, *w), tuple(weights))


def test_compiled_airlight_is_used_only_where_it_applies(kernel):
    net = _net(8)
    dirs, t, desc, _ = _inputs(10)
    x = torch.cat([dirs, t[:, None], desc.expand(10, 6)], dim=1)
    weights = [p for p in net.parameters()]
    assert airlight_kernel.usable(x, desc[:3], *weights)
    assert not airlight_kernel.usable(x.requires_grad_(), desc[:3], *weights)  # the kernel differentiates weights only
    assert not airlight_kernel.usable(x.detach().double(), desc[:3], *weights)  # one dtype


def test_compiled_airlight_is_the_same_bits_at_any_thread_count(kernel):
    net = _net(32)
    args = _inputs(9000)
    target = torch.rand(9000, 3, generator=torch.Generator().manual_seed(5))
    threads = torch.get_num_threads()
    try:
        results = []
        for n in (1, 2, 2):
            torch.set_num_threads(n)
            results.append(_values_and_grads(net, args, target, compiled=True))
    finally:
        torch.set_num_threads(threads)
    (a1, g1), (a2, g2), (a2b, g2b) = results
    assert torch.equal(a1, a2)  # the forward is per row
    assert all(torch.equal(x, y) for x, y in zip(g2, g2b))
    # The rows are split into parts by their number alone (9000 rows: 4 parts), not by the threads.
    assert all(torch.equal(x, y) for x, y in zip(g1, g2))
