"""NimbusGS: 3DGS plus the degradation model I_deg = I_hat * T + P + R (supplementary Algorithm 1).

Stage 1 (iterations 1..M_init, geometry initialisation): the Gaussians are rendered to
the clean image I_hat, the continuous medium composes ``I_con = I_hat T + P`` and the
loss is ``(1 - lambda_r) L1(I_in, I_con) + lambda_r (1 - SSIM) + L_DCP(I_hat) + L_TV``,
with the Gaussians' scale learning rate lowered to ``lr_scales_init``.  At the end of
stage 1 every training view's particulate layer is extracted, ``R = ReLU(I_in - I_con)``.

With CSM, both stages also add the dehazed-view prior (ours, ``lambda_dehaze``): the same photometric loss
between I_hat and the view's single-image dark-channel dehaze (weight ``lambda_dehaze``, times ``prior_stage2``
in stage 2), which keeps the clean render from keeping the veil the degraded-image loss cannot see.

Stage 2 (M_init+1..iterations, joint optimisation): ``I_deg = I_con + R``, loss
``(1 - lambda_r) L1(I_in, I_deg) + lambda_r (1 - SSIM) + L_TV``, R re-extracted every
``refresh_interval`` iterations, and GGS rescales each Gaussian's gradients and hands the
weights to the densification strategy (``info["grad2d_weight"]``) before it accumulates.

The degradation model itself (medium, composite, residuals) is :mod:`nimbus.methods.nimbusgs.degradation`;
this file is its schedule on top of :class:`~nimbus.methods.gs3d.GaussianSplatting`.

Only what the scene needs is built (``components``; ``auto``: :mod:`nimbus.methods.nimbusgs.auto`):
without CSM there is no grid, no airlight and no ray march (I_con = I_hat, no DCP);
without PLM no residual is stored or refreshed (I_deg = I_con); without GGS gradients
are left alone.  The decision, its evidence and the estimated time saved are logged
(event ``components``) and reported under ``nimbus`` in ``results.json``.

:meth:`NimbusGS.render` of a novel camera gives the clean render (what is scored).  The
decomposition of a training view is asked for with ``view_index``:
``render(method.train_views[i].camera, view_index=i)`` adds ``transmission`` (T [H, W, 1]),
``airlight`` (the scattered light P [H, W, 3]), ``residual`` (R [H, W, 3], zeros without PLM)
and ``degraded`` (I_con + R, what the loss compares with the input).

Extra outputs in the run directory::

    decomposition/NAME.png   per training view: I_in | I_hat | T | P | R (each clipped to [0, 1])
    extinction/beta_*.png    slices of the extinction grid, normalised by its maximum
"""

from __future__ import annotations

import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from nimbus.data import Camera
from nimbus.data.images import write_image
from nimbus.kernels import train_step
from nimbus.losses import loss_target_moments
from nimbus.methods.gs3d import GaussianSplatting
from nimbus.methods.nimbusgs.airlight import network_airlight_bytes, view_descriptor
from nimbus.methods.nimbusgs.auto import (ParticleEvidence, haze_evidence, particle_evidence, particle_thresholds,
                                  residual_tail_counts)
from nimbus.methods.nimbusgs.config import NimbusConfig
from nimbus.methods.nimbusgs.degradation import (DEHAZE_MIN_TRANSMISSION, INIT_TRANSMISSION_RANGE, Medium,
                                         ParticulateLayer, compose, consistency_check, estimate_march_time,
                                         valid_image, view_excesses)
from nimbus.methods.nimbusgs.ggs import GGSFactors, ggs_weights, scale_gradients
from nimbus.methods.nimbusgs.losses import dcp_loss, stage_loss
from nimbus.methods.nimbusgs.particulate import ViewGeometry, is_refresh_step
from nimbus.restore import pixel_sizes
from nimbus.restore.classical import RestoreConfig, classical_restore, dehaze, remove_particles
from nimbus.methods.nimbusgs.scattering import (GRID_BYTES_PER_VOXEL, MARCH_BYTES_PER_SAMPLE, Box, ExtinctionGrid, ViewRays,
                                        camera_rays)
from nimbus.render.gaussians import Gaussians
from nimbus.render.rasterize import rasterize
from nimbus.render.sh import rgb_to_sh, sh_to_rgb
from nimbus.utils.memory import SizeCost

#: Bytes of the prior's loss moments kept across steps (two float planes per pixel and channel per view; the small
#: scenes' 35 views take 36 MB, a 252-view capture at 199x133 64 MB); views past it are filtered at every step.
PRIOR_MOMENTS_BUDGET = 256 << 20

#: Smallest side of a written extinction slice (pixels); small grids are upsampled (nearest).
_SLICE_MIN_SIDE = 128


class NimbusGS(GaussianSplatting):
    """NimbusGS on a scene of degraded views (same constructor as :class:`GaussianSplatting`).

    ``config`` is a :class:`~nimbus.methods.nimbusgs.config.NimbusConfig`.
    """

    cfg: NimbusConfig

    def __init__(self, scene, config: NimbusConfig, **kwargs) -> None:
        super().__init__(scene, config, **kwargs)
        c = config
        self.stage = 1
        self.timing: dict[str, float] = defaultdict(float)
        self.counts: dict[str, int] = defaultdict(int)
        self._pending: list[tuple[str, dict]] = []
        self._rays: dict[int, ViewRays] = {}
        #: The residual's consistency check (built at its first use: only runs with PLM refresh it).
        self._consistency = None
        #: ``refresh_mode=lazy``: each training view's rendered surface when it was last rendered (None until needed).
        self._surfaces: list[ViewGeometry] | None = None
        #: This step's gradients that GGS scaled, and whether they were finite (its pass checks them).
        self._checked_grads: tuple[list[Tensor], bool] | None = None
        #: This step's GGS weights and the rasterizer's :class:`~nimbus.kernels.raster.RowScale` they were handed
        #: to (None where it has none), from :meth:`before_backward` to :meth:`reweight_gradients`.
        self._ggs_weights: tuple[Tensor, object] | None = None
        self.medium: Medium | None = None
        self.particulate: ParticulateLayer | None = None
        self.ggs = GGSFactors(c.ggs_depth, c.ggs_radius, c.ggs_error, c.ggs_r0, tuple(c.ggs_clip))
        forced = c.forced_components
        self.auto = forced is None
        with torch.no_grad():
            self.descriptors = torch.stack([view_descriptor(img.float(), c.dcp_patch) for img in self.train_images])
        t0 = time.perf_counter()
        self.haze = haze_evidence(self.train_images, [v.camera for v in self.train_views], self.scene.points,
                                  c.dcp_patch, c.auto_dark_threshold, c.auto_depth_corr)
        self.timing["evidence_s"] += time.perf_counter() - t0
        self.use_csm = self.haze.present if self.auto else "csm" in forced
        # PLM and GGS are decided from the stage-1 residual when automatic (None until then).
        self.use_plm: bool | None = None if self.auto else "plm" in forced
        self.use_ggs: bool | None = None if self.auto else "ggs" in forced
        self.particles = None
        self.time_saved: dict[str, float] = {}
        #: Per training view, its single-image dehaze (``lambda_dehaze``), or None.
        self.prior_clean: list[Tensor] | None = None
        #: Per training view, the loss's moments of its prior, once used (:meth:`_prior_moments`).
        self._prior_cache: dict[int, Tensor | None] = {}
        if self.use_csm and c.lambda_dehaze > 0:
            self.prior_clean = self._dehazed_views()
        if self.use_csm:
            self.medium = self._build_medium(self.params["means"].detach())
            if c.init_dehaze:
                self._dehaze_initial_colours()
        elif self.auto:
            box = self._content_box(self.params["means"].detach())
            self.time_saved["csm_ray_march_s"] = estimate_march_time(c, box, self.train_views[0].camera,
                                                                     self.device) * c.iterations
        self._pending.append(("csm_decision", {
            "mode": "auto" if self.auto else "forced", "csm": self.use_csm, "haze_evidence": self.haze.to_dict(),
            "estimated_time_saved_s": self.time_saved.get("csm_ray_march_s", 0.0)}))
        self._sync_stage(1)

    # --- sizes --------------------------------------------------------------------------
    def size_costs(self) -> list[SizeCost]:
        """3DGS's, plus the ray march (per view), the extinction grid and the airlight network, at the largest
        training view (the views are trained one at a time)."""
        c = self.cfg
        costs = super().size_costs()
        cam = max((v.camera for v in self.train_views), key=lambda cam: cam.width * cam.height)
        pixels, size = cam.width * cam.height, f"{cam.width}x{cam.height}"
        if c.extinction != "gaussian":
            costs.append(SizeCost("ray_samples", c.ray_samples, lambda k: float(pixels) * k * MARCH_BYTES_PER_SAMPLE,
                                  lambda k: f"one view's march at {size} ({k} samples a ray)"))
        if c.extinction == "grid":
            costs.append(SizeCost("grid_resolution", c.grid_resolution, lambda r: float(r) ** 3 * GRID_BYTES_PER_VOXEL,
                                  lambda r: f"the {r}^3 extinction grid and its optimiser state"))
        if c.airlight == "network":
            s = c.airlight_stride
            blocks = -(-cam.width // s) * -(-cam.height // s)
            costs.append(SizeCost("airlight_hidden", c.airlight_hidden, lambda n: network_airlight_bytes(n, blocks),
                                  lambda n: f"the airlight network, {n} wide, on one view at {size}"))
        return costs

    def frame_bytes(self, pixels: int) -> float:
        """3DGS's, plus the march and the airlight of the degraded layers."""
        c, need = self.cfg, super().frame_bytes(pixels)
        if c.extinction != "gaussian":
            need += float(pixels) * c.ray_samples * MARCH_BYTES_PER_SAMPLE
        if c.airlight == "network":
            need += network_airlight_bytes(c.airlight_hidden, -(-pixels // c.airlight_stride ** 2))
        return need

    # --- parameters ---------------------------------------------------------------------
    def _gaussian_extinction(self) -> bool:
        forced = self.cfg.forced_components
        return self.cfg.extinction == "gaussian" and (forced is None or "csm" in forced)

    def _init_tensors(self, g: Gaussians) -> dict[str, Tensor]:
        t = super()._init_tensors(g)
        if self._gaussian_extinction():
            # beta_i = softplus(logit_i) * density scale: a per-Gaussian attribute that
            # densification clones, splits and prunes with the rest.
            t["extinction_logit"] = torch.zeros(t["means"].shape[0], device=self.device)
        return t

    def _learning_rates(self) -> dict[str, float]:
        lrs = super()._learning_rates()
        if self._gaussian_extinction():
            lrs["extinction_logit"] = self.cfg.lr_extinction
        return lrs

    def setup_events(self) -> list[tuple[str, dict]]:
        events, self._pending = self._pending, []
        return events

    # --- the medium ---------------------------------------------------------------------
    def _mean_ray_length(self, means: Tensor) -> float:
        """Median over training cameras of the median distance to the Gaussian centres in front of them."""
        pts = means.detach().cpu().double().numpy()
        dists = []
        for v in self.train_views:
            cam = v.camera
            z = pts @ cam.R[2] + cam.t[2]
            front = pts[z > self.cfg.near_plane]
            if len(front):
                dists.append(float(np.median(np.linalg.norm(front - cam.center, axis=1))))
        return float(np.median(dists)) if dists else 1.0

    def _content_box(self, means: Tensor) -> Box:
        cameras = np.array([v.camera.center for v in self.train_views])
        return Box.around_content(means.detach().cpu(), cameras, self.cfg.box_scale, self.cfg.box_content_factor)

    def _build_medium(self, means: Tensor, box: Box | None = None) -> Medium:
        """The extinction field, airlight and their optimiser (CSM), from the data-driven initial transmission."""
        c = self.cfg
        t0 = c.init_transmission or min(max(self.haze.transmission_estimate, INIT_TRANSMISSION_RANGE[0]),
                                        INIT_TRANSMISSION_RANGE[1])
        a0 = (self.descriptors[:, :3].mean(0) if c.airlight_init == 0
              else torch.full((3,), c.airlight_init, device=self.descriptors.device))
        return Medium(c, box or self._content_box(means), t0, self._mean_ray_length(means),
                      a0, self.seed, self.device, views=len(self.train_views))

    @torch.no_grad()
    def _dehaze_initial_colours(self) -> None:
        """Start the Gaussians' colours at the clean colours the initial medium implies (``init_dehaze``)."""
        dc = self.params.tensors["sh_dc"]
        T0 = self.medium.initial_transmission_to(self.params.tensors["means"],
                                                 [v.camera for v in self.train_views]).to(dc)[:, None]
        a0 = self.descriptors[:, :3].mean(0).to(dc)
        rgb = sh_to_rgb(dc[:, 0])
        clean = ((rgb - a0 * (1 - T0)) / T0.clamp_min(DEHAZE_MIN_TRANSMISSION)).clamp(0.0, 1.0)
        dc[:, 0] = rgb_to_sh(clean)
        self._pending.append(("init_dehaze", {"mean_transmission": round(float(T0.mean()), 4),
                                              "airlight": [round(float(x), 4) for x in a0]}))

    @torch.no_grad()
    def _dehazed_views(self) -> list[Tensor]:
        """Each training view's single-image dark-channel dehaze, the prior of ``lambda_dehaze``."""
        t0 = time.perf_counter()
        out = []
        for img in self.train_images:
            dcp, particles = pixel_sizes(*img.shape[:2])
            x = img.float().cpu()
            if self.cfg.prior_particles:
                x = torch.from_numpy(remove_particles(np.ascontiguousarray(x.numpy()), particles))
            out.append(dehaze(x, dcp)[0].to(img))
        self.timing["prior_s"] += time.perf_counter() - t0
        return out

    def _prior_moments(self, vi: int) -> Tensor | None:
        """The SSIM moments of view ``vi``'s prior, which is the same target at every step (the loss's
        ``gt_moments``): kept per view up to :data:`PRIOR_MOMENTS_BUDGET` bytes in all, None past it or where
        the loss's kernel does not run (the loss is the same either way, bit for bit)."""
        if vi not in self._prior_cache:
            used = sum(t.nbytes for t in self._prior_cache.values() if t is not None)
            target = self.prior_clean[vi]
            fits = used + 2 * target.numel() * target.element_size() <= PRIOR_MOMENTS_BUDGET
            self._prior_cache[vi] = loss_target_moments(target) if fits else None
        return self._prior_cache[vi]

    def _rays_for(self, vi: int) -> ViewRays:
        if vi not in self._rays:
            self._rays[vi] = camera_rays(self.train_views[vi].camera, self.device)
        return self._rays[vi]

    def _extinction_image(self, camera: Camera) -> Tensor:
        """Alpha-blended per-Gaussian extinction ``[H, W]`` (Gaussian-driven ablation)."""
        t = self.params.tensors
        beta = F.softplus(t["extinction_logit"]) * torch.exp(self.medium.ext_log_scale)
        g = Gaussians(means=t["means"], log_scales=t["log_scales"], quats=t["quats"],
                      opacity_logits=t["opacity_logits"], sh_dc=rgb_to_sh(beta[:, None, None].expand(-1, 1, 3)),
                      sh_rest=t["means"].new_zeros(t["means"].shape[0], 0, 3))
        rgb, _, _, _ = rasterize(g, camera, sh_degree=0, background=torch.zeros(3, device=self.device),
                                 backend=self.cfg.backend, config=self.raster_config)
        return rgb[..., 0]

    def compose(self, vi: int, render: dict) -> dict[str, Tensor]:
        """``clean`` (I_hat), ``T``, ``P`` and ``con`` (I_con) of training view ``vi`` for a render of it."""
        clean = render["rgb"]
        if not self.use_csm:
            return {"clean": clean, "T": torch.ones_like(clean[..., :1]), "P": torch.zeros_like(clean), "con": clean}
        t0 = time.perf_counter()
        ext = self._extinction_image(self.train_views[vi].camera) if self.medium.field is None else None
        T, P = self.medium.forward(self._rays_for(vi), render, self.descriptors[vi], ext, self.train_images[vi], vi)
        self.timing["csm_forward_s"] += time.perf_counter() - t0
        return {"clean": clean, "T": T, "P": P, "con": compose(clean, T, P)}

    def render(self, camera: Camera, sh_degree: int | None = None, background: Tensor | None = None,
               view_index: int | None = None) -> dict:
        """The clean render of ``camera``; with ``view_index`` (``camera`` is that training view's) also its
        ``transmission``, ``airlight`` (P), ``residual`` and ``degraded`` (see the module docstring)."""
        out = super().render(camera, sh_degree, background)
        if view_index is None:
            return out
        parts = self.compose(view_index, out)
        r = (self.particulate.store.get(view_index) if self.particulate is not None
             else torch.zeros_like(parts["clean"]))
        return {**out, "transmission": parts["T"], "airlight": parts["P"], "residual": r,
                "degraded": parts["con"] + r}

    # --- the step -----------------------------------------------------------------------
    def _sync_stage(self, step: int) -> None:
        self.stage = 1 if step <= self.cfg.m_init else 2
        self.params.set_lr("log_scales", self.cfg.lr_scales_init if self.stage == 1 else self.cfg.lr_scales)

    def loss(self, step: int, view_index: int, render: dict, gt: Tensor) -> tuple[Tensor, Tensor]:
        """The stage's loss against the degraded render ``I_con (+ R)``, which is also returned."""
        c = self.cfg
        self._sync_stage(step)
        parts = self.compose(view_index, render)
        pred = parts["con"]
        layer = self.particulate
        if self.stage == 2 and layer is not None:
            if c.refresh_mode == "lazy" and c.residual_source == "render":
                self._lazy_refresh(step, view_index, render, pred)
            pred = pred + layer.store.get(view_index)
        loss = stage_loss(pred, gt, c.lambda_dssim, self.train_masks[view_index])
        if self.use_csm:
            dcp_on = c.lambda_dcp > 0 and (self.stage == 1 or c.dcp_stage2)
            prior_weight = 0.0
            if self.prior_clean is not None:
                prior_weight = c.lambda_dehaze * (1.0 if self.stage == 1 else c.prior_stage2)
            # The pixels whose march ends at a surface in the box: computed once, for whichever term needs it.
            surface = (self.medium.surface_mask(self._rays_for(view_index), render)
                       if (dcp_on and c.dcp_surface_only) or (prior_weight > 0 and c.prior_surface_only) else None)
            if dcp_on:
                loss = loss + c.lambda_dcp * dcp_loss(parts["clean"], c.dcp_patch, c.dcp_temperature, c.dcp_form,
                                                      surface if c.dcp_surface_only else None)
            if c.lambda_tv > 0 and self.medium.field is not None:
                loss = loss + c.lambda_tv * self.medium.field.tv()
            mask = self.train_masks[view_index]
            if prior_weight > 0 and c.prior_surface_only:  # not on the sky, where the dark-channel prior is false
                mask = surface if mask is None else surface & mask
                prior_weight = prior_weight if bool(mask.any()) else 0.0
            if prior_weight > 0:
                kept = None if mask is not None else self._prior_moments(view_index)
                loss = loss + prior_weight * stage_loss(parts["clean"], self.prior_clean[view_index], c.lambda_dssim,
                                                        mask, kept)
        return loss, pred.detach()

    def before_backward(self, step: int, view_index: int, render: dict, pred: Tensor, gt: Tensor) -> None:
        """GGS (stage 2): the per-Gaussian weights, from this step's forward alone; handed to the rasterizer's
        backward to apply where it can (:meth:`reweight_gradients` scales the gradients itself otherwise)."""
        self._ggs_weights = None
        if self.stage != 2 or not self.use_ggs:
            return
        t0 = time.perf_counter()
        meta = render["meta"]
        error = (pred - gt).abs().sum(dim=-1)
        if self.train_masks[view_index] is not None:  # ignored pixels must not steer the rescaling
            error = error * self.train_masks[view_index]
        means2d = meta["means2d"].detach().reshape(-1, 2)
        w, _ = ggs_weights(meta["depths"], meta["radii"], means2d, error, meta["visible"], self.ggs)
        holder = meta.get("row_scale")
        # Folding the weights into the projection's backward gives the bits of scaling afterwards only when that
        # backward is the Gaussians' sole gradient (not so in the Gaussian-driven extinction ablation, which
        # rasterizes them a second time) and the weights are finite.
        if (holder is not None and not (self.use_csm and self.medium.field is None)
                and w.dtype == meta["depths"].dtype and train_step.all_finite([w])):
            holder.weights = w
        self._ggs_weights = (w, holder)
        self.timing["ggs_s"] += time.perf_counter() - t0

    def reweight_gradients(self, step: int, view_index: int, render: dict, pred: Tensor, gt: Tensor,
                           info: dict) -> None:
        """GGS (stage 2): each Gaussian's gradients scaled by its weight (already, by the rasterizer's backward,
        when it took them), and the weights handed to the strategy."""
        if self._ggs_weights is None:
            return
        (w, holder), self._ggs_weights = self._ggs_weights, None
        self._checked_grads = None  # folded: the guard checks every gradient itself
        if holder is None or holder.weights is None or holder.applied == 0:
            t0 = time.perf_counter()
            self._checked_grads = scale_gradients(self.params.tensors, w)
            self.timing["ggs_s"] += time.perf_counter() - t0
        info["grad2d_weight"] = w

    def _grads_finite(self) -> bool:
        """The gradient guard, less the gradients that GGS's scaling pass checked this step."""
        checked, self._checked_grads = self._checked_grads, None
        if checked is None:
            return super()._grads_finite()
        scaled, ok = checked
        done = {id(g) for g in scaled}
        return ok and train_step.all_finite([g for g in self._gradients() if id(g) not in done])

    def optimizer_step(self) -> None:
        super().optimizer_step()
        if self.medium is not None:
            self.medium.step()

    def param_groups(self) -> list[dict]:
        groups = super().param_groups()
        return groups + (self.medium.param_groups() if self.medium is not None else [])

    def after_step(self, step: int) -> list[tuple[str, dict]]:
        c = self.cfg
        if step == c.m_init:
            return self._end_stage1(step)
        if (self.particulate is not None and c.residual_source == "render" and c.refresh_mode == "all"
                and is_refresh_step(step, c.m_init, c.refresh_interval)):
            self._refresh_all(step)
        return []

    # --- particulate layer --------------------------------------------------------------
    @torch.no_grad()
    def _surface(self, vi: int, render: dict) -> ViewGeometry:
        """The rendered surface of training view ``vi`` in ``render`` (depth / alpha, valid where alpha is high)."""
        alpha = render["alpha"].detach()
        valid = alpha >= self.cfg.surface_alpha_min
        if self.train_masks[vi] is not None:  # masked pixels neither ask nor answer the consistency check
            valid = valid & self.train_masks[vi].reshape(valid.shape)
        return ViewGeometry(self.train_views[vi].camera, render["depth"].detach() / alpha.clamp_min(1e-6), valid)

    @torch.no_grad()
    def _composites(self, step: int) -> tuple[list[Tensor], list[ViewGeometry]]:
        """I_con and the rendered surface of every training view with the current model."""
        cons, geometry = [], []
        deg = self.active_sh_degree(step)
        for vi, view in enumerate(self.train_views):
            render = super().render(view.camera, deg)
            cons.append(self.compose(vi, render)["con"])
            geometry.append(self._surface(vi, render))
        return cons, geometry

    @torch.no_grad()
    def _lazy_refresh(self, step: int, vi: int, render: dict, con: Tensor) -> None:
        """``refresh_mode=lazy``: R of view ``vi`` from this step's render when it is stale (no extra render).

        Its view-consistency check uses this step's surface of ``vi`` and its neighbours' surfaces from when
        they were last rendered (each at most about one refresh period old; every view's from the end of
        stage 1, or from one render of every view after a resumed run, before that).
        """
        c = self.cfg
        check = self._consistency_check()
        if check is not None:
            if self._surfaces is None:
                self._surfaces = self._composites(step)[1]
            self._surfaces[vi] = self._surface(vi, render)
        point = c.m_init + (step - 1 - c.m_init) // c.refresh_interval * c.refresh_interval
        if not self.particulate.store.is_stale(vi, point):
            return
        t0 = time.perf_counter()
        excess = check.excess(vi, self._surfaces) if check is not None else None
        self.particulate.store.set(vi, self.particulate.residual(vi, con.detach(), excess), step)
        self.counts["lazy_refreshes"] += 1
        self.timing["plm_refresh_s"] += time.perf_counter() - t0

    def _consistency_check(self):
        if self._consistency is None:
            self._consistency = consistency_check(self.cfg, [v.camera for v in self.train_views], self.train_images)
        return self._consistency

    def _refresh_all(self, step: int) -> None:
        if len(self.params) == 0:
            return  # the runner stops with its own message
        t0 = time.perf_counter()
        cons, geometry = self._composites(step)
        layer = self.particulate
        for vi, (con, excess) in enumerate(zip(cons, view_excesses(self._consistency_check(), geometry))):
            layer.store.set(vi, layer.residual(vi, con, excess), step)
        layer.store.refreshes += 1
        self.timing["plm_refresh_s"] += time.perf_counter() - t0

    def _end_stage1(self, step: int) -> list[tuple[str, dict]]:
        c = self.cfg
        if len(self.params) == 0:
            return []
        # The restored source needs the renders too: its residual goes through the same particle
        # mask (view-consistency against the rendered surfaces) as the render source's.
        need_renders = self.use_plm is None or self.use_plm
        composites = excesses = None
        render_time = 0.0
        if need_renders:
            t0 = time.perf_counter()
            composites, geometry = self._composites(step)
            if c.refresh_mode == "lazy":
                self._surfaces = list(geometry)
            render_time = (time.perf_counter() - t0) / len(composites)
            excesses = view_excesses(self._consistency_check(), geometry)
            self.timing["evidence_s" if self.use_plm is None else "plm_refresh_s"] += time.perf_counter() - t0
        if self.use_plm is None:
            counts = [residual_tail_counts(valid_image(self.train_images[vi], self.train_masks[vi], con), con, ex)
                      for vi, (con, ex) in enumerate(zip(composites, excesses))]
            # In auto mode use_csm is the haze decision: a hazy scene has its own thresholds.
            pixels = sum(img.shape[0] * img.shape[1] for img in self.train_images) / max(len(self.train_images), 1)
            self.particles = particle_evidence(counts, *particle_thresholds(c, self.use_csm, pixels),
                                               hazy=self.use_csm)
            self.use_plm = self.particles.present
            self.use_ggs = self.use_csm or self.use_plm
            if not self.use_plm:
                refreshes = c.m_joint // c.refresh_interval if c.refresh_mode == "all" else 0
                self.time_saved["plm_refresh_s"] = refreshes * len(self.train_views) * render_time
        if self.use_plm:
            layer = self.particulate = ParticulateLayer(c, self.train_images, self.train_masks, self.device)
            for vi, img in enumerate(self.train_images):
                # Only the reference differs between the sources (one change for the ablation):
                # the outlier / consistency mask and the top-hat cap apply to both.
                reference = (composites[vi] if c.residual_source == "render"
                             else classical_restore(img, RestoreConfig(patch=c.dcp_patch)))
                layer.store.set(vi, layer.residual(vi, reference, excesses[vi]), step)
            layer.store.refreshes += 1
        return [("components", self.components_record())]

    # --- records ------------------------------------------------------------------------
    @property
    def components(self) -> list[str]:
        on = {"csm": self.use_csm, "plm": bool(self.use_plm), "ggs": bool(self.use_ggs)}
        return [k for k, v in on.items() if v]

    def components_record(self) -> dict:
        rec = {"mode": "auto" if self.auto else "forced", "components": self.components,
               "haze_evidence": self.haze.to_dict(),
               "particle_evidence": self.particles.to_dict() if self.particles is not None else None,
               "estimated_time_saved_s": {k: round(v, 3) for k, v in self.time_saved.items()}}
        if self.use_csm:
            rec["initial_transmission"] = self.medium.initial_transmission
        return rec

    def get_info(self) -> dict:
        """``components`` and ``nimbus``: the decision record (:meth:`components_record`), the schedule,
        ``time_s`` (wall seconds spent on the auto evidence ``evidence_s``, the medium's forward pass
        ``csm_forward_s`` -- its backward runs inside the training step --, ``ggs_s`` and ``plm_refresh_s``),
        the residual store's size and refresh counts, beta statistics (1/m, per world unit) and, with
        ``view_density``, each training view's density factor."""
        c = self.cfg
        store = self.particulate.store if self.particulate is not None else None
        rec = self.components_record()
        rec.update(m_init=c.m_init, m_joint=c.m_joint, extinction=c.extinction if self.use_csm else None,
                   airlight=c.airlight if self.use_csm else None,
                   time_s={k: round(v, 3) for k, v in self.timing.items()},
                   residual_bytes=store.nbytes if store is not None else 0,
                   residual_refreshes=(store.refreshes if store is not None else 0),
                   lazy_refreshes=self.counts.get("lazy_refreshes", 0))
        if self.use_csm:
            beta = self.medium.beta_values(self.params.tensors.get("extinction_logit"))
            if beta is not None:  # trained per unit of the training frame (extent 1): report per world unit
                beta = beta / self.frame.scale
            rec["beta_max"] = float(beta.max()) if beta is not None else None
            rec["beta_mean"] = float(beta.mean()) if beta is not None else None
            if self.medium.view_log_density is not None:  # view_density: each training view's factor, by name
                rec["view_density"] = {v.name: round(float(self.medium.view_density(i).detach()), 4)
                                       for i, v in enumerate(self.train_views)}
        return {"components": self.components, "nimbus": rec}

    # --- state --------------------------------------------------------------------------
    def state_dict(self) -> dict:
        """3DGS's state with ``extra``: the decisions, records, medium and residuals (tensors and plain Python
        values only, numbers cast from numpy; see :func:`~nimbus.train.checkpoint.check_plain`)."""
        particles = None
        if self.particles is not None:
            particles = {k: bool(v) if isinstance(v, (bool, np.bool_)) else float(v)
                         for k, v in self.particles.to_dict().items()}
        extra = {"use_csm": bool(self.use_csm),
                 "use_plm": None if self.use_plm is None else bool(self.use_plm),
                 "use_ggs": None if self.use_ggs is None else bool(self.use_ggs),
                 "particles": particles,
                 "time_saved": {k: float(v) for k, v in self.time_saved.items()},
                 "timing": {k: float(v) for k, v in self.timing.items()},
                 "counts": {k: int(v) for k, v in self.counts.items()},
                 "medium": self.medium.state_dict() if self.use_csm else None,
                 "store": self.particulate.store.state_dict() if self.particulate is not None else None,
                 # refresh_mode=lazy: the neighbours' surfaces its consistency check uses, so a resumed run goes on
                 # exactly as an uninterrupted one.
                 "surfaces": None if self._surfaces is None else [(g.depth, g.valid) for g in self._surfaces]}
        return {**super().state_dict(), "extra": extra}

    def load_state_dict(self, state: dict) -> None:
        super().load_state_dict(state)
        extra = state["extra"]
        self._pending = []  # the decision was logged by the interrupted run
        self.use_csm, self.use_plm, self.use_ggs = extra["use_csm"], extra["use_plm"], extra["use_ggs"]
        self.particles = ParticleEvidence(**extra["particles"]) if extra["particles"] else None
        self.time_saved = dict(extra["time_saved"])
        self.timing = defaultdict(float, extra["timing"])
        self.counts = defaultdict(int, extra["counts"])
        m = extra["medium"]
        if m is not None:
            self.medium = self._build_medium(self.params["means"].detach(),
                                             Box(tuple(m["box"][0]), tuple(m["box"][1])))
            self.medium.load_state_dict(m)
        else:
            self.medium = None
        if extra["store"] is not None:
            self.particulate = ParticulateLayer(self.cfg, self.train_images, self.train_masks, self.device)
            self.particulate.store.load_state_dict(extra["store"])
        surfaces = extra.get("surfaces")  # absent from a checkpoint written before refresh_mode=lazy kept them
        self._surfaces = None if surfaces is None else [
            ViewGeometry(view.camera, depth.to(self.device), valid.to(self.device))
            for view, (depth, valid) in zip(self.train_views, surfaces)]
        self._sync_stage(self.iteration + 1)

    # --- outputs ------------------------------------------------------------------------
    @torch.no_grad()
    def write_outputs(self, out_dir) -> None:
        """``decomposition/NAME.png`` strips (I_in | I_hat | T | P | R) and ``extinction/beta_*.png`` slices
        (when ``write_decomposition``)."""
        if not self.cfg.write_decomposition:
            return
        out = Path(out_dir)
        for vi, view in enumerate(self.train_views):
            parts = self.render(view.camera, view_index=vi)
            strip = torch.cat([self.train_images[vi], parts["rgb"], parts["transmission"].expand(-1, -1, 3),
                               parts["airlight"], parts["residual"]], dim=1).clamp(0, 1)
            write_image(out / "decomposition" / f"{view.stem}.png", strip.float().cpu().numpy())
        field = self.medium.field if self.medium is not None else None
        if isinstance(field, ExtinctionGrid):
            self._write_slices(out, field.values().detach().float().cpu())

    @staticmethod
    def _write_slices(out: Path, beta: Tensor) -> None:
        top = float(beta.max())
        norm = beta / top if top > 0 else beta
        res = beta.shape[0]
        slices = {f"beta_z{int(100 * f):02d}": norm[min(int(f * res), res - 1)] for f in (0.25, 0.5, 0.75)}
        slices["beta_y50"] = norm[:, res // 2]
        slices["beta_x50"] = norm[:, :, res // 2]
        for name, s in slices.items():
            rep = max(1, -(-_SLICE_MIN_SIDE // res))
            img = s.repeat_interleave(rep, 0).repeat_interleave(rep, 1)
            write_image(out / "extinction" / f"{name}.png", img[..., None].expand(-1, -1, 3).numpy())
