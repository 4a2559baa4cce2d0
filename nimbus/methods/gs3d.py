"""Vanilla 3D Gaussian Splatting (Inria defaults) as a :class:`~nimbus.methods.base.Method`.

:class:`GaussianSplatting` holds the shared 3DGS machinery: the Gaussian parameters and
their Adam (:class:`~nimbus.train.params.GaussianParams`), the densification strategy
(:class:`~nimbus.train.strategy.DefaultStrategy`), the SH and learning-rate schedules,
the view order, and a complete :meth:`GaussianSplatting.train_iteration`.

Methods that are 3DGS plus something (NimbusGS: a degradation model in front of the
loss) derive from it and override only the points where their model enters the step,
each a plain method with one job: :meth:`~GaussianSplatting.loss` (what the render is
compared with), :meth:`~GaussianSplatting.before_backward` and
:meth:`~GaussianSplatting.reweight_gradients` (per-Gaussian gradient weights, handed to the
rasterizer's backward or applied after it, and to the strategy in ``info``),
:meth:`~GaussianSplatting.param_groups` / :meth:`~GaussianSplatting.optimizer_step` (extra optimised tensors) and
:meth:`~GaussianSplatting.after_step` (their own schedule).  The step itself, its guards
and its order stay here, in one place, rather than being copied.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from nimbus.data import Camera, Scene, View
from nimbus.errors import NimbusError
from nimbus.kernels import train_step
from nimbus.losses import photometric_loss
from nimbus.metrics import peak_signal_noise_ratio
from nimbus.methods.base import TrainingDiverged, default_device
from nimbus.render.gaussians import GaussianInitConfig, Gaussians, init_from_scene
from nimbus.render.projection import ProjectionConfig
from nimbus.render.rasterize import FRAME_BYTES_PER_PIXEL, RasterConfig, means2d_grad, rasterize, tile_buffer_bytes
from nimbus.train.config import TrainConfig
from nimbus.train.frame import SceneFrame
from nimbus.train.params import BYTES_PER_GAUSSIAN, GaussianParams
from nimbus.train.strategy import DefaultStrategy
from nimbus.train.views import downscaled_view, view_mask
from nimbus.utils.memory import SizeCost, check_sizes


class GaussianSplatting:
    """Vanilla 3DGS on the training views of ``scene`` (in the training frame; see :mod:`nimbus.methods.base`).

    Parameters
    ----------
    scene : Scene
        In the training frame; ``scene.train_views`` are trained on.
    config : TrainConfig
    seed : int
    device : torch.device or None
        Default: CUDA when available.
    frame : SceneFrame or None
        How ``scene`` maps to the world (default: it is the world).

    Extras of :meth:`render`: ``meta`` (the rasterizer's per-Gaussian ``radii``, ``depths``,
    ``visible``, ``means2d``).
    """

    def __init__(self, scene: Scene, config: TrainConfig, *, seed: int = 0, device: torch.device | None = None,
                 frame: SceneFrame | None = None) -> None:
        if not scene.train_views:
            raise NimbusError("the scene has no training views; check its train/test split")
        self.scene = scene
        self.cfg = config
        self.seed = int(seed)
        self.device = device or default_device()
        self.frame = frame or SceneFrame((0.0, 0.0, 0.0), 1.0)
        #: The last step trained (0 before the first).
        self.iteration = 0
        torch.manual_seed(self.seed)
        np.random.seed(self.seed % 2**32)
        self.gen = torch.Generator().manual_seed(self.seed)
        self.train_views: list[View] = [downscaled_view(v, config.train_downscale) for v in scene.train_views]
        # Before anything sized by the config is allocated: a huge --set value is one error, not a crash or a hang.
        check_sizes(self.size_costs(), self.device)
        self.train_images = [torch.from_numpy(v.load_image()).to(self.device) for v in self.train_views]
        #: Per training view, its validity mask (bool [H, W] on the device) or None: views without a
        #: mask take the plain loss, with no all-ones tensor on the hot path.
        self.train_masks: list[Tensor | None] = [
            None if m is None else torch.from_numpy(m).to(self.device) for m in map(view_mask, self.train_views)]
        init = init_from_scene(scene, GaussianInitConfig(sh_degree=config.sh_degree, init_opacity=config.init_opacity,
                                                         random_points=config.init_random_points, seed=self.seed))
        self.params = GaussianParams(self._init_tensors(init), self._learning_rates(), config.adam_eps)
        centers = scene.camera_centers
        self.strategy = DefaultStrategy.from_config(config, scene.extent, centers.mean(0) if len(centers) else None)
        self.strategy_state = self.strategy.initialize_state()
        #: The configured background colour [3], on the device once (not rebuilt every render).
        self.background = torch.tensor(config.background, device=self.device)
        self.raster_config = RasterConfig(tile_size=config.tile_size,
                                          projection=ProjectionConfig(near=config.near_plane))
        self._order: list[int] = []

    # --- set-up ------------------------------------------------------------------------
    def _init_tensors(self, g: Gaussians) -> dict[str, Tensor]:
        """The per-Gaussian parameter tensors (their order is the optimiser's, and the checkpoint's)."""
        return {k: v.to(self.device) for k, v in g.tensors().items()}

    def _learning_rates(self) -> dict[str, float]:
        c = self.cfg
        return {"means": c.lr_means_init * self.scene.extent, "log_scales": c.lr_scales, "quats": c.lr_quats,
                "opacity_logits": c.lr_opacity, "sh_dc": c.lr_sh_dc, "sh_rest": c.lr_sh_rest}

    def setup_events(self) -> list[tuple[str, dict]]:
        return []

    def size_costs(self) -> list[SizeCost]:
        """What each size-like config field would allocate at this scene's sizes (:func:`check_sizes` refuses
        one that cannot fit before anything is allocated).  A method adds its own fields to ``super()``'s."""
        c = self.cfg
        threads = torch.get_num_threads()
        costs = [SizeCost("tile_size", c.tile_size, lambda t: tile_buffer_bytes(t, c.backend, threads),
                          lambda t: f"the rasterizer's {t}x{t} tiles ({c.backend} backend, {threads} thread(s))")]
        if not len(self.scene.points):  # the random initialisation
            costs.append(SizeCost("init_random_points", c.init_random_points, lambda n: n * BYTES_PER_GAUSSIAN,
                                  lambda n: f"{n} initial Gaussians and their optimiser state"))
        return costs

    def frame_bytes(self, pixels: int) -> float:
        """About how many bytes one render of ``pixels`` pixels takes besides the model (every layer the
        method draws for it; what the viewer sizes its frames by)."""
        return float(pixels) * FRAME_BYTES_PER_PIXEL

    # --- the model ---------------------------------------------------------------------
    @property
    def num_gaussians(self) -> int:
        return len(self.params)

    def gaussians(self) -> Gaussians:
        """The Gaussians being trained, in the training frame (what :meth:`render` draws)."""
        t = self.params.tensors
        return Gaussians(means=t["means"], log_scales=t["log_scales"], quats=t["quats"],
                         opacity_logits=t["opacity_logits"], sh_dc=t["sh_dc"], sh_rest=t["sh_rest"])

    def render(self, camera: Camera, sh_degree: int | None = None, background: Tensor | None = None,
               view_index: int | None = None) -> dict:
        """``rgb``, ``depth``, ``alpha`` and ``meta`` of ``camera`` (default: full SH degree, the configured
        background); 3DGS has no per-view extras, so ``view_index`` changes nothing."""
        bg = self.background if background is None else background
        deg = self.cfg.sh_degree if sh_degree is None else sh_degree
        rgb, depth, alpha, meta = rasterize(self.gaussians(), camera, sh_degree=deg, background=bg,
                                            backend=self.cfg.backend, config=self.raster_config)
        return {"rgb": rgb, "depth": depth, "alpha": alpha, "meta": meta}

    # --- schedules ---------------------------------------------------------------------
    def active_sh_degree(self, step: int) -> int:
        return min(self.cfg.sh_degree, step // self.cfg.sh_degree_interval)

    def means_lr(self, step: int) -> float:
        """Log-linear decay from ``lr_means_init`` to ``lr_means_final`` over the run, times the extent."""
        c = self.cfg
        t = min(max(step / max(c.iterations, 1), 0.0), 1.0)
        lr = math.exp(math.log(c.lr_means_init) * (1 - t) + math.log(c.lr_means_final) * t)
        return lr * self.scene.extent

    def _next_view(self) -> int:
        if not self._order:
            self._order = torch.randperm(len(self.train_views), generator=self.gen).tolist()
        return self._order.pop()

    # --- the step ----------------------------------------------------------------------
    def train_iteration(self, step: int) -> dict:
        """One 3DGS step on the next training view (see :meth:`nimbus.methods.base.Method.train_iteration`)."""
        c = self.cfg
        self.params.set_lr("means", self.means_lr(step))
        vi = self._next_view()
        view, gt = self.train_views[vi], self.train_images[vi]
        bg = torch.rand(3, generator=self.gen).to(self.device) if c.random_background else None
        render = self.render(view.camera, self.active_sh_degree(step), bg)
        loss, pred = self.loss(step, vi, render, gt)
        if not torch.isfinite(loss):
            raise TrainingDiverged("loss", float(loss.detach()))
        events: list[tuple[str, dict]] = []
        info: dict = {}
        visible = loss.requires_grad and bool(render["meta"]["visible"].any())
        if visible:
            self.before_backward(step, vi, render, pred, gt)
            loss.backward()
            meta = render["meta"]
            info = {"means2d_grad": means2d_grad(meta), "radii": meta["radii"], "visible": meta["visible"],
                    "width": view.camera.width, "height": view.camera.height}
            self.reweight_gradients(step, vi, render, pred, gt, info)
            if not self._grads_finite():
                raise TrainingDiverged("gradients")
            self.optimizer_step()
        else:  # nothing in this view depends on the Gaussians: nothing to learn from it
            events.append(("no_visible_gaussians", {"view": view.name, "iteration": step}))
        self.iteration = step
        events += self.strategy.step_post_backward(self.params, self.strategy_state, step, info, self.gen)
        events += self.after_step(step)
        with torch.no_grad():
            lv = float(loss)
            pv = peak_signal_noise_ratio(pred, gt, quantize=False, mask=self.train_masks[vi])
        return {"loss": lv, "psnr": pv, "visible": visible, "events": events}

    def loss(self, step: int, view_index: int, render: dict, gt: Tensor) -> tuple[Tensor, Tensor]:
        """The training loss of one view and the prediction it compared with ``gt`` (3DGS: the render).

        Pixels outside the view's validity mask (``self.train_masks``) take no part.
        """
        return photometric_loss(render["rgb"], gt, self.cfg.lambda_dssim, self.train_masks[view_index]), render["rgb"]

    def before_backward(self, step: int, view_index: int, render: dict, pred: Tensor, gt: Tensor) -> None:
        """Just before ``backward`` of a step that will update the Gaussians (3DGS: nothing); a method that
        rescales gradients can hand its factors to the rasterizer here (``render["meta"]["row_scale"]``)."""

    def reweight_gradients(self, step: int, view_index: int, render: dict, pred: Tensor, gt: Tensor,
                           info: dict) -> None:
        """After ``backward``: rescale gradients, and put the weights in ``info`` for the strategy (3DGS: none)."""

    def optimizer_step(self) -> None:
        """Step and clear every optimiser."""
        self.params.optimizer.step()
        self.params.optimizer.zero_grad(set_to_none=True)

    def after_step(self, step: int) -> list[tuple[str, dict]]:
        """The method's own schedule after densification; returns events (3DGS: none)."""
        return []

    def param_groups(self) -> list[dict]:
        return list(self.params.optimizer.param_groups)

    def _gradients(self) -> list[Tensor]:
        """Every optimised parameter's gradient (those that have one)."""
        return [p.grad for group in self.param_groups() for p in group["params"] if p.grad is not None]

    def _grads_finite(self) -> bool:
        return train_step.all_finite(self._gradients())

    # --- state -------------------------------------------------------------------------
    def state_dict(self) -> dict:
        """Parameters and Adam, densification statistics, generators and view order; ``extra`` for methods
        built on this one (the checkpoint layout of earlier Nimbus versions)."""
        return {"params": self.params.state_dict(), "density": dict(self.strategy_state),
                "generator": self.gen.get_state(), "torch_rng": torch.get_rng_state(),
                "order": [int(i) for i in self._order], "extra": {}}

    def load_state_dict(self, state: dict) -> None:
        self.iteration = int(state["iteration"])
        self.params.load_state_dict(state["params"])
        d = state["density"]
        for key in ("grad_accum", "denom", "max_radii"):
            if tuple(d[key].shape[:1]) != (len(self.params),):
                raise ValueError(f"density statistic {key!r} has shape {tuple(d[key].shape)}, for "
                                 f"{len(self.params)} Gaussians")
        self.strategy_state = {"grad_accum": d["grad_accum"], "denom": d["denom"], "max_radii": d["max_radii"]}
        # The generators live on the CPU whatever map_location moved the tensors to.
        self.gen.set_state(state["generator"].cpu())
        torch.set_rng_state(state["torch_rng"].cpu())
        self._order = [int(i) for i in state["order"]]

    def get_info(self) -> dict:
        return {}

    def write_outputs(self, out_dir) -> None:
        """3DGS writes nothing beyond the runner's outputs."""
