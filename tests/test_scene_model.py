"""The scene model's conventions: camera maths, splits, extent, atomic writes and image IO."""

import numpy as np
import pytest

from nimbus.data import Camera, Scene, View, llff_test_names
from nimbus.data.camera import rotation_from_quaternion_wxyz
from nimbus.data.images import read_depth, read_image, to_uint8, write_depth, write_image
from nimbus.data.scene import read_split_lists
from nimbus.errors import NimbusError
from nimbus.utils.fs import atomic_dir, atomic_write_text


def _cam(eye=(0.0, -5.0, 1.0), w=32, h=24):
    return Camera.look_at(eye, (0, 0, 0), (0, 0, 1), w, h, fov_x_deg=60)


def test_look_at_puts_target_on_optical_axis_and_up_is_image_up():
    cam = _cam()
    uv, z = cam.project(np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.5]]))
    np.testing.assert_allclose(uv[0], [16, 12], atol=1e-9)
    assert z[0] == pytest.approx(np.sqrt(26))
    assert uv[1, 1] < uv[0, 1]  # a point above the target appears higher in the image (smaller v)
    np.testing.assert_allclose(cam.center, [0, -5, 1], atol=1e-12)


def test_pixel_rays_hit_pixel_centres_and_ray_distance():
    cam = _cam()
    rays = cam.pixel_rays(np.float64)
    # A point along the ray of pixel (u=3, v=7) projects to that pixel's centre (3.5, 7.5).
    p_cam = 4.0 * rays[7, 3]
    p_world = cam.R.T @ (p_cam - cam.t)
    uv, z = cam.project(p_world[None])
    np.testing.assert_allclose(uv[0], [3.5, 7.5], atol=1e-9)
    assert z[0] == pytest.approx(4.0)
    dist = cam.ray_distance_from_z(np.full((24, 32), 4.0))
    assert dist[7, 3] == pytest.approx(np.linalg.norm(p_cam))
    d, o = cam.world_rays(np.float64)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-12)
    np.testing.assert_allclose(o + np.linalg.norm(p_cam) * d[7, 3], p_world, atol=1e-9)


def test_scaled_camera_keeps_projections_consistent():
    cam = _cam(w=64, h=48)
    half = cam.scaled(0.5)
    pts = np.random.default_rng(0).normal(size=(10, 3))
    uv, _ = cam.project(pts)
    uv2, _ = half.project(pts)
    np.testing.assert_allclose(uv2, uv * 0.5, atol=1e-9)
    assert (half.width, half.height) == (32, 24)


def test_camera_rejects_bad_values():
    with pytest.raises(NimbusError):
        Camera(0, 10, 1, 1, 0, 0)
    with pytest.raises(NimbusError):
        Camera(10, 10, -1, 1, 0, 0)
    with pytest.raises(NimbusError):
        Camera(10, 10, 1, 1, 0, 0, R=np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(NimbusError):
        Camera(10, 10, 1, 1, 0, 0, t=[np.nan, 0, 0])


def test_camera_dict_round_trip_and_quaternion():
    cam = _cam()
    back = Camera.from_dict(cam.to_dict())
    np.testing.assert_allclose(back.world_to_camera, cam.world_to_camera)
    np.testing.assert_allclose(cam.camera_to_world @ cam.world_to_camera, np.eye(4), atol=1e-12)
    R = rotation_from_quaternion_wxyz([np.cos(0.3), 0, 0, np.sin(0.3)])
    np.testing.assert_allclose(R[:2, :2], [[np.cos(0.6), -np.sin(0.6)], [np.sin(0.6), np.cos(0.6)]], atol=1e-12)


def test_llff_rule_and_split_lists(tmp_path):
    names = [f"{i:03d}.png" for i in range(17)]
    assert llff_test_names(reversed(names)) == ["000.png", "008.png", "016.png"]
    assert read_split_lists(tmp_path, names) is None
    (tmp_path / "test_list.txt").write_text("001.png\n# comment\n\n002.png\n")
    assert read_split_lists(tmp_path, names) == {"001.png", "002.png"}
    (tmp_path / "test_list.txt").write_text("nope.png\n")
    with pytest.raises(NimbusError, match="nope.png"):
        read_split_lists(tmp_path, names)
    (tmp_path / "test_list.txt").unlink()
    (tmp_path / "train_list.txt").write_text("\n".join(names[1:]) + "\n")
    assert read_split_lists(tmp_path, names) == {"000.png"}


def test_scene_views_sorted_split_and_extent():
    cams = [_cam(eye=(5 * np.cos(a), 5 * np.sin(a), 1.0)) for a in np.linspace(0, 2 * np.pi, 8, endpoint=False)]
    views = [View(f"{i:02d}.png", c) for i, c in reversed(list(enumerate(cams)))]
    scene = Scene(views, test_names={"00.png"})
    assert scene.names == sorted(scene.names)
    assert [v.name for v in scene.test_views] == ["00.png"]
    assert len(scene.train_views) == 7
    assert scene.extent == pytest.approx(1.1 * 5.0)
    assert Scene([View("a.png", cams[0])]).extent == 1.0  # single camera, no points: a sane default
    with pytest.raises(NimbusError, match="duplicate"):
        Scene([View("a.png", cams[0]), View("a.png", cams[1])])
    with pytest.raises(NimbusError, match="not in the scene"):
        Scene(views, test_names={"zz.png"})


def test_view_checks_image_size_against_camera():
    v = View("a.png", _cam(w=32, h=24), image=np.zeros((10, 10, 3), np.float32))
    with pytest.raises(NimbusError, match="10x10 but its camera is 32x24"):
        v.load_image()


def test_image_io_round_trip_and_corrupt_files(tmp_path):
    rng = np.random.default_rng(1)
    img = rng.random((12, 16, 3)).astype(np.float32)
    write_image(tmp_path / "a.png", img)
    back = read_image(tmp_path / "a.png")
    assert back.dtype == np.float32 and back.shape == (12, 16, 3)
    np.testing.assert_array_equal(to_uint8(back), to_uint8(img))
    data = (tmp_path / "a.png").read_bytes()
    (tmp_path / "trunc.png").write_bytes(data[: len(data) // 2])
    with pytest.raises(NimbusError, match="trunc.png"):
        read_image(tmp_path / "trunc.png")
    (tmp_path / "junk.png").write_bytes(b"not an image")
    with pytest.raises(NimbusError, match="junk.png"):
        read_image(tmp_path / "junk.png")
    with pytest.raises(NimbusError, match="does not exist"):
        read_image(tmp_path / "missing.png")
    depth = rng.random((12, 16)).astype(np.float32) * 10
    write_depth(tmp_path / "d.npy", depth)
    np.testing.assert_array_equal(read_depth(tmp_path / "d.npy"), depth)


def test_atomic_dir_leaves_nothing_on_failure_and_refuses_non_empty(tmp_path):
    out = tmp_path / "out"
    with pytest.raises(RuntimeError):
        with atomic_dir(out) as tmp:
            atomic_write_text(tmp / "half.txt", "x")
            raise RuntimeError("boom")
    assert not out.exists() and list(tmp_path.iterdir()) == []
    with atomic_dir(out) as tmp:
        atomic_write_text(tmp / "a.txt", "first")
    assert (out / "a.txt").read_text() == "first"
    with pytest.raises(NimbusError, match="--overwrite"):
        with atomic_dir(out):
            pass
    with atomic_dir(out, overwrite=True) as tmp:
        atomic_write_text(tmp / "b.txt", "second")
    assert sorted(p.name for p in out.iterdir()) == ["b.txt"]
    assert [p.name for p in tmp_path.iterdir()] == ["out"]


def test_a_mask_stored_as_0_and_1_reads_as_valid_where_1(tmp_path):
    """nerfstudio masks are often 0/1 PNGs: any non-zero value marks a valid pixel."""
    import cv2

    from nimbus.data.images import read_mask

    raw = np.zeros((4, 6), np.uint8)
    raw[:, 3:] = 1
    cv2.imwrite(str(tmp_path / "m.png"), raw)
    np.testing.assert_array_equal(read_mask(tmp_path / "m.png"), raw > 0)


def test_project_seen_keeps_points_in_front_and_inside_the_image():
    cam = Camera.look_at((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), (0.0, -1.0, 0.0), 16, 12, 60)
    pts = np.array([[0.0, 0.0, 2.0],     # straight ahead: seen
                    [0.0, 0.0, -2.0],    # behind: not seen
                    [50.0, 0.0, 2.0],    # far outside the image
                    [0.0, 0.0, 0.0],     # at the centre: z = 0, uv not finite
                    [0.0, 0.0, 0.005]])  # in front, but nearer than a near plane of 0.01
    uv, z, seen = cam.project_seen(pts)
    np.testing.assert_allclose(uv[0], (cam.cx, cam.cy))
    np.testing.assert_allclose(z[:2], (2.0, -2.0))
    assert seen.tolist() == [True, False, False, False, True]
    assert cam.project_seen(pts, near=0.01)[2].tolist() == [True, False, False, False, False]
