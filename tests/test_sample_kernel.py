"""The compiled bilinear sampling of GGS's error (nimbus/kernels/sample.py) against the grid_sample path it replaces."""

import pytest
import torch

from nimbus.kernels import sample as kernel
from nimbus.kernels.march import EXTENSION
from nimbus.methods.nimbusgs.ggs import sample_error

pytestmark = pytest.mark.skipif(not EXTENSION.available(warn=False), reason="the compiled NimbusGS library did not build")

# torch's vectorised grid_sample (AVX2 / AVX-512 kernels) rounds its unnormalisation and weighted sum as fused
# multiply-adds, which the kernel reproduces; torch's generic kernel (a CPU without AVX2) rounds each product.
TORCH_FUSES = torch.backends.cpu.get_cpu_capability() in ("AVX2", "AVX512")


def _positions(n, w, h, seed):
    """Pixel positions inside and outside the image, on its edges and pixel centres, and non-finite ones."""
    g = torch.Generator().manual_seed(seed)
    xy = torch.rand(n, 2, generator=g) * torch.tensor([w + 8.0, h + 8.0]) - 4.0
    special = torch.tensor([[0.0, 0.0], [w, h], [w - 0.5, h - 0.5], [0.5, 0.5], [-1e6, 3.0], [3.0, 1e6],
                            [float("nan"), 2.0], [2.0, float("inf")], [float("-inf"), float("nan")], [w - 1e-4, 0.25]])
    return torch.cat([special, xy])


@pytest.mark.parametrize("h, w", [(180, 240), (1, 1), (7, 3), (2, 31)])
@pytest.mark.parametrize("threads", [1, 2])
def test_the_kernel_is_grid_samples_bits(h, w, threads):
    error = torch.rand(h, w, generator=torch.Generator().manual_seed(h * w)) * 3
    xy = _positions(20_000, w, h, seed=w)
    rows = torch.randperm(xy.shape[0], generator=torch.Generator().manual_seed(1))[: xy.shape[0] // 2]
    rows = torch.cat([torch.arange(10), rows])  # the special positions, and some rows twice
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        got = kernel.bilinear_border(error, xy, rows)
    finally:
        torch.set_num_threads(before)
    want = sample_error(error, xy.index_select(0, rows))  # no rows: the torch path
    assert got.shape == want.shape and got.dtype == torch.float32
    if TORCH_FUSES:
        assert torch.equal(got, want)
    else:
        torch.testing.assert_close(got, want, rtol=1e-6, atol=1e-6)
    assert torch.equal(sample_error(error, xy, rows), got)  # GGS's call takes the kernel


def test_no_rows_and_refused_inputs():
    error = torch.rand(6, 8)
    assert kernel.bilinear_border(error, torch.zeros(0, 2), torch.zeros(0, dtype=torch.int64)).shape == (0,)
    with pytest.raises(RuntimeError, match="index out of range"):
        kernel.bilinear_border(error, torch.zeros(3, 2), torch.tensor([0, 3]))
    with pytest.raises(RuntimeError, match="float32"):
        kernel.bilinear_border(error.double(), torch.zeros(3, 2), torch.tensor([0]))
    assert not kernel.usable(error.double())  # so sample_error takes the torch path for float64
    d = error.double()
    torch.testing.assert_close(sample_error(d, torch.full((2, 2), 1.5, dtype=torch.float64), torch.tensor([1])),
                               d[1:2, 1], rtol=0, atol=1e-12)  # a pixel centre: that pixel's value
