"""The "cpp" backend: the torch backend's mathematics in compiled CPU kernels (:mod:`nimbus.kernels.raster`).

Projection + SH + sigmoid fused into one op with a hand-written backward, binning by a
counting sort, and the C++ compositor, all over the N Gaussians (culled ones have radius
0 and zero opacity and are in no tile list), so a render is a handful of ops instead of
~100 small torch ops and their autograd records, with no gathers or scatters.  A camera
whose ``viewmat``/``K`` need gradients takes the torch projection with the C++
compositor.  The only backend that collects ``absgrad`` (with a fixed camera), and the only one
whose ``meta["row_scale"]`` folds per-Gaussian gradient factors into its backward (with a fixed camera).
"""

from __future__ import annotations

import functools

from nimbus.errors import NimbusError
from nimbus.render.backends import torch as torch_backend
from nimbus.render.backends.base import Backend, make_meta
from nimbus.render.gaussians import Gaussians


@functools.lru_cache(maxsize=1)
def kernel_available() -> bool:
    """Whether the compiled kernels can be imported and built/loaded (cached per process)."""
    try:
        from nimbus.kernels import raster
    except ImportError:
        return False
    try:
        return bool(raster.available())
    except NimbusError:  # NIMBUS_CPU_ISA names a clone this CPU cannot run: forcing it must not fall back
        raise
    except Exception:  # a failed build must fall back, never break rendering
        return False


def rasterize(gaussians: Gaussians, viewmat, K, width, height, sh_degree, background, config, absgrad):
    """The :class:`~nimbus.render.backends.base.Backend` call of this backend (see there)."""
    from nimbus.kernels import raster

    if viewmat.requires_grad or K.requires_grad:  # the compiled projection does not differentiate the camera
        if absgrad is not None:
            raise NimbusError("absgrad is only collected by backend 'cpp' with a fixed camera (viewmat and K "
                              "without gradients); leave absgrad unset")
        s, args = torch_backend.project_and_bin(gaussians, viewmat, K, width, height, sh_degree, config)
        rgb, depth, alpha = raster.composite(*args, background)
        return rgb, depth, alpha, make_meta(s.means2d, s.radii, s.depths, args[5].numel(), "cpp", width, height)
    row_scale = raster.RowScale()
    means2d, conics, colors, opacities, depths, radii = raster.project_and_shade(
        gaussians.means, gaussians.quats, gaussians.log_scales, gaussians.opacity_logits, gaussians.sh_dc,
        gaussians.sh_rest, viewmat, K, width, height, sh_degree, config.projection, row_scale)
    if means2d.requires_grad:
        means2d.retain_grad()
    isect_ids, tile_offsets = raster.bin_gaussians(means2d, radii, depths, width, height, config.tile_size)
    rgb, depth, alpha = raster.composite(means2d, conics, colors, opacities, depths, isect_ids, tile_offsets,
                                         width, height, config.tile_size, background, absgrad=absgrad)
    return rgb, depth, alpha, make_meta(means2d, radii, depths, isect_ids.numel(), "cpp", width, height,
                                        row_scale=row_scale)


def _available(device) -> bool:
    return device.type == "cpu" and kernel_available()


BACKEND = Backend(name="cpp", rasterize=rasterize, available=_available, absgrad=True, auto_rank=1,
                  needs="CPU tensors and a working C++ compositing kernel (nimbus.kernels.raster, built with a "
                        "C++ compiler and ninja)")
