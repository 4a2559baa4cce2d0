"""Where random starting points go for a scene without sparse points: the cameras' focus, or their frusta."""

from __future__ import annotations

import math

import numpy as np
import pytest

from nimbus.data.builtin import get_scene
from nimbus.data.camera import Camera
from nimbus.data.camera_focus import (RandomInitConfig, camera_focus, optical_axes, plan_random_points,
                                      sample_random_points)
from nimbus.data.scene import Scene, View
from nimbus.render.gaussians import GaussianInitConfig, init_from_scene

UP = (0.0, 0.0, 1.0)


def orbit(focus, radius=3.0, height=1.2, n=24, jitter=0.0, seed=0, arc_deg=360.0):
    """Cameras on a (partial) circle about ``focus``, ``height`` above it, looking at it (targets jittered)."""
    rng = np.random.default_rng(seed)
    focus = np.asarray(focus, np.float64)
    cams = []
    for i in range(n):
        a = math.radians(arc_deg) * i / (n if arc_deg >= 360 else n - 1)
        eye = focus + [radius * math.cos(a), radius * math.sin(a), height]
        cams.append(Camera.look_at(eye, focus + rng.normal(0, jitter, 3), UP, 64, 48, 60.0))
    return cams


def grid(n_x=5, n_z=3, width=2.0, height=0.8, look=(0.0, 40.0, 1.6), parallel=False):
    """An LLFF-style grid at y = 0 looking down +y: at one point ``look`` ahead, or all parallel."""
    cams = []
    for i in range(n_x):
        for j in range(n_z):
            eye = np.array([(i / (n_x - 1) - 0.5) * width, 0.0, 1.6 + (j / (n_z - 1) - 0.5) * height])
            target = eye + [0.0, 40.0, 0.0] if parallel else np.asarray(look)
            cams.append(Camera.look_at(eye, target, UP, 64, 48, 60.0))
    return cams


def test_focus_of_orbit_cameras_matches_the_truth_and_a_plain_least_squares():
    truth = np.array([1.0, -2.0, 0.5])
    exact = camera_focus(*optical_axes(orbit(truth)))
    np.testing.assert_allclose(exact.point, truth, atol=1e-9)
    assert exact.front_fraction == 1.0 and exact.median_distance == pytest.approx(math.hypot(3.0, 1.2))
    assert exact.axis_spread_deg > 40  # a full orbit: the axes point every way round

    # Noisy aims: the closed form equals the least-squares point of the stacked point-to-line residuals
    # (I - d d^T)(p - c), solved independently by SVD, and stays near the truth.
    cams = orbit(truth, jitter=0.05, seed=3)
    centers, dirs = optical_axes(cams)
    noisy = camera_focus(centers, dirs)
    proj = np.eye(3)[None] - dirs[:, :, None] * dirs[:, None, :]
    ref = np.linalg.lstsq(proj.reshape(-1, 3), np.einsum("nij,nj->ni", proj, centers).reshape(-1), rcond=None)[0]
    np.testing.assert_allclose(noisy.point, ref, atol=1e-9)
    assert np.linalg.norm(noisy.point - truth) < 0.05

    # A 40-degree arc (a turntable seen from one side) still pins the focus down.
    arc = camera_focus(*optical_axes(orbit(truth, n=9, arc_deg=40.0, jitter=0.01, seed=1)))
    assert np.linalg.norm(arc.point - truth) < 0.1 and arc.axis_spread_deg > RandomInitConfig().min_axis_spread_deg


def test_orbit_plan_is_a_ball_about_the_focus_not_the_camera_centroid():
    truth = np.array([0.0, 0.0, 0.6])
    cams = orbit(truth, radius=4.0, height=1.2)
    plan = plan_random_points(cams)
    assert plan.kind == "focus"
    assert plan.radius == pytest.approx(0.5 * math.hypot(4.0, 1.2))
    pts, cols = sample_random_points(plan, cams, 4000, seed=0)
    assert pts.shape == (4000, 3) and cols.shape == (4000, 3) and 0 <= cols.min() and cols.max() <= 1
    dist = np.linalg.norm(pts - truth, axis=1)
    assert dist.max() <= plan.radius + 1e-9
    assert np.mean(dist < 0.5 * plan.radius) == pytest.approx(1 / 8, abs=0.03)  # uniform in the volume
    np.testing.assert_allclose(pts.mean(0), truth, atol=0.1)
    centroid = np.mean([c.center for c in cams], axis=0)
    assert np.linalg.norm(centroid - truth) == pytest.approx(1.2)  # what the old cube was centred on
    # The same seed gives the same points; another seed others.
    np.testing.assert_array_equal(sample_random_points(plan, cams, 4000, seed=0)[0], pts)
    assert not np.array_equal(sample_random_points(plan, cams, 4000, seed=1)[0], pts)


@pytest.mark.parametrize("parallel", [True, False])
def test_forward_facing_grid_falls_back_to_the_view_frusta(parallel):
    cams = grid(parallel=parallel)
    focus = camera_focus(*optical_axes(cams))
    if parallel:
        assert focus.point is None and focus.axis_spread_deg == pytest.approx(0.0, abs=1e-6)
    else:  # converging on a point 40 m ahead: solvable, but the axes spread by about a degree
        assert focus.axis_spread_deg < 2.0
    plan = plan_random_points(cams)
    assert plan.kind == "forward" and "nearly parallel" in plan.reason
    spread = np.max(np.linalg.norm(np.stack([c.center for c in cams]) - np.mean([c.center for c in cams], 0), axis=1))
    half_fov_y = math.atan(24 / cams[0].fy)  # the narrower half-angle of a 64 x 48 image
    assert plan.near == pytest.approx(spread / math.tan(half_fov_y))
    assert plan.far == pytest.approx(100 * plan.near)
    pts, _ = sample_random_points(plan, cams, 3000, seed=0)
    # Every point lies in the frustum of some camera, between near and far, ahead of the grid (+y) ...
    z = np.stack([c.project(pts)[1] for c in cams])
    uv = np.stack([c.project(pts)[0] for c in cams])
    inside = (z >= plan.near * (1 - 1e-9)) & (z <= plan.far * (1 + 1e-9)) & (uv[..., 0] >= -1e-6) & \
        (uv[..., 0] <= 64 + 1e-6) & (uv[..., 1] >= -1e-6) & (uv[..., 1] <= 48 + 1e-6)
    assert inside.any(0).all()
    assert (pts[:, 1] > 0).all()
    # ... with inverse depth uniform: half the points nearer than the harmonic midpoint.
    mid = 2 / (1 / plan.near + 1 / plan.far)
    assert np.mean(pts[:, 1] < mid) == pytest.approx(0.5, abs=0.05)


def test_outward_ring_is_not_mistaken_for_an_inward_focus():
    cams = []
    for i in range(12):
        a = 2 * math.pi * i / 12
        eye = np.array([math.cos(a), math.sin(a), 0.0])
        cams.append(Camera.look_at(eye, 3 * eye, UP, 64, 48, 60.0))
    focus = camera_focus(*optical_axes(cams))
    np.testing.assert_allclose(focus.point, 0.0, atol=1e-9)  # the axes meet at the ring's centre, behind them all
    assert focus.front_fraction == 0.0
    plan = plan_random_points(cams)
    assert plan.kind == "forward" and "in front of only 0%" in plan.reason


def test_points_less_builtin_garden_gets_points_about_the_table():
    cfg = get_scene("garden").config
    cams = cfg.cameras(16, 64, 48, seed=0)
    scene = Scene(tuple(View(f"{i:03d}.png", c) for i, c in enumerate(cams)), frozenset({"000.png"}))
    g = init_from_scene(scene, GaussianInitConfig(random_points=3000, sh_degree=0))
    means = g.means.double().numpy()
    target = np.asarray(cfg.target)  # the table the orbit looks at
    centroid = scene.camera_centers.mean(0)
    middle = np.median(means, axis=0)
    assert np.linalg.norm(middle - target) < 0.15
    assert np.linalg.norm(middle - centroid) > 1.0  # the old cube's centre: among the cameras, 1.2 m above it
    # With points, the points are used as they are.
    pts = np.random.default_rng(0).normal(size=(30, 3))
    with_points = Scene(scene.views, scene.test_names, pts, np.zeros((30, 3), np.uint8))
    np.testing.assert_allclose(init_from_scene(with_points).means.double().numpy(), pts, atol=1e-6)
