"""What every rasterizer backend is: a :class:`Backend` record, and the ``meta`` dict all of them return."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor


@dataclass(frozen=True)
class Backend:
    """A rasterizer backend, as registered in :data:`nimbus.render.backends.REGISTRY`.

    Attributes
    ----------
    name : str
        The name ``rasterize(backend=...)`` takes.
    rasterize : callable
        ``rasterize(gaussians, viewmat, K, width, height, sh_degree, background, config, absgrad)
        -> (rgb [H, W, 3], depth [H, W], alpha [H, W], meta)`` with the arguments already
        checked by :func:`nimbus.render.rasterize` (``viewmat`` [4, 4], ``K`` [3, 3] and
        ``background`` [3] on the Gaussians' device and dtype; ``absgrad`` None unless
        :attr:`absgrad`) and ``meta`` made by :func:`make_meta`.
    available : callable
        ``available(device) -> bool``: whether it can render tensors on this ``torch.device``
        here (cheap after the first call).
    needs : str
        What it needs, for the error when it is asked for where it cannot run.
    absgrad : bool
        Whether it collects the absgrad densification statistic (others refuse it by name).
    auto_rank : int or None
        Preference of ``backend="auto"``: the available backend with the highest rank is
        used; None: never picked by "auto".
    """

    name: str
    rasterize: Callable
    available: Callable
    needs: str = ""
    absgrad: bool = False
    auto_rank: int | None = None


def make_meta(means2d: Tensor, radii: Tensor, depths: Tensor, num_intersections: int, backend: str, width: int,
              height: int, visible: Tensor | None = None, row_scale=None) -> dict:
    """The ``meta`` dict of :func:`nimbus.render.rasterize`, the same keys and shapes for every backend.

    Parameters
    ----------
    means2d : Tensor [N, 2]
        Pixel-space centres of all N Gaussians (culled ones included); backward must fill
        its ``.grad`` (``retain_grad()`` on it, or set it from a hook).
    radii : Tensor [N]
        Screen radius in pixels (stored as int32), 0 where culled.
    depths : Tensor [N]
        Camera z.
    num_intersections : int
        Gaussian-tile pairs composited (-1 when the backend does not say).
    backend : str
        The backend used.
    width, height : int
        Image size.
    visible : Tensor [N] bool, optional
        Which Gaussians were drawn; default ``radii > 0``.
    row_scale : nimbus.kernels.raster.RowScale, optional
        Where the backend can fold per-Gaussian factors into the parameters' gradients (set its
        ``weights`` before ``backward``); None where it cannot.
    """
    return {"means2d": means2d, "radii": radii.to(torch.int32), "depths": depths,
            "visible": radii > 0 if visible is None else visible, "num_intersections": int(num_intersections),
            "backend": backend, "width": width, "height": height, "row_scale": row_scale}
