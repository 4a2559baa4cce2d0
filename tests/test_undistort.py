"""Undistortion on load (issue 15 item 4): distorted COLMAP and transforms.json cameras become pinhole views.

The reference is the built-in ray caster.  A garden view is rendered through a known lens (every
sub-pixel sample's ray comes from OpenCV's undistortion of its pixel position), saved as a COLMAP
OPENCV / OPENCV_FISHEYE scene and as a transforms.json scene, loaded, and compared with the pinhole
render of the camera the loader chose.  PSNR over the valid region (the crop leaves no pixel without
source data, so that is every pixel the source's own mask keeps), measured on this machine at 64x48
with 4x4 samples per pixel: 27.5 and 28.3 dB on the two views through an OPENCV lens, 27.8 and 28.6 dB
through an OPENCV_FISHEYE lens, against 17.2 to 20.6 dB for the distorted image taken as pinhole.
Asserted: at least 26 dB and at least 5 dB above that.  What is left is resampling blur of 64x48
procedural textures, not misalignment: moving the reference's principal point by 0.3 px costs 2 dB.
"""

from __future__ import annotations

import hashlib
import json
import logging
import struct
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest

from nimbus.data.builtin.raycast import RenderSettings, render_view, shade, subpixel_offsets, trace
from nimbus.data.builtin.scenes import GardenConfig
from nimbus.data.camera import Camera
from nimbus.data.colmap import COLMAP_LENSES, colmap_lens
from nimbus.data.images import read_image, write_image, write_mask
from nimbus.data.io import load_scene
from nimbus.data.transforms import camera_to_opengl_c2w
from nimbus.data.undistort import Lens, distort_points, plan_undistortion, undistort_points
from nimbus.errors import NimbusError
from weather_synth.cli import main as synth_main

W, H = 64, 48
SAMPLES = 4  # per axis, for both the distorted and the reference renders
PSNR_FLOOR_DB = 26.0  # measured 27.5 / 28.3 (OPENCV) and 27.8 / 28.6 (OPENCV_FISHEYE) on the two views
PSNR_GAIN_DB = 5.0  # over the distorted image read as pinhole (measured 7.7 to 10.6 dB)
BROWN = Lens("OPENCV", False, (-0.25, 0.05, 0.002, -0.001))  # a phone's barrel distortion
FISHEYE = Lens("OPENCV_FISHEYE", True, (0.05, 0.01, 0.0, 0.0))


@pytest.fixture(autouse=True)
def cache(tmp_path, monkeypatch) -> Path:
    """Every test gets its own cache folder (never the user's)."""
    folder = tmp_path / "user-cache"
    monkeypatch.setenv("NIMBUS_CACHE", str(folder))
    return folder / "undistorted"


# --- rendering through a lens ----------------------------------------------------------------------
def _psnr(a: np.ndarray, b: np.ndarray, valid: np.ndarray) -> float:
    return float(-10 * np.log10(np.mean((a - b)[valid] ** 2)))


def render_through_lens(world, camera: Camera, lens: Lens):
    """Image, z-depth and sky mask of ``camera`` seen through ``lens`` (every sample's ray undistorted by cv2)."""
    offsets, n_color, centre = subpixel_offsets(SAMPLES)
    u = np.arange(W)[None, None, :] + offsets[:, 0, None, None] + np.zeros((1, H, 1))
    v = np.arange(H)[None, :, None] + offsets[:, 1, None, None] + np.zeros((1, 1, W))
    xy = undistort_points(np.stack([u.ravel(), v.ravel()], axis=1), camera, lens)
    rays = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    dirs = (rays @ camera.R).T.reshape(3, len(offsets), H, W).astype(np.float32)
    origin = camera.center.astype(np.float32)
    t, idx = trace(world.primitives, camera, dirs, origin, cull=False)  # culling assumes a pinhole
    color = shade(world, origin, dirs.reshape(3, -1), t.reshape(-1), idx.reshape(-1)).reshape(len(offsets), H, W, 3)
    forward = camera.R[2]
    depth = t[centre] * np.tensordot(forward, dirs[:, centre], axes=1)
    backdrop = [k for k, p in enumerate(world.primitives) if p.material in world.backdrop_materials]
    image = np.round(color[:n_color].mean(axis=0) * 255) / 255  # what an 8-bit file holds
    return image.astype(np.float32), depth.astype(np.float32), np.isin(idx[centre], backdrop)


@pytest.fixture(scope="module")
def garden():
    """The tiny garden's world, two of its cameras and their views through each lens."""
    config = GardenConfig()
    world = config.world(0)
    cameras = config.cameras(4, W, H, 0)[1:3]
    renders = {lens.model: [render_through_lens(world, c, lens) for c in cameras] for lens in (BROWN, FISHEYE)}
    return world, cameras, renders


def _reference(world, camera: Camera):
    return render_view(world, camera, RenderSettings(SAMPLES, adaptive_threshold=None, cull=False))


# Source validity mask: the left 10 columns carry no data (e.g. a lens hood).
def _source_mask() -> np.ndarray:
    mask = np.ones((H, W), bool)
    mask[:, :10] = False
    return mask


# --- writing distorted scenes ------------------------------------------------------------------------
def _write_files(root: Path, names, renders, mask: bool = True) -> None:
    for name, (image, depth, sky) in zip(names, renders):
        if name.endswith(".jpg"):
            (root / "images").mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(root / "images" / name), np.round(image[:, :, ::-1] * 255).astype(np.uint8),
                        [cv2.IMWRITE_JPEG_QUALITY, 95])
        else:
            write_image(root / "images" / name, image)
        stem = Path(name).stem
        (root / "depths").mkdir(parents=True, exist_ok=True)
        np.save(root / "depths" / f"{stem}.npy", depth)
        write_mask(root / "sky" / f"{stem}.png", sky)
        if mask:
            write_mask(root / "masks" / f"{stem}.png", _source_mask())


def write_colmap_scene(root: Path, model: str, params, cameras, renders, names=("a.png", "b.png"),
                       mask: bool = True, text: bool = False) -> Path:
    """A COLMAP scene: one ``model`` camera, the views' poses and files, a few sparse points."""
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera(model=model, width=W, height=H, params=list(params), camera_id=1))
    for i, (name, cam) in enumerate(zip(names, cameras), start=1):
        rec.add_image_with_trivial_frame(pycolmap.Image(name=name, camera_id=1, image_id=i),
                                         pycolmap.Rigid3d(pycolmap.Rotation3d(cam.R), cam.t))
    for xyz in ([0.0, 0.0, 0.6], [1.0, -0.5, 0.2]):
        rec.add_point3D(np.array(xyz), pycolmap.Track(), np.array([10, 20, 30], np.uint8))
    (root / "sparse" / "0").mkdir(parents=True)
    rec.write_text(root / "sparse" / "0") if text else rec.write(root / "sparse" / "0")
    _write_files(root, names, renders, mask)
    return root


def _colmap_params(lens: Lens, camera: Camera) -> list[float]:
    k = lens.coeffs
    if lens.fisheye:
        return [camera.fx, camera.fy, camera.cx, camera.cy, *k]
    return [camera.fx, camera.fy, camera.cx, camera.cy, *k[:4]]


def write_transforms_scene(root: Path, lens_keys: dict, cameras, renders, names=("a.png", "b.png")) -> Path:
    """A nerfstudio transforms.json scene with per-frame mask_path (and no masks/ folder)."""
    frames = []
    for name, cam in zip(names, cameras):
        frames.append({"file_path": f"images/{name}", "mask_path": f"masks/{Path(name).stem}.png",
                       "transform_matrix": camera_to_opengl_c2w(cam).tolist()})
    c = cameras[0]
    meta = {"fl_x": c.fx, "fl_y": c.fy, "cx": c.cx, "cy": c.cy, "w": W, "h": H, **lens_keys, "frames": frames}
    (root / "images").mkdir(parents=True)
    (root / "transforms.json").write_text(json.dumps(meta))
    _write_files(root, names, renders)
    return root


def _folder_state(root: Path) -> dict[str, str]:
    return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def _check_against_reference(world, scene, cameras, renders, lens: Lens) -> None:
    """Undistorted images, depths, sky and validity masks against the pinhole renders and the lens geometry."""
    for view, source_cam, (distorted, depth, sky) in zip(scene.views, cameras, renders):
        cam = view.camera
        assert (cam.fx, cam.fy) == (source_cam.fx, source_cam.fy)  # the focal length is kept
        np.testing.assert_allclose(cam.world_to_camera, source_cam.world_to_camera, atol=1e-9)
        ref = _reference(world, cam)
        image, mask = view.load_image(), view.load_mask()
        assert image.shape == (cam.height, cam.width, 3)
        # The crop leaves no pixel without source data: the only invalid pixels are the source mask's.
        xy = np.stack(np.meshgrid((np.arange(cam.width) + 0.5 - cam.cx) / cam.fx,
                                  (np.arange(cam.height) + 0.5 - cam.cy) / cam.fy), axis=-1).reshape(-1, 2)
        src = distort_points(xy, source_cam, lens).reshape(cam.height, cam.width, 2)
        assert (src >= -0.01).all() and (src[..., 0] <= W + 0.01).all() and (src[..., 1] <= H + 0.01).all()
        # The mask follows: False exactly where the source column is < 10 (away from the boundary).
        clear = np.abs(src[..., 0] - 10) > 1
        np.testing.assert_array_equal(mask[clear], src[..., 0][clear] >= 10)
        valid = mask
        psnr = _psnr(image, ref.image, valid)
        naive = _psnr(distorted, _reference(world, source_cam).image, _source_mask())
        assert psnr >= PSNR_FLOOR_DB, f"{lens.model}: {psnr:.2f} dB over the valid region"
        assert psnr >= naive + PSNR_GAIN_DB, (psnr, naive)
        # Depth stays z-depth: interpolated where smooth, nearest at edges.
        rel = np.abs(view.load_depth() - ref.depth) / ref.depth
        assert np.median(rel) < 1e-3 and np.mean(rel < 0.01) > 0.8, (np.median(rel), np.mean(rel < 0.01))
        assert np.mean(view.load_sky() == ref.sky) > 0.95


# --- the lens models -------------------------------------------------------------------------------
@pytest.mark.parametrize("model", sorted(COLMAP_LENSES))
def test_colmap_models_map_onto_opencv_exactly(model):
    """pycolmap's own projection of every supported model equals OpenCV's through the lens table."""
    n = len(pycolmap.Camera.create_from_model_name(1, model, 1.0, 1, 1).params)
    one_focal = model.startswith(("SIMPLE", "RADIAL"))
    intrinsics = [30.0, 16.5, 12.25] if one_focal else [30.0, 31.0, 16.5, 12.25]
    extra = [-0.12, 0.03, 0.004, -0.002, 0.01, 0.05, 0.02, 0.01][:n - len(intrinsics)]
    cam = pycolmap.Camera(model=model, width=W, height=H, params=intrinsics + extra, camera_id=1)
    lens = colmap_lens(cam)
    assert lens is not None and lens.fisheye == ("FISHEYE" in model)
    xy = np.random.default_rng(0).uniform(-0.6, 0.6, (50, 2))
    camera = Camera(W, H, cam.focal_length_x, cam.focal_length_y, cam.principal_point_x, cam.principal_point_y)
    expected = np.asarray(cam.img_from_cam(np.concatenate([xy, np.ones((50, 1))], axis=1)))[:, :2]
    np.testing.assert_allclose(distort_points(xy, camera, lens), expected, atol=1e-9)
    np.testing.assert_allclose(undistort_points(expected, camera, lens), xy, atol=1e-9)


def test_zero_distortion_needs_no_resampling_but_a_zero_fisheye_does():
    assert colmap_lens(pycolmap.Camera(model="OPENCV", width=W, height=H, params=[30, 30, 32, 24, 0, 0, 0, 0])) is None
    fisheye = colmap_lens(pycolmap.Camera(model="SIMPLE_FISHEYE", width=W, height=H, params=[30, 32, 24]))
    assert fisheye is not None and fisheye.fisheye
    # Planning an (almost) identity lens keeps the camera as it was.
    plan = plan_undistortion(Camera(W, H, 30, 30, 32, 24), Lens("OPENCV", False, (1e-12, 0, 0, 0)))
    assert (plan.camera.width, plan.camera.height) == (W, H)
    assert (plan.camera.cx, plan.camera.cy) == (pytest.approx(32, abs=1e-6), pytest.approx(24, abs=1e-6))
    assert plan.valid.all()
    # A fisheye wider than 180 degrees: the pinhole image stops at twice the source size, centred on the axis.
    wide = plan_undistortion(Camera(W, H, 15, 15, 32, 24), fisheye)
    assert (wide.camera.width, wide.camera.height, wide.camera.cx, wide.camera.cy) == (2 * W, 2 * H, W, H)
    assert wide.valid.all()


# --- loading distorted scenes ------------------------------------------------------------------------
def test_colmap_opencv_scene_loads_as_the_pinhole_render(tmp_path, garden, caplog, cache):
    world, cameras, renders = garden
    root = write_colmap_scene(tmp_path / "opencv", "OPENCV", _colmap_params(BROWN, cameras[0]), cameras,
                              renders["OPENCV"])
    before = _folder_state(root)
    with caplog.at_level(logging.INFO, logger="nimbus.data.undistort"):
        scene = load_scene(root)
    notices = [r.getMessage() for r in caplog.records if r.name == "nimbus.data.undistort"]
    assert len(notices) == 1 and "undistorted 2 view(s)" in notices[0] and str(cache) in notices[0], notices
    assert "OPENCV (k1=-0.25" in notices[0]
    assert scene.metadata["undistorted"]["views"] == 2
    _check_against_reference(world, scene, cameras, renders["OPENCV"], BROWN)
    # Sparse points are 3D and unchanged; the split and names are the scene's.
    np.testing.assert_allclose(scene.points, [[0, 0, 0.6], [1, -0.5, 0.2]])
    assert scene.names == ["a.png", "b.png"]
    # Nothing in the scene was written; every undistorted file is in the cache.
    assert _folder_state(root) == before
    for v in scene.views:
        for p in (v.image_path, v.depth_path, v.mask_path, v.sky_path):
            assert cache in p.parents


@pytest.mark.parametrize("lens", [BROWN, FISHEYE], ids=["OPENCV", "OPENCV_FISHEYE"])
def test_transforms_scene_loads_like_the_colmap_scene(tmp_path, garden, lens):
    world, cameras, renders = garden
    keys = {"camera_model": lens.model, **dict(zip(("k1", "k2", "k3", "k4") if lens.fisheye
                                                    else ("k1", "k2", "p1", "p2"), lens.coeffs))}
    scene = load_scene(write_transforms_scene(tmp_path / "tf", keys, cameras, renders[lens.model]))
    _check_against_reference(world, scene, cameras, renders[lens.model], lens)
    # The same photos and calibration as a COLMAP scene: the same cameras, and the same cache entries.
    colmap = load_scene(write_colmap_scene(tmp_path / "colmap", lens.model, _colmap_params(lens, cameras[0]),
                                           cameras, renders[lens.model]))
    for a, b in zip(scene.views, colmap.views):
        np.testing.assert_allclose([a.camera.width, a.camera.height, a.camera.cx, a.camera.cy],
                                   [b.camera.width, b.camera.height, b.camera.cx, b.camera.cy], atol=1e-9)
        np.testing.assert_allclose(a.camera.world_to_camera, b.camera.world_to_camera, atol=1e-9)
        assert (a.image_path, a.mask_path, a.depth_path) == (b.image_path, b.mask_path, b.depth_path)


def test_transforms_mask_path_is_the_validity_mask(tmp_path, garden):
    """nerfstudio's per-frame mask_path is read (confined to the scene) and wins over masks/."""
    _, cameras, renders = garden
    root = write_transforms_scene(tmp_path / "tf", {}, cameras, renders["OPENCV"])
    write_mask(root / "own" / "a.png", np.zeros((H, W), bool))
    meta = json.loads((root / "transforms.json").read_text())
    meta["frames"][0]["mask_path"] = "own/a.png"
    (root / "transforms.json").write_text(json.dumps(meta))
    scene = load_scene(root)  # no distortion: the files are the scene's own
    assert scene.view("a.png").mask_path == root / "own" / "a.png"
    assert not scene.view("a.png").load_mask().any()
    assert scene.view("b.png").mask_path == root / "masks" / "b.png"
    meta["frames"][1]["mask_path"] = "masks/missing.png"
    (root / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(NimbusError, match=r"frame 1 .*mask_path: mask .*missing.png does not exist"):
        load_scene(root)


def test_fisheye_colmap_scene_loads_as_the_pinhole_render(tmp_path, garden):
    world, cameras, renders = garden
    root = write_colmap_scene(tmp_path / "fish", "OPENCV_FISHEYE", _colmap_params(FISHEYE, cameras[0]), cameras,
                              renders["OPENCV_FISHEYE"], text=True)
    scene = load_scene(root)
    _check_against_reference(world, scene, cameras, renders["OPENCV_FISHEYE"], FISHEYE)
    assert scene.views[0].camera.width > W  # an equidistant lens: the pinhole image is larger


def test_second_load_reads_the_cache_and_a_changed_photo_gets_a_new_entry(tmp_path, garden, cache, monkeypatch,
                                                                         caplog):
    _, cameras, renders = garden
    root = write_colmap_scene(tmp_path / "s", "OPENCV", _colmap_params(BROWN, cameras[0]), cameras,
                              renders["OPENCV"])
    first = load_scene(root)
    files = sorted(p for p in cache.rglob("*") if p.is_file())
    # Image, depth, validity and sky mask of two views; their (identical) validity masks share one entry.
    assert len(files) == 7
    stamps = {p: p.stat().st_mtime_ns for p in files}

    def no_resampling(*args, **kwargs):
        raise AssertionError("a cached view was resampled again")

    caplog.clear()
    with monkeypatch.context() as m, caplog.at_level(logging.INFO, logger="nimbus.data.undistort"):
        m.setattr(cv2, "remap", no_resampling)
        second = load_scene(root)
    notices = [r.getMessage() for r in caplog.records if r.name == "nimbus.data.undistort"]
    assert len(notices) == 1 and "0 file(s) new, 8 reused" in notices[0], notices
    assert [v.image_path for v in second.views] == [v.image_path for v in first.views]
    assert {p: p.stat().st_mtime_ns for p in files} == stamps
    # The key is the content: a retouched photo is undistorted again, its depth and masks are not.
    image = read_image(root / "images" / "a.png")
    write_image(root / "images" / "a.png", 1.0 - image)
    third = load_scene(root)
    assert third.view("a.png").image_path != first.view("a.png").image_path
    assert third.view("a.png").depth_path == first.view("a.png").depth_path
    assert third.view("b.png").image_path == first.view("b.png").image_path
    assert len([p for p in cache.rglob("*") if p.is_file()]) == 8
    # A cache that cannot be written is a clear error naming the way out.
    (tmp_path / "a-file").write_text("")
    monkeypatch.setenv("NIMBUS_CACHE", str(tmp_path / "a-file"))  # a file, not a folder
    with pytest.raises(NimbusError, match="cannot write the undistortion cache.*NIMBUS_CACHE"):
        load_scene(root)


def test_downscaled_images_undistort_to_the_scaled_camera(tmp_path, garden):
    _, cameras, renders = garden
    root = write_colmap_scene(tmp_path / "s", "OPENCV", _colmap_params(BROWN, cameras[0]), cameras,
                              renders["OPENCV"], mask=False)
    for name, (image, _, _) in zip(("a.png", "b.png"), renders["OPENCV"]):
        write_image(root / "images_2" / name, cv2.resize(image, (W // 2, H // 2), interpolation=cv2.INTER_AREA))
    full, half = load_scene(root).views[0].camera, load_scene(root, downscale=2).views[0].camera
    assert half.fx == pytest.approx(full.fx / 2)
    assert abs(half.width - full.width / 2) <= 1 and abs(half.height - full.height / 2) <= 1
    assert abs(half.cx - full.cx / 2) <= 0.5 and abs(half.cy - full.cy / 2) <= 0.5


# --- the CLI verb --------------------------------------------------------------------------------------
def _cli(capsys, *argv) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as e:
        synth_main([str(a) for a in argv])
    captured = capsys.readouterr()
    return e.value.code, captured.out, captured.err


def test_undistort_verb_writes_a_pinhole_colmap_scene(tmp_path, garden, capsys, cache):
    _, cameras, renders = garden
    root = write_colmap_scene(tmp_path / "phone", "OPENCV", _colmap_params(BROWN, cameras[0]), cameras,
                              renders["OPENCV"], names=("a.jpg", "b.png"))
    before = _folder_state(root)
    code, out, err = _cli(capsys, "undistort", root, "--out", tmp_path / "pinhole")
    assert code == 0, err
    assert "undistorted 2 of 2 views (OPENCV (k1=-0.25" in out
    rec = pycolmap.Reconstruction(tmp_path / "pinhole" / "sparse" / "0")
    assert {c.model_name for c in rec.cameras.values()} == {"PINHOLE"}
    written = load_scene(tmp_path / "pinhole")
    loaded = load_scene(root)
    assert "undistorted" not in written.metadata
    # The JPEG's undistorted image is a PNG and is written under a .png name.
    assert written.names == ["a.png", "b.png"]
    for w, v in zip(written.views, loaded.views):
        np.testing.assert_allclose([w.camera.fx, w.camera.cx, w.camera.width], [v.camera.fx, v.camera.cx,
                                                                                v.camera.width], atol=1e-9)
        np.testing.assert_array_equal(w.load_image(), v.load_image())
        np.testing.assert_array_equal(w.load_depth(), v.load_depth())
        np.testing.assert_array_equal(w.load_mask(), v.load_mask())
        np.testing.assert_array_equal(w.load_sky(), v.load_sky())
    assert not list(tmp_path.glob(".pinhole*"))  # no temporary folder left
    assert _folder_state(root) == before
    # The verb used its own cache inside --out's temporary folder (the loads above filled the user cache).
    assert all(".undistort-cache" not in p for p in _folder_state(tmp_path / "pinhole"))

    code, _, err = _cli(capsys, "undistort", root, "--out", tmp_path / "pinhole")
    assert code == 2 and "not empty; pass --overwrite" in err
    assert _cli(capsys, "undistort", root, "--out", tmp_path / "pinhole", "--overwrite")[0] == 0
    code, _, err = _cli(capsys, "undistort", root, "--out", root / "inside", "--overwrite")
    assert code == 2 and "lies inside the input" in err and "Traceback" not in err
    assert _folder_state(root) == before


def test_undistort_verb_writes_nothing_outside_out(tmp_path, garden, capsys, cache):
    _, cameras, renders = garden
    root = write_colmap_scene(tmp_path / "phone", "OPENCV", _colmap_params(BROWN, cameras[0]), cameras,
                              renders["OPENCV"])
    assert _cli(capsys, "undistort", root, "--out", tmp_path / "pinhole")[0] == 0
    assert not cache.parent.exists()  # the user cache was not touched
    assert sorted(p.name for p in tmp_path.iterdir()) == ["phone", "pinhole"]


# --- bad parameters ------------------------------------------------------------------------------------
def _tiny_colmap(root: Path, model: str, params, text: bool = True) -> Path:
    cam = Camera(W, H, 30, 30, 32, 24)
    return write_colmap_scene(root, model, params, [cam], [(np.zeros((H, W, 3), np.float32),
                                                            np.ones((H, W), np.float32), np.zeros((H, W), bool))],
                              names=("a.png",), text=text)


def test_nan_coefficient_in_a_colmap_model_is_a_clear_error(tmp_path):
    # Binary: pycolmap reads the NaN; the lens refuses it, naming the camera, model and parameter.
    root = _tiny_colmap(tmp_path / "bin", "OPENCV", [30, 30, 32, 24, 0.125, 0, 0, 0], text=False)
    cameras_bin = root / "sparse" / "0" / "cameras.bin"
    data = cameras_bin.read_bytes()
    k1 = data.index(struct.pack("<d", 0.125))
    cameras_bin.write_bytes(data[:k1] + struct.pack("<d", float("nan")) + data[k1 + 8:])
    with pytest.raises(NimbusError, match=r"camera 1 in .*OPENCV distortion parameter k1 must be finite"):
        load_scene(root)
    # Text: pycolmap refuses the line; the message names the file and line.
    root = _tiny_colmap(tmp_path / "txt", "OPENCV", [30, 30, 32, 24, 0.125, 0, 0, 0])
    cameras_txt = root / "sparse" / "0" / "cameras.txt"
    cameras_txt.write_text(cameras_txt.read_text().replace("0.125", "nan"))
    with pytest.raises(NimbusError, match=r"cameras.txt line \d+: camera parameters must be finite"):
        load_scene(root)


@pytest.mark.parametrize("model, params", [("FOV", [30, 30, 32, 24, 0.9]),
                                           ("EQUIRECTANGULAR", [64, 48])])
def test_colmap_model_nimbus_cannot_undistort_is_refused_with_the_fix(tmp_path, model, params):
    root = _tiny_colmap(tmp_path / "s", model, params, text=False)
    with pytest.raises(NimbusError, match=rf"{model} camera model, which Nimbus cannot undistort.*image_undistorter"):
        load_scene(root)


@pytest.mark.parametrize("keys, message", [
    ({"k1": float("nan")}, "field 'k1' must be a finite number"),
    ({"k1": "strong"}, "field 'k1' must be a number"),
    ({"camera_model": "EQUIRECTANGULAR"}, "camera_model EQUIRECTANGULAR is not supported"),
    ({"camera_model": "OPENCV", "k4": 0.01}, "k4=0.01 with camera_model OPENCV"),
    ({"camera_model": "OPENCV_FISHEYE", "p1": 0.01}, "OPENCV_FISHEYE has no tangential distortion"),
    ({"k1": -2.0}, "cannot be inverted at the border"),
])
def test_bad_transforms_lens_is_a_clear_error(tmp_path, garden, keys, message):
    _, cameras, renders = garden
    root = write_transforms_scene(tmp_path / "tf", keys, cameras, renders["OPENCV"])
    with pytest.raises(NimbusError, match=message):
        load_scene(root)


def test_degrading_a_distorted_scene_writes_its_pinhole_cameras(tmp_path, garden):
    """The benchmark writer must not copy the input's distorted model beside undistorted images."""
    from weather_synth.config import protocol_config
    from weather_synth.dataset import degrade_scene
    from weather_synth.settings import parse_weather

    _, cameras, renders = garden
    scene = load_scene(write_colmap_scene(tmp_path / "phone", "OPENCV", _colmap_params(BROWN, cameras[0]), cameras,
                                          renders["OPENCV"]))
    degrade_scene(scene, tmp_path / "bench", parse_weather("H"), protocol_config(), progress=False)
    rec = pycolmap.Reconstruction(tmp_path / "bench" / "H" / "sparse" / "0")
    assert {c.model_name for c in rec.cameras.values()} == {"PINHOLE"}
    hazy = load_scene(tmp_path / "bench" / "H")
    assert "undistorted" not in hazy.metadata
    for h, v in zip(hazy.views, scene.views):
        assert (h.camera.width, h.camera.height, h.camera.cx) == (v.camera.width, v.camera.height, v.camera.cx)
        assert h.load_image().shape == (v.camera.height, v.camera.width, 3)
