"""The compiled view-consistency excess (nimbus/kernels/consistency.py) against the torch path it replaces."""

import numpy as np
import pytest
import torch

from nimbus.data.camera import Camera
from nimbus.kernels import consistency as kernel
from nimbus.kernels.march import EXTENSION
from nimbus.methods.nimbusgs import particulate
from nimbus.methods.nimbusgs.particulate import ViewConsistency, ViewGeometry

pytestmark = pytest.mark.skipif(not EXTENSION.available(warn=False), reason="the compiled NimbusGS library did not build")

# torch's vectorised grid_sample (AVX2 / AVX-512 kernels) rounds its unnormalisation and weighted sum as fused
# multiply-adds, which the kernel reproduces; torch's generic kernel (a CPU without AVX2) rounds each product.
TORCH_FUSES = torch.backends.cpu.get_cpu_capability() in ("AVX2", "AVX512")


def _views(n=7, seed=0, size=(40, 30)):
    """Rotated cameras around a bumpy surface, partly invalid renders: every branch of the check (out of view,
    behind a neighbour's surface, no valid neighbour, one or several counted) is taken somewhere."""
    gen = np.random.default_rng(seed)
    w, h = size
    cams, images, geometry = [], [], []
    for i in range(n):
        a = 0.12 * (i - n // 2)
        R = np.array([[np.cos(a), 0.0, -np.sin(a)], [0.0, 1.0, 0.0], [np.sin(a), 0.0, np.cos(a)]])
        cam = Camera(w, h, 0.78 * w, 0.97 * h, 0.51 * w, 0.49 * h, R, np.array([0.4 * (i - n // 2), 0.05 * i, 0.3]))
        depth = torch.from_numpy(4.0 + gen.uniform(-0.6, 0.6, (h, w))).float()
        valid = torch.from_numpy(gen.uniform(size=(h, w)) > 0.2)
        cams.append(cam)
        images.append(torch.from_numpy(gen.uniform(size=(h, w, 3))).float())
        geometry.append(ViewGeometry(cam, depth, valid))
    return cams, images, geometry


def _torch_excess(check, i, geometry):
    return particulate._excess_torch(check.images[i], geometry[i], check._view(i),
                                     [(geometry[j], check._view(j)) for j in check.others[i]])


def _assert_same(a, b):
    assert torch.equal(torch.isnan(a), torch.isnan(b))
    if TORCH_FUSES:
        assert torch.equal(a.nan_to_num(), b.nan_to_num())  # bit for bit
    else:
        torch.testing.assert_close(a.nan_to_num(), b.nan_to_num(), rtol=0, atol=1e-5)


@pytest.mark.parametrize("count", [1, 2, 3, 4, 6])
def test_kernel_is_the_torch_check(count):
    cams, images, geometry = _views()
    check = ViewConsistency(cams, images, count)
    counted = {0: 0, "some": 0}
    batched = check.excesses(geometry)
    for i in range(len(cams)):
        ref = _torch_excess(check, i, geometry)
        _assert_same(check.excess(i, geometry), ref)
        _assert_same(batched[i], ref)
        counted[0] += int(torch.isnan(ref).sum())
        counted["some"] += int((~torch.isnan(ref)).sum())
    assert counted[0] > 0 and counted["some"] > 0


def test_kernel_on_views_of_different_sizes_and_without_neighbours():
    cams, images, geometry = _views(n=4)
    small = Camera(20, 15, 15.5, 14.5, 10.1, 7.3, cams[0].R, cams[0].t)
    geometry[0] = ViewGeometry(small, geometry[0].depth[::2, ::2].clone(), geometry[0].valid[::2, ::2].clone())
    images[0] = images[0][::2, ::2].clone()
    check = ViewConsistency([g.camera for g in geometry], images, 3)
    for i, kept in enumerate(check.excesses(geometry)):
        _assert_same(kept, _torch_excess(check, i, geometry))
    alone = ViewConsistency([cams[1]], [images[1]], 3)  # one view: no neighbour, no verdict
    assert torch.isnan(alone.excess(0, [geometry[1]])).all()


def test_kernel_gives_the_same_bits_for_any_thread_count():
    cams, images, geometry = _views(size=(160, 120))  # several parallel chunks
    check = ViewConsistency(cams, images, 4)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = check.excesses(geometry)
        torch.set_num_threads(max(2, threads))
        many = check.excesses(geometry)
    finally:
        torch.set_num_threads(threads)
    for a, b in zip(one, many):
        assert torch.equal(a.nan_to_num(), b.nan_to_num()) and torch.equal(torch.isnan(a), torch.isnan(b))


def test_kernel_refuses_mismatched_inputs():
    lum, rays, depth, valid, pose = torch.zeros(6), torch.zeros(6, 3), torch.zeros(6), torch.ones(6), torch.zeros(12)
    nb = (torch.zeros(12), torch.ones(4), torch.zeros(2, 3), torch.ones(2, 4), torch.zeros(2, 3), (3, 2))
    with pytest.raises(RuntimeError, match="differ in size"):
        kernel.consistency_excess(lum, rays, depth, valid, pose, [nb])
    with pytest.raises(RuntimeError, match="do not match"):
        kernel.consistency_excess(lum, torch.zeros(5, 3), depth, valid, pose, [])
