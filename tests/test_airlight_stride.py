"""The network airlight evaluated per block of pixels and upsampled (``airlight_stride``)."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from nimbus.data.camera import Camera
from nimbus.methods.nimbusgs.config import NimbusConfig, preset
from nimbus.methods.nimbusgs.degradation import Medium, block_mean, upsample_blocks
from nimbus.methods.nimbusgs.scattering import Box, camera_rays


@pytest.mark.parametrize("h, w, s", [(6, 8, 2), (5, 7, 2), (7, 5, 3), (4, 4, 1), (3, 2, 4)])
def test_block_mean_averages_the_pixels_each_block_has(h, w, s):
    x = torch.rand(h * w, 3, generator=torch.Generator().manual_seed(h * w + s), dtype=torch.float64)
    img = x.reshape(h, w, 3)
    got = block_mean(x, h, w, s).reshape(-(-h // s), -(-w // s), 3)
    for i in range(got.shape[0]):
        for j in range(got.shape[1]):
            want = img[i * s:(i + 1) * s, j * s:(j + 1) * s].reshape(-1, 3).mean(0)  # edge blocks: fewer pixels
            torch.testing.assert_close(got[i, j], want, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("s", [1, 2, 3, 4])
def test_upsampled_blocks_reproduce_a_linear_image_between_block_centres(s):
    h, w = 6 * s, 5 * s
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    ramp = torch.stack([0.3 * u - 0.2 * v, 0.1 * v + 2.0, torch.ones_like(u)], -1).reshape(-1, 3)
    up = upsample_blocks(block_mean(ramp, h, w, s), h, w, s).reshape(h, w, 3)
    c = (s - 1) / 2  # the first block's centre, in pixels; beyond the outer centres the values are flat
    inner = (v >= c) & (v <= h - 1 - c) & (u >= c) & (u <= w - 1 - c)
    torch.testing.assert_close(up[inner], ramp.reshape(h, w, 3)[inner], rtol=1e-10, atol=1e-10)
    assert upsample_blocks(torch.full((-(-7 // s) * -(-9 // s), 2), 0.25), 7, 9, s).eq(0.25).all()


def _medium(stride: int, inputs: str = "view") -> Medium:
    cfg = dataclasses.replace(preset("tiny"), airlight_stride=stride, airlight_input=inputs)
    torch.manual_seed(0)
    m = Medium(cfg, Box((-3.0,) * 3, (3.0,) * 3), 0.6, 4.0, torch.tensor([0.7, 0.75, 0.8]), seed=0,
               device=torch.device("cpu"))
    with torch.no_grad():  # a network whose output depends on its inputs (the last layer starts at zero)
        torch.nn.init.normal_(m.airlight.mlp[-1].weight, std=0.5, generator=torch.Generator().manual_seed(1))
    return m


def _view(h=24, w=32):
    cam = Camera.look_at((0.0, 0.0, -1.0), (0.0, 0.0, 1.0), (0.0, -1.0, 0.0), w, h, fov_x_deg=60)
    yy = torch.linspace(1.5, 4.0, h)[:, None].expand(h, w)
    render = {"depth": yy.contiguous(), "alpha": torch.ones(h, w)}
    image = torch.rand(h, w, 3, generator=torch.Generator().manual_seed(2))
    return camera_rays(cam), render, image


@pytest.mark.parametrize("inputs", ["view", "pixel"])
def test_a_strided_airlight_is_close_to_the_per_pixel_one_and_trains_the_same_weights(inputs):
    rays, render, image = _view()
    desc = torch.tensor([0.7, 0.75, 0.8, 0.5, 0.5, 0.5])
    t1, p1 = _medium(1, inputs).forward(rays, render, desc, image=image)
    m2 = _medium(2, inputs)
    t2, p2 = m2.forward(rays, render, desc, image=image)
    assert torch.equal(t1, t2) and p2.shape == p1.shape  # T stays per pixel
    assert 0 < float((p2 - p1).detach().abs().max()) < (0.1 if inputs == "view" else 0.3)
    p2.sum().backward()
    grads = [p.grad for p in m2.airlight.parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in grads) and float(grads[-2].abs().sum()) > 0


def test_the_block_directions_are_computed_once_per_view_and_equal_fresh_ones(monkeypatch):
    """A view's block-mean unit directions depend on its rays alone: kept on the rays, the same bits as a fresh pass."""
    import nimbus.methods.nimbusgs.degradation as degradation

    rays, render, image = _view(23, 31)  # edge blocks cut by the image border
    desc = torch.tensor([0.7, 0.75, 0.8, 0.5, 0.5, 0.5])
    m = _medium(2)
    calls = []
    block = degradation.block_mean
    monkeypatch.setattr(degradation, "block_mean", lambda x, *a: calls.append(x.shape[1]) or block(x, *a))
    _, p_first = m.forward(rays, render, desc)
    _, p_again = m.forward(rays, render, desc)
    assert calls.count(3) == 1 and calls.count(1) == 2  # directions once, T every time
    assert torch.equal(p_first, p_again)
    fresh = block(rays.dirs, 23, 31, 2)
    fresh = fresh / fresh.norm(dim=1, keepdim=True).clamp_min(1e-12)
    assert torch.equal(rays.derived(("block_dirs", 2), lambda: None), fresh)


def test_stride_one_is_the_per_pixel_airlight_bit_for_bit():
    rays, render, image = _view()
    desc = torch.tensor([0.7, 0.75, 0.8, 0.5, 0.5, 0.5])
    m = _medium(1)
    _, p = m.forward(rays, render, desc)
    from nimbus.methods.nimbusgs.scattering import march, march_interval
    lo, hi = m.box_tensors
    ts, te = march_interval(rays, lo, hi, render["depth"], render["alpha"], m.cfg.near_plane, m.cfg.surface_alpha_min)
    res = march(m.field, rays.origin, rays.dirs, ts, te, m.cfg.ray_samples, "auto")
    a = m.airlight(rays.dirs, res.transmission, desc)
    assert torch.equal(p, (res.scatter[:, None] * a).reshape(p.shape))


def test_the_stride_is_checked():
    from nimbus.config_set import apply_overrides
    from nimbus.errors import NimbusError

    with pytest.raises(NimbusError, match="airlight_stride"):
        apply_overrides(NimbusConfig(), {"airlight_stride": "0"})
