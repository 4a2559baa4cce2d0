"""The 3DGS training loop: run directory, checkpoints, logging, evaluation.

:class:`GaussianTrainer` implements vanilla 3DGS.  Methods built on it (NimbusGS)
subclass it and override the hooks :meth:`GaussianTrainer.extra_setup`,
:meth:`GaussianTrainer.compute_loss`, :meth:`GaussianTrainer.before_step` and
:meth:`GaussianTrainer.extra_state`, so checkpoints, resume, densification, guards
and outputs are shared.

A run directory holds::

    config.json           the run's settings (scene path, method, seed, every config field)
    checkpoint.pt         latest checkpoint (parameters, optimiser, densification stats, RNG); tensors and
                          plain values only, read back with ``torch.load(weights_only=True)``
    train_log.jsonl       one JSON line every ``log_interval`` iterations and for every event
    point_cloud.ply       the final Gaussians in the standard 3DGS PLY layout
    renders/test/NAME.png renders of the held-out views
    results.json          test-view PSNR / SSIM, train time, peak memory, Gaussian count

A view's validity mask (:func:`view_mask`) limits its training loss and its scores to the
valid pixels; ``results.json`` records ``masked`` and each masked test view's ``valid_fraction``.
"""

from __future__ import annotations

import collections
import dataclasses
import io
import json
import math
import os
import pickle
import resource
import shutil
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from tqdm import tqdm

import nimbus
from nimbus.data import Scene, View
from nimbus.data.images import read_image, write_image
from nimbus.errors import NimbusError
from nimbus.losses import photometric_loss, psnr, ssim
from nimbus.render.gaussians import GaussianInitConfig, Gaussians, init_from_scene
from nimbus.versions import software_versions
from nimbus.render.projection import ProjectionConfig
from nimbus.render.rasterize import RasterConfig, means2d_grad, rasterize
from nimbus.train.config import TrainConfig
from nimbus.train.densify import DensityController, GaussianParams
from nimbus.train.ply import write_gaussian_ply
from nimbus.utils.fs import atomic_write_bytes, atomic_write_json, atomic_write_text

CHECKPOINT = "checkpoint.pt"
LAST_GOOD = "checkpoint_last_good.pt"
LOG = "train_log.jsonl"

#: What a checkpoint may hold: tensors and these plain values, in dicts / lists / tuples.  This is what
#: ``torch.load(weights_only=True)`` rebuilds without running code from the file, so a run folder received
#: from someone else cannot execute anything on ``--resume``.
PLAIN_TYPES = (type(None), bool, int, float, str)


def check_plain(obj: Any, where: str = "state") -> None:
    """Raise TypeError unless ``obj`` is tensors and :data:`PLAIN_TYPES` in dicts, lists and tuples.

    Called on every checkpoint before it is written, so a method that puts a numpy scalar,
    a dataclass or a module into its :meth:`GaussianTrainer.extra_state` fails at once (a
    programming error) instead of writing a checkpoint that ``--resume`` would refuse.
    """
    if isinstance(obj, torch.Tensor) or type(obj) in PLAIN_TYPES:
        return
    if type(obj) in (dict, collections.OrderedDict):  # modules' state_dict() are OrderedDicts
        for k, v in obj.items():
            if type(k) not in (str, int):
                raise TypeError(f"{where} has a {type(k).__name__} key {k!r}; checkpoint keys must be str or int")
            check_plain(v, f"{where}[{k!r}]")
        return
    if type(obj) in (list, tuple):
        for i, v in enumerate(obj):
            check_plain(v, f"{where}[{i}]")
        return
    raise TypeError(f"{where} is a {type(obj).__module__}.{type(obj).__qualname__}; a checkpoint holds only "
                    "tensors, None, bool, int, float and str in dicts, lists and tuples (torch.load weights_only)")


def default_device() -> torch.device:
    return torch.device("cuda") if torch.cuda.is_available() else torch.device("cpu")


def peak_memory_mb(device: torch.device) -> float:
    """Peak memory of this process: CUDA allocator peak on a GPU, else the resident-set high-water mark."""
    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device) / 2**20
    rss_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return rss_kb / 1024.0


def quantize_8bit(img: torch.Tensor) -> torch.Tensor:
    return torch.round(img.clamp(0, 1) * 255.0) / 255.0


def view_mask(view: View) -> np.ndarray | None:
    """The view's validity mask, bool ``(H, W)`` (True = the pixel counts), or None when every pixel counts.

    Checked here, at the boundary of training and scoring, for in-memory masks too: a mask
    of another size than the camera, or one that keeps no pixel (most likely the inverse
    convention, 0 = keep), is a :class:`NimbusError`, since training on it would silently
    learn nothing and scoring it would divide by zero.
    """
    mask = view.load_mask()
    if mask is None:
        return None
    mask = np.asarray(mask)
    size = (view.camera.height, view.camera.width)
    if mask.shape != size:
        raise NimbusError(f"the mask of view {view.name} is {'x'.join(map(str, mask.shape[::-1]))} but its camera "
                          f"is {size[1]}x{size[0]}; give a mask of the image's size (masks/<name>.png)")
    mask = mask.astype(bool)
    if not mask.any():
        raise NimbusError(f"the mask of view {view.name} keeps no pixel; masks mark the pixels to use with a "
                          "non-zero value and the pixels to ignore with 0 (invert it if it is the other way "
                          "round), or remove the view")
    return mask


def downscale_mask(mask: np.ndarray, height: int, width: int) -> np.ndarray:
    """A validity mask shrunk to ``height`` x ``width`` with the image's area averaging.

    A small pixel is valid only when every pixel it averages is valid: the shrunk image
    mixes the colours of its whole block, so a block that holds a single ignored pixel
    (a moving person, an undistortion border) would leak that pixel's colour into the loss.
    """
    m = torch.from_numpy(mask.astype(np.float32))[None, None]
    small = torch.nn.functional.interpolate(m, size=(height, width), mode="area")[0, 0]
    return (small >= 1.0 - 1e-6).numpy()


def downscaled_view(view: View, factor: int) -> View:
    """``view`` with its image shrunk ``factor`` times (area average) and its camera scaled to the new size.

    The image and the validity mask (:func:`downscale_mask`) are held in memory; depth and
    the sky mask are dropped, since their files keep the full size.  ``factor`` 1 returns
    ``view`` itself.
    """
    if factor == 1:
        return view
    img = torch.from_numpy(view.load_image()).permute(2, 0, 1)[None]  # [1, 3, H, W]
    h, w = max(img.shape[2] // factor, 1), max(img.shape[3] // factor, 1)
    small = torch.nn.functional.interpolate(img, size=(h, w), mode="area")[0].permute(1, 2, 0)
    mask = view_mask(view)
    if mask is not None:
        mask = downscale_mask(mask, h, w)
        if not mask.any():
            raise NimbusError(f"the mask of view {view.name} keeps no pixel once shrunk {factor} times "
                              "(train_downscale): a small pixel counts only when its whole block is valid; "
                              "lower train_downscale or remove the view")
    return dataclasses.replace(view, camera=view.camera.scaled(1.0 / factor, width=w, height=h),
                               image=small.contiguous().numpy(), image_path=None, depth=None, depth_path=None,
                               mask=mask, mask_path=None, sky=None, sky_path=None)


@dataclasses.dataclass(frozen=True)
class SceneFrame:
    """The similarity frame training runs in: ``x_train = (x_world - center) / scale``.

    ``center`` is the mean camera centre and ``scale`` the scene extent
    (:attr:`nimbus.data.Scene.extent`), so every scene trains centred with extent 1,
    whatever the units and the origin of its reconstruction (gsplat's
    ``normalize_world_space``, nerfstudio's ``auto_scale_poses``).  Without it the
    settings that are lengths (``near_plane``, the initial scale floor) meant different
    things in a scene reconstructed in millimetres or kilometres, and a geo-referenced
    scene (coordinates ~1e6) lost its detail to float32 rounding of the means.
    Projections, and so every render and score, are unchanged by the frame; only lengths
    inside the trainer (depth renders, NimbusGS's extinction) are in extent units.

    Attributes
    ----------
    center : tuple of 3 float
        World point that becomes the origin.
    scale : float
        World length that becomes 1 (> 0).
    """

    center: tuple[float, float, float]
    scale: float

    @classmethod
    def of(cls, scene: Scene) -> "SceneFrame":
        centers = scene.camera_centers
        center = centers.mean(0) if len(centers) else np.zeros(3)
        return cls(tuple(float(x) for x in center), float(scene.extent))

    def camera(self, camera):
        """``camera`` posed in this frame (same image: the camera-space scale does not change projections)."""
        c = np.asarray(self.center, dtype=np.float64)
        return camera.with_pose(camera.R, (np.asarray(camera.t, dtype=np.float64) + camera.R @ c) / self.scale)

    def points(self, points: np.ndarray) -> np.ndarray:
        return (np.asarray(points, dtype=np.float64) - np.asarray(self.center)) / self.scale

    def scene(self, scene: Scene) -> Scene:
        """``scene`` in this frame.  Depth maps are dropped: no trainer reads them, and they hold world lengths."""
        views = tuple(dataclasses.replace(v, camera=self.camera(v.camera), depth=None, depth_path=None)
                      for v in scene.views)
        return dataclasses.replace(scene, views=views, points=self.points(scene.points))

    def to_world(self, g: Gaussians) -> Gaussians:
        """Gaussians of this frame in world coordinates (centres and scales; rotations and colours are the same)."""
        c = torch.as_tensor(self.center, dtype=torch.float64, device=g.means.device)
        means = (g.means.to(torch.float64) * self.scale + c).to(g.means.dtype)
        return dataclasses.replace(g, means=means, log_scales=g.log_scales + math.log(self.scale))

    def as_list(self) -> list[float]:
        return [*self.center, self.scale]


class GaussianTrainer:
    """Vanilla 3DGS on a :class:`~nimbus.data.Scene`.

    Training runs in the scene's :class:`SceneFrame` (centred, extent 1): ``self.scene``
    and ``self.train_views`` are in that frame, ``self.world_scene`` is the scene as given;
    :meth:`gaussians` and ``point_cloud.ply`` are in world coordinates.

    Parameters
    ----------
    scene : Scene
        Training views are ``scene.train_views``; evaluation uses ``scene.test_views``.
    config : TrainConfig
    out_dir : Path
        The run directory (created; must be empty unless ``resume``).
    seed : int
    method : str
        Name recorded in the outputs.
    scene_path : str or None
        Where the scene was loaded from (recorded so ``--resume`` can reload it).
    progress : bool
        Show a progress bar on stderr.
    """

    method_name = "3dgs"

    def __init__(self, scene: Scene, config: TrainConfig, out_dir: str | os.PathLike, seed: int = 0,
                 scene_path: str | None = None, progress: bool = True, device: torch.device | None = None,
                 scene_load_args: dict | None = None) -> None:
        if not scene.train_views:
            raise NimbusError("the scene has no training views; check its train/test split")
        self.world_scene = scene
        self.frame = SceneFrame.of(scene)
        scene = self.frame.scene(scene)
        self.scene = scene
        self.cfg = config
        self.out = Path(out_dir)
        self.seed = int(seed)
        self.scene_path = scene_path
        self.scene_load_args = scene_load_args or {}
        self.progress = progress
        self.device = device or default_device()
        self.iteration = 0
        self.train_time = 0.0
        #: Training steps in which at least one Gaussian was visible (a run with none learned nothing).
        self.visible_steps = 0
        self.events: list[dict] = []
        torch.manual_seed(self.seed)
        np.random.seed(self.seed % 2**32)
        self.gen = torch.Generator().manual_seed(self.seed)
        self.train_views: list[View] = [downscaled_view(v, config.train_downscale) for v in scene.train_views]
        self.train_images = [torch.from_numpy(v.load_image()).to(self.device) for v in self.train_views]
        #: Per training view, its validity mask (bool [H, W] on the device) or None: views without a
        #: mask take the plain loss, with no all-ones tensor on the hot path.
        self.train_masks: list[torch.Tensor | None] = [
            None if m is None else torch.from_numpy(m).to(self.device) for m in map(view_mask, self.train_views)]
        init = init_from_scene(scene, GaussianInitConfig(sh_degree=config.sh_degree, init_opacity=config.init_opacity,
                                                         random_points=config.init_random_points, seed=self.seed))
        self.params = GaussianParams(self._init_tensors(init), self._learning_rates(), config.adam_eps)
        centers = scene.camera_centers
        self.density = DensityController(config, scene.extent, self.gen,
                                         centers.mean(0) if len(centers) else None)
        self.raster_config = RasterConfig(tile_size=config.tile_size,
                                          projection=ProjectionConfig(near=config.near_plane))
        self._order: list[int] = []
        self.extra_setup()

    # --- hooks for derived methods -------------------------------------------------
    def extra_setup(self) -> None:
        """Create method-specific modules and optimisers (called at the end of ``__init__``)."""

    def extra_state(self) -> dict:
        """Method-specific state to checkpoint."""
        return {}

    def load_extra_state(self, state: dict) -> None:
        """Restore what :meth:`extra_state` saved."""

    def compute_loss(self, view_index: int, render: dict[str, torch.Tensor], gt: torch.Tensor) -> torch.Tensor:
        """The training loss for one view; ``render`` has ``rgb``, ``depth``, ``alpha`` and ``meta``.

        Pixels outside the view's validity mask (``self.train_masks``) take no part.
        """
        return photometric_loss(render["rgb"], gt, self.cfg.lambda_dssim, self.train_masks[view_index])

    def training_prediction(self, render: dict) -> torch.Tensor:
        """What the last loss compared with the training image (the progress bar's PSNR)."""
        return render["rgb"]

    def before_step(self, view_index: int, render: dict) -> None:
        """Called after ``backward`` and the densification statistics, before the optimiser step."""

    def optimizer_step(self) -> None:
        """Step and clear every optimiser (derived methods add theirs)."""
        self.params.optimizer.step()
        self.params.optimizer.zero_grad(set_to_none=True)

    def eval_image(self, view: View, render: dict) -> torch.Tensor:
        """The image scored against the clean ground truth (3DGS: the render itself)."""
        return render["rgb"]

    # --- set-up helpers ----------------------------------------------------------------
    def _init_tensors(self, g: Gaussians) -> dict[str, torch.Tensor]:
        return {k: v.to(self.device) for k, v in g.tensors().items()}

    def _learning_rates(self) -> dict[str, float]:
        c = self.cfg
        return {"means": c.lr_means_init * self.scene.extent, "log_scales": c.lr_scales, "quats": c.lr_quats,
                "opacity_logits": c.lr_opacity, "sh_dc": c.lr_sh_dc, "sh_rest": c.lr_sh_rest}

    def frame_gaussians(self) -> Gaussians:
        """The Gaussians being trained, in the training frame (:class:`SceneFrame`; what :meth:`render` draws)."""
        t = self.params.tensors
        return Gaussians(means=t["means"], log_scales=t["log_scales"], quats=t["quats"],
                         opacity_logits=t["opacity_logits"], sh_dc=t["sh_dc"], sh_rest=t["sh_rest"])

    def gaussians(self) -> Gaussians:
        """The Gaussians in the scene's world coordinates (render them with the cameras of ``world_scene``)."""
        return self.frame.to_world(self.frame_gaussians())

    def active_sh_degree(self, it: int) -> int:
        return min(self.cfg.sh_degree, it // self.cfg.sh_degree_interval)

    def means_lr(self, it: int) -> float:
        """Log-linear decay from ``lr_means_init`` to ``lr_means_final`` over the run, times the extent."""
        c = self.cfg
        t = min(max(it / max(c.iterations, 1), 0.0), 1.0)
        lr = math.exp(math.log(c.lr_means_init) * (1 - t) + math.log(c.lr_means_final) * t)
        return lr * self.scene.extent

    def render(self, view: View, sh_degree: int | None = None, background: torch.Tensor | None = None) -> dict:
        bg = background if background is not None else torch.tensor(self.cfg.background, device=self.device)
        deg = self.cfg.sh_degree if sh_degree is None else sh_degree
        rgb, depth, alpha, meta = rasterize(self.frame_gaussians(), view.camera, sh_degree=deg, background=bg,
                                            backend=self.cfg.backend, config=self.raster_config)
        return {"rgb": rgb, "depth": depth, "alpha": alpha, "meta": meta}

    # --- training ----------------------------------------------------------------------
    def _next_view(self) -> int:
        if not self._order:
            self._order = torch.randperm(len(self.train_views), generator=self.gen).tolist()
        return self._order.pop()

    def log(self, record: dict) -> None:
        record = {"iteration": self.iteration, **record}
        with open(self.out / LOG, "a") as f:
            f.write(json.dumps(record) + "\n")

    def event(self, kind: str, **info: Any) -> None:
        self.log({"event": kind, **info})

    def train(self) -> dict:
        """Run (or continue) training to ``config.iterations``, then evaluate and write the outputs."""
        self.out.mkdir(parents=True, exist_ok=True)
        if self.iteration == 0:
            self.write_config()
        c = self.cfg
        bar = tqdm(total=c.iterations, initial=self.iteration, disable=not self.progress, file=sys.stderr,
                   desc=f"{self.method_name}", dynamic_ncols=True, leave=True)
        loss_ema = psnr_ema = None
        start = time.perf_counter()
        time_offset = self.train_time
        try:
            while self.iteration < c.iterations:
                it = self.iteration + 1
                if len(self.params) == 0:
                    self.save_checkpoint(LAST_GOOD)
                    raise NimbusError(f"every Gaussian was pruned by iteration {it}; lower prune_opacity or "
                                      "densify_grad_threshold (--set key=value), or check that the input views "
                                      "are not blank")
                self.params.set_lr("means", self.means_lr(it))
                vi = self._next_view()
                view, gt = self.train_views[vi], self.train_images[vi]
                bg = torch.rand(3, generator=self.gen).to(self.device) if c.random_background else None
                render = self.render(view, self.active_sh_degree(it), bg)
                loss = self.compute_loss(vi, render, gt)
                if not torch.isfinite(loss):
                    self.save_checkpoint(LAST_GOOD)
                    raise NimbusError(f"the loss became {float(loss.detach())} at iteration {it}; the last good state is in "
                                      f"{self.out / LAST_GOOD}. Lower the learning rates (--set lr_...=...) or "
                                      "check the input images")
                if loss.requires_grad and bool(render["meta"]["visible"].any()):
                    self.visible_steps += 1
                    loss.backward()
                    meta = render["meta"]
                    grad2d = means2d_grad(meta)
                    if grad2d is not None:
                        self.density.accumulate(grad2d, meta["radii"], view.camera.width, view.camera.height)
                    self.before_step(vi, render)
                    if not self._grads_finite():
                        self.save_checkpoint(LAST_GOOD)
                        raise NimbusError(f"non-finite gradients at iteration {it}; the last good state is in "
                                          f"{self.out / LAST_GOOD}. Lower the learning rates or check the inputs")
                    self.optimizer_step()
                else:  # nothing in this view depends on the Gaussians: nothing to learn from it
                    self.event("no_visible_gaussians", view=view.name, iteration=it)
                self.iteration = it
                self.after_step(it)
                with torch.no_grad():
                    lv = float(loss)
                    pv = psnr(self.training_prediction(render), gt, self.train_masks[vi])
                loss_ema = lv if loss_ema is None else 0.9 * loss_ema + 0.1 * lv
                psnr_ema = pv if psnr_ema is None else 0.9 * psnr_ema + 0.1 * pv
                if it % c.log_interval == 0 or it == c.iterations:
                    self.train_time = time_offset + time.perf_counter() - start
                    self.log({"loss": round(loss_ema, 6), "psnr": round(psnr_ema, 3), "gaussians": len(self.params),
                              "elapsed_s": round(self.train_time, 3)})
                    bar.set_postfix(loss=f"{loss_ema:.4f}", psnr=f"{psnr_ema:.2f}", gs=len(self.params))
                bar.update(1)
                if it % c.checkpoint_interval == 0 and it < c.iterations:
                    self.train_time = time_offset + time.perf_counter() - start
                    self.save_checkpoint()
        except KeyboardInterrupt:
            # Keep the progress so `--resume` continues from here (an interrupt inside an
            # optimiser step may make the resumed run differ from an uninterrupted one by a step).
            self.train_time = time_offset + time.perf_counter() - start
            self.save_checkpoint()
            print(f"interrupted at iteration {self.iteration}; continue with: nimbus-train --resume {self.out}",
                  file=sys.stderr)
            raise
        finally:
            bar.close()
        self.train_time = time_offset + time.perf_counter() - start
        self.save_checkpoint()
        self.check_trained()
        return self.finish()

    def after_step(self, it: int) -> None:
        """Densification, pruning and opacity resets on the Inria schedule."""
        if self.density.is_densify_step(it):
            counts = self.density.densify_and_prune(self.params, it)
            self.event("densify", gaussians=len(self.params), **counts)
        if self.density.is_reset_step(it):
            self.density.reset_opacity(self.params)
            self.event("opacity_reset")

    def _grads_finite(self) -> bool:
        for group in self.all_param_groups():
            for p in group["params"]:
                if p.grad is not None and not torch.isfinite(p.grad).all():
                    return False
        return True

    def all_param_groups(self) -> list[dict]:
        return list(self.params.optimizer.param_groups)

    def check_trained(self) -> None:
        """Refuse to write results from a model that is not one: non-finite parameters, or nothing ever seen.

        The loss guard misses both: Gaussians that became NaN (e.g. an infinite learning rate)
        or lie outside every view project to nothing, so the loss stays finite (the background
        alone) while nothing is learned, and the PLY and the scores would be garbage.
        """
        bad = []
        for group in self.all_param_groups():
            for p in group["params"]:
                if not bool(torch.isfinite(p.detach()).all()):
                    bad.append(str(group.get("name", "?")))
        if bad:
            raise NimbusError(f"training ended with non-finite parameters ({', '.join(sorted(set(bad)))}) at "
                              f"iteration {self.iteration}; no results were written. Lower the learning rates "
                              "(--set lr_...=...) and check the inputs, then start a new run")
        if self.iteration > 0 and self.visible_steps == 0:
            raise NimbusError(f"no Gaussian was visible in any training view in {self.iteration} iterations, so "
                              "nothing was learned; no results were written. Check the cameras (intrinsics, "
                              "poses) and near_plane, and that the sparse points lie in front of the cameras")

    # --- checkpoints -------------------------------------------------------------------
    def state(self) -> dict:
        """Everything :meth:`load_checkpoint` restores: tensors and plain values only (:func:`check_plain`)."""
        return {"iteration": self.iteration, "train_time": float(self.train_time), "frame": self.frame.as_list(),
                "params": self.params.state_dict(),
                "density": self.density.state_dict(), "generator": self.gen.get_state(),
                "torch_rng": torch.get_rng_state(), "order": [int(i) for i in self._order],
                "visible_steps": self.visible_steps, "extra": self.extra_state()}

    def save_checkpoint(self, name: str = CHECKPOINT) -> Path:
        state = self.state()
        check_plain(state)
        buf = io.BytesIO()
        torch.save(state, buf)
        return atomic_write_bytes(self.out / name, buf.getvalue())

    def load_checkpoint(self, path: str | os.PathLike) -> None:
        """Restore the state saved in ``path`` and cut the training log back to its iteration.

        The file is read with ``torch.load(weights_only=True)``: only tensors and plain values
        are rebuilt, never arbitrary objects, since unpickling those can run code that the
        file names.  A file holding anything else (a foreign or tampered file, a checkpoint of
        an old Nimbus that pickled objects), a truncated file or one that does not fit this run
        raises :class:`NimbusError`; the run folder is left as it was.
        """
        path = Path(path)
        try:
            state = torch.load(path, map_location=self.device, weights_only=True)
        except pickle.UnpicklingError:
            raise NimbusError(f"checkpoint {path} holds objects other than tensors and plain values (a file "
                              "from an older Nimbus, or one that was tampered with); Nimbus does not load such "
                              "files because unpickling them can run code. Start a new run with --out "
                              "(nothing was loaded)") from None
        except Exception as e:  # a truncated, empty or foreign file
            raise NimbusError(f"cannot read checkpoint {path} ({e.__class__.__name__}: {str(e)[:200]}); it is "
                              "corrupt or not a Nimbus checkpoint. Start a new run with --out") from None
        try:
            self._restore(state)
        except (KeyError, TypeError, ValueError, IndexError, AttributeError, RuntimeError) as e:
            raise NimbusError(f"checkpoint {path} does not fit this run ({e.__class__.__name__}: {str(e)[:200]}); "
                              "it was written for other settings or by another Nimbus version. Start a new run "
                              "with --out") from None
        self._truncate_log(self.iteration)

    def _restore(self, state: dict) -> None:
        # Parameters are stored in the training frame: a checkpoint of another frame (another scene,
        # or an older Nimbus that trained in world coordinates) would be misplaced, not resumed.
        if not np.allclose([float(x) for x in state["frame"]], self.frame.as_list(), rtol=1e-9, atol=0):
            raise ValueError(f"it was trained in the frame {state['frame']}, this scene's is {self.frame.as_list()}")
        self.iteration = int(state["iteration"])
        self.train_time = float(state["train_time"])
        self.params.load_state_dict(state["params"])
        self.density.load_state_dict(state["density"])
        # The generators live on the CPU whatever map_location moved the tensors to.
        self.gen.set_state(state["generator"].cpu())
        torch.set_rng_state(state["torch_rng"].cpu())
        self._order = [int(i) for i in state["order"]]
        # Checkpoints written before the count existed: assume every step saw something.
        self.visible_steps = int(state.get("visible_steps", self.iteration))
        self.load_extra_state(state["extra"])

    def _truncate_log(self, iteration: int) -> None:
        """Drop the log lines written after the checkpoint at ``iteration`` (the resumed run writes them again).

        A line cut short by a kill is dropped too.  The log is rewritten atomically.
        """
        log = self.out / LOG
        if not log.is_file():
            return
        kept, dropped = [], 0
        for line in log.read_text(errors="replace").splitlines():
            try:
                rec = json.loads(line)
                keep = isinstance(rec, dict) and int(rec.get("iteration", 0)) <= iteration
            except (ValueError, TypeError):
                keep = False
            if keep:
                kept.append(line)
            else:
                dropped += 1
        if dropped:
            atomic_write_text(log, "".join(f"{line}\n" for line in kept))

    def write_config(self) -> None:
        atomic_write_json(self.out / "config.json", {
            "method": self.method_name, "scene": self.scene_path, "scene_load_args": self.scene_load_args,
            "seed": self.seed, "config": dataclasses.asdict(self.cfg), "config_type": type(self.cfg).__name__,
            "nimbus_version": nimbus.__version__, "device": str(self.device),
        })

    # --- outputs -----------------------------------------------------------------------
    @torch.no_grad()
    def evaluate(self) -> dict:
        """Render the test views (or the training views if there are none), save them, and score them."""
        views = self.scene.test_views or self.scene.train_views
        split = "test" if self.scene.test_views else "train"
        clean = [self._clean_path(v) for v in views]
        reference = "clean" if all(p is not None for p in clean) else "input"
        per_view = {}
        render_times = []
        seen = 0
        for view, clean_path in zip(views, clean):
            t0 = time.perf_counter()
            render = self.render(view)
            render_times.append(time.perf_counter() - t0)
            seen += bool(render["meta"]["visible"].any())
            # Scored after the 8-bit round trip that the saved PNGs (and the benchmark) go through.
            pred = quantize_8bit(self.eval_image(view, render))
            write_image(self.out / "renders" / split / f"{view.stem}.png", pred.cpu().numpy())
            gt_image = read_image(clean_path) if reference == "clean" else view.load_image()
            if gt_image.shape != tuple(pred.shape):  # a downscaled load (images_<d>/): clean/ is full size
                gt_image = cv2.resize(gt_image, (pred.shape[1], pred.shape[0]), interpolation=cv2.INTER_AREA)
            gt = quantize_8bit(torch.from_numpy(gt_image).to(pred))
            # Scored over the view's valid pixels only, as nimbus-bench score does.
            mask = view_mask(view)
            mask_t = None if mask is None else torch.from_numpy(mask).to(pred.device)
            per_view[view.name] = {"psnr": psnr(pred, gt, mask_t), "ssim": float(ssim(pred, gt, mask_t))}
            if mask is not None:
                per_view[view.name]["valid_fraction"] = round(float(mask.mean()), 6)
        mean = {k: float(np.mean([v[k] for v in per_view.values()])) for k in ("psnr", "ssim")}
        fps = len(render_times) / max(sum(render_times), 1e-9)
        masked = sum("valid_fraction" in v for v in per_view.values())
        return {"split": split, "reference": reference, "per_view": per_view, "render_fps": fps,
                "visible_views": seen, "masked_views": masked, **mean}

    def _clean_path(self, view: View) -> Path | None:
        """``SCENE/clean/<name>`` of a dataset written by ``nimbus-synth degrade`` (its ``images/`` are the
        degraded inputs, so a score against them rewards reproducing the weather), else None."""
        if self.scene.root is None:
            return None
        path = Path(self.scene.root) / "clean" / view.name
        return path if path.is_file() else None

    def finish(self) -> dict:
        """Evaluate, then write ``point_cloud.ply`` and ``results.json`` (call :meth:`check_trained` first)."""
        ev = self.evaluate()
        if ev["visible_views"] == 0:
            shutil.rmtree(self.out / "renders" / ev["split"], ignore_errors=True)
            raise NimbusError(f"no Gaussian is visible in any {ev['split']} view, so its scores would only measure "
                              "the background; no results were written. Check the cameras of those views "
                              "(intrinsics, poses) and near_plane")
        g = self.gaussians().detach()
        write_gaussian_ply(self.out / "point_cloud.ply", g.means.cpu().numpy(), g.sh.cpu().numpy(),
                           g.opacity_logits.cpu().numpy(), g.log_scales.cpu().numpy(), g.quats.cpu().numpy())
        results = {
            "method": self.method_name, "scene": self.scene_path, "seed": self.seed,
            "iterations": self.iteration, "train_time_s": round(self.train_time, 3),
            "peak_memory_mb": round(peak_memory_mb(self.device), 1), "num_gaussians": len(self.params),
            "eval_split": ev["split"], "eval_reference": ev["reference"], "psnr": ev["psnr"], "ssim": ev["ssim"],
            "render_fps": ev["render_fps"],
            # Validity masks: test views scored over their valid pixels only, training views whose
            # loss ignored masked pixels (per_view[name]["valid_fraction"] where a test view has one).
            "masked": ev["masked_views"] > 0, "eval_masked_views": ev["masked_views"],
            "train_masked_views": sum(m is not None for m in self.train_masks),
            "per_view": ev["per_view"], "device": str(self.device), "nimbus_version": nimbus.__version__,
            "versions": software_versions(), **self.extra_results(),
        }
        atomic_write_json(self.out / "results.json", results)
        return results

    def extra_results(self) -> dict:
        return {}
