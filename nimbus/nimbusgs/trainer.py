"""The NimbusGS trainer: 3DGS plus the degradation model I_deg = I_hat * T + P + R (supplementary Algorithm 1).

Stage 1 (iterations 1..M_init, geometry initialisation): the Gaussians are rendered to
the clean image I_hat, the continuous medium composes ``I_con = I_hat T + P`` and the
loss is ``(1 - lambda_r) L1(I_in, I_con) + lambda_r (1 - SSIM) + L_DCP(I_hat) + L_TV``,
with the Gaussians' scale learning rate lowered to ``lr_scales_init``.  At the end of
stage 1 every training view's particulate layer is extracted, ``R = ReLU(I_in - I_con)``.

Stage 2 (M_init+1..iterations, joint optimisation): ``I_deg = I_con + R``, loss
``(1 - lambda_r) L1(I_in, I_deg) + lambda_r (1 - SSIM) + L_TV``, R re-extracted every
``refresh_interval`` iterations, and GGS rescales each Gaussian's gradients (and so the
densification statistics) before the optimiser step.

Only what the scene needs is built (``components``; ``auto``: :mod:`nimbus.nimbusgs.auto`):
without CSM there is no grid, no airlight and no ray march (I_con = I_hat, no DCP);
without PLM no residual is stored or refreshed (I_deg = I_con); without GGS gradients
are left alone.  The decision, its evidence and the estimated time saved are logged
(event ``components``) and reported under ``nimbus`` in ``results.json``.

Extra outputs in the run directory::

    decomposition/NAME.png   per training view: I_in | I_hat | T | P | R (each clipped to [0, 1])
    extinction/beta_*.png    slices of the extinction grid, normalised by its maximum

The scored test renders are the clean I_hat.
"""

from __future__ import annotations

import math
import time
from collections import defaultdict

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from nimbus.data import View
from nimbus.data.images import write_image
from nimbus.nimbusgs.airlight import make_airlight, view_descriptor
from nimbus.nimbusgs.auto import ParticleEvidence, haze_evidence, particle_evidence, residual_tail_counts
from nimbus.nimbusgs.config import NimbusConfig
from nimbus.nimbusgs.ggs import GGSFactors, ggs_weights, ndc_grad_norm, scale_gradients
from nimbus.nimbusgs.losses import dcp_loss, stage_loss
from nimbus.nimbusgs.particulate import (ResidualStore, ViewGeometry, consistency_excess, extract_residual,
                                         is_refresh_step, neighbours, tophat_window, white_tophat)
from nimbus.nimbusgs.restore import RestoreConfig, classical_restore
from nimbus.nimbusgs.scattering import (Box, ExtinctionGrid, UniformExtinction, ViewRays,
                                        camera_rays, density_scale_for, gaussian_extinction_map, march,
                                        march_interval, ray_box_interval, surface_in_box)
from nimbus.render.gaussians import Gaussians
from nimbus.render.rasterize import means2d_grad, rasterize
from nimbus.render.sh import rgb_to_sh, sh_to_rgb
from nimbus.train.trainer import GaussianTrainer

#: Bounds of the data-driven initial transmission (ours): keeps the initial medium neither absent nor opaque.
INIT_TRANSMISSION_RANGE = (0.2, 0.95)
#: ``init_dehaze`` divides by at least this transmission (He et al.'s t0), so far points are not amplified.
DEHAZE_MIN_TRANSMISSION = 0.1
#: Voxels per axis of the throw-away grid used to time the ray march a haze-free scene skips.
_TIMING_GRID = 4
#: Smallest side of a written extinction slice (pixels); small grids are upsampled (nearest).
_SLICE_MIN_SIDE = 128


class NimbusTrainer(GaussianTrainer):
    """NimbusGS on a scene of degraded views (same constructor as :class:`GaussianTrainer`).

    ``config`` is a :class:`~nimbus.nimbusgs.config.NimbusConfig`.
    """

    method_name = "nimbus"
    cfg: NimbusConfig

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

    # --- set-up -------------------------------------------------------------------------
    def extra_setup(self) -> None:
        c = self.cfg
        self.stage = 1
        self.timing: dict[str, float] = defaultdict(float)
        self.counts: dict[str, int] = defaultdict(int)
        self._pending: list[tuple[str, dict]] = []
        self._rays: dict[int, ViewRays] = {}
        self._last: tuple[Tensor, Tensor] | None = None
        self.field = self.airlight = self.medium_opt = None
        self.ext_log_scale: Tensor | None = None
        self.box: Box | None = None
        self._box_tensors: tuple[Tensor, Tensor] | None = None
        self.store: ResidualStore | None = None
        #: Per training view, the input's white top-hat (uint8), the cap of R (filled on first use).
        self._tophat: dict[int, Tensor] = {}
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
        if self.use_csm:
            self._build_medium(self.params["means"].detach())
            if c.init_dehaze:
                self._dehaze_initial_colours()
        elif self.auto:
            self.time_saved["csm_ray_march_s"] = self._estimate_march_time() * c.iterations
        self._pending.append(("csm_decision", {
            "mode": "auto" if self.auto else "forced", "csm": self.use_csm, "haze_evidence": self.haze.to_dict(),
            "estimated_time_saved_s": self.time_saved.get("csm_ray_march_s", 0.0)}))
        self._sync_stage(1)

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

    def _build_medium(self, means: Tensor, box: Box | None = None) -> None:
        """The extinction field, airlight and their optimiser (CSM)."""
        c = self.cfg
        self.box = box or self._content_box(means)
        self._box_tensors = self.box.tensors(self.device)
        t0 = c.init_transmission or min(max(self.haze.transmission_estimate, INIT_TRANSMISSION_RANGE[0]),
                                        INIT_TRANSMISSION_RANGE[1])
        scale = density_scale_for(t0, self._mean_ray_length(means))
        gen = torch.Generator().manual_seed(self.seed + 1)
        groups = []
        if c.extinction == "grid":
            self.field = ExtinctionGrid(self.box, c.grid_resolution, c.grid_init_std, scale, gen).to(self.device)
            groups.append({"params": list(self.field.parameters()), "lr": c.lr_extinction, "name": "extinction"})
        elif c.extinction == "uniform":
            self.field = UniformExtinction(self.box, scale).to(self.device)
            groups.append({"params": list(self.field.parameters()), "lr": c.lr_extinction, "name": "extinction"})
        else:
            self.ext_log_scale = torch.tensor(math.log(scale), device=self.device, requires_grad=True)
            groups.append({"params": [self.ext_log_scale], "lr": c.lr_extinction, "name": "extinction"})
        init_a = self.descriptors[:, :3].mean(0)
        self.airlight = make_airlight(c.airlight, init_a, c.airlight_hidden, c.airlight_sh_degree).to(self.device)
        groups.append({"params": list(self.airlight.parameters()), "lr": c.lr_airlight, "name": "airlight"})
        self.medium_opt = torch.optim.Adam(groups, lr=0.0, eps=c.adam_eps)
        self.initial_transmission = t0
        self.initial_density_scale = scale

    def _initial_transmission(self, points: Tensor) -> Tensor:
        """``[N]`` transmission of the initial medium from the training cameras to ``points``: the median over
        the cameras that see a point (in front, inside the image), through the box only."""
        lo, hi = (x.double().cpu() for x in self._box_tensors)
        beta0 = math.log(2.0) * self.initial_density_scale  # softplus(0) * scale: the initial features are ~0
        pts = points.detach().double().cpu()
        taus = torch.full((len(self.train_views), pts.shape[0]), float("nan"), dtype=torch.float64)
        for k, view in enumerate(self.train_views):
            cam = view.camera
            uv, z = cam.project(pts.numpy())
            seen = torch.as_tensor((z > self.cfg.near_plane) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width)
                                   & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height))
            origin = torch.as_tensor(cam.center, dtype=torch.float64)
            vec = pts - origin
            dist = vec.norm(dim=1).clamp_min(1e-12)
            entry, exit_ = ray_box_interval(origin, vec / dist[:, None], lo, hi)
            length = (torch.minimum(dist, exit_) - entry.clamp_min(self.cfg.near_plane)).clamp_min(0.0)
            taus[k] = torch.where(seen, beta0 * length, torch.nan)
        tau = taus.nanmedian(dim=0).values
        tau = torch.where(torch.isnan(tau), torch.zeros_like(tau), tau)  # seen by no camera: leave the colour
        return torch.exp(-tau).float()

    @torch.no_grad()
    def _dehaze_initial_colours(self) -> None:
        """Start the Gaussians' colours at the clean colours the initial medium implies (``init_dehaze``)."""
        if self.field is None and self.ext_log_scale is None:
            return
        dc = self.params.tensors["sh_dc"]
        T0 = self._initial_transmission(self.params.tensors["means"]).to(dc)[:, None]
        a0 = self.descriptors[:, :3].mean(0).to(dc)
        rgb = sh_to_rgb(dc[:, 0])
        clean = ((rgb - a0 * (1 - T0)) / T0.clamp_min(DEHAZE_MIN_TRANSMISSION)).clamp(0.0, 1.0)
        dc[:, 0] = rgb_to_sh(clean)
        self._pending.append(("init_dehaze", {"mean_transmission": round(float(T0.mean()), 4),
                                              "airlight": [round(float(x), 4) for x in a0]}))

    def _estimate_march_time(self) -> float:
        """Seconds of one training view's ray march (forward + backward), timed on a throw-away coarse grid."""
        view = self.train_views[0]
        cam = view.camera
        box = self._content_box(self.params["means"].detach())
        grid = ExtinctionGrid(box, _TIMING_GRID, 0.01, 0.01).to(self.device)
        rays = camera_rays(cam, self.device)
        depth = torch.full((cam.height, cam.width), 1.0, device=self.device)
        t0 = time.perf_counter()
        lo, hi = grid.lo, grid.hi
        ts, te = march_interval(rays, lo, hi, depth, torch.ones_like(depth), self.cfg.near_plane,
                                self.cfg.surface_alpha_min)
        res = march(grid, rays.origin, rays.dirs, ts, te, self.cfg.ray_samples, self._march_backend)
        (res.transmission.sum() + res.scatter.sum()).backward()
        return time.perf_counter() - t0

    # --- stages -------------------------------------------------------------------------
    def _sync_stage(self, it: int) -> None:
        self.stage = 1 if it <= self.cfg.m_init else 2
        self.params.set_lr("log_scales", self.cfg.lr_scales_init if self.stage == 1 else self.cfg.lr_scales)

    @property
    def _march_backend(self) -> str:
        """The ray march follows the rasterizer's backend: ``auto`` and ``cpp`` march compiled where the kernel
        applies (:func:`~nimbus.nimbusgs.scattering.march`), ``torch`` and gsplat's CUDA march in torch."""
        return "auto" if self.cfg.backend in ("auto", "cpp") else "torch"

    def _rays_for(self, vi: int) -> ViewRays:
        if vi not in self._rays:
            self._rays[vi] = camera_rays(self.train_views[vi].camera, self.device)
        return self._rays[vi]

    def _extinction_image(self, view: View) -> Tensor:
        """Alpha-blended per-Gaussian extinction ``[H, W]`` (Gaussian-driven ablation)."""
        t = self.params.tensors
        beta = F.softplus(t["extinction_logit"]) * torch.exp(self.ext_log_scale)
        g = Gaussians(means=t["means"], log_scales=t["log_scales"], quats=t["quats"],
                      opacity_logits=t["opacity_logits"], sh_dc=rgb_to_sh(beta[:, None, None].expand(-1, 1, 3)),
                      sh_rest=t["means"].new_zeros(t["means"].shape[0], 0, 3))
        rgb, _, _, _ = rasterize(g, view.camera, sh_degree=0, background=torch.zeros(3, device=self.device),
                                 backend=self.cfg.backend, config=self.raster_config)
        return rgb[..., 0]

    def medium(self, view: View, rays: ViewRays, render: dict, descriptor: Tensor) -> tuple[Tensor, Tensor]:
        """``(T [H, W, 1], P [H, W, 3])`` of one view's continuous medium (CSM)."""
        c = self.cfg
        t0 = time.perf_counter()
        depth, alpha = render["depth"], render["alpha"]
        if not c.surface_depth_grad:
            depth, alpha = depth.detach(), alpha.detach()
        lo, hi = self._box_tensors
        t_start, t_end = march_interval(rays, lo, hi, depth, alpha, c.near_plane, c.surface_alpha_min)
        if self.field is not None:
            res = march(self.field, rays.origin, rays.dirs, t_start, t_end, c.ray_samples, self._march_backend)
        else:
            res = gaussian_extinction_map(self._extinction_image(view), alpha, t_start, t_end)
        a = self.airlight(rays.dirs, res.transmission, descriptor)
        h, w = rays.height, rays.width
        T = res.transmission.reshape(h, w, 1)
        P = (res.scatter[:, None] * a).reshape(h, w, 3)
        self.timing["csm_forward_s"] += time.perf_counter() - t0
        return T, P

    def compose(self, vi: int, render: dict) -> dict[str, Tensor]:
        """``I_hat``, ``T``, ``P`` and ``I_con`` of training view ``vi`` for a render of it."""
        clean = render["rgb"]
        if not self.use_csm:
            return {"clean": clean, "T": torch.ones_like(clean[..., :1]), "P": torch.zeros_like(clean), "con": clean}
        T, P = self.medium(self.train_views[vi], self._rays_for(vi), render, self.descriptors[vi])
        return {"clean": clean, "T": T, "P": P, "con": clean * T + P}

    def _dcp_mask(self, vi: int, render: dict) -> Tensor:
        """Pixels of training view ``vi`` whose march ends at a surface inside the box (``dcp_surface_only``)."""
        rays = self._rays_for(vi)
        lo, hi = self._box_tensors
        mask = surface_in_box(rays, lo, hi, render["depth"].detach(), render["alpha"].detach(),
                              self.cfg.surface_alpha_min)
        return mask.reshape(rays.height, rays.width)

    # --- hooks --------------------------------------------------------------------------
    def compute_loss(self, view_index: int, render: dict, gt: Tensor) -> Tensor:
        c = self.cfg
        it = self.iteration + 1
        self._sync_stage(it)
        parts = self.compose(view_index, render)
        pred = parts["con"]
        if self.stage == 2 and self.store is not None:
            if c.refresh_mode == "lazy" and c.residual_source == "render":
                point = c.m_init + (it - 1 - c.m_init) // c.refresh_interval * c.refresh_interval
                if self.store.is_stale(view_index, point):
                    self.store.set(view_index, self._residual(view_index, pred.detach()), it)
                    self.counts["lazy_refreshes"] += 1
            pred = pred + self.store.get(view_index)
        loss = stage_loss(pred, gt, c.lambda_dssim, self.train_masks[view_index])
        if self.use_csm:
            if c.lambda_dcp > 0 and (self.stage == 1 or c.dcp_stage2):
                mask = self._dcp_mask(view_index, render) if c.dcp_surface_only else None
                loss = loss + c.lambda_dcp * dcp_loss(parts["clean"], c.dcp_patch, c.dcp_temperature, c.dcp_form,
                                                      mask)
            if c.lambda_tv > 0 and self.field is not None:
                loss = loss + c.lambda_tv * self.field.tv()
        self._last = (pred.detach(), gt)
        return loss

    def training_prediction(self, render: dict) -> Tensor:
        """The degraded render ``I_con (+ R)`` the loss compared, not the clean ``I_hat``."""
        return self._last[0] if self._last is not None else render["rgb"]

    def before_step(self, view_index: int, render: dict) -> None:
        if self.stage != 2 or not self.use_ggs or self._last is None:
            return
        t0 = time.perf_counter()
        pred, gt = self._last
        meta = render["meta"]
        error = (pred - gt).abs().sum(dim=-1)
        if self.train_masks[view_index] is not None:  # ignored pixels must not steer the rescaling
            error = error * self.train_masks[view_index]
        means2d = meta["means2d"].detach().reshape(-1, 2)
        w, info = ggs_weights(meta["depths"], meta["radii"], means2d, error, meta["visible"], self.ggs)
        scale_gradients(self.params.tensors, w)
        # The densification statistic was accumulated from the unscaled gradient before
        # this hook: replace this view's contribution by the scaled one.
        grad2d = means2d_grad(meta)
        if grad2d is not None and self.density.grad_accum.shape[0] == w.shape[0]:
            vis = meta["visible"]
            ndc = ndc_grad_norm(grad2d, meta["width"], meta["height"])
            self.density.grad_accum[vis] += ((w - 1.0) * ndc)[vis].to(self.density.grad_accum)
        self.timing["ggs_s"] += time.perf_counter() - t0

    def optimizer_step(self) -> None:
        super().optimizer_step()
        if self.medium_opt is not None:
            self.medium_opt.step()
            self.medium_opt.zero_grad(set_to_none=True)

    def all_param_groups(self) -> list[dict]:
        groups = super().all_param_groups()
        return groups + (list(self.medium_opt.param_groups) if self.medium_opt is not None else [])

    def after_step(self, it: int) -> None:
        super().after_step(it)
        c = self.cfg
        if it == c.m_init:
            self._end_stage1(it)
        elif (self.store is not None and c.residual_source == "render" and c.refresh_mode == "all"
              and is_refresh_step(it, c.m_init, c.refresh_interval)):
            self._refresh_all(it)

    def eval_image(self, view: View, render: dict) -> Tensor:
        """The clean render I_hat (the degradation model is not applied to scored views)."""
        return render["rgb"]

    # --- particulate layer --------------------------------------------------------------
    @torch.no_grad()
    def _composites(self, it: int) -> tuple[list[Tensor], list[ViewGeometry]]:
        """I_con and the rendered surface of every training view with the current model."""
        cons, geometry = [], []
        deg = self.active_sh_degree(it)
        for vi, view in enumerate(self.train_views):
            render = self.render(view, deg)
            cons.append(self.compose(vi, render)["con"])
            alpha = render["alpha"]
            valid = alpha >= self.cfg.surface_alpha_min
            if self.train_masks[vi] is not None:  # masked pixels neither ask nor answer the consistency check
                valid = valid & self.train_masks[vi].reshape(valid.shape)
            geometry.append(ViewGeometry(view.camera, render["depth"] / alpha.clamp_min(1e-6), valid))
        return cons, geometry

    def _excess(self, geometry: list[ViewGeometry]) -> list[Tensor | None]:
        """Per view, the view-inconsistent excess (None when the check is off)."""
        c = self.cfg
        if c.consistency_neighbours < 1 or c.residual_outlier_sigmas <= 0:
            return [None] * len(geometry)
        others = neighbours([g.camera for g in geometry], c.consistency_neighbours)
        return [consistency_excess(i, self.train_images, geometry, others[i]) for i in range(len(geometry))]

    def _residual(self, vi: int, composite: Tensor, excess: Tensor | None = None) -> Tensor:
        """R of training view ``vi`` against ``composite`` (I_con), capped by the view's top-hat."""
        c = self.cfg
        image = self.train_images[vi]
        bound = None
        window = tophat_window(image.shape[1], c.residual_tophat)
        if window:
            if vi not in self._tophat:  # from the input alone: computed once, kept as 8 bits
                self._tophat[vi] = torch.round(white_tophat(image, window).clamp(0, 1) * 255).to(torch.uint8)
            bound = self._tophat[vi].float() / 255
        return self._masked_residual(vi, extract_residual(image, composite, c.residual_outlier_sigmas, excess, bound,
                                                          c.residual_outlier_scope))

    def _masked_residual(self, vi: int, r: Tensor) -> Tensor:
        """``r`` with view ``vi``'s masked pixels zeroed: the loss ignores them, so R has nothing to explain there."""
        mask = self.train_masks[vi]
        return r if mask is None else r * mask[..., None].to(r.dtype)

    def _valid_image(self, vi: int, composite: Tensor) -> Tensor:
        """Training image ``vi`` with its masked pixels taken from ``composite``: no residual there."""
        mask = self.train_masks[vi]
        image = self.train_images[vi]
        return image if mask is None else torch.where(mask[..., None], image, composite.to(image.dtype))

    def _refresh_all(self, it: int) -> None:
        if len(self.params) == 0:
            return  # the training loop stops with its own message
        t0 = time.perf_counter()
        cons, geometry = self._composites(it)
        for vi, (con, excess) in enumerate(zip(cons, self._excess(geometry))):
            self.store.set(vi, self._residual(vi, con, excess), it)
        self.store.refreshes += 1
        self.timing["plm_refresh_s"] += time.perf_counter() - t0

    def _end_stage1(self, it: int) -> None:
        c = self.cfg
        if len(self.params) == 0:
            return
        need_renders = self.use_plm is None or (self.use_plm and c.residual_source == "render")
        composites = excesses = None
        render_time = 0.0
        if need_renders:
            t0 = time.perf_counter()
            composites, geometry = self._composites(it)
            render_time = (time.perf_counter() - t0) / len(composites)
            excesses = self._excess(geometry)
            self.timing["evidence_s" if self.use_plm is None else "plm_refresh_s"] += time.perf_counter() - t0
        if self.use_plm is None:
            counts = [residual_tail_counts(self._valid_image(vi, con), con, ex)
                      for vi, (con, ex) in enumerate(zip(composites, excesses))]
            self.particles = particle_evidence(counts, c.auto_particle_threshold, c.auto_particle_energy)
            self.use_plm = self.particles.present
            self.use_ggs = self.use_csm or self.use_plm
            if not self.use_plm:
                refreshes = c.m_joint // c.refresh_interval if c.refresh_mode == "all" else 0
                self.time_saved["plm_refresh_s"] = refreshes * len(self.train_views) * render_time
        if self.use_plm:
            self.store = ResidualStore([(v.camera.height, v.camera.width) for v in self.train_views], self.device)
            for vi, img in enumerate(self.train_images):
                if c.residual_source == "render":
                    self.store.set(vi, self._residual(vi, composites[vi], excesses[vi]), it)
                else:
                    restored = classical_restore(img, RestoreConfig(patch=c.dcp_patch))
                    self.store.set(vi, self._masked_residual(vi, extract_residual(img, restored)), it)
            self.store.refreshes += 1
        self.event("components", **self.components_record())

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
            rec["initial_transmission"] = self.initial_transmission
        return rec

    def train(self) -> dict:
        self.out.mkdir(parents=True, exist_ok=True)
        for kind, info in self._pending:
            self.event(kind, **info)
        self._pending = []
        return super().train()

    def extra_results(self) -> dict:
        """``components`` and ``nimbus``: the decision record (:meth:`components_record`), the schedule, the
        variant, ``time_s`` (wall seconds spent on the auto evidence ``evidence_s``, the medium's forward
        pass ``csm_forward_s`` -- its backward runs inside the training step --, ``ggs_s`` and
        ``plm_refresh_s``), the residual store's size and refresh counts, and beta statistics (1/m)."""
        c = self.cfg
        rec = self.components_record()
        rec.update(m_init=c.m_init, m_joint=c.m_joint, extinction=c.extinction if self.use_csm else None,
                   airlight=c.airlight if self.use_csm else None,
                   time_s={k: round(v, 3) for k, v in self.timing.items()},
                   residual_bytes=self.store.nbytes if self.store is not None else 0,
                   residual_refreshes=(self.store.refreshes if self.store is not None else 0),
                   lazy_refreshes=self.counts.get("lazy_refreshes", 0))
        if self.use_csm:
            beta = self._beta_values()
            if beta is not None:  # trained per unit of the training frame (extent 1): report per world unit
                beta = beta / self.frame.scale
            rec["beta_max"] = float(beta.max()) if beta is not None else None
            rec["beta_mean"] = float(beta.mean()) if beta is not None else None
        return {"components": self.components, "nimbus": rec}

    # --- checkpoints --------------------------------------------------------------------
    def extra_state(self) -> dict:
        """Tensors and plain Python values only (numbers cast from numpy), so ``--resume`` can load the
        checkpoint with ``torch.load(weights_only=True)`` (see :func:`~nimbus.train.trainer.check_plain`)."""
        medium = None
        if self.use_csm:
            medium = {"box": ([float(x) for x in self.box.lo], [float(x) for x in self.box.hi]),
                      "optimizer": self.medium_opt.state_dict(), "airlight": self.airlight.state_dict(),
                      "field": self.field.state_dict() if self.field is not None else None,
                      "ext_log_scale": self.ext_log_scale.detach().clone() if self.ext_log_scale is not None else None,
                      "initial_transmission": float(self.initial_transmission)}
        particles = None
        if self.particles is not None:
            particles = {k: bool(v) if isinstance(v, (bool, np.bool_)) else float(v)
                         for k, v in self.particles.to_dict().items()}
        return {"use_csm": bool(self.use_csm),
                "use_plm": None if self.use_plm is None else bool(self.use_plm),
                "use_ggs": None if self.use_ggs is None else bool(self.use_ggs),
                "particles": particles,
                "time_saved": {k: float(v) for k, v in self.time_saved.items()},
                "timing": {k: float(v) for k, v in self.timing.items()},
                "counts": {k: int(v) for k, v in self.counts.items()},
                "medium": medium, "store": self.store.state_dict() if self.store is not None else None}

    def load_extra_state(self, state: dict) -> None:
        self._pending = []  # the decision was logged by the interrupted run
        self.use_csm, self.use_plm, self.use_ggs = state["use_csm"], state["use_plm"], state["use_ggs"]
        self.particles = ParticleEvidence(**state["particles"]) if state["particles"] else None
        self.time_saved = dict(state["time_saved"])
        self.timing = defaultdict(float, state["timing"])
        self.counts = defaultdict(int, state["counts"])
        m = state["medium"]
        if m is not None:
            self._build_medium(self.params["means"].detach(), Box(tuple(m["box"][0]), tuple(m["box"][1])))
            if m["field"] is not None:
                self.field.load_state_dict(m["field"])
            if m["ext_log_scale"] is not None:
                with torch.no_grad():
                    self.ext_log_scale.copy_(m["ext_log_scale"])
            self.airlight.load_state_dict(m["airlight"])
            self.medium_opt.load_state_dict(m["optimizer"])
            self.initial_transmission = m["initial_transmission"]
        else:
            self.field = self.airlight = self.medium_opt = None
        if state["store"] is not None:
            self.store = ResidualStore([(v.camera.height, v.camera.width) for v in self.train_views], self.device)
            self.store.load_state_dict(state["store"])
        self._sync_stage(self.iteration + 1)

    # --- outputs ------------------------------------------------------------------------
    def _beta_values(self) -> Tensor | None:
        if self.field is not None:
            return self.field.values().detach()
        if self.ext_log_scale is not None:
            return (F.softplus(self.params["extinction_logit"].detach()) * torch.exp(self.ext_log_scale.detach()))
        return None

    @torch.no_grad()
    def write_decomposition(self) -> None:
        """``decomposition/NAME.png`` strips (I_in | I_hat | T | P | R) and ``extinction/beta_*.png`` slices."""
        deg = self.cfg.sh_degree
        for vi, view in enumerate(self.train_views):
            parts = self.compose(vi, self.render(view, deg))
            r = self.store.get(vi) if self.store is not None else torch.zeros_like(parts["clean"])
            strip = torch.cat([self.train_images[vi], parts["clean"], parts["T"].expand(-1, -1, 3), parts["P"], r],
                              dim=1).clamp(0, 1)
            write_image(self.out / "decomposition" / f"{view.stem}.png", strip.float().cpu().numpy())
        if isinstance(self.field, ExtinctionGrid):
            beta = self.field.values().detach().float().cpu()
            top = float(beta.max())
            norm = beta / top if top > 0 else beta
            res = beta.shape[0]
            slices = {f"beta_z{int(100 * f):02d}": norm[min(int(f * res), res - 1)] for f in (0.25, 0.5, 0.75)}
            slices["beta_y50"] = norm[:, res // 2]
            slices["beta_x50"] = norm[:, :, res // 2]
            for name, s in slices.items():
                rep = max(1, -(-_SLICE_MIN_SIDE // res))
                img = s.repeat_interleave(rep, 0).repeat_interleave(rep, 1)
                write_image(self.out / "extinction" / f"{name}.png", img[..., None].expand(-1, -1, 3).numpy())

    def finish(self) -> dict:
        if self.cfg.write_decomposition and len(self.params):
            self.write_decomposition()
        return super().finish()
