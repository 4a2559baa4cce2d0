"""The trainer on scenes of any scale and origin (issue 15 item 1): SfM scenes come in arbitrary units.

The trainer works in :class:`SceneFrame` (centred on the mean camera centre, extent 1), so a
scaled or shifted copy of a scene trains to the same model, and the outputs are in world units.
Measured on the tiny garden (400 iterations of the tiny preset, SH 0; test PSNR in dB), before ->
after the frame: 1x 19.73 -> 19.92, 100x 19.80 -> 19.92, 0.01x 19.92 -> 19.92, 0.001x 15.55 -> 19.92
(the near plane, 0.01 world units, culled the scene), 0.0001x "no Gaussian visible" -> 19.92,
shifted by 1e6 19.11 -> 19.96 (float32 means), 0.01x shifted by (300, 100, -50) 19.84 -> 20.10.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from nimbus.data.builtin import render_builtin
from nimbus.errors import NimbusError
from nimbus.losses import photometric_loss
from nimbus.render.rasterize import means2d_grad, rasterize
from nimbus.train.config import TrainConfig, preset
from nimbus.train.checkpoint import CHECKPOINT
from nimbus.train.frame import SceneFrame
from nimbus.train.runner import Runner
from nimbus.train.strategy import DefaultStrategy


@pytest.fixture(scope="module")
def garden():
    return render_builtin("garden", size="tiny", seed=0)


def transformed(scene, scale: float, shift=(0.0, 0.0, 0.0)):
    """``scene`` under ``x -> scale x + shift``: the same photos, cameras and points in other units and origin."""
    d = np.broadcast_to(np.asarray(shift, dtype=np.float64), (3,))
    views = [dataclasses.replace(v, camera=v.camera.with_pose(v.camera.R, scale * v.camera.t - v.camera.R @ d))
             for v in scene.views]
    return dataclasses.replace(scene, views=tuple(views), points=scene.points * scale + d)


def test_frame_is_centred_with_unit_extent_and_changes_no_projection(garden):
    world = transformed(garden, 0.003, (2e3, -1e3, 40.0))
    frame = SceneFrame.of(world)
    assert frame.scale == pytest.approx(world.extent)
    local = frame.scene(world)
    assert local.extent == pytest.approx(1.0, rel=1e-9)
    np.testing.assert_allclose(local.camera_centers.mean(0), 0.0, atol=1e-7)
    for vw, vl in zip(world.views[:3], local.views[:3]):
        uv_w, z_w = vw.camera.project(world.points)
        uv_l, z_l = vl.camera.project(local.points)
        np.testing.assert_allclose(uv_l, uv_w, rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(z_l * frame.scale, z_w, rtol=1e-7)


def test_outputs_are_in_world_coordinates(garden, tmp_path):
    world = transformed(garden, 50.0, (1e4, 0.0, -3e3))
    t = Runner("3dgs", world, TrainConfig(iterations=2, sh_degree=0), tmp_path / "r", progress=False)
    g = t.gaussians().detach()
    np.testing.assert_allclose(g.means.double().numpy(), world.points, rtol=0, atol=1e-3 * world.extent)
    ref = Runner("3dgs", garden, TrainConfig(iterations=2, sh_degree=0), tmp_path / "ref", progress=False)
    # the initial (kNN) scales are world lengths: 50 times the original's
    np.testing.assert_allclose(g.log_scales.numpy(), ref.gaussians().log_scales.detach().numpy() + np.log(50.0),
                               atol=1e-4)


def test_a_tiny_scene_unit_does_not_put_the_scene_behind_the_near_plane(garden, tmp_path):
    """With the near plane in world units (0.01), a scene in kilometres (0.0001 x) rendered black."""
    cfg = TrainConfig(iterations=2, sh_degree=0)
    a = Runner("3dgs", garden, cfg, tmp_path / "a", progress=False)
    b = Runner("3dgs", transformed(garden, 1e-4), cfg, tmp_path / "b", progress=False)
    with torch.no_grad():
        ra = a.method.render(a.method.train_views[0].camera)["rgb"]
        rb = b.method.render(b.method.train_views[0].camera)["rgb"]
    assert float(ra.mean()) > 0.05
    torch.testing.assert_close(rb, ra, atol=2e-3, rtol=0)


def test_a_checkpoint_of_another_frame_is_refused(garden, tmp_path):
    cfg = TrainConfig(iterations=2, sh_degree=0)
    t = Runner("3dgs", garden, cfg, tmp_path / "a", progress=False)
    t.run()
    other = Runner("3dgs", transformed(garden, 2.0), cfg, tmp_path / "b", progress=False)
    with pytest.raises(NimbusError, match="does not fit this run.*frame"):
        other.load_checkpoint(tmp_path / "a" / CHECKPOINT)
    again = Runner("3dgs", garden, cfg, tmp_path / "c", progress=False)
    again.load_checkpoint(tmp_path / "a" / CHECKPOINT)
    assert again.iteration == 2


def test_densification_statistic_does_not_depend_on_the_image_size(garden, tmp_path):
    """The gradient threshold is in NDC units (Inria): the statistic stays within a factor 1.5 from 64 to 256 px
    wide (measured 4.6e-4, 4.1e-4, 3.0e-4 mean), where the pixel-unit gradient shrinks about 6 times."""
    t = Runner("3dgs", garden, TrainConfig(iterations=2, sh_degree=0), tmp_path / "r", progress=False)
    g0 = t.method.gaussians().detach()
    gen = torch.Generator().manual_seed(0)
    target_g = dataclasses.replace(g0, means=g0.means + 0.01 * torch.randn(g0.means.shape, generator=gen),
                                   sh_dc=g0.sh_dc + 0.1 * torch.randn(g0.sh_dc.shape, generator=gen))
    cam = t.method.train_views[0].camera
    means = {}
    for f in (1, 4):
        c = cam.scaled(f, width=cam.width * f, height=cam.height * f)
        with torch.no_grad():
            target, *_ = rasterize(target_g, c, sh_degree=0, background=torch.zeros(3))
        g = dataclasses.replace(g0, means=g0.means.clone()).requires_grad_(True)
        rgb, _, _, meta = rasterize(g, c, sh_degree=0, background=torch.zeros(3))
        photometric_loss(rgb, target, 0.2).backward()
        strategy = DefaultStrategy.from_config(t.cfg)
        state = strategy.initialize_state()
        info = {"means2d_grad": means2d_grad(meta), "radii": meta["radii"], "visible": meta["visible"],
                "width": c.width, "height": c.height}
        assert strategy.step_post_backward(t.method.params, state, 1, info, gen) == []  # step 1: accumulate only
        means[f] = float(state["grad_accum"][state["denom"] > 0].mean())
    assert 1 / 2 < means[1] / means[4] < 2, means


@pytest.mark.slow
def test_scaled_and_shifted_copies_train_to_the_same_psnr(garden, tmp_path):
    """Copies of a scene in other units and origins train to the test PSNR of the original.

    Scaled copies keep densification (its thresholds are the scale-dependent part; measured equal to the
    original's PSNR to 1e-3 dB at seeds 0, 1, 2).  The geo-referenced shifts (1e6 to 1e7) run without it:
    moving the origin by 1e6 perturbs the normalised poses in their last float64 bits, and with densification on
    a 150-iteration run is chaotic enough to turn that into -0.49 / +0.24 / -0.16 dB at seeds 0 / 1 / 2 (on an
    AVX2 machine; an AVX-512 one stayed within 0.3 dB), the same spread as a change of seed.  Without it the
    shifted runs matched to 2e-4 dB, where training in world coordinates loses the means to float32 rounding.
    """
    cfg = dataclasses.replace(preset("tiny").rescaled(150), sh_degree=0)
    s = garden.with_views(garden.train_views[::2] + garden.test_views)

    def run(label, scene, config=cfg):
        return Runner("3dgs", scene, config, tmp_path / label, seed=0, progress=False).run()["psnr"]

    base = run("base", s)
    for label, scene in [("x100", transformed(s, 100.0)), ("x0.001", transformed(s, 1e-3)),
                         ("x0.01+shift", transformed(s, 0.01, (300.0, 100.0, -50.0)))]:
        assert run(label, scene) == pytest.approx(base, abs=0.05), label
    still = dataclasses.replace(cfg, densify_until=0)
    base = run("base-still", s, still)
    for label, shift in [("shift1e6", (1e6, -2e6, 5e5)), ("shift1e7", (1e7, -2e7, 5e6))]:
        assert run(label, transformed(s, 1.0, shift), still) == pytest.approx(base, abs=0.05), label
