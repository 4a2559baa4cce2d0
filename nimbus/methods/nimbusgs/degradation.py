"""NimbusGS's degradation model: ``I_deg = I_hat * T + P + R`` (supplementary Algorithm 1).

- :class:`Medium` (CSM): the extinction (a grid, one uniform coefficient, or a per-Gaussian
  attribute with a global scale), the airlight, and their optimiser; it gives a view's
  transmission ``T`` [H, W, 1] and scattered light ``P`` [H, W, 3] by marching the rays
  through the content box up to the rendered surface.
- :func:`compose`: the continuous composite ``I_con = I_hat T + P``.
- :class:`ParticulateLayer` (PLM): the per-view residuals ``R`` (rain, snow), extracted as
  ``ReLU(I_in - I_con)`` capped by the input's white top-hat, and stored per training view.

The training schedule around them (stages, refreshes, the automatic component choice, GGS)
is the method's: :mod:`nimbus.methods.nimbusgs.method`.
"""

from __future__ import annotations

import math
import time

import torch
import torch.nn.functional as F
from torch import Tensor

from nimbus.data import Camera
from nimbus.methods.nimbusgs.airlight import make_airlight
from nimbus.methods.nimbusgs.config import NimbusConfig
from nimbus.methods.nimbusgs.particulate import (ResidualStore, ViewConsistency, ViewGeometry, extract_residual,
                                         tophat_window, white_tophat)
from nimbus.methods.nimbusgs.scattering import (Box, ExtinctionGrid, UniformExtinction, ViewRays, camera_rays,
                                        density_scale_for, gaussian_extinction_map, march, march_interval,
                                        ray_box_interval, surface_in_box)
from nimbus.train.params import adam

#: Bounds of the data-driven initial transmission (ours): keeps the initial medium neither absent nor opaque.
INIT_TRANSMISSION_RANGE = (0.2, 0.95)
#: ``init_dehaze`` divides by at least this transmission (He et al.'s t0), so far points are not amplified.
DEHAZE_MIN_TRANSMISSION = 0.1
#: Voxels per axis of the throw-away grid used to time the ray march a haze-free scene skips.
_TIMING_GRID = 4


def march_backend(config: NimbusConfig) -> str:
    """The ray march and the network airlight follow the rasterizer's backend: ``auto`` and ``cpp`` use the
    compiled CPU kernels where they apply (:func:`~nimbus.methods.nimbusgs.scattering.march`,
    :class:`~nimbus.methods.nimbusgs.airlight.NetworkAirlight`), ``torch`` and gsplat's CUDA path torch ops."""
    return "auto" if config.backend in ("auto", "cpp") else "torch"


def block_mean(x: Tensor, h: int, w: int, s: int) -> Tensor:
    """Means of ``x`` [H * W, C] (row-major pixels) over ``s`` x ``s`` blocks: ``[ceil(H/s) * ceil(W/s), C]``;
    a block cut by the image edge averages the pixels it has."""
    c = x.shape[1]
    img = x.reshape(h, w, c).permute(2, 0, 1)[None]
    return F.avg_pool2d(img, s, s, ceil_mode=True)[0].permute(1, 2, 0).reshape(-1, c)


def _unit(dirs: Tensor) -> Tensor:
    return dirs / dirs.norm(dim=1, keepdim=True).clamp_min(1e-12)


def upsample_blocks(low: Tensor, h: int, w: int, s: int) -> Tensor:
    """Per-block values ``low`` [ceil(H/s) * ceil(W/s), C] bilinearly interpolated to every pixel ``[H * W, C]``,
    each block's value sitting at its centre (edge blocks extrapolate flat)."""
    hb, wb = -(-h // s), -(-w // s)
    c = low.shape[1]
    img = low.reshape(hb, wb, c).permute(2, 0, 1)[None]
    up = F.interpolate(img, scale_factor=s, mode="bilinear", align_corners=False, recompute_scale_factor=False)
    return up[0, :, :h, :w].permute(1, 2, 0).reshape(-1, c)


def compose(clean: Tensor, transmission: Tensor, scatter: Tensor) -> Tensor:
    """``I_con = I_hat T + P``: the clean render [H, W, 3] seen through the medium."""
    return clean * transmission + scatter


class Medium:
    """The continuous medium (CSM) in a content box, and the Adam of its parameters.

    Parameters
    ----------
    config : NimbusConfig
        ``extinction`` (grid / uniform / gaussian), ``grid_*``, ``airlight*``, learning rates.
    box : Box
        The region the medium fills (training frame).
    transmission : float
        The initial transmission along a typical ray (sets the initial density scale).
    ray_length : float
        The typical ray length that transmission is for.
    airlight : Tensor
        [3] initial airlight colour.
    seed : int
        Seeds the grid's initial noise (``seed + 1``, apart from the Gaussians' generator).
    device : torch.device
    """

    def __init__(self, config: NimbusConfig, box: Box, transmission: float, ray_length: float, airlight: Tensor,
                 seed: int, device: torch.device, views: int = 0) -> None:
        c = config
        self.cfg = config
        self.box = box
        self.box_tensors = box.tensors(device)
        scale = density_scale_for(transmission, ray_length)
        gen = torch.Generator().manual_seed(seed + 1)
        self.field = None
        #: Global scale of per-Gaussian extinction (``extinction="gaussian"``), else None.
        self.ext_log_scale: Tensor | None = None
        groups = []
        if c.extinction == "grid":
            self.field = ExtinctionGrid(box, c.grid_resolution, c.grid_init_std, scale, gen).to(device)
            groups.append({"params": list(self.field.parameters()), "lr": c.lr_extinction, "name": "extinction"})
        elif c.extinction == "uniform":
            self.field = UniformExtinction(box, scale).to(device)
            groups.append({"params": list(self.field.parameters()), "lr": c.lr_extinction, "name": "extinction"})
        else:
            self.ext_log_scale = torch.tensor(math.log(scale), device=device, requires_grad=True)
            groups.append({"params": [self.ext_log_scale], "lr": c.lr_extinction, "name": "extinction"})
        #: Per training view, the log of its density factor (``view_density``), else None.
        self.view_log_density: Tensor | None = None
        if c.view_density and views > 0:
            self.view_log_density = torch.zeros(views, device=device, requires_grad=True)
            groups.append({"params": [self.view_log_density], "lr": c.lr_extinction, "name": "view_density"})
        self.airlight = make_airlight(c.airlight, airlight, c.airlight_hidden, c.airlight_sh_degree,
                                      c.airlight_input, compiled=march_backend(c) != "torch").to(device)
        groups.append({"params": list(self.airlight.parameters()), "lr": c.lr_airlight, "name": "airlight"})
        self.optimizer = adam(groups, c.adam_eps)  # fused on the CPU, as the Gaussians' Adam
        self.initial_transmission = transmission
        self.initial_density_scale = scale

    # --- T and P ---------------------------------------------------------------------------
    def view_density(self, view_index: int | None) -> Tensor | None:
        """The density factor ``s_v`` of training view ``view_index`` (``view_density``), or None."""
        if self.view_log_density is None or view_index is None:
            return None
        logs = self.view_log_density
        return torch.exp(logs[view_index] - logs.mean())

    def forward(self, rays: ViewRays, render: dict, descriptor: Tensor,
                extinction_image: Tensor | None = None, image: Tensor | None = None,
                view_index: int | None = None) -> tuple[Tensor, Tensor]:
        """``(T [H, W, 1], P [H, W, 3])`` of one view.

        ``render`` has the view's ``depth`` and ``alpha`` (the march ends at the surface); ``descriptor``
        and ``image`` (the degraded input [H, W, 3]; needed by ``airlight_input="pixel"``) condition the
        airlight; ``extinction_image`` [H, W] is the alpha-blended per-Gaussian extinction (only for
        ``extinction="gaussian"``); ``view_index`` (a training view) applies its density factor
        (``view_density``: ``T ** s_v``), None the field alone.
        """
        c = self.cfg
        depth, alpha = render["depth"], render["alpha"]
        if not c.surface_depth_grad:
            depth, alpha = depth.detach(), alpha.detach()
        lo, hi = self.box_tensors
        t_start, t_end = march_interval(rays, lo, hi, depth, alpha, c.near_plane, c.surface_alpha_min)
        if self.field is not None:
            res = march(self.field, rays.origin, rays.dirs, t_start, t_end, c.ray_samples, march_backend(c))
        else:
            res = gaussian_extinction_map(extinction_image, alpha, t_start, t_end)
        transmission, scatter = res.transmission, res.scatter
        factor = self.view_density(view_index)
        if factor is not None:  # T ** s and 1 - T ** s, from the optical depth
            tau = -torch.log(transmission.clamp_min(1e-30)) * factor
            transmission, scatter = torch.exp(-tau), -torch.expm1(-tau)
        a = self._airlight(rays, transmission, descriptor, image)
        h, w = rays.height, rays.width
        return transmission.reshape(h, w, 1), (scatter[:, None] * a).reshape(h, w, 3)

    def _airlight(self, rays: ViewRays, transmission: Tensor, descriptor: Tensor, image: Tensor | None) -> Tensor:
        """A [P, 3] at every pixel; the network's evaluated per ``airlight_stride`` block and upsampled."""
        s = self.cfg.airlight_stride
        pixels = None if image is None else image.reshape(-1, 3)
        if s == 1 or self.cfg.airlight != "network":
            return self.airlight(rays.dirs, transmission, descriptor, pixels)
        h, w = rays.height, rays.width
        dirs = rays.derived(("block_dirs", s), lambda: _unit(block_mean(rays.dirs, h, w, s)))
        low = self.airlight(dirs, block_mean(transmission.detach()[:, None], h, w, s)[:, 0], descriptor,
                            None if pixels is None else block_mean(pixels, h, w, s))
        return upsample_blocks(low, h, w, s)

    def surface_mask(self, rays: ViewRays, render: dict) -> Tensor:
        """[H, W] bool: pixels whose march ends at a surface inside the box (``dcp_surface_only``)."""
        lo, hi = self.box_tensors
        mask = surface_in_box(rays, lo, hi, render["depth"].detach(), render["alpha"].detach(),
                              self.cfg.surface_alpha_min)
        return mask.reshape(rays.height, rays.width)

    def initial_transmission_to(self, points: Tensor, cameras: list[Camera]) -> Tensor:
        """``[N]`` transmission of the initial medium from the cameras to ``points``: the median over the
        cameras that see a point (in front, inside the image), through the box only."""
        lo, hi = (x.double().cpu() for x in self.box_tensors)
        beta0 = math.log(2.0) * self.initial_density_scale  # softplus(0) * scale: the initial features are ~0
        pts = points.detach().double().cpu()
        taus = torch.full((len(cameras), pts.shape[0]), float("nan"), dtype=torch.float64)
        for k, cam in enumerate(cameras):
            seen = torch.as_tensor(cam.project_seen(pts.numpy(), self.cfg.near_plane)[2])
            origin = torch.as_tensor(cam.center, dtype=torch.float64)
            vec = pts - origin
            dist = vec.norm(dim=1).clamp_min(1e-12)
            entry, exit_ = ray_box_interval(origin, vec / dist[:, None], lo, hi)
            length = (torch.minimum(dist, exit_) - entry.clamp_min(self.cfg.near_plane)).clamp_min(0.0)
            taus[k] = torch.where(seen, beta0 * length, torch.nan)
        tau = taus.nanmedian(dim=0).values
        tau = torch.where(torch.isnan(tau), torch.zeros_like(tau), tau)  # seen by no camera: leave the colour
        return torch.exp(-tau).float()

    # --- parameters ------------------------------------------------------------------------
    def beta_values(self, extinction_logit: Tensor | None) -> Tensor | None:
        """The extinction coefficients (per voxel, the uniform one, or per Gaussian), training-frame units."""
        if self.field is not None:
            return self.field.values().detach()
        if self.ext_log_scale is not None and extinction_logit is not None:
            return torch.nn.functional.softplus(extinction_logit.detach()) * torch.exp(self.ext_log_scale.detach())
        return None

    def param_groups(self) -> list[dict]:
        return list(self.optimizer.param_groups)

    def step(self) -> None:
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)

    def state_dict(self) -> dict:
        """Tensors and plain values only (``box`` as two lists of floats)."""
        return {"box": ([float(x) for x in self.box.lo], [float(x) for x in self.box.hi]),
                "optimizer": self.optimizer.state_dict(), "airlight": self.airlight.state_dict(),
                "field": self.field.state_dict() if self.field is not None else None,
                "ext_log_scale": self.ext_log_scale.detach().clone() if self.ext_log_scale is not None else None,
                "view_log_density": (self.view_log_density.detach().clone() if self.view_log_density is not None
                                     else None),
                "initial_transmission": float(self.initial_transmission)}

    def load_state_dict(self, state: dict) -> None:
        if state["field"] is not None:
            self.field.load_state_dict(state["field"])
        if state["ext_log_scale"] is not None:
            with torch.no_grad():
                self.ext_log_scale.copy_(state["ext_log_scale"])
        if state.get("view_log_density") is not None and self.view_log_density is not None:
            with torch.no_grad():
                self.view_log_density.copy_(state["view_log_density"])
        self.airlight.load_state_dict(state["airlight"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.initial_transmission = state["initial_transmission"]


def estimate_march_time(config: NimbusConfig, box: Box, camera: Camera, device: torch.device) -> float:
    """Seconds of one view's ray march (forward + backward), timed on a throw-away coarse grid in ``box``."""
    grid = ExtinctionGrid(box, _TIMING_GRID, 0.01, 0.01).to(device)
    rays = camera_rays(camera, device)
    depth = torch.full((camera.height, camera.width), 1.0, device=device)
    t0 = time.perf_counter()
    ts, te = march_interval(rays, grid.lo, grid.hi, depth, torch.ones_like(depth), config.near_plane,
                            config.surface_alpha_min)
    res = march(grid, rays.origin, rays.dirs, ts, te, config.ray_samples, march_backend(config))
    (res.transmission.sum() + res.scatter.sum()).backward()
    if device.type == "cuda":  # CUDA runs asynchronously: the clock must wait for the march to finish
        torch.cuda.synchronize(device)
    return time.perf_counter() - t0


def masked(r: Tensor, mask: Tensor | None) -> Tensor:
    """``r`` with the masked pixels zeroed: the loss ignores them, so R has nothing to explain there."""
    return r if mask is None else r * mask[..., None].to(r.dtype)


def valid_image(image: Tensor, mask: Tensor | None, composite: Tensor) -> Tensor:
    """``image`` with its masked pixels taken from ``composite``: no residual there."""
    return image if mask is None else torch.where(mask[..., None], image, composite.to(image.dtype))


def consistency_check(config: NimbusConfig, cameras: list[Camera], images: list[Tensor]) -> ViewConsistency | None:
    """The training views' consistency check (:class:`ViewConsistency`), or None when it is off."""
    if config.consistency_neighbours < 1 or config.residual_outlier_sigmas <= 0:
        return None
    return ViewConsistency(cameras, images, config.consistency_neighbours)


def view_excesses(check: ViewConsistency | None, geometry: list[ViewGeometry]) -> list[Tensor | None]:
    """Per view, the view-inconsistent excess over its neighbours (None when the check is off)."""
    if check is None:
        return [None] * len(geometry)
    return check.excesses(geometry)


class ParticulateLayer:
    """The per-view residuals R (PLM) of the training views.

    Parameters
    ----------
    config : NimbusConfig
        ``residual_*`` settings.
    images, masks : list
        The training images [H, W, 3] and their validity masks ([H, W] bool or None).
    device : torch.device
    """

    def __init__(self, config: NimbusConfig, images: list[Tensor], masks: list[Tensor | None],
                 device: torch.device) -> None:
        self.cfg = config
        self.images = images
        self.masks = masks
        self.store = ResidualStore([tuple(img.shape[:2]) for img in images], device)
        #: Per view, the input's white top-hat (uint8), the cap of R (filled on first use).
        self._tophat: dict[int, Tensor] = {}

    def residual(self, vi: int, composite: Tensor, excess: Tensor | None = None) -> Tensor:
        """R of view ``vi`` against ``composite`` (I_con, or a classical restoration for
        ``residual_source=restored``), masked as a particle layer and capped by the view's top-hat."""
        c = self.cfg
        image = self.images[vi]
        bound = None
        window = tophat_window(image.shape[1], c.residual_tophat)
        if window:
            if vi not in self._tophat:  # from the input alone: computed once, kept as 8 bits
                self._tophat[vi] = torch.round(white_tophat(image, window).clamp(0, 1) * 255).to(torch.uint8)
            bound = self._tophat[vi].float() / 255
        return masked(extract_residual(image, composite, c.residual_outlier_sigmas, excess, bound,
                                       c.residual_outlier_scope), self.masks[vi])
