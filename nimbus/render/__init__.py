"""Differentiable Gaussian-splatting rasterizer (CPU-first; torch, C++ or gsplat backends, :mod:`nimbus.render.backends`).

Public entry points: :class:`Gaussians` and its initialisers, :func:`rasterize`.
"""

from nimbus.render.gaussians import (
    GaussianInitConfig,
    Gaussians,
    init_from_points,
    init_from_scene,
    random_init_plan,
)
from nimbus.render.backends import BACKENDS
from nimbus.render.rasterize import RasterConfig, means2d_grad, rasterize

__all__ = [
    "BACKENDS",
    "GaussianInitConfig",
    "Gaussians",
    "RasterConfig",
    "init_from_points",
    "init_from_scene",
    "random_init_plan",
    "means2d_grad",
    "rasterize",
]
