"""Depth sources of the synthesizer: scene maps, densified sparse points, an ONNX monocular model."""

import numpy as np
import pytest

from nimbus.data.camera import Camera
from nimbus.data.scene import Scene, View
from nimbus.errors import NimbusError
from weather_synth.depth import (
    DepthConfig,
    DepthSource,
    OnnxDepthModel,
    align_inverse_depth,
    densify_sparse_depth,
    fill_sparse,
    onnx_depth,
    visible_points,
)

W, H = 56, 42  # multiples of 14: the ONNX input needs no resizing


def camera():
    """Looking 45 degrees down at the ground plane z = 0: every pixel sees the ground."""
    return Camera.look_at((0.0, -3.0, 3.0), (0.0, 0.0, 0.0), (0, 0, 1), W, H, 60)


def backproject(cam, u, v, z):
    """World points seen at pixel centres (u + 0.5, v + 0.5) with z-depths z."""
    p = np.stack([(u + 0.5 - cam.cx) / cam.fx * z, (v + 0.5 - cam.cy) / cam.fy * z, z], -1)
    return (p - cam.t) @ cam.R


def smooth_image(seed=0):
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:H, 0:W] / max(H, W)
    img = np.stack([0.5 + 0.4 * np.sin(3 * xx + rng.uniform(0, 6)) * np.cos(2 * yy + c) for c in range(3)], -1)
    return img.astype(np.float32)


def test_visible_points_keep_the_nearest_and_drop_occluded():
    cam = camera()
    near = backproject(cam, np.array([10]), np.array([10]), np.array([2.0]))
    far_same_pixel = backproject(cam, np.array([10]), np.array([10]), np.array([6.0]))
    far_next_pixel = backproject(cam, np.array([11]), np.array([10]), np.array([6.0]))  # seen through a gap
    elsewhere = backproject(cam, np.array([40]), np.array([30]), np.array([6.0]))
    behind = np.array([cam.center - 3 * cam.R[2]])
    pts = np.concatenate([near, far_same_pixel, far_next_pixel, elsewhere, behind])
    u, v, z = visible_points(cam, pts, window=0.02, tolerance=0.1)
    assert sorted(zip(u.tolist(), v.tolist(), np.round(z, 6).tolist())) == [(10, 10, 2.0), (40, 30, 6.0)]


def test_fill_sparse_fills_every_pixel_and_keeps_known_values():
    vals = np.zeros((H, W), np.float32)
    wts = np.zeros((H, W), np.float32)
    vals[5, 5], vals[30, 40] = 1.0, 3.0
    wts[5, 5] = wts[30, 40] = 1
    out = fill_sparse(vals, wts)
    assert out[5, 5] == 1.0 and out[30, 40] == 3.0
    assert np.isfinite(out).all() and out.min() >= 1.0 - 1e-6 and out.max() <= 3.0 + 1e-6


def test_sparse_points_are_densified_to_the_plane_they_sample():
    cam = camera()
    rng = np.random.default_rng(1)
    u, v = rng.integers(0, W, 250), rng.integers(0, H, 250)
    # The ground plane z = 0 (world): exact z-depth per pixel.
    d, o = cam.world_rays(np.float64)
    s = -o[2] / d[..., 2]
    true_z = (s * (d @ cam.R[2])).astype(np.float32)
    pts = backproject(cam, u, v, true_z[v, u])
    depth, info = densify_sparse_depth(cam, pts, smooth_image(), DepthConfig())
    assert info["sparse_points"] > 150
    rel = np.abs(depth - true_z) / true_z
    assert true_z.min() > 0
    assert np.median(rel) < 0.03 and np.quantile(rel, 0.9) < 0.1
    with pytest.raises(NimbusError, match="sees only 3 sparse points"):
        densify_sparse_depth(cam, pts[:3], None, DepthConfig(), name="v")


def test_robust_alignment_recovers_scale_and_shift_despite_outliers():
    rng = np.random.default_rng(2)
    mono = rng.uniform(0, 1, 400)
    target = 0.7 * mono + 0.2
    for method in ("mad", "huber"):
        s, c = align_inverse_depth(mono, target, method)
        assert (s, c) == (pytest.approx(0.7, rel=1e-9), pytest.approx(0.2, rel=1e-9))
    noisy = target + rng.normal(0, 0.002, 400)
    noisy[:60] = rng.uniform(0, 3, 60)  # 15 % gross outliers
    s, c = align_inverse_depth(mono, noisy, "huber")
    assert abs(s - 0.7) < 0.01 and abs(c - 0.2) < 0.01
    with pytest.raises(NimbusError, match="constant"):
        align_inverse_depth(np.ones(10), np.arange(10.0))


def build_onnx_model(path):
    """A stand-in monocular model: relative inverse depth = 1 / (4 + mean over channels of the normalised input)."""
    import onnx
    from onnx import TensorProto, helper

    x = helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 3, "h", "w"])
    y = helper.make_tensor_value_info("inverse_depth", TensorProto.FLOAT, [1, 1, "h", "w"])
    four = helper.make_tensor("four", TensorProto.FLOAT, [], [4.0])
    nodes = [
        helper.make_node("ReduceMean", ["image"], ["m"], axes=[1], keepdims=1),
        helper.make_node("Add", ["m", "four"], ["a"]),
        helper.make_node("Reciprocal", ["a"], ["inverse_depth"]),
    ]
    graph = helper.make_graph(nodes, "mono", [x], [y], initializer=[four])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


def test_onnx_model_is_run_and_aligned_to_the_sparse_points(tmp_path):
    path = build_onnx_model(tmp_path / "mono.onnx")
    cam, img = camera(), smooth_image(3)
    model = OnnxDepthModel(path, input_size=H)
    assert model.input_resolution(W, H) == (W, H)
    expected_mono = 1 / (4 + ((img - [0.485, 0.456, 0.406]) / [0.229, 0.224, 0.225]).mean(-1))
    np.testing.assert_allclose(model(img), expected_mono, rtol=1e-5)
    scale, shift = 0.3, 0.05  # the truth: inverse depth = 0.3 * mono + 0.05
    rng = np.random.default_rng(4)
    u, v = rng.integers(0, W, 120), rng.integers(0, H, 120)
    z = 1 / (scale * expected_mono[v, u] + shift)
    cfg = DepthConfig(source=f"onnx:{path}", input_size=H, occlusion_tolerance=10.0)
    depth, info = onnx_depth(model, cam, img, backproject(cam, u, v, z), cfg)
    assert info["align_scale"] == pytest.approx(scale, rel=1e-4)
    assert info["align_shift"] == pytest.approx(shift, rel=1e-3, abs=1e-6)
    np.testing.assert_allclose(depth, 1 / (scale * expected_mono + shift), rtol=1e-4)
    # Through the depth source of a scene (what --depth onnx:MODEL uses); sizes that are not
    # multiples of 14 are resized for the model and back.
    pts = backproject(cam, u, v, z)
    scene = Scene((View("a.png", cam, image=img),), points=pts, colors=np.zeros_like(pts, np.uint8))
    d2, info2 = DepthSource(scene, cfg)(scene.views[0])
    np.testing.assert_allclose(d2, depth)
    assert DepthSource(scene, cfg).describe()["model_sha256"]
    wide = OnnxDepthModel(path, input_size=518)
    assert all(s % 14 == 0 for s in wide.input_resolution(W, H))
    assert wide(img).shape == (H, W)


def test_depth_source_errors_name_the_fix(tmp_path):
    cam = camera()
    no_depth = Scene((View("a.png", cam, image=smooth_image()),))
    with pytest.raises(NimbusError, match="no depth map.*--depth sparse"):
        DepthSource(no_depth, DepthConfig("scene"))
    with pytest.raises(NimbusError, match="needs the scene's sparse points"):
        DepthSource(no_depth, DepthConfig("sparse"))
    pts = np.random.default_rng(0).normal(size=(50, 3))
    with_points = Scene((View("a.png", cam, image=smooth_image()),), points=pts, colors=np.zeros((50, 3), np.uint8))
    with pytest.raises(NimbusError, match="does not exist"):
        DepthSource(with_points, DepthConfig(f"onnx:{tmp_path / 'missing.onnx'}"))
    (tmp_path / "junk.onnx").write_bytes(b"not a model")
    with pytest.raises(NimbusError, match="could not be loaded"):
        DepthSource(with_points, DepthConfig(f"onnx:{tmp_path / 'junk.onnx'}"))
    with pytest.raises(NimbusError, match="unknown depth source"):
        DepthConfig("lidar")


def test_sky_backdrop_is_infinitely_far():
    cam = camera()
    mask = np.zeros((H, W), bool)
    mask[:10] = True
    scene = Scene((View("a.png", cam, image=smooth_image(), depth=np.full((H, W), 3.0, np.float32), sky=mask),))
    d, _ = DepthSource(scene, DepthConfig("scene"))(scene.views[0])
    assert np.all(np.isinf(d[:10])) and np.all(d[10:] == 3.0)
    d, _ = DepthSource(scene, DepthConfig("scene", backdrop_at_infinity=False))(scene.views[0])
    assert np.all(d == 3.0)
