"""The public rasterizer: Gaussians + camera -> RGB, expected depth, alpha and per-Gaussian meta.

:func:`rasterize` checks its arguments and hands them to a backend of
:mod:`nimbus.render.backends` ("torch": the reference pipeline in torch ops; "cpp": the same
mathematics in compiled CPU kernels; "gsplat": gsplat's CUDA rasterizer), each with the same
signature and the same ``meta``.

Everything runs on the device of the Gaussian parameters.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor

from nimbus.errors import NimbusError
from nimbus.render import backends
from nimbus.render.composite_torch import CompositeConfig
from nimbus.render.gaussians import Gaussians
from nimbus.render.projection import ProjectionConfig


#: Bytes per pixel of a tile in the compiled kernel's scratch, one scratch per thread: the forward keeps five
#: float sums, a count and a flag, the backward seven sums and a count (``csrc/composite.cpp``).
TILE_SCRATCH_BYTES_PER_PIXEL = 32
#: About how many bytes one rendered frame takes per pixel besides the tiles: rgb, depth, alpha, final
#: transmittance and contributor count (float32 / int32), and their copies on the way to an image.
FRAME_BYTES_PER_PIXEL = 64


def tile_buffer_bytes(tile_size: int, backend: str, threads: int, composite: "CompositeConfig | None" = None) -> float:
    """About how many bytes a backend's per-tile working buffers take at ``tile_size``: the torch compositor's
    largest block (:meth:`CompositeConfig.block_bytes`), else the compiled kernel's scratch on ``threads`` threads."""
    if backend == "torch":
        return (composite or CompositeConfig()).block_bytes(tile_size)
    return float(tile_size) ** 2 * TILE_SCRATCH_BYTES_PER_PIXEL * threads


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
    backend : str
        One of :data:`nimbus.render.backends.BACKENDS` ("auto", "torch", "cpp", "gsplat").
        "auto" picks gsplat for CUDA tensors when gsplat imports, else the C++ kernel when
        it builds/loads (CPU tensors), else torch.
    config : RasterConfig, optional
    absgrad : Tensor [N, 2], optional
        The backward ADDS to it, per Gaussian and axis, the sum over pixels of
        ``|d loss / d means2d|`` (gsplat's "absgrad" densification statistic).  Collected
        by the backends whose ``Backend.absgrad`` is set ("cpp", with a fixed camera);
        the others refuse it.

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
        (zero rows for culled Gaussians), ``radii`` [N] int32, ``depths`` [N],
        ``visible`` [N] bool,
        ``num_intersections`` int, ``backend`` (the one used), ``width``, ``height``, and ``row_scale``: a
        :class:`nimbus.kernels.raster.RowScale` whose ``weights``, set before ``backward``, multiply each
        Gaussian's parameter gradients in the backward itself ("cpp" with a fixed camera), else None.
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
    chosen = backends.resolve(backend, device)
    if absgrad is not None:
        n = len(gaussians)
        if not chosen.absgrad:
            able = [name for name in backends.REGISTRY if backends.get(name).absgrad]
            raise NimbusError(f"backend {chosen.name!r} does not collect absgrad (backends that do: "
                              f"{', '.join(able)}); use one of those or leave absgrad unset")
        if tuple(absgrad.shape) != (n, 2) or absgrad.dtype != dtype:
            raise NimbusError(f"absgrad must be a [{n}, 2] {dtype} tensor, got {tuple(absgrad.shape)} "
                              f"{absgrad.dtype}")
    return chosen.rasterize(gaussians, viewmat, K, width, height, sh_degree, bg, cfg, absgrad)


def means2d_grad(meta: dict) -> Tensor | None:
    """The screen-space mean gradient [N, 2] after backward (pixel units), whatever the backend."""
    return meta["means2d"].grad
