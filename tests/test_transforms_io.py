"""Blender / nerfstudio transforms.json: conventions, round trips, splits, points and bad input."""

import json

import numpy as np
import pytest

from nimbus.data.images import write_image
from nimbus.data.io import detect_format, load_scene, write_scene
from nimbus.data.transforms import read_ply_points, write_ply_points
from nimbus.errors import NimbusError


def test_round_trip_and_opengl_convention(tmp_path, make_scene, assert_same_scene):
    scene = make_scene(depth=True, test_names={"002.png"})
    out = write_scene(scene, tmp_path / "ns", format="transforms")
    assert detect_format(out) == "transforms"
    meta = json.loads((out / "transforms.json").read_text())
    assert meta["ply_file_path"] == "sparse_pc.ply" and meta["frames"][0]["file_path"] == "images/000.png"
    # OpenGL camera-to-world: the camera looks along its -z axis; y is image-up.
    c2w = np.array(meta["frames"][0]["transform_matrix"])
    cam = scene.views[0].camera
    np.testing.assert_allclose(c2w[:3, 3], cam.center, atol=1e-12)
    look = -cam.center / np.linalg.norm(cam.center)  # the cameras look at the origin
    np.testing.assert_allclose(-c2w[:3, 2], look, atol=1e-9)
    assert c2w[2, 1] > 0  # image-up has a positive world-z component (world up is +z)

    back = load_scene(out)
    assert back.source_format == "transforms"
    assert_same_scene(scene, back)
    np.testing.assert_array_equal(back.view("003.png").load_depth(), scene.view("003.png").depth)
    # Cross-format: transforms -> COLMAP -> same scene.
    assert_same_scene(scene, load_scene(write_scene(back, tmp_path / "colmap")))


def _blender_scene(root, w=20, h=16, angle=0.7):
    rng = np.random.default_rng(1)
    for split, n in (("train", 3), ("test", 2)):
        frames = []
        for i in range(n):
            write_image(root / split / f"r_{i}.png", rng.random((h, w, 3), dtype=np.float32))
            c2w = np.eye(4)
            c2w[:3, 3] = [0.1 * i, 0, 4.0]  # OpenGL camera at z=4 looking down -z at the origin
            frames.append({"file_path": f"./{split}/r_{i}", "rotation": 0.0, "transform_matrix": c2w.tolist()})
        (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": angle, "frames": frames}))


def test_blender_synthetic_layout(tmp_path):
    _blender_scene(tmp_path)
    scene = load_scene(tmp_path)
    assert scene.names == ["test/r_0.png", "test/r_1.png", "train/r_0.png", "train/r_1.png", "train/r_2.png"]
    assert scene.test_names == {"test/r_0.png", "test/r_1.png"}
    assert len(scene.points) == 0
    cam = scene.view("train/r_1.png").camera
    f = 0.5 * 20 / np.tan(0.35)
    np.testing.assert_allclose([cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height], [f, f, 10, 8, 20, 16])
    np.testing.assert_allclose(cam.center, [0.1, 0, 4.0], atol=1e-12)
    uv, z = cam.project(np.array([[0.1, 0.0, 0.0], [0.1, 1.0, 0.0]]))
    np.testing.assert_allclose(uv[0], [10, 8], atol=1e-9)  # the origin below the camera is on the optical axis
    assert z[0] == pytest.approx(4.0) and uv[1, 1] < uv[0, 1]  # world +y (OpenGL up) appears higher


def _nerfstudio_scene(root, frames_extra=None, top_extra=None):
    rng = np.random.default_rng(2)
    frames = []
    for i in range(4):
        write_image(root / "images" / f"frame_{i:05d}.png", rng.random((12, 16, 3), dtype=np.float32))
        c2w = np.eye(4)
        c2w[:3, 3] = [i * 0.2, 0, 3]
        frames.append({"file_path": f"images/frame_{i:05d}.png", "transform_matrix": c2w.tolist()})
    frames[1]["fl_x"] = 30.0
    for k, v in (frames_extra or {}).items():
        frames[0][k] = v
    meta = {"fl_x": 20.0, "fl_y": 21.0, "cx": 7.5, "cy": 6.5, "w": 16, "h": 12, "camera_model": "OPENCV",
            "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, "frames": frames, **(top_extra or {})}
    (root / "transforms.json").write_text(json.dumps(meta))


def test_nerfstudio_layout_per_frame_intrinsics_ply_and_split_lists(tmp_path):
    pts = np.array([[0.5, -1.0, 2.25], [1, 2, 3]])
    (tmp_path / "pc.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
        "0.5 -1 2.25 255 0 10\n1 2 3 1 2 3\n")
    _nerfstudio_scene(tmp_path, top_extra={"ply_file_path": "pc.ply"})
    scene = load_scene(tmp_path)
    assert scene.names == [f"frame_{i:05d}.png" for i in range(4)]  # the shared images/ folder is not in the name
    assert scene.view("frame_00001.png").camera.fx == 30.0 and scene.view("frame_00002.png").camera.fx == 20.0
    assert scene.view("frame_00002.png").camera.fy == 21.0
    np.testing.assert_allclose(scene.points, pts)
    np.testing.assert_array_equal(scene.colors, [[255, 0, 10], [1, 2, 3]])
    assert scene.test_names == {"frame_00000.png"}  # LLFF rule
    (tmp_path / "test_list.txt").write_text("frame_00003.png\n")
    assert load_scene(tmp_path).test_names == {"frame_00003.png"}


def test_nerfstudio_test_filenames_and_downscale(tmp_path):
    _nerfstudio_scene(tmp_path, top_extra={"test_filenames": ["images/frame_00002.png"]})
    assert load_scene(tmp_path).test_names == {"frame_00002.png"}
    for i in range(4):
        write_image(tmp_path / "images_2" / f"frame_{i:05d}.png", np.zeros((6, 8, 3), np.float32))
    half = load_scene(tmp_path, downscale=2)
    cam = half.view("frame_00003.png").camera
    np.testing.assert_allclose([cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy], [8, 6, 10, 10.5, 3.75, 3.25])
    assert half.view("frame_00003.png").load_image().shape == (6, 8, 3)


def test_ply_round_trip_binary(tmp_path):
    rng = np.random.default_rng(0)
    pts, cols = rng.normal(size=(5, 3)), rng.integers(0, 256, (5, 3), dtype=np.uint8)
    write_ply_points(tmp_path / "p.ply", pts, cols)
    back_pts, back_cols = read_ply_points(tmp_path / "p.ply")
    np.testing.assert_array_equal(back_pts, pts)
    np.testing.assert_array_equal(back_cols, cols)


def test_distorted_frame_is_undistorted_and_the_others_are_read_as_they_are(tmp_path, monkeypatch):
    """Per-frame k1 undistorts that frame only (tests/test_undistort.py checks the pixels)."""
    monkeypatch.setenv("NIMBUS_CACHE", str(tmp_path / "cache"))
    _nerfstudio_scene(tmp_path / "s", frames_extra={"k1": 0.05})
    scene = load_scene(tmp_path / "s")
    distorted, plain = scene.view("frame_00000.png"), scene.view("frame_00002.png")
    assert (tmp_path / "cache" / "undistorted") in distorted.image_path.parents
    assert distorted.camera.fx == 20.0 and (distorted.camera.width, distorted.camera.height) != (16, 12)
    assert distorted.load_image().shape == (distorted.camera.height, distorted.camera.width, 3)
    assert plain.image_path == tmp_path / "s" / "images" / "frame_00002.png"
    assert scene.metadata["undistorted"]["views"] == 1


def test_fisheye_model_is_undistorted_and_unknown_models_refused(tmp_path, monkeypatch):
    monkeypatch.setenv("NIMBUS_CACHE", str(tmp_path / "cache"))
    _nerfstudio_scene(tmp_path / "f", top_extra={"camera_model": "OPENCV_FISHEYE"})
    scene = load_scene(tmp_path / "f")  # zero coefficients are still an equidistant projection: resampled
    assert scene.metadata["undistorted"]["views"] == 4
    assert all((tmp_path / "cache" / "undistorted") in v.image_path.parents for v in scene.views)
    _nerfstudio_scene(tmp_path / "e", top_extra={"camera_model": "EQUIRECTANGULAR"})
    with pytest.raises(NimbusError, match="camera_model EQUIRECTANGULAR is not supported"):
        load_scene(tmp_path / "e")


def test_bad_json_missing_image_and_bad_matrix(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "transforms.json").write_text('{"frames": [ {"file_path": "x.png",, } ]}')
    with pytest.raises(NimbusError, match=r"not valid JSON .*line 1"):
        load_scene(tmp_path / "a")
    _nerfstudio_scene(tmp_path / "b")
    (tmp_path / "b" / "images" / "frame_00002.png").unlink()
    with pytest.raises(NimbusError, match="missing.*frame_00002.png"):
        load_scene(tmp_path / "b")
    _nerfstudio_scene(tmp_path / "c", frames_extra={"transform_matrix": (2 * np.eye(4)).tolist()})
    with pytest.raises(NimbusError, match="frame 0.*rotation"):
        load_scene(tmp_path / "c")
    _nerfstudio_scene(tmp_path / "d", frames_extra={"w": 99})
    with pytest.raises(NimbusError, match="frame_00000.png is 16x12"):
        load_scene(tmp_path / "d")


def _long_transforms(root, n_frames: int, duplicate_at: int | None = None, duplicate_name: str = "images/0.png",
                     blender: bool = False):
    """A transforms.json of ``n_frames`` frames over 3 image files (only frames 0-2 name files that exist),
    frame ``duplicate_at`` naming ``duplicate_name`` again; Blender's file when ``blender``."""
    for i in range(3):
        write_image(root / "images" / f"{i}.png", np.zeros((12, 16, 3), np.float32))
    frames = [{"file_path": f"images/{i}.png", "transform_matrix": np.eye(4).tolist()} for i in range(n_frames)]
    if duplicate_at is not None:
        frames[duplicate_at]["file_path"] = duplicate_name
    meta = {"fl_x": 20.0, "fl_y": 20.0, "cx": 8.0, "cy": 6.0, "w": 16, "h": 12, "frames": frames}
    (root / ("transforms_train.json" if blender else "transforms.json")).write_text(json.dumps(meta))
    return root


@pytest.mark.parametrize("name", ["images/0.png", "./images/0.png", "images/0"])  # "images/0": .png is added
def test_a_duplicate_frame_is_refused_before_the_frames_after_it_are_resolved(tmp_path, monkeypatch, name):
    """20,000 frames, the third naming the first's image again: refused at the third, naming both frames,
    without resolving the other 19,997 (that took minutes for a 200 MB transforms.json)."""
    from nimbus.data import transforms

    root = _long_transforms(tmp_path / "s", 20_000, duplicate_at=2, duplicate_name=name)
    resolved = []
    resolve = transforms._resolve_image
    monkeypatch.setattr(transforms, "_resolve_image", lambda *a: resolved.append(a[1]) or resolve(*a))
    with pytest.raises(NimbusError) as info:
        load_scene(root)
    message = str(info.value)
    assert f"frame 2 ({name}) lists the same image as " in message and "frame 0 (images/0.png)" in message
    assert len(resolved) <= 3


def test_a_long_scene_load_shows_its_progress_on_stderr(tmp_path, monkeypatch, capsys):
    """After SHOW_AFTER_S seconds (made 0 here) the frames being read are counted on stderr; a quick load
    prints nothing."""
    from nimbus.utils import progress

    root = _long_transforms(tmp_path / "s", 3)
    load_scene(root)
    assert capsys.readouterr().err == ""
    monkeypatch.setattr(progress, "SHOW_AFTER_S", 0.0)
    load_scene(root)
    err = capsys.readouterr().err
    assert "reading transforms.json" in err and "/3 [" in err and "frame/s" in err
