"""The rasterizer's compiled CPU kernels: alpha compositing, fused projection + shading, tile binning.

:func:`composite` is a drop-in replacement for :func:`nimbus.render.composite_torch.composite`
(same positional signature, rules and outputs), built from ``csrc/composite.cpp``;
:func:`project_and_shade` (projection, SH colour and opacity of all Gaussians in one op
with a hand-written backward) and :func:`bin_gaussians` (tile binning) come from
``csrc/project.cpp``.  Both files make one library, the "cpp" rasterizer backend's
(:mod:`nimbus.render.backends.cpp`), built and cached by :class:`nimbus.kernels.extension.Extension`
(build folder, ``NIMBUS_EXT_DIR``, ``NIMBUS_DISABLE_CPP``: see there).

Call :func:`available` before :func:`composite`: it builds/loads the kernel once per
process and returns False, after ONE warning line, when that is impossible (no
compiler, failed build); the caller then uses the torch compositor.

Instruction sets.  The float32 compositing tiles and the projection (both dtypes) are
compiled three times: for generic x86-64, AVX2 and AVX-512 (x86-64-v4); by default the
best clone the CPU runs is used, the same for both.  ``NIMBUS_CPU_ISA=generic|avx2|avx512``
(or :func:`set_cpu_isa`) forces one, so that every path can be tested on one machine
(``auto`` or unset: the best); :func:`cpu_isas` lists the clones this machine runs and
:func:`cpu_isa` names the one in use.  The clones run the same IEEE operations in the
same order (no FMA contraction), so they give bitwise identical results
(``tests/test_composite_cpp.py``, ``tests/test_rasterizer.py``).

Contract
--------
Pixel ``(u, v)`` has its centre at ``(u + 0.5, v + 0.5)``.  For a pixel, walk its tile's
list front to back; for Gaussian ``i`` with ``dx = u + 0.5 - mean_x`` (``dy`` alike)::

    sigma   = 0.5 * (a dx^2 + c dy^2) + b dx dy
    alpha_i = min(0.99, opacity_i * exp(-sigma))      # skipped if sigma < 0 or alpha_i < 1/255
    stop BEFORE Gaussian i if T * (1 - alpha_i) < 1e-4 (that Gaussian is excluded)
    rgb   = sum c_i alpha_i T_i + T_final * background
    depth = sum z_i alpha_i T_i                       # not normalised by alpha
    alpha = 1 - T_final

Gradients flow to means2d, conics, colors, opacities, depths and background; where
alpha is clamped at 0.99 the gradient w.r.t. opacity and sigma is zero.  Gaussians with
a non-finite mean, conic or opacity contribute nothing.  float32 and float64 are both
supported (float32 evaluates exp with a ~1 ulp polynomial, float64 with ``std::exp``).

Densification statistic ("absgrad"): pass ``absgrad=`` a zero [M, 2] tensor; the
backward adds to it, per Gaussian and axis, the sum over pixels of ``|d loss / d means2d|``
of each pixel's contribution (gsplat's absgrad).  The ordinary ``means2d.grad`` is the
signed sum.

Threads follow :func:`torch.get_num_threads`; tiles are scheduled dynamically and the
gradients are summed in a fixed order, so every output is bitwise identical for any
thread count.
"""

from __future__ import annotations

import os

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from nimbus.errors import NimbusError
from nimbus.kernels.extension import Extension

__all__ = ["available", "load_error", "composite", "project_and_shade", "bin_gaussians", "RowScale", "cpu_isa",
           "cpu_isas", "set_cpu_isa", "CPU_ISAS", "ISA_ENV", "EXTENSION"]

#: Environment variable that forces the compositing kernel's instruction-set clone.
ISA_ENV = "NIMBUS_CPU_ISA"
#: The clones, slowest first (the names ISA_ENV accepts, besides ``auto``).
CPU_ISAS = ("generic", "avx2", "avx512")

#: composite.cpp (torch.ops.nimbus_composite) and project.cpp (torch.ops.nimbus_project):
#: one library, one load, one availability flag for the whole "cpp" backend.
EXTENSION = Extension("nimbus_raster", ("composite.cpp", "project.cpp"), kernel="compositing kernel",
                      fallback="the slower torch compositor")

# The NIMBUS_CPU_ISA value last applied ("auto": the kernel's own default).
_isa_env = ["auto"]


def available(warn: bool = True) -> bool:
    """Whether the compiled kernel can be used; builds or loads it on the first call.

    Parameters
    ----------
    warn : bool
        On failure, emit one :class:`RuntimeWarning` per process saying why and that the
        slower torch compositor will be used.

    Returns
    -------
    bool
        False when ``NIMBUS_DISABLE_CPP=1`` or when the build/load failed (reason in
        :func:`load_error`).

    Raises
    ------
    NimbusError
        Only when ``NIMBUS_CPU_ISA`` names a clone that does not exist or that this CPU
        cannot run: forcing an instruction set must not fall back silently.
    """
    ok = EXTENSION.available(warn)
    if ok:
        _apply_isa_env()
    return ok


def load_error() -> str | None:
    """Why the kernel could not be built or loaded (one line), or None."""
    return EXTENSION.load_error()


def _require() -> None:
    if not EXTENSION.state["ok"]:
        available(warn=False)  # a first load also applies NIMBUS_CPU_ISA
    EXTENSION.require("nimbus.kernels.raster")


def cpu_isas() -> tuple[str, ...]:
    """The instruction-set clones of the compositing kernel this build has and this CPU runs, slowest first."""
    _require()
    return tuple(torch.ops.nimbus_composite.cpu_isas())


def cpu_isa() -> str:
    """The clone in use: ``"generic"``, ``"avx2"`` or ``"avx512"``."""
    _require()
    return str(torch.ops.nimbus_composite.cpu_isa())


def set_cpu_isa(name: str) -> str:
    """Force the compositing kernel's clone for this process; ``"auto"`` picks the best this CPU runs.

    Parameters
    ----------
    name : str
        ``"auto"`` or one of :data:`CPU_ISAS`.

    Returns
    -------
    str
        The clone now in use.

    Raises
    ------
    NimbusError
        An unknown name, or a clone this CPU (or this build) cannot run.
    """
    _require()
    key = str(name).strip().lower()
    if key not in ("auto",) + CPU_ISAS:
        raise NimbusError(f"{ISA_ENV}={name} is not an instruction set of the kernel; use auto, "
                          f"{', '.join(CPU_ISAS)} or leave {ISA_ENV} unset")
    runs = cpu_isas()
    if key != "auto" and key not in runs:
        raise NimbusError(f"{ISA_ENV}={name}: this CPU (or this build of the kernel) cannot run the {key} clone; "
                          f"it runs {', '.join(runs)}: pick one of those or leave {ISA_ENV} unset")
    return str(torch.ops.nimbus_composite.set_cpu_isa(key))


def _apply_isa_env() -> None:
    """Apply ``NIMBUS_CPU_ISA`` when it changed since it was last applied (cheap when it did not)."""
    want = os.environ.get(ISA_ENV, "").strip().lower() or "auto"
    if want != _isa_env[0]:
        set_cpu_isa(want)
        _isa_env[0] = want


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, colors, opacities, depths, background, isect_ids, tile_offsets,
                width, height, tile_size, absgrad):
        rgb, depth, alpha, t_final, last = torch.ops.nimbus_composite.composite_forward(
            means2d, conics, colors, opacities, depths, isect_ids, tile_offsets,
            width, height, tile_size, background)
        ctx.save_for_backward(means2d, conics, colors, opacities, depths, background, isect_ids,
                              tile_offsets, t_final, last)
        ctx.size = (width, height, tile_size)
        ctx.absgrad = absgrad
        return rgb, depth, alpha

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_rgb, grad_depth, grad_alpha):
        means2d, conics, colors, opacities, depths, background, isect_ids, tile_offsets, t_final, last = (
            ctx.saved_tensors)
        width, height, tile_size = ctx.size
        g_means, g_conics, g_colors, g_opac, g_depths, g_abs = torch.ops.nimbus_composite.composite_backward(
            means2d, conics, colors, opacities, depths, isect_ids, tile_offsets, width, height, tile_size,
            background, t_final, last, grad_rgb.contiguous(), grad_depth.contiguous(),
            grad_alpha.contiguous())
        if ctx.absgrad is not None:
            ctx.absgrad.add_(g_abs)
        g_bg = None
        if ctx.needs_input_grad[5]:
            g_bg = (grad_rgb * t_final[..., None]).sum(dim=(0, 1))
        return g_means, g_conics, g_colors, g_opac, g_depths, g_bg, None, None, None, None, None, None


def composite(
    means2d: Tensor,
    conics: Tensor,
    colors: Tensor,
    opacities: Tensor,
    depths: Tensor,
    isect_ids: Tensor,
    tile_offsets: Tensor,
    width: int,
    height: int,
    tile_size: int,
    background: Tensor,
    *,
    absgrad: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Alpha-composite tile-sorted 2D Gaussians into an image (compiled kernel; see module doc).

    Builds/loads the kernel on first use; raises RuntimeError when that is impossible
    (call :func:`available` first to fall back instead).

    Parameters
    ----------
    means2d : Tensor [M, 2]
        Pixel coordinates of the centres, pixel-corner origin.
    conics : Tensor [M, 3]
        (a, b, c) of the inverse 2D covariance, in 1 / pixel^2.
    colors : Tensor [M, 3]
        Colours (any range; typically [0, 1]).
    opacities : Tensor [M]
        Opacities in (0, 1) (after the sigmoid).
    depths : Tensor [M]
        Camera z of the Gaussians (> 0), composited into the depth output.
    isect_ids : Tensor [I] int64
        Gaussian indices grouped by tile (row-major) and front to back within a tile.
    tile_offsets : Tensor [T + 1] int64
        Tile ``t`` owns ``isect_ids[tile_offsets[t]:tile_offsets[t + 1]]``;
        ``T = ceil(width / tile_size) * ceil(height / tile_size)``.
    width, height, tile_size : int
        Image and tile size in pixels.
    background : Tensor [3]
        Colour behind all Gaussians (converted to the inputs' dtype).
    absgrad : Tensor [M, 2], optional
        Densification statistic.  When given, the backward ADDS to it, per Gaussian and
        per axis, the sum over pixels of ``|d loss / d means2d|`` of that pixel's
        contribution (gsplat's "absgrad").  Pass a zero tensor (or a running
        accumulator) of the inputs' dtype; it is filled when ``loss.backward()`` runs.

    All float tensors must share one dtype, float32 or float64, and live on the CPU.

    Returns
    -------
    rgb : Tensor [H, W, 3]
    depth : Tensor [H, W]
        Expected depth ``sum z_i alpha_i T_i`` (divide by ``alpha`` to normalise).
    alpha : Tensor [H, W]
        Accumulated opacity ``1 - T_final`` in [0, 1).
    """
    _require()
    dtype = means2d.dtype
    background = torch.as_tensor(background).to(dtype=dtype).reshape(3)
    floats = (means2d, conics, colors, opacities, depths, background)
    if dtype not in (torch.float32, torch.float64):
        raise TypeError(f"composite: float32 or float64 expected, got {dtype}")
    if any(t.dtype != dtype for t in floats) or any(t.device.type != "cpu" for t in floats):
        raise TypeError("composite: all float inputs must be CPU tensors of one dtype")
    m = means2d.shape[0]
    if absgrad is not None and (absgrad.shape != (m, 2) or absgrad.dtype != dtype):
        raise ValueError(f"composite: absgrad must be [{m}, 2] {dtype}, got {tuple(absgrad.shape)} "
                         f"{absgrad.dtype}")
    # Shapes, index ranges and offsets are checked in C++ (they guard memory accesses).
    return _Composite.apply(
        means2d.contiguous(), conics.contiguous(), colors.contiguous(), opacities.contiguous(),
        depths.contiguous(), background.contiguous(), isect_ids.contiguous(), tile_offsets.contiguous(),
        int(width), int(height), int(tile_size), absgrad)


# --------------------------------------------------------------------------------------
# Fused projection + SH shading, and tile binning (csrc/project.cpp)
# --------------------------------------------------------------------------------------
class RowScale:
    """Per-Gaussian factors for the parameter gradients of one :func:`project_and_shade` call, set between its
    forward and its backward.

    A caller that will multiply row ``i`` of every Gaussian parameter's gradient by ``w[i]`` after
    ``backward`` (NimbusGS's GGS) can set :attr:`weights` instead, before ``backward``: the projection's
    backward then writes the scaled gradients directly, the same bits as ``grad.mul_(w)`` afterwards
    (each gradient rounded to the dtype, then multiplied in the dtype), without a second pass over them.
    Exact only when this call's backward is the sole source of those gradients, and for finite factors;
    :attr:`applied` counts the backward passes that used the factors, so that the caller can tell.
    """

    __slots__ = ("weights", "applied")

    def __init__(self) -> None:
        #: ``[N]`` tensor of the Gaussians' dtype (CPU, contiguous), or None: no scaling.
        self.weights: Tensor | None = None
        self.applied = 0


class _ProjectShade(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, log_scales, opacity_logits, sh_dc, sh_rest, viewmat, K, width, height,
                sh_degree, proj, row_scale):
        args = (viewmat, K, width, height, sh_degree, proj.near, proj.far, proj.eps2d, proj.fov_clamp,
                proj.radius_sigmas)
        means2d, conics, colors, opacities, depths, radii = torch.ops.nimbus_project.project_forward(
            means, quats, log_scales, opacity_logits, sh_dc, sh_rest, *args)
        ctx.save_for_backward(means, quats, log_scales, opacity_logits, sh_dc, sh_rest, radii)
        ctx.args = args
        ctx.row_scale = row_scale
        ctx.mark_non_differentiable(radii)
        return means2d, conics, colors, opacities, depths, radii

    @staticmethod
    @once_differentiable
    def backward(ctx, g_means2d, g_conics, g_colors, g_opac, g_depths, _g_radii):
        means, quats, log_scales, opacity_logits, sh_dc, sh_rest, radii = ctx.saved_tensors
        n = means.shape[0]

        def grad(g, *shape):  # an output that did not reach the loss has no gradient
            return torch.zeros((n,) + shape, dtype=means.dtype) if g is None else g.contiguous()

        holder = ctx.row_scale
        scale = None if holder is None else holder.weights
        if scale is not None:
            if scale.shape != (n,) or scale.dtype != means.dtype or scale.device.type != "cpu":
                raise NimbusError(f"RowScale.weights must be a [{n}] CPU {means.dtype} tensor, got "
                                  f"{tuple(scale.shape)} {scale.dtype} on {scale.device}")
            holder.applied += 1
        grads = torch.ops.nimbus_project.project_backward(
            means, quats, log_scales, opacity_logits, sh_dc, sh_rest, *ctx.args, radii,
            grad(g_means2d, 2), grad(g_conics, 3), grad(g_colors, 3), grad(g_opac), grad(g_depths),
            means.new_empty(0) if scale is None else scale.contiguous())
        if ctx.args[4] == 0:  # as in the torch path, unused higher bands get no gradient at degree 0
            grads = grads[:5] + (None,)
        return tuple(grads) + (None,) * 7


def project_and_shade(means: Tensor, quats: Tensor, log_scales: Tensor, opacity_logits: Tensor, sh_dc: Tensor,
                      sh_rest: Tensor, viewmat: Tensor, K: Tensor, width: int, height: int, sh_degree: int,
                      config, row_scale: RowScale | None = None) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor,
                                                                          Tensor]:
    """Projection (:func:`nimbus.render.projection.project_gaussians`) and colour/opacity
    (:func:`nimbus.render.sh.sh_colors`, sigmoid) of N Gaussians in one compiled pass.

    Parameters
    ----------
    means [N, 3], quats [N, 4], log_scales [N, 3], opacity_logits [N], sh_dc [N, 1, 3], sh_rest [N, K, 3]
        Raw Gaussian parameters (one dtype, CPU); gradients flow to all of them.
    viewmat : Tensor [4, 4]   world-to-camera (no gradient).
    K : Tensor [3, 3]         intrinsics (no gradient).
    width, height, sh_degree : int
    config : ProjectionConfig
    row_scale : RowScale, optional
        Factors the backward multiplies the parameters' gradients by, when set before it runs.

    Returns
    -------
    means2d [N, 2], conics [N, 3], colors [N, 3], opacities [N], depths [N], radii [N] int32
        Per Gaussian, zeros where culled by depth; colours and opacities are zero where
        the radius is 0 (not drawn).  Same values as the torch path up to rounding
        (the compiled maths runs in float64).
    """
    _require()
    dtype = means.dtype
    if dtype not in (torch.float32, torch.float64):
        raise TypeError(f"project_and_shade: float32 or float64 expected, got {dtype}")
    tensors = [t.contiguous() for t in (means, quats, log_scales, opacity_logits, sh_dc, sh_rest)]
    return _ProjectShade.apply(*tensors, viewmat.detach(), K.detach(), int(width), int(height), int(sh_degree),
                               config, row_scale)


def bin_gaussians(means2d: Tensor, radii: Tensor, depths: Tensor, width: int, height: int,
                  tile_size: int) -> tuple[Tensor, Tensor]:
    """Compiled :func:`nimbus.render.binning.bin_gaussians` (same contract and output).

    ``radii`` must be int32; a counting sort by tile of the depth-ordered Gaussians
    replaces the sort of all intersections.
    """
    _require()
    return torch.ops.nimbus_project.bin_gaussians(means2d.detach().contiguous(), radii.to(torch.int32).contiguous(),
                                                  depths.detach().contiguous(), int(width), int(height),
                                                  int(tile_size))
