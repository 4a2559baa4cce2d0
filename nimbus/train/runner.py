"""One runner for every method: run folder, checkpoints and resume, log, progress, guards, evaluation, outputs.

:class:`Runner` drives any :class:`~nimbus.methods.base.Method` named in the registry
(:mod:`nimbus.methods.registry`).  Training runs in the scene's :class:`~nimbus.train.frame.SceneFrame`
(centred, extent 1): the method receives the scene in that frame; ``point_cloud.ply`` is in world
coordinates.

A run directory holds::

    config.json           the run's settings (scene path, method, seed, every config field)
    checkpoint.pt         latest checkpoint (the runner's iteration, train time, frame and visible-step
                          count, and the method's state_dict); tensors and plain values only, read back
                          with ``torch.load(weights_only=True)``
    train_log.jsonl       one JSON line every ``log_interval`` iterations and for every event
    point_cloud.ply       the final Gaussians in the standard 3DGS PLY layout
    renders/test/NAME.png renders of the held-out views
    results.json          test-view PSNR / SSIM, train time, peak memory, Gaussian count, what training
                          started from (``init_points``: the scene's sparse points, triangulated or random
                          ones, :mod:`nimbus.train.init_points`), and the method's
                          :meth:`~nimbus.methods.base.Method.get_info`

A view's validity mask (:func:`~nimbus.train.views.view_mask`) limits its training loss and its scores to
the valid pixels; ``results.json`` records ``masked`` and each masked test view's ``valid_fraction``.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import sys
import time
from pathlib import Path
from typing import Any, Callable

import cv2
import numpy as np
import torch
from tqdm import tqdm

import nimbus
from nimbus.data import Scene, View
from nimbus.data.images import read_image, write_image
from nimbus.errors import NimbusError
from nimbus.metrics import peak_signal_noise_ratio, quantize_8bit, structural_similarity
from nimbus.methods.base import TrainingDiverged, default_device
from nimbus.methods.registry import get_method
from nimbus.render.gaussians import Gaussians
from nimbus.train.checkpoint import CHECKPOINT, LAST_GOOD, read_checkpoint, write_checkpoint
from nimbus.train.frame import SceneFrame
from nimbus.train.init_points import choose_init_points
from nimbus.train.ply import write_gaussian_ply
from nimbus.train.run_folder import (config_from_record, config_record, load_scene_arg, read_run_config,
                                     scene_input_folder)
from nimbus.train.views import view_mask
from nimbus.utils.fs import atomic_write_json, atomic_write_text, refuse_overlap, write_problem
from nimbus.utils.memory import peak_rss_mb
from nimbus.versions import software_versions

LOG = "train_log.jsonl"


def _count(state: dict, key: str, default=None) -> int:
    """``state[key]``, a checkpoint's step count: a non-negative integer (bool and fractions refused), else
    ValueError naming it."""
    value = state.get(key, default) if default is not None else state[key]
    if isinstance(value, torch.Tensor) and value.numel() == 1:
        value = value.item()
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
        raise ValueError(f"{key!r} is {value!r}, not a non-negative integer")
    return int(value)


def peak_memory_mb(device: torch.device) -> float:
    """Peak memory of this process: CUDA allocator peak on a GPU, else the resident-set high-water mark
    (:func:`nimbus.utils.memory.peak_rss_mb`)."""
    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device) / 2**20
    return peak_rss_mb()



class Runner:
    """Train a registered method on a scene into a run folder, and evaluate it.

    Parameters
    ----------
    method_name : str
        A name of :data:`nimbus.methods.registry.METHODS` (recorded in the outputs).
    scene : Scene
        As loaded (world coordinates); training views are ``scene.train_views``, evaluation uses
        ``scene.test_views`` (or the training views when there are none).
    config : dataclass
        The method's config (from its presets).
    out_dir : path
        The run directory (created).
    seed : int
    scene_path : str or None
        Where the scene was loaded from (recorded so ``--resume`` can reload it).
    scene_load_args : dict or None
        Keyword arguments the scene was loaded with (recorded for ``--resume``).
    progress : bool
        Show a progress bar on stderr.
    device : torch.device or None
        Default: CUDA when available.
    checkpoints : bool
        Write checkpoints (False for throw-away fits that are never resumed).
    on_log : callable or None
        Called with every periodic log record (``iteration``, ``loss``, ``psnr``, ``gaussians``, ``elapsed_s``).

    Attributes
    ----------
    method : Method
        The method instance (trained in :attr:`frame`).
    scene : Scene
        ``scene`` in the training frame.
    """

    def __init__(self, method_name: str, scene: Scene, config, out_dir: str | os.PathLike, *, seed: int = 0,
                 scene_path: str | None = None, scene_load_args: dict | None = None, progress: bool = True,
                 device: torch.device | None = None, checkpoints: bool = True,
                 on_log: Callable[[dict], None] | None = None) -> None:
        self.method_name = method_name
        method_cls = get_method(method_name).load()  # an unknown method is refused before any triangulation
        self.frame = SceneFrame.of(scene)
        self.cfg = config
        self.seed = int(seed)
        self.progress = progress
        #: Whether an interrupt prints how to continue with ``nimbus-train --resume`` (False where the caller
        #: resumes the folder itself: a benchmark cell).
        self.resume_hint = True
        #: What training starts from (:func:`~nimbus.train.init_points.choose_init_points`): a points-less
        #: scene gets triangulated points (cached) or random ones; recorded in results.json and the log.
        init = choose_init_points(scene, config, self.seed,
                                  log_step=(lambda line: print(f"init: {line}", file=sys.stderr, flush=True))
                                  if progress else None)
        self.init_points = init.record
        self.scene = self.frame.scene(init.scene)
        self.out = Path(out_dir)
        self.scene_path = scene_path
        self.scene_load_args = scene_load_args or {}
        self.device = device or default_device()
        self.checkpoints = checkpoints
        self.on_log = on_log
        self.iteration = 0
        self.train_time = 0.0
        #: True while a training step runs: a checkpoint saved then (Ctrl-C) holds a half-done step.
        self._in_step = False
        #: Whether the checkpoint this runner was loaded from was saved in the middle of a step.
        self.resumed_mid_step = False
        #: Training steps in which the view depended on the model (a run with none learned nothing).
        self.visible_steps = 0
        self.method = method_cls(self.scene, config, seed=self.seed, device=self.device, frame=self.frame)

    @classmethod
    def resume(cls, out_dir: str | os.PathLike, *, progress: bool = True,
               device: torch.device | None = None) -> "Runner":
        """The runner of run folder ``out_dir`` at its last checkpoint: scene, method, seed and config as its
        ``config.json`` records them (:func:`~nimbus.train.run_folder.read_run_config`).  :meth:`run` then
        continues it.  A folder that is not a resumable run, cannot be written, or whose files do not fit
        raises :class:`NimbusError`; nothing in it is changed by a refusal."""
        run = Path(out_dir)
        cfg_file, ckpt = run / "config.json", run / CHECKPOINT
        if not cfg_file.is_file() or not ckpt.is_file():
            raise NimbusError(f"{run} is not a resumable run (needs config.json and {CHECKPOINT})")
        if not os.access(run, os.W_OK | os.X_OK):
            raise NimbusError(f"{run} cannot be written (read-only or not ours); a resumed run writes its checkpoint "
                              "and outputs there. Fix its permissions or copy the run folder somewhere writable")
        # A run folder in the scene it trains on would fill the input with checkpoints, renders and logs.
        scene = scene_input_folder(read_run_config(run)["scene"])
        try:
            refuse_overlap(run, [scene], "--resume")
        except NimbusError:
            raise NimbusError(f"--resume {run} overlaps the scene {scene} it trains on, and a resumed run writes into "
                              "its folder; move the run folder apart from the scene and resume it there (nothing "
                              "was written)") from None
        # Everything (config, scene, checkpoint) is checked before the log is touched: a refusal changes nothing.
        runner = cls.open(run, progress=progress, device=device)
        runner._truncate_log(runner.iteration)
        return runner

    @classmethod
    def open(cls, out_dir: str | os.PathLike, *, progress: bool = True,
             device: torch.device | None = None) -> "Runner":
        """The runner of run folder ``out_dir`` at its last checkpoint, read without changing anything in the
        folder (``nimbus-view`` shows it; :meth:`resume` continues it).  A folder that is not a run, or whose
        files do not fit, raises :class:`NimbusError`."""
        run = Path(out_dir)
        cfg_file, ckpt = run / "config.json", run / CHECKPOINT
        if not cfg_file.is_file() or not ckpt.is_file():
            raise NimbusError(f"{run} is not a run folder of nimbus-train (needs config.json and {CHECKPOINT})")
        saved = read_run_config(run)
        try:
            method = get_method(saved["method"])
        except NimbusError as e:  # a name the file holds, not one the user typed: say which file
            raise NimbusError(f"{cfg_file}: field 'method': {e}") from None
        config_cls = type(method.preset("tiny"))
        try:
            config = config_from_record(config_cls, saved["config"])
        except (TypeError, ValueError, NimbusError) as e:
            raise NimbusError(f"{cfg_file}: its 'config' does not fit method {saved['method']!r} ({e}); restore "
                              "the file or start a new run with --out") from None
        scene = load_scene_arg(saved["scene"], **saved["scene_load_args"])
        runner = cls(saved["method"], scene, config, run, seed=saved["seed"], scene_path=saved["scene"],
                     scene_load_args=saved["scene_load_args"], progress=progress, device=device)
        runner.load_checkpoint(ckpt, truncate_log=False)
        return runner

    # --- log -----------------------------------------------------------------------------
    def log(self, record: dict) -> None:
        record = {"iteration": self.iteration, **record}
        line = json.dumps(record) + "\n"
        try:
            with open(self.out / LOG, "a") as f:
                f.write(line)
        except OSError as e:  # a line cut short by a full disk is dropped on --resume (_truncate_log)
            problem = write_problem(e, self.out / LOG, len(line.encode()))
            if problem is None:
                raise
            raise problem from None
        if self.on_log is not None and "psnr" in record:
            self.on_log(record)

    def event(self, kind: str, **info: Any) -> None:
        self.log({"event": kind, **info})

    # --- training ------------------------------------------------------------------------
    def run(self) -> dict:
        """Train (or continue) to ``config.iterations``, then evaluate and write the outputs; the results."""
        self.train()
        return self.finish()

    def train(self) -> None:
        """Train (or continue) to ``config.iterations``, with checkpoints, log and progress bar."""
        self.out.mkdir(parents=True, exist_ok=True)
        for kind, info in self.method.setup_events():
            self.event(kind, **info)
        if self.iteration == 0:
            self.write_config()
            self.event("init_points", **self.init_points)
        c = self.cfg
        bar = tqdm(total=c.iterations, initial=self.iteration, disable=not self.progress, file=sys.stderr,
                   desc=f"{self.method_name}", dynamic_ncols=True, leave=True)
        loss_ema = psnr_ema = None
        start = time.perf_counter()
        time_offset = self.train_time
        try:
            while self.iteration < c.iterations:
                it = self.iteration + 1
                if self.method.num_gaussians == 0:
                    self.save_checkpoint(LAST_GOOD)
                    raise NimbusError(f"every Gaussian was pruned by iteration {it}; lower prune_opacity or "
                                      "densify_grad_threshold (--set key=value), or check that the input views "
                                      "are not blank")
                self._in_step = True
                try:
                    step = self.method.train_iteration(it)
                except TrainingDiverged as e:
                    kept = self._keep_last_good()
                    if e.what == "loss":
                        raise NimbusError(f"the loss became {e.value} at iteration {it}{kept}. Lower the learning "
                                          "rates (--set lr_...=...) or check the input images") from None
                    raise NimbusError(f"non-finite gradients at iteration {it}{kept}. Lower the learning rates or "
                                      "check the inputs") from None
                self.iteration = it
                self._in_step = False
                self.visible_steps += bool(step["visible"])
                for kind, info in step["events"]:
                    self.event(kind, **info)
                lv, pv = step["loss"], step["psnr"]
                loss_ema = lv if loss_ema is None else 0.9 * loss_ema + 0.1 * lv
                psnr_ema = pv if psnr_ema is None else 0.9 * psnr_ema + 0.1 * pv
                if it % c.log_interval == 0 or it == c.iterations:
                    self.train_time = time_offset + time.perf_counter() - start
                    n = self.method.num_gaussians
                    self.log({"loss": round(loss_ema, 6), "psnr": round(psnr_ema, 3), "gaussians": n,
                              "elapsed_s": round(self.train_time, 3)})
                    bar.set_postfix(loss=f"{loss_ema:.4f}", psnr=f"{psnr_ema:.2f}", gs=n)
                bar.update(1)
                if it % c.checkpoint_interval == 0 and it < c.iterations:
                    self.train_time = time_offset + time.perf_counter() - start
                    self.save_checkpoint()
        except KeyboardInterrupt:
            # Keep the progress so `--resume` continues from here (an interrupt inside an
            # optimiser step may make the resumed run differ from an uninterrupted one by a step).
            self.train_time = time_offset + time.perf_counter() - start
            self.save_checkpoint()
            if self.resume_hint:
                print(f"interrupted at iteration {self.iteration}; continue with: nimbus-train --resume {self.out}",
                      file=sys.stderr)
            raise
        finally:
            bar.close()
        self.train_time = time_offset + time.perf_counter() - start
        self.save_checkpoint()
        self.check_trained()

    def check_trained(self) -> None:
        """Refuse to write results from a model that is not one: non-finite parameters, or nothing ever seen.

        The loss guard misses both: Gaussians that became NaN (e.g. an infinite learning rate)
        or lie outside every view project to nothing, so the loss stays finite (the background
        alone) while nothing is learned, and the PLY and the scores would be garbage.
        """
        bad = []
        for group in self.method.param_groups():
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

    # --- checkpoints ---------------------------------------------------------------------
    def state_dict(self) -> dict:
        """The checkpoint: the runner's keys (iteration, train_time, frame, visible_steps, mid_step: saved by an
        interrupt inside a step; run_method: the method's registry name) and the method's state_dict."""
        return {"iteration": self.iteration, "train_time": float(self.train_time), "frame": self.frame.as_list(),
                "visible_steps": self.visible_steps, "mid_step": self._in_step, "run_method": self.method_name,
                **self.method.state_dict()}

    def _keep_last_good(self) -> str:
        """Save the last good state and say where (empty for a run without checkpoints: nothing was saved)."""
        if not self.checkpoints:
            return ""
        return f"; the last good state is in {self.save_checkpoint(LAST_GOOD)}"

    def save_checkpoint(self, name: str = CHECKPOINT) -> Path:
        if not self.checkpoints:
            return self.out / name
        return write_checkpoint(self.out / name, self.state_dict())

    def load_checkpoint(self, path: str | os.PathLike, *, truncate_log: bool = True) -> None:
        """Restore the state saved in ``path`` and (``truncate_log``) cut the training log back to its iteration.

        A file that is not a checkpoint of tensors and plain values, a truncated one
        (:func:`~nimbus.train.checkpoint.read_checkpoint`) or one that does not fit this run raises
        :class:`NimbusError`; the run folder is left as it was.
        """
        path = Path(path)
        state = read_checkpoint(path, self.device)
        try:
            # Parameters are stored in the training frame: a checkpoint of another frame (another scene,
            # or an older Nimbus that trained in world coordinates) would be misplaced, not resumed.
            if not np.allclose([float(x) for x in state["frame"]], self.frame.as_list(), rtol=1e-9, atol=0):
                raise ValueError(f"it was trained in the frame {state['frame']}, this scene's is "
                                 f"{self.frame.as_list()}")
            # A config.json whose method was edited would load one method's state into another's class (3dgs
            # resumed as restore-3dgs trains on other targets): refused.  Checkpoints from before the name was
            # saved cannot be checked.
            saved_method = state.get("run_method")
            if saved_method is not None and saved_method != self.method_name:
                raise NimbusError(f"checkpoint {path} was written by method {saved_method!r}, but the run's "
                                  f"config.json says {self.method_name!r} (was it edited?); restore config.json's "
                                  "'method' or start a new run with --out")
            # Checked before anything is restored or the log is cut back to the iteration: a negative one
            # would leave no line of it (every line is "after" it).
            iteration, train_time = _count(state, "iteration"), float(state["train_time"])
            # Checkpoints written before the count existed: assume every step saw something.
            visible = _count(state, "visible_steps", default=iteration)
            if not (math.isfinite(train_time) and train_time >= 0):
                raise ValueError(f"'train_time' is {train_time}, not a number of seconds >= 0")
            if visible > iteration:
                raise ValueError(f"'visible_steps' is {visible}, more than the {iteration} steps taken")
            self.method.load_state_dict(state)
            self.iteration, self.train_time, self.visible_steps = iteration, train_time, visible
            self.resumed_mid_step = bool(state.get("mid_step", False))
        except (KeyError, TypeError, ValueError, IndexError, AttributeError, RuntimeError) as e:
            raise NimbusError(f"checkpoint {path} does not fit this run ({e.__class__.__name__}: {str(e)[:200]}); "
                              "it was written for other settings or by another Nimbus version. Start a new run "
                              "with --out") from None
        if truncate_log:
            self._truncate_log(self.iteration)

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
            "seed": self.seed, "config": config_record(self.cfg), "config_type": type(self.cfg).__name__,
            "nimbus_version": nimbus.__version__, "device": str(self.device),
        })

    # --- outputs -------------------------------------------------------------------------
    def rasterizer(self) -> str | None:
        """The rasterizer backend that rendered (``config.backend`` resolved on this device: ``auto`` is gsplat
        on CUDA when it loads, else the compiled CPU kernels, else torch); None for a config without one."""
        from nimbus.render import backends

        name = getattr(self.cfg, "backend", None)
        if name is None:
            return None
        try:
            return backends.resolve(name, self.device).name
        except NimbusError:  # training ran, so this cannot happen; a record never fails for it
            return None

    def gaussians(self) -> Gaussians:
        """The method's Gaussians in the scene's world coordinates (render them with the cameras of the
        scene as given)."""
        return self.frame.to_world(self.method.gaussians())

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
            render = self.method.render(view.camera)
            render_times.append(time.perf_counter() - t0)
            seen += "meta" not in render or bool(render["meta"]["visible"].any())
            # Scored after the 8-bit round trip that the saved PNGs (and the benchmark) go through.
            pred = quantize_8bit(render["rgb"])
            write_image(self.out / "renders" / split / f"{view.stem}.png", pred.cpu().numpy())
            gt_image = read_image(clean_path) if reference == "clean" else view.load_image()
            if gt_image.shape != tuple(pred.shape):  # a downscaled load (images_<d>/): clean/ is full size
                gt_image = cv2.resize(gt_image, (pred.shape[1], pred.shape[0]), interpolation=cv2.INTER_AREA)
            gt = quantize_8bit(torch.from_numpy(gt_image).to(pred))
            # Scored over the view's valid pixels only, as nimbus-bench score does.
            mask = view_mask(view)
            mask_t = None if mask is None else torch.from_numpy(mask).to(pred.device)
            per_view[view.name] = {"psnr": peak_signal_noise_ratio(pred, gt, quantize=False, mask=mask_t),
                                   "ssim": structural_similarity(pred, gt, quantize=False, mask=mask_t)}
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
        """Evaluate, then write ``point_cloud.ply`` and ``results.json`` (after :meth:`check_trained`)."""
        if self.method.num_gaussians:
            self.method.write_outputs(self.out)
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
            "peak_memory_mb": round(peak_memory_mb(self.device), 1), "threads": torch.get_num_threads(),
            "num_gaussians": self.method.num_gaussians,
            "eval_split": ev["split"], "eval_reference": ev["reference"], "psnr": ev["psnr"], "ssim": ev["ssim"],
            "render_fps": ev["render_fps"],
            # Validity masks: test views scored over their valid pixels only, training views whose
            # loss ignored masked pixels (per_view[name]["valid_fraction"] where a test view has one).
            "masked": ev["masked_views"] > 0, "eval_masked_views": ev["masked_views"],
            "train_masked_views": sum(view_mask(v) is not None for v in self.scene.train_views),
            "per_view": ev["per_view"], "init_points": self.init_points, "device": str(self.device),
            "rasterizer": self.rasterizer(),
            "nimbus_version": nimbus.__version__, "versions": software_versions(), **self.method.get_info(),
        }
        atomic_write_json(self.out / "results.json", results)
        return results
