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
from nimbus.methods.nimbusgs.config import NimbusConfig
from nimbus.methods.nimbusgs.degradation import view_excesses
from nimbus.methods.nimbusgs.particulate import extract_residual
from nimbus.restore.classical import RestoreConfig, classical_restore
from nimbus.train.runner import Runner

M_INIT = 3


@pytest.fixture(scope="module")
def rainy():
    """The tiny garden at 32 x 24 px, every fourth training view, with bright streaks on the training views."""
    scene = render_builtin("garden", size="tiny", seed=0)
    rng = np.random.default_rng(0)
    views = []
    for v in scene.train_views[::4] + scene.test_views[:1]:
        h, w = v.image.shape[:2]
        img = v.image.reshape(h // 2, 2, w // 2, 2, 3).mean((1, 3)).astype(np.float32)
        depth = v.depth.reshape(h // 2, 2, w // 2, 2).mean((1, 3)).astype(np.float32)
        if v.name not in scene.test_names:
            for _ in range(24):
                x, y = int(rng.integers(0, w // 2)), int(rng.integers(0, h // 2 - 4))
                img[y:y + 4, x] += 0.6
        views.append(View(v.name, v.camera.scaled(0.5), image=np.clip(img, 0, 1), depth=depth))
    return scene.with_views(views)


def _stage1(scene, out, source: str) -> dict:
    """Train one stage-2 step past stage 1 and keep what the end of stage 1 left: the Gaussians, each
    view's consistency excess over its neighbours and each stored residual, and the method."""
    cfg = NimbusConfig(iterations=M_INIT + 1, m_init=M_INIT, refresh_interval=4, components="csm,plm,ggs",
                       sh_degree=1, sh_degree_interval=8, densify_from=4, densify_until=12, densify_interval=4,
                       opacity_reset_interval=1000, checkpoint_interval=100, log_interval=4, grid_resolution=8,
                       ray_samples=8, dcp_patch=5, airlight_hidden=8, write_decomposition=False,
                       residual_source=source)
    runner = Runner("nimbus", scene, cfg, out, seed=0, progress=False)
    m = runner.method
    end_stage1 = m._end_stage1
    kept: dict = {"method": m}

    def end_and_keep(step):
        events = end_stage1(step)
        kept["params"] = {k: v.detach().clone() for k, v in m.params.tensors.items()}
        kept["excesses"] = view_excesses(m._consistency_check(), m._composites(step)[1])
        kept["stored"] = [m.particulate.store.get(i).clone() for i in range(len(m.train_images))]
        return events

    m._end_stage1 = end_and_keep
    runner.run()
    return kept


def test_restored_residual_is_the_render_pipeline_on_the_restoration(rainy, tmp_path):
    restored = _stage1(rainy, tmp_path / "restored", "restored")
    render = _stage1(rainy, tmp_path / "render", "render")
    # Stage 1 does not depend on the residual source: both runs reach the same model.
    for k, v in render["params"].items():
        assert torch.equal(v, restored["params"][k]), k
    m = render["method"]
    masked_somewhere = False
    for vi, img in enumerate(m.train_images):
        reference = classical_restore(img, RestoreConfig(patch=m.cfg.dcp_patch))
        # The render source's pipeline (mask, consistency test, top-hat cap), with I_restore for I_con.
        expected = m.particulate.residual(vi, reference, render["excesses"][vi])
        expected = torch.round(expected.clamp(0, 1) * 255) / 255  # as the store keeps it
        assert torch.equal(restored["stored"][vi], expected), vi
        masked_somewhere |= not torch.equal(expected, torch.round(extract_residual(img, reference) * 255) / 255)
    # The mask and the cap do act here: the bare ReLU(I_in - I_restore) the old variant stored differs.
    assert masked_somewhere
