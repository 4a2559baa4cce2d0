"""A minimal reconstruction method: the whole of what adding a method takes, besides one registry line.

Gaussians sit fixed at the scene's sparse points (3DGS's initialisation) and only their colours are learned,
with an L1 loss.  It implements :class:`nimbus.methods.base.Method` from scratch (no 3DGS machinery), so the
runner's run folder, checkpoints, resume, log, guards, scores, PLY and results all come for free.  The line
that makes it ``--method example`` is, in :data:`nimbus.methods.registry.METHODS`::

    "example": MethodSpec("example", "fixed Gaussians, learned colours", "tests.example_method:ExampleMethod"),
"""

from __future__ import annotations

import dataclasses

import torch

from nimbus.metrics import peak_signal_noise_ratio
from nimbus.methods.base import TrainingDiverged
from nimbus.render.gaussians import GaussianInitConfig, init_from_scene
from nimbus.render.rasterize import rasterize


class ExampleMethod:
    """Fixed Gaussians with learned colours; ``config`` is a :class:`~nimbus.train.config.TrainConfig`."""

    def __init__(self, scene, config, *, seed=0, device=None, frame=None) -> None:
        self.cfg = config
        self.device = device or torch.device("cpu")
        self.train_views = list(scene.train_views)
        self.images = [torch.from_numpy(v.load_image()).to(self.device) for v in self.train_views]
        init = init_from_scene(scene, GaussianInitConfig(sh_degree=0, init_opacity=0.5, seed=seed))
        self.model = dataclasses.replace(init, sh_dc=init.sh_dc.to(self.device).requires_grad_(True))
        self.optimizer = torch.optim.Adam([{"params": [self.model.sh_dc], "lr": config.lr_sh_dc, "name": "sh_dc"}])
        self.gen = torch.Generator().manual_seed(seed)

    def train_iteration(self, step: int) -> dict:
        vi = int(torch.randint(len(self.train_views), (1,), generator=self.gen))
        render, gt = self.render(self.train_views[vi].camera), self.images[vi]
        loss = (render["rgb"] - gt).abs().mean()
        if not torch.isfinite(loss):
            raise TrainingDiverged("loss", float(loss.detach()))
        loss.backward()
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)
        pv = peak_signal_noise_ratio(render["rgb"].detach(), gt, quantize=False)
        return {"loss": float(loss.detach()), "psnr": pv,
                "visible": bool(render["meta"]["visible"].any()), "events": []}

    def render(self, camera, *, view_index=None) -> dict:  # no per-view extras
        rgb, depth, alpha, meta = rasterize(self.model, camera, sh_degree=0, background=torch.zeros(3))
        return {"rgb": rgb, "depth": depth, "alpha": alpha, "meta": meta}

    def state_dict(self) -> dict:
        return {"sh_dc": self.model.sh_dc.detach().clone(), "optimizer": self.optimizer.state_dict(),
                "generator": self.gen.get_state()}

    def load_state_dict(self, state: dict) -> None:
        with torch.no_grad():
            self.model.sh_dc.copy_(state["sh_dc"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.gen.set_state(state["generator"].cpu())

    def get_info(self) -> dict:
        return {"example": {"points": self.num_gaussians}}

    def gaussians(self):
        return self.model

    def param_groups(self) -> list[dict]:
        return list(self.optimizer.param_groups)

    @property
    def num_gaussians(self) -> int:
        return self.model.means.shape[0]

    def setup_events(self) -> list:
        return []

    def write_outputs(self, out_dir) -> None:
        pass
