"""The "gsplat" backend: gsplat's CUDA rasterizer with our parameterisation.

Scales and opacities are activated and the SH coefficients passed as colours.  Differences
from the torch backend: gsplat 1.5.x clamps alpha at 0.999 (0.99 here), and gsplat >= 1.5
bins with opacity-aware radii, so its ``radii`` (and, rarely, which faint Gaussians are
visible) differ from the 3-sigma radii here.  ``absgrad`` is refused: gsplat's own
statistic is not accumulated into the caller's tensor.
"""

from __future__ import annotations

import functools
import importlib

import torch

from nimbus.render.backends.base import Backend, make_meta
from nimbus.render.gaussians import Gaussians


@functools.lru_cache(maxsize=1)
def package_available() -> bool:
    """Whether gsplat imports, its CUDA extension loads, and CUDA is usable (cached per process).

    gsplat loads (JIT-builds, the first time) its CUDA extension lazily, at its first rasterization;
    it is loaded here instead, so that a build that fails makes ``auto`` fall back to torch before
    training rather than crash its first iteration, and so that the load is not timed as training.
    """
    if not torch.cuda.is_available():
        return False
    try:
        import gsplat  # noqa: F401
    except Exception:
        return False
    try:  # gsplat 1.x: the module that builds or loads the extension when imported
        _backend = importlib.import_module("gsplat.cuda._backend")
    except ModuleNotFoundError as e:
        # No such module: another layout, whose first rasterization loads the extension.  A module
        # that exists but cannot import (a dependency of it missing) is a failed load.
        return bool(e.name) and "gsplat.cuda._backend".startswith(e.name)
    except Exception:  # noqa: BLE001 - a failed build or load raises whatever the compiler's wrapper raises,
        # ImportError for a built .so that is gone (seen when several processes built it at once)
        return False
    return getattr(_backend, "_C", True) is not None  # None: gsplat could not build or load it


def rasterize(gaussians: Gaussians, viewmat, K, width, height, sh_degree, background, config, absgrad):
    """The :class:`~nimbus.render.backends.base.Backend` call of this backend (see there)."""
    import gsplat

    pc = config.projection
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
        tile_size=config.tile_size,
        backgrounds=background[None],
        render_mode="RGB+D",
        rasterize_mode="classic",
    )
    radii = info["radii"][0]
    if radii.ndim == 2:  # gsplat >= 1.5: per-axis radii [N, 2], visible when both are positive
        visible = (radii > 0).all(dim=-1)
        radii = torch.where(visible, radii.max(dim=-1).values, torch.zeros_like(radii[:, 0]))
    else:
        visible = radii > 0
    isect = info.get("isect_ids")
    meta = make_meta(first_camera(info["means2d"]), radii, info["depths"][0],
                     isect.numel() if isect is not None else -1, "gsplat", width, height, visible=visible)
    return render[0, :, :, :3], render[0, :, :, 3], alphas[0, :, :, 0], meta


def first_camera(means2d: torch.Tensor) -> torch.Tensor:
    """gsplat's ``means2d`` [1, N, 2] as the [N, 2] of every backend, with its ``.grad`` filled by backward.

    The [N, 2] view is not what gsplat's rasterizer consumes, so its gradient is copied from
    the [1, N, 2] tensor's by a hook (added up over backward passes, as a retained gradient is).
    """
    flat = means2d[0]
    if means2d.requires_grad:
        flat.retain_grad()  # marks the view as keeping .grad (reading it then does not warn)

        def keep(grad: torch.Tensor) -> None:
            flat.grad = grad[0] if flat.grad is None else flat.grad + grad[0]

        means2d.register_hook(keep)
    return flat


def _available(device) -> bool:
    return device.type == "cuda" and package_available()


BACKEND = Backend(name="gsplat", rasterize=rasterize, available=_available, auto_rank=2,
                  needs="CUDA tensors and the gsplat package")
