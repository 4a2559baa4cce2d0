"""The plane sweep (nimbus.data.sweep) on a textured plane seen by cameras at known poses."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from nimbus.data.camera import Camera
from nimbus.data.sweep import SweepConfig, neighbour_views, sweep_depths
from nimbus.errors import NimbusError

W, H, F = 96, 72, 80.0
PLANE_Z = 6.0


def _texture(seed: int = 0, size: int = 512) -> np.ndarray:
    rng = np.random.default_rng(seed)
    tex = cv2.GaussianBlur(rng.random((size, size, 3)).astype(np.float32), (0, 0), 2.0)
    return (tex - tex.min()) / (tex.max() - tex.min())


def _view_of_plane(tex: np.ndarray, x: float) -> tuple[Camera, np.ndarray]:
    """A camera at (x, 0, 0) looking down +z at the plane z = PLANE_Z, whose texture spans [-4, 4]^2, and its image
    (each pixel centre's ray meets the plane; bilinear texture lookup)."""
    cam = Camera(W, H, F, F, W / 2, H / 2, np.eye(3), np.array([-x, 0.0, 0.0]))
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    wx = x + (u - cam.cx) / F * PLANE_Z
    wy = (v - cam.cy) / F * PLANE_Z
    size = tex.shape[0]
    mx = ((wx + 4) / 8 * size - 0.5).astype(np.float32)
    my = ((wy + 4) / 8 * size - 0.5).astype(np.float32)
    return cam, cv2.remap(tex, mx, my, cv2.INTER_LINEAR)


@pytest.fixture(scope="module")
def plane_views():
    tex = _texture()
    views = [_view_of_plane(tex, x) for x in (-0.6, -0.3, 0.0, 0.3, 0.6)]
    return [c for c, _ in views], [i for _, i in views]


def _pixels(n: int = 200, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.uniform([8, 8], [W - 8, H - 8], (n, 2))


def test_sweep_measures_the_plane_depth(plane_views):
    cams, imgs = plane_views
    z = sweep_depths(cams, imgs, 2, _pixels(), near=1.0, far=100.0)
    measured = np.isfinite(z)
    assert measured.mean() > 0.8
    assert np.median(np.abs(z[measured] / PLANE_Z - 1)) < 0.02 and np.all(np.abs(z[measured] / PLANE_Z - 1) < 0.1)


def test_sweep_refuses_to_guess_on_a_flat_image_or_without_neighbours(plane_views):
    cams, imgs = plane_views
    flat = [np.full_like(i, 0.5) for i in imgs]
    assert np.isnan(sweep_depths(cams, flat, 2, _pixels(), 1.0, 100.0)).all()  # no texture: nothing measured
    # One neighbour is not enough to trust a depth.
    assert np.isnan(sweep_depths(cams[1:3], imgs[1:3], 1, _pixels(), 1.0, 100.0)).all()
    # Unrelated images (another texture per view): no depth matches, so nothing is measured.
    noise = [_view_of_plane(_texture(seed), x)[1] for seed, x in zip(range(10, 15), (-0.6, -0.3, 0.0, 0.3, 0.6))]
    assert np.isfinite(sweep_depths(cams, noise, 2, _pixels(), 1.0, 100.0)).mean() < 0.05


def test_sweep_ignores_neighbours_facing_elsewhere(plane_views):
    cams, _ = plane_views
    turned = cams[3].with_pose(cv2.Rodrigues(np.array([0.0, np.pi / 2, 0.0]))[0], cams[3].t)
    order = neighbour_views([*cams[:3], turned, cams[4]], 2, 4, 60.0)
    assert order == [1, 0, 4]  # nearest first; the turned camera (index 3) is skipped


@pytest.mark.parametrize("kwargs, message", [
    ({"near": 0.0, "far": 10.0}, "0 < near < far"),
    ({"near": 5.0, "far": 5.0}, "0 < near < far"),
    ({"near": 1.0, "far": float("inf")}, "0 < near < far"),
])
def test_bad_sweep_range_is_a_clear_error(plane_views, kwargs, message):
    cams, imgs = plane_views
    with pytest.raises(NimbusError, match=message):
        sweep_depths(cams, imgs, 2, _pixels(5), **kwargs)


@pytest.mark.parametrize("field, value", [("steps", 1), ("neighbours", 1), ("patch", 0), ("max_cost", 0.0),
                                          ("max_axis_angle", 0.0), ("margin", -0.1)])
def test_bad_sweep_config_is_a_clear_error(field, value):
    with pytest.raises(NimbusError, match="sweep"):
        SweepConfig(**{field: value})
