"""COLMAP scenes: write -> read round trips (bin and txt), Mip-NeRF360 downscaled folders, bad input."""

import logging
import shutil

import cv2
import numpy as np
import pycolmap
import pytest

from nimbus.data.camera import Camera
from nimbus.data.images import read_image, write_image
from nimbus.data.io import detect_format, load_scene, write_scene, write_scene_into
from nimbus.data.scene_files import image_size
from nimbus.data.scene import Scene, View
from nimbus.errors import NimbusError
from nimbus.utils.fs import atomic_dir


@pytest.mark.parametrize("text", [False, True], ids=["bin", "txt"])
def test_round_trip_keeps_poses_intrinsics_points_images_depths_masks(tmp_path, make_scene, assert_same_scene, text):
    scene = make_scene(depth=True, mask=True, sky=True, test_names={"001.png", "003.png"})
    out = write_scene(scene, tmp_path / "scene", text=text)
    suffix = ".txt" if text else ".bin"
    assert (out / "sparse" / "0" / f"cameras{suffix}").is_file()
    assert detect_format(out) == "colmap"

    back = load_scene(out)
    assert back.source_format == "colmap" and back.root == out
    assert_same_scene(scene, back)
    for v, w in zip(scene.views, back.views):
        # 8-bit PNG: within half a quantisation step.
        np.testing.assert_allclose(w.load_image(), v.image, atol=0.5 / 255 + 1e-6)
        np.testing.assert_array_equal(w.load_depth(), v.depth)
        np.testing.assert_array_equal(w.load_mask(), v.mask)
        np.testing.assert_array_equal(w.load_sky(), v.sky)
    # COLMAP itself (pycolmap) reads the written model with every image.
    rec = pycolmap.Reconstruction(out / "sparse" / "0")
    assert rec.num_reg_images() == len(scene) and rec.num_points3D() == len(scene.points)
    assert {c.model_name for c in rec.cameras.values()} == {"PINHOLE"}
    assert len(rec.cameras) == 1  # every view shares the intrinsics

    # Writing a scene read from disk copies the image bytes, and reading it again changes nothing.
    again = write_scene(back, tmp_path / "again", text=not text)
    assert (again / "images" / "002.png").read_bytes() == (out / "images" / "002.png").read_bytes()
    assert_same_scene(back, load_scene(again))


def test_one_camera_per_distinct_intrinsics(tmp_path, make_scene):
    scene = make_scene(n_views=4)
    v = scene.views[2]
    c = v.camera
    other = Camera(c.width, c.height, c.fx * 1.1, c.fy * 1.1, c.cx, c.cy, c.R, c.t)
    scene = scene.with_views([*scene.views[:2], View(v.name, other, image=v.image), *scene.views[3:]])
    out = write_scene(scene, tmp_path / "s")
    assert len(pycolmap.Reconstruction(out / "sparse" / "0").cameras) == 2
    assert load_scene(out).view("002.png").camera.fx == pytest.approx(c.fx * 1.1)


def test_in_memory_image_with_jpg_name_is_written_as_png(tmp_path, make_scene):
    scene = make_scene(n_views=3)
    views = [View(v.name.replace(".png", ".jpg"), v.camera, image=v.image) for v in scene.views]
    scene = Scene(tuple(views), frozenset({"001.jpg"}))
    back = load_scene(write_scene(scene, tmp_path / "s"))
    assert back.names == ["000.png", "001.png", "002.png"] and back.test_names == {"001.png"}


def test_no_split_lists_means_llff_rule(tmp_path, make_scene):
    out = write_scene(make_scene(n_views=10), tmp_path / "s")
    (out / "train_list.txt").unlink()
    (out / "test_list.txt").unlink()
    assert load_scene(out).test_names == {"000.png", "008.png"}


def _mipnerf_scene(tmp_path, make_scene):
    """images/ at 64x48 and a half-size images_2/ at 32x24, as Mip-NeRF360 ships them."""
    out = write_scene(make_scene(n_views=3, width=64, height=48), tmp_path / "m360")
    (out / "images_2").mkdir()
    for f in sorted((out / "images").iterdir()):
        write_image(out / "images_2" / f.name, cv2.resize(read_image(f), (32, 24), interpolation=cv2.INTER_AREA))
    return out


def test_mipnerf360_downscale_uses_images_n_and_scales_intrinsics(tmp_path, make_scene):
    out = _mipnerf_scene(tmp_path, make_scene)
    full, half = load_scene(out), load_scene(out, downscale=2)
    assert half.view("000.png").image_path.parent.name == "images_2"
    for a, b in zip(full.views, half.views):
        assert (b.camera.width, b.camera.height) == (32, 24)
        np.testing.assert_allclose([b.camera.fx, b.camera.fy, b.camera.cx, b.camera.cy],
                                   [a.camera.fx / 2, a.camera.fy / 2, a.camera.cx / 2, a.camera.cy / 2])
        np.testing.assert_allclose(b.camera.world_to_camera, a.camera.world_to_camera)
        assert b.load_image().shape == (24, 32, 3)
    with pytest.raises(NimbusError, match="images_4"):
        load_scene(out, downscale=4)


def test_mipnerf360_downscaled_image_of_wrong_size_is_named(tmp_path, make_scene):
    out = _mipnerf_scene(tmp_path, make_scene)
    write_image(out / "images_2" / "001.png", np.zeros((24, 28, 3), np.float32))
    with pytest.raises(NimbusError, match=r"images_2/001\.png is 28x24"):
        load_scene(out, downscale=2)


def test_image_size_reads_png_and_jpeg_headers(tmp_path):
    img = np.zeros((7, 13, 3), np.uint8)
    cv2.imwrite(str(tmp_path / "a.jpg"), img)
    cv2.imwrite(str(tmp_path / "a.png"), img)
    cv2.imwrite(str(tmp_path / "a.bmp"), img)
    assert image_size(tmp_path / "a.jpg") == image_size(tmp_path / "a.png") == image_size(tmp_path / "a.bmp") == (13, 7)


def test_unregistered_image_is_a_warning_and_missing_image_an_error(tmp_path, make_scene, caplog):
    out = write_scene(make_scene(n_views=3), tmp_path / "s")
    shutil.copy(out / "images" / "000.png", out / "images" / "extra.png")
    with caplog.at_level(logging.WARNING):
        scene = load_scene(out)
    assert "extra.png" not in scene.names and "extra.png" in caplog.text
    (out / "images" / "001.png").unlink()
    with pytest.raises(NimbusError, match="missing.*001.png"):
        load_scene(out)


def test_image_size_not_matching_camera(tmp_path, make_scene):
    out = write_scene(make_scene(n_views=3), tmp_path / "s")
    view = load_scene(out).view("002.png")
    write_image(out / "images" / "002.png", np.zeros((10, 10, 3), np.float32))
    with pytest.raises(NimbusError, match="10x10"):
        view.load_image()
    with pytest.raises(NimbusError, match=r"002\.png is 10x10"):
        load_scene(out)


def test_truncated_image_raises_through_load_image(tmp_path, make_scene):
    out = write_scene(make_scene(n_views=3), tmp_path / "s")
    f = out / "images" / "001.png"
    f.write_bytes(f.read_bytes()[:-30])
    view = load_scene(out).view("001.png")  # the header is intact: only decoding finds the damage
    with pytest.raises(NimbusError, match="truncated|corrupt"):
        view.load_image()


def _write_model(root, model, params, with_image=True):
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera(model=model, width=32, height=24, params=params, camera_id=1))
    if with_image:
        rec.add_image_with_trivial_frame(pycolmap.Image(name="a.png", camera_id=1, image_id=1),
                                         pycolmap.Rigid3d(pycolmap.Rotation3d(np.eye(3)), np.zeros(3)))
        write_image(root / "images" / "a.png", np.zeros((24, 32, 3), np.float32))
    (root / "sparse" / "0").mkdir(parents=True)
    rec.write(root / "sparse" / "0")


def test_distorted_camera_is_undistorted_zero_distortion_accepted_and_other_models_refused(tmp_path, monkeypatch):
    """Distorted models load as undistorted pinhole views (tests/test_undistort.py checks the pixels)."""
    monkeypatch.setenv("NIMBUS_CACHE", str(tmp_path / "cache"))
    _write_model(tmp_path / "d", "OPENCV", [30, 30, 16, 12, 0.1, 0, 0, 0])
    scene = load_scene(tmp_path / "d")
    cam = scene.views[0].camera
    assert (cam.fx, cam.fy) == (30, 30) and (cam.width, cam.height) != (32, 24)  # pincushion: a smaller crop
    assert scene.metadata["undistorted"]["views"] == 1
    assert (tmp_path / "cache" / "undistorted") in scene.views[0].image_path.parents
    _write_model(tmp_path / "z", "SIMPLE_RADIAL", [30, 16, 12, 0.0])
    scene = load_scene(tmp_path / "z")
    cam = scene.views[0].camera
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (30, 30, 16, 12)
    assert scene.views[0].image_path == tmp_path / "z" / "images" / "a.png" and "undistorted" not in scene.metadata
    # A fisheye with zero coefficients is still an equidistant projection, so it is resampled.
    _write_model(tmp_path / "f", "OPENCV_FISHEYE", [30, 30, 16, 12, 0, 0, 0, 0])
    assert load_scene(tmp_path / "f").views[0].camera.width > 32
    _write_model(tmp_path / "fov", "FOV", [30, 30, 16, 12, 0.9])
    with pytest.raises(NimbusError, match="FOV camera model, which Nimbus cannot undistort.*image_undistorter"):
        load_scene(tmp_path / "fov")


def test_model_without_rigs_and_frames_files_is_read(tmp_path):
    """Models from COLMAP before 3.12 (Mip-NeRF360, 3DGS datasets) have only cameras/images/points3D."""
    _write_model(tmp_path / "old", "PINHOLE", [30, 30, 16, 12])
    for f in ("rigs.bin", "frames.bin"):
        (tmp_path / "old" / "sparse" / "0" / f).unlink()
    assert load_scene(tmp_path / "old").names == ["a.png"]


def test_empty_model_corrupt_model_missing_folder_and_photos_only(tmp_path):
    _write_model(tmp_path / "empty", "PINHOLE", [30, 30, 16, 12], with_image=False)
    with pytest.raises(NimbusError, match="no registered images"):
        load_scene(tmp_path / "empty")
    _write_model(tmp_path / "bad", "PINHOLE", [30, 30, 16, 12])
    images_bin = tmp_path / "bad" / "sparse" / "0" / "images.bin"
    images_bin.write_bytes(images_bin.read_bytes()[:50])
    with pytest.raises(NimbusError, match="unreadable"):
        load_scene(tmp_path / "bad")
    with pytest.raises(NimbusError, match="does not exist"):
        load_scene(tmp_path / "nope")
    write_image(tmp_path / "photos" / "a.jpg", np.zeros((8, 8, 3), np.float32))
    with pytest.raises(NimbusError, match="nimbus-synth sfm"):
        load_scene(tmp_path / "photos")
    (tmp_path / "void").mkdir()
    with pytest.raises(NimbusError, match="not a scene folder"):
        load_scene(tmp_path / "void")


def test_write_refuses_non_empty_output_and_the_input_itself(tmp_path, make_scene):
    out = write_scene(make_scene(n_views=2), tmp_path / "s")
    with pytest.raises(NimbusError, match="not empty"):
        write_scene(make_scene(n_views=2), out)
    with pytest.raises(NimbusError, match="own input"):
        write_scene(load_scene(out), out, overwrite=True)
    assert load_scene(out).names == ["000.png", "001.png"]  # untouched
    with pytest.raises(NimbusError, match="format"):
        write_scene(make_scene(n_views=2), tmp_path / "x", format="ply")
    assert not (tmp_path / "x").exists()


def test_write_scene_into_shares_an_atomic_directory(tmp_path, make_scene):
    with atomic_dir(tmp_path / "built") as tmp:
        write_scene_into(make_scene(n_views=2), tmp)
        (tmp / "manifest.json").write_text("{}")
    assert (tmp_path / "built" / "manifest.json").is_file()
    assert len(load_scene(tmp_path / "built")) == 2
    # A failure inside the block leaves nothing behind.
    with pytest.raises(NimbusError), atomic_dir(tmp_path / "failed") as tmp:
        write_scene_into(make_scene(n_views=2), tmp)
        raise NimbusError("generator failed")
    assert not (tmp_path / "failed").exists()
