"""The public rasterizer: Gaussians + camera -> RGB, expected depth, alpha and per-Gaussian meta.

Pipeline of the torch backend (the reference path): EWA projection with near/frustum
culling (:mod:`~nimbus.render.projection`), SH colour of the visible Gaussians
(:mod:`~nimbus.render.sh`), tile binning (:mod:`~nimbus.render.binning`) and per-tile
front-to-back compositing (:mod:`~nimbus.render.composite_torch`).  The cpp backend runs
the same mathematics compiled (``nimbus.render.composite_cpp``): projection + SH +
sigmoid fused into one op with a hand-written backward, binning by a counting sort, and
the C++ compositor, all over the N Gaussians (culled ones have radius 0), so a render
is a handful of ops instead of ~100 small torch ops and their autograd records.  A
camera whose ``viewmat``/``K`` need gradients takes the torch projection with the C++
compositor.  The ``gsplat`` backend hands the whole job to gsplat's CUDA rasterizer.

Everything runs on the device of the Gaussian parameters.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import torch
from torch import Tensor

from nimbus.errors import NimbusError
from nimbus.render.binning import bin_gaussians
from nimbus.render.composite_torch import CompositeConfig
from nimbus.render.composite_torch import composite as composite_torch
from nimbus.render.gaussians import Gaussians
from nimbus.render.projection import ProjectionConfig, project_gaussians
from nimbus.render.sh import sh_colors

BACKENDS = ("torch", "cpp", "gsplat", "auto")


@dataclass(frozen=True)
class RasterConfig:
    """Rasterizer settings.

    Attributes
    ----------
    tile_size : int
        Tile side in pixels (binning and compositing; gsplat uses 16).
    projection : ProjectionConfig
        Near/far planes, 2D dilation, FoV clamp, radius in sigmas.
    composite : CompositeConfig
        Work sizes of the torch compositor (speed/memory only).
    """

    tile_size: int = 16
    projection: ProjectionConfig = field(default_factory=ProjectionConfig)
    composite: CompositeConfig = field(default_factory=CompositeConfig)

    def __post_init__(self) -> None:
        if self.tile_size < 1:
            raise NimbusError(f"tile_size must be >= 1, got {self.tile_size}")


@dataclass
class Shaded:
    """Projected, culled and coloured Gaussians: what a compositor needs.

    ``means2d``, ``radii`` and ``depths`` are per Gaussian ([N, ...], zeros where culled);
    the ``vis_*`` tensors hold the M visible ones, in the order of ``visible_ids``.
    """

    means2d: Tensor      # [N, 2], the tensor whose .grad feeds densification
    radii: Tensor        # [N] int32
    depths: Tensor       # [N]
    visible_ids: Tensor  # [M] int64
    vis_means2d: Tensor  # [M, 2]
    vis_conics: Tensor   # [M, 3]
    vis_colors: Tensor   # [M, 3]
    vis_opacities: Tensor  # [M]
    vis_depths: Tensor   # [M]
    vis_radii: Tensor    # [M]


def camera_tensors(camera, dtype=torch.float32, device=None) -> tuple[Tensor, Tensor, int, int]:
    """``(viewmat [4, 4], K [3, 3], width, height)`` of a :class:`nimbus.data.Camera`."""
    return (torch.as_tensor(camera.world_to_camera, dtype=dtype, device=device),
            torch.as_tensor(camera.K, dtype=dtype, device=device), camera.width, camera.height)


def resolve_camera(gaussians: Gaussians, camera, viewmat, K, width, height) -> tuple[Tensor, Tensor, int, int]:
    """Camera arguments of :func:`rasterize` as ``(viewmat, K, width, height)`` on the Gaussians' device/dtype."""
    if camera is not None:
        if any(v is not None for v in (viewmat, K, width, height)):
            raise ValueError("give either camera or viewmat/K/width/height, not both")
        viewmat, K, width, height = camera_tensors(camera, torch.float64)
    elif viewmat is None or K is None or width is None or height is None:
        raise ValueError("rasterize needs a camera, or viewmat, K, width and height")
    dtype, device = gaussians.means.dtype, gaussians.device
    viewmat = torch.as_tensor(viewmat).to(dtype=dtype, device=device)
    K = torch.as_tensor(K).to(dtype=dtype, device=device)
    if tuple(viewmat.shape) != (4, 4) or tuple(K.shape) != (3, 3):
        raise ValueError(f"viewmat must be [4, 4] and K [3, 3], got {tuple(viewmat.shape)} and {tuple(K.shape)}")
    width, height = int(width), int(height)
    if width <= 0 or height <= 0:
        raise NimbusError(f"image size must be positive, got {width}x{height}")
    return viewmat, K, width, height


def project_and_shade(
    gaussians: Gaussians,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    sh_degree: int,
    config: ProjectionConfig,
) -> Shaded:
    """Project all Gaussians, keep the visible ones and evaluate their SH colour and opacity."""
    proj = project_gaussians(gaussians.means, gaussians.quats, gaussians.log_scales, viewmat, K, width, height,
                             config)
    means2d = proj.means2d
    if means2d.requires_grad:
        means2d.retain_grad()
    vis = torch.nonzero(proj.radii > 0).squeeze(1)
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    center = -(R.T @ t)
    n_rest = (sh_degree + 1) ** 2 - 1  # only the active bands are gathered (and get gradients)
    sh = torch.cat([gaussians.sh_dc[vis], gaussians.sh_rest[vis, :n_rest]], dim=1) if n_rest else gaussians.sh_dc[vis]
    colors = sh_colors(sh_degree, sh, gaussians.means[vis], center)
    return Shaded(
        means2d=means2d, radii=proj.radii, depths=proj.depths, visible_ids=vis,
        vis_means2d=means2d[vis], vis_conics=proj.conics[vis], vis_colors=colors,
        vis_opacities=torch.sigmoid(gaussians.opacity_logits[vis]), vis_depths=proj.depths[vis],
        vis_radii=proj.radii[vis],
    )


def rasterize(
    gaussians: Gaussians,
    camera=None,
    *,
    viewmat: Tensor | None = None,
    K: Tensor | None = None,
    width: int | None = None,
    height: int | None = None,
    sh_degree: int | None = None,
    background=None,
    backend: str = "torch",
    config: RasterConfig | None = None,
    absgrad: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor, dict]:
    """Render N Gaussians from one camera.

    Parameters
    ----------
    gaussians : Gaussians
        N Gaussians (raw parameters; see :mod:`nimbus.render.gaussians`).
    camera : nimbus.data.Camera, optional
        The camera; or give ``viewmat`` [4, 4] (world-to-camera, OpenCV axes), ``K`` [3, 3],
        ``width`` and ``height`` instead.
    sh_degree : int, optional
        Active SH degree, 0..``gaussians.sh_degree`` (default: all stored bands).
    background : [3] tensor or sequence, optional
        Colour behind the Gaussians, default black.
    backend : {"torch", "cpp", "gsplat", "auto"}
        Compositor.  "auto" picks gsplat for CUDA tensors when gsplat imports, else the
        C++ kernel when it builds/loads (CPU tensors), else torch.
    config : RasterConfig, optional
    absgrad : Tensor [N, 2], optional
        Backend "cpp" only: the backward ADDS to it, per Gaussian and axis, the sum over
        pixels of ``|d loss / d means2d|`` (gsplat's "absgrad" densification statistic).

    Returns
    -------
    rgb : Tensor [H, W, 3]
        Colour, ``sum c_i alpha_i T_i + T_final * background``.
    depth : Tensor [H, W]
        Accumulated camera z, ``sum z_i alpha_i T_i`` (divide by ``alpha`` to normalise).
    alpha : Tensor [H, W]
        Accumulated opacity ``1 - T_final``.
    meta : dict
        ``means2d`` [N, 2] pixel-space centres whose ``.grad`` is filled by backward
        (gsplat backend: gsplat's [1, N, 2] tensor; use :func:`means2d_grad`),
        ``radii`` [N] int, ``depths`` [N], ``visible`` [N] bool (radius > 0),
        ``num_intersections`` int, ``backend`` (the one used), ``width``, ``height``.
    """
    cfg = config or RasterConfig()
    viewmat, K, width, height = resolve_camera(gaussians, camera, viewmat, K, width, height)
    dtype, device = gaussians.means.dtype, gaussians.device
    if sh_degree is None:
        sh_degree = gaussians.sh_degree
    if not 0 <= sh_degree <= gaussians.sh_degree:
        raise NimbusError(f"sh_degree must be in 0..{gaussians.sh_degree} (the stored bands), got {sh_degree}")
    bg = torch.zeros(3, dtype=dtype, device=device) if background is None else \
        torch.as_tensor(background).to(dtype=dtype, device=device).reshape(3)
    backend = _resolve_backend(backend, device)
    if absgrad is not None:
        n = len(gaussians)
        if backend != "cpp" or viewmat.requires_grad or K.requires_grad:
            raise NimbusError("absgrad is only collected by backend 'cpp' with a fixed camera; "
                              "use backend='cpp' or leave absgrad unset")
        if tuple(absgrad.shape) != (n, 2) or absgrad.dtype != dtype:
            raise NimbusError(f"absgrad must be a [{n}, 2] {dtype} tensor, got {tuple(absgrad.shape)} "
                              f"{absgrad.dtype}")

    if backend == "gsplat":
        return _rasterize_gsplat(gaussians, viewmat, K, width, height, sh_degree, bg, cfg)

    if backend == "cpp" and not (viewmat.requires_grad or K.requires_grad):
        rgb, depth, alpha, means2d, radii, depths, n_isect = _rasterize_cpp(gaussians, viewmat, K, width, height,
                                                                            sh_degree, bg, cfg, absgrad)
    else:
        s = project_and_shade(gaussians, viewmat, K, width, height, sh_degree, cfg.projection)
        isect_ids, tile_offsets = bin_gaussians(s.vis_means2d, s.vis_radii, s.vis_depths, width, height,
                                                cfg.tile_size)
        args = (s.vis_means2d, s.vis_conics, s.vis_colors, s.vis_opacities, s.vis_depths, isect_ids,
                tile_offsets, width, height, cfg.tile_size, bg)
        if backend == "cpp":  # a camera that needs gradients: torch projection, compiled compositing
            from nimbus.render import composite_cpp

            rgb, depth, alpha = composite_cpp.composite(*args)
        else:
            rgb, depth, alpha = composite_torch(*args, config=cfg.composite)
        means2d, radii, depths, n_isect = s.means2d, s.radii, s.depths, int(isect_ids.numel())
    meta = {
        "means2d": means2d,
        "radii": radii,
        "depths": depths,
        "visible": radii > 0,
        "num_intersections": n_isect,
        "backend": backend,
        "width": width,
        "height": height,
    }
    return rgb, depth, alpha, meta


def _rasterize_cpp(gaussians: Gaussians, viewmat, K, width, height, sh_degree, bg, cfg: RasterConfig, absgrad):
    """The compiled pipeline: fused projection + shading, counting-sort binning, compositing.

    Works on all N Gaussians (culled ones have radius 0 and zero opacity and are in no
    tile list), so no gathers/scatters and their autograd records are needed.
    """
    from nimbus.render import composite_cpp

    means2d, conics, colors, opacities, depths, radii = composite_cpp.project_and_shade(
        gaussians.means, gaussians.quats, gaussians.log_scales, gaussians.opacity_logits, gaussians.sh_dc,
        gaussians.sh_rest, viewmat, K, width, height, sh_degree, cfg.projection)
    if means2d.requires_grad:
        means2d.retain_grad()
    isect_ids, tile_offsets = composite_cpp.bin_gaussians(means2d, radii, depths, width, height, cfg.tile_size)
    rgb, depth, alpha = composite_cpp.composite(means2d, conics, colors, opacities, depths, isect_ids, tile_offsets,
                                                width, height, cfg.tile_size, bg, absgrad=absgrad)
    return rgb, depth, alpha, means2d, radii, depths, int(isect_ids.numel())


def means2d_grad(meta: dict) -> Tensor | None:
    """The screen-space mean gradient [N, 2] after backward (pixel units), whatever the backend."""
    g = meta["means2d"].grad
    return None if g is None else g.reshape(-1, 2)


# --------------------------------------------------------------------------------------
# Backend selection
# --------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=1)
def cpp_available() -> bool:
    """Whether the C++ compositing kernel can be imported and built/loaded (cached per process)."""
    try:
        from nimbus.render import composite_cpp
    except ImportError:
        return False
    try:
        return bool(composite_cpp.available())
    except NimbusError:  # NIMBUS_CPU_ISA names a clone this CPU cannot run: forcing it must not fall back
        raise
    except Exception:  # a failed build must fall back, never break rendering
        return False


@functools.lru_cache(maxsize=1)
def gsplat_available() -> bool:
    """Whether gsplat imports and CUDA is usable."""
    if not torch.cuda.is_available():
        return False
    try:
        import gsplat  # noqa: F401
    except Exception:
        return False
    return True


def _resolve_backend(backend: str, device: torch.device) -> str:
    if backend not in BACKENDS:
        raise NimbusError(f"unknown rasterizer backend {backend!r}; choose one of {', '.join(BACKENDS)}")
    on_cuda = device.type == "cuda"
    if backend == "auto":
        if on_cuda and gsplat_available():
            return "gsplat"
        if not on_cuda and cpp_available():
            return "cpp"
        return "torch"
    if backend == "gsplat" and not (on_cuda and gsplat_available()):
        raise NimbusError("backend 'gsplat' needs CUDA tensors and the gsplat package; "
                          "use backend='torch' or 'auto' on this machine")
    if backend == "cpp" and (on_cuda or not cpp_available()):
        raise NimbusError("backend 'cpp' needs CPU tensors and a working C++ compositing kernel "
                          "(nimbus.render.composite_cpp, built with a C++ compiler and ninja); "
                          "use backend='torch' or 'auto'")
    return backend


def _rasterize_gsplat(gaussians: Gaussians, viewmat, K, width, height, sh_degree, bg, cfg: RasterConfig):
    """gsplat.rasterization with our parameterisation (scales and opacities activated, SH as colours).

    Differences from the torch path: gsplat 1.5.x clamps alpha at 0.999 (0.99 here), and
    gsplat >= 1.5 bins with opacity-aware radii, so its ``radii`` (and, rarely, which faint
    Gaussians are visible) differ from the 3-sigma radii here.
    """
    import gsplat

    pc = cfg.projection
    render, alphas, info = gsplat.rasterization(
        means=gaussians.means,
        quats=gaussians.quats,
        scales=torch.exp(gaussians.log_scales),
        opacities=torch.sigmoid(gaussians.opacity_logits),
        colors=gaussians.sh,
        viewmats=viewmat[None],
        Ks=K[None],
        width=width,
        height=height,
        near_plane=pc.near,
        far_plane=pc.far,
        eps2d=pc.eps2d,
        sh_degree=sh_degree,
        packed=False,
        tile_size=cfg.tile_size,
        backgrounds=bg[None],
        render_mode="RGB+D",
        rasterize_mode="classic",
    )
    means2d = info["means2d"]  # [1, N, 2]
    if means2d.requires_grad:
        means2d.retain_grad()
    radii = info["radii"][0]
    if radii.ndim == 2:  # gsplat >= 1.5: per-axis radii [N, 2], visible when both are positive
        visible = (radii > 0).all(dim=-1)
        radii = torch.where(visible, radii.max(dim=-1).values, torch.zeros_like(radii[:, 0]))
    else:
        visible = radii > 0
    isect = info.get("isect_ids")
    meta = {
        "means2d": means2d,
        "radii": radii.to(torch.int32),
        "depths": info["depths"][0],
        "visible": visible,
        "num_intersections": int(isect.numel()) if isect is not None else -1,
        "backend": "gsplat",
        "width": width,
        "height": height,
    }
    return render[0, :, :, :3], render[0, :, :, 3], alphas[0, :, :, 0], meta
