"""The PLM ablation ``nimbus-restored-residuals`` changes one thing: the residual's reference.

``residual_source=restored`` takes R against a classical 2D restoration instead of the
continuous composite I_con; the particle mask (outlier + view-consistency test) and the
input's top-hat cap are those of the render source, so the ablation row measures the
source alone.
"""

import numpy as np
import pytest
import torch

from nimbus.data.builtin import render_builtin
from nimbus.data.scene import View
from nimbus.nimbusgs.config import NimbusConfig
from nimbus.nimbusgs.degradation import view_excesses
from nimbus.nimbusgs.particulate import extract_residual
from nimbus.restore.classical import RestoreConfig, classical_restore
from nimbus.train.runner import Runner

M_INIT = 6


@pytest.fixture(scope="module")
def rainy():
    """The tiny garden at 32 x 24 px, every other training view, with bright streaks on the training views."""
    scene = render_builtin("garden", size="tiny", seed=0)
    rng = np.random.default_rng(0)
    views = []
    for v in scene.train_views[::2] + scene.test_views:
        h, w = v.image.shape[:2]
        img = v.image.reshape(h // 2, 2, w // 2, 2, 3).mean((1, 3)).astype(np.float32)
        depth = v.depth.reshape(h // 2, 2, w // 2, 2).mean((1, 3)).astype(np.float32)
        if v.name not in scene.test_names:
            for _ in range(24):
                x, y = int(rng.integers(0, w // 2)), int(rng.integers(0, h // 2 - 4))
                img[y:y + 4, x] += 0.6
        views.append(View(v.name, v.camera.scaled(0.5), image=np.clip(img, 0, 1), depth=depth))
    return scene.with_views(views)


def _stage1(scene, out, source: str) -> Runner:
    """A run that stops at the end of stage 1, where the residuals are first extracted."""
    cfg = NimbusConfig(iterations=M_INIT, m_init=M_INIT, refresh_interval=4, components="csm,plm,ggs", sh_degree=1,
                       sh_degree_interval=8, densify_from=4, densify_until=12, densify_interval=4,
                       opacity_reset_interval=1000, checkpoint_interval=100, log_interval=4, grid_resolution=8,
                       ray_samples=8, dcp_patch=5, airlight_hidden=8, write_decomposition=False,
                       residual_source=source)
    runner = Runner("nimbus", scene, cfg, out, seed=0, progress=False)
    runner.run()
    return runner


def test_restored_residual_is_the_render_pipeline_on_the_restoration(rainy, tmp_path):
    restored = _stage1(rainy, tmp_path / "restored", "restored").method
    render = _stage1(rainy, tmp_path / "render", "render").method
    # Stage 1 does not depend on the residual source: both runs reach the same model.
    for k, v in render.params.tensors.items():
        assert torch.equal(v, restored.params.tensors[k]), k
    cfg = render.cfg
    _, geometry = render._composites(M_INIT)
    excesses = view_excesses(cfg, render.train_images, geometry)
    layer = render.particulate
    masked_somewhere = False
    for vi, img in enumerate(render.train_images):
        reference = classical_restore(img, RestoreConfig(patch=cfg.dcp_patch))
        # The render source's pipeline (mask, consistency test, top-hat cap), with I_restore for I_con.
        expected = layer.residual(vi, reference, excesses[vi])
        expected = torch.round(expected.clamp(0, 1) * 255) / 255  # as the store keeps it
        assert torch.equal(restored.particulate.store.get(vi), expected), vi
        masked_somewhere |= not torch.equal(expected, torch.round(extract_residual(img, reference) * 255) / 255)
    # The mask and the cap do act here: the bare ReLU(I_in - I_restore) the old variant stored differs.
    assert masked_somewhere
