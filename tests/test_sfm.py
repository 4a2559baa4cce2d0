"""Structure from motion on small synthetic photos of a textured room corner, and the `sfm` command."""

import argparse
import json

import cv2
import numpy as np
import pycolmap
import pytest

from nimbus.cli_util import run_cli
from nimbus.data.align import pose_error, umeyama
from nimbus.data.camera import Camera
from nimbus.data.images import write_image
from nimbus.data.io import load_scene
from nimbus.data.sfm import (FEW_VIEWS, STRONG_DISTORTION, CameraPrior, SfmConfig, _distortion, calibration_report,
                             choose_camera_model, choose_camera_sharing, exif_focal_px, list_photos, resolve_prior,
                             run_sfm)
from nimbus.errors import NimbusError
from weather_synth.commands import sfm as sfm_command

WIDTH, HEIGHT, N_VIEWS = 160, 120, 10
# Floor z=0 and walls x=-1, y=-1: three textured planes (axis, offset), non-planar so SfM is well posed.
PLANES = ((2, 0.0), (0, -1.0), (1, -1.0))
PLANE_HALF_SIZE = 2.0


def _texture(rng, size=256):
    """Multi-scale value noise: blobs at several sizes give SIFT plenty of distinctive corners."""
    t = np.zeros((size, size, 3), np.float32)
    for cells, weight in ((4, 0.5), (8, 0.5), (16, 0.4), (32, 0.3), (64, 0.2)):
        t += weight * cv2.resize(rng.random((cells, cells, 3), dtype=np.float32), (size, size),
                                 interpolation=cv2.INTER_CUBIC)
    return (t - t.min()) / (t.max() - t.min())


def _render(cam, textures):
    """Ray-cast the textured planes (nearest hit wins)."""
    d, o = cam.world_rays(np.float64)
    best = np.full(d.shape[:2], np.inf)
    img = np.zeros(d.shape, np.float32)
    for (axis, offset), tex in zip(PLANES, textures):
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (offset - o[axis]) / d[..., axis]
        p = o + s[..., None] * d
        a, b = (p[..., i] for i in range(3) if i != axis)
        hit = (s > 0) & (s < best) & (np.abs(a) < PLANE_HALF_SIZE) & (np.abs(b) < PLANE_HALF_SIZE)
        scale = tex.shape[0] / (2 * PLANE_HALF_SIZE)
        col = cv2.remap(tex, ((a + PLANE_HALF_SIZE) * scale).astype(np.float32),
                        ((b + PLANE_HALF_SIZE) * scale).astype(np.float32), cv2.INTER_LINEAR)
        img[hit] = col[hit]
        best[hit] = s[hit]
    return img


@pytest.fixture(scope="module")
def photos(tmp_path_factory):
    """10 photos on an arc looking into the corner, and their true cameras."""
    root = tmp_path_factory.mktemp("photos")
    rng = np.random.default_rng(0)
    textures = [_texture(rng) for _ in PLANES]
    cams = {}
    for i in range(N_VIEWS):
        ang = np.radians(20 + 50 * i / (N_VIEWS - 1))
        cam = Camera.look_at([3 * np.cos(ang), 3 * np.sin(ang), 1.6], [0, 0, 0.3], [0, 0, 1], WIDTH, HEIGHT, 60)
        write_image(root / f"{i:03d}.png", _render(cam, textures))
        cams[f"{i:03d}.png"] = cam
    return root, cams


def _similarity_residual(src, dst):
    """RMS distance after the best similarity transform src -> dst (Umeyama), relative to dst's spread."""
    res = umeyama(src, dst).apply(src) - dst
    return np.sqrt((res ** 2).sum(1).mean()) / np.sqrt(((dst - dst.mean(0)) ** 2).sum(1).mean())


def test_sfm_registers_the_photos_and_recovers_the_camera_path(photos, tmp_path):
    root, cams = photos
    result = run_sfm(root, tmp_path / "scene", seed=0)
    scene, registered, total = result.scene, result.registered, result.total
    assert total == N_VIEWS and registered >= N_VIEWS - 2 and registered == len(scene)
    # The default SIMPLE_RADIAL model is undistorted to PINHOLE, which load_scene accepts.
    rec = pycolmap.Reconstruction(tmp_path / "scene" / "sparse" / "0")
    assert {c.model_name for c in rec.cameras.values()} == {"PINHOLE"}
    assert len(scene.points) > 50
    est = np.stack([v.camera.center for v in scene.views])
    true = np.stack([cams[v.name].center for v in scene.views])
    assert _similarity_residual(est, true) < 0.05
    f_true = cams["000.png"].fx
    assert scene.views[0].camera.fx == pytest.approx(f_true, rel=0.1)
    # Same photos and seed: the same reconstruction, bit for bit (single-threaded by default).
    again = run_sfm(root, tmp_path / "again", seed=0).scene
    assert again.names == scene.names
    for a, b in zip(scene.views, again.views):
        np.testing.assert_array_equal(a.camera.world_to_camera, b.camera.world_to_camera)


def _args(*argv):
    parser = argparse.ArgumentParser()
    sfm_command.add_arguments(parser)
    return parser.parse_args(argv)


def test_sfm_command_prints_registration_and_copies_photos(photos, tmp_path, capsys):
    root, _ = photos
    out = tmp_path / "scene"
    code = sfm_command.run(_args(str(root), "--out", str(out), "--matcher", "sequential",
                                 "--camera-model", "SIMPLE_PINHOLE", "--single-camera"))
    text = capsys.readouterr().out
    assert code == 0
    registered = len(load_scene(out))
    assert f"registered {registered} / {N_VIEWS} views" in text and registered >= N_VIEWS - 2
    # Pinhole photos are copied byte for byte, not resampled.
    assert (out / "images" / "005.png").read_bytes() == (root / "005.png").read_bytes()
    # A second run into the same folder needs --overwrite.
    assert run_cli(lambda _: sfm_command.run(_args(str(root), "--out", str(out)))) == 2
    assert "not empty" in capsys.readouterr().err


def test_sfm_errors_leave_no_output(tmp_path, photos):
    (tmp_path / "empty").mkdir()
    with pytest.raises(NimbusError, match="no photos"):
        run_sfm(tmp_path / "empty", tmp_path / "out")
    rng = np.random.default_rng(0)
    for i in range(4):  # unrelated noise: nothing matches
        write_image(tmp_path / "noise" / f"{i}.png", rng.random((48, 64, 3), dtype=np.float32))
    with pytest.raises(NimbusError, match="no reconstruction"):
        run_sfm(tmp_path / "noise", tmp_path / "out")
    assert not (tmp_path / "out").exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []
    root, _ = photos
    with pytest.raises(NimbusError, match="outside the photo folder"):
        run_sfm(root, root / "scene")


# --- priors, EXIF and the calibration report (issue 15) -------------------------------------------------

def test_focal_prior_kept_fixed_and_reported_in_the_manifest(photos, tmp_path):
    root, cams = photos
    f_true = cams["000.png"].fx
    result = run_sfm(root, tmp_path / "scene", camera_model="SIMPLE_PINHOLE", focal_px=f_true, fix_intrinsics=True)
    cal = result.calibration
    # Fixed: every camera keeps the prior exactly, and the report says where it came from.
    assert [v.camera.fx for v in result.scene.views] == pytest.approx([f_true] * len(result.scene))
    assert cal.prior_source == "--focal" and cal.fixed and cal.focal_vs_prior == pytest.approx(0, abs=1e-9)
    assert cal.focal_probe_rise is None  # nothing to probe when the focal is not estimated
    manifest = json.loads((tmp_path / "scene" / "manifest.json").read_text())
    assert manifest["calibration"]["prior_source"] == "--focal"
    assert manifest["calibration"]["registered"] == result.registered == len(result.scene)
    assert manifest["sfm_config"]["fix_intrinsics"] is True


def test_report_flags_a_focal_far_from_the_prior(photos, tmp_path):
    """A prior 40 % too long, refined: the photos pull the focal back, and the report says the prior disagrees."""
    root, cams = photos
    f_true = cams["000.png"].fx
    cal = run_sfm(root, tmp_path / "scene", camera_model="SIMPLE_PINHOLE", single_camera=True,
                  focal_px=1.4 * f_true).calibration
    assert cal.focal_px == pytest.approx(f_true, rel=0.1)
    assert "focal-prior" in cal.flags
    text = "\n".join(cal.lines())
    assert "WARNING: the focal length" in text and "off the prior" in text
    # The right prior raises no focal warning.
    good = run_sfm(root, tmp_path / "good", camera_model="SIMPLE_PINHOLE", single_camera=True,
                   focal_px=f_true).calibration
    assert not {"focal-prior", "focal-range", "focal-unconstrained"} & set(good.flags)
    assert good.focal_probe_rise > 0.05  # 10 views of three planes do pin the focal length down


def test_fov_prior_and_camera_params_become_colmap_params(photos, tmp_path):
    root, cams = photos
    cam = cams["000.png"]
    config = SfmConfig(camera_model="SIMPLE_RADIAL", fov_deg=60.0)
    prior, notes = resolve_prior(root, list_photos(root), config, "SIMPLE_RADIAL")
    # f = (W/2) / tan(fov/2): the test photos were rendered with a 60 degree horizontal field of view.
    assert prior.source == "--fov" and prior.focal_px == pytest.approx(cam.fx, rel=1e-6)
    assert prior.params == pytest.approx((cam.fx, WIDTH / 2, HEIGHT / 2, 0.0))
    config = SfmConfig(camera_model="OPENCV", camera_params=(150, 151, 80, 60, 0.01, 0, 0, 0))
    prior, _ = resolve_prior(root, list_photos(root), config, "OPENCV")
    assert prior.focal_px == pytest.approx(150.5) and prior.params[4] == 0.01
    # PNGs have no EXIF: self-calibrated, with a note.
    prior, notes = resolve_prior(root, list_photos(root), SfmConfig(), "SIMPLE_RADIAL")
    assert prior is None and "no EXIF" in notes[0]


@pytest.mark.parametrize("changes, message", [
    (dict(focal_px=100.0, fov_deg=60.0), "give only one"),
    (dict(fov_deg=180.0), "--fov"),
    (dict(focal_px=-3.0), "--focal"),
    (dict(camera_params=(100.0, 80.0, 60.0)), "needs --camera-model"),
    (dict(camera_model="SIMPLE_RADIAL", camera_params=(100.0, 80.0, 60.0)), "needs 4 values"),
    (dict(camera_model="PINHOLE", camera_params=(0.0, 1.0, 80.0, 60.0)), "positive focal"),
])
def test_bad_priors_are_refused(changes, message):
    with pytest.raises(NimbusError, match=message):
        SfmConfig(**changes)


def test_fix_intrinsics_needs_a_prior_and_one_photo_size(photos, tmp_path):
    root, _ = photos
    with pytest.raises(NimbusError, match="--fix-intrinsics needs a camera prior"):
        run_sfm(root, tmp_path / "out", fix_intrinsics=True)
    mixed = tmp_path / "mixed"
    write_image(mixed / "a.png", np.zeros((40, 60, 3), np.float32))
    write_image(mixed / "b.png", np.zeros((30, 60, 3), np.float32))
    with pytest.raises(NimbusError, match="different sizes"):
        run_sfm(mixed, tmp_path / "out", focal_px=50.0)
    assert not (tmp_path / "out").exists()


def test_command_rejects_bad_camera_params_and_prints_the_report(photos, tmp_path, capsys):
    with pytest.raises(SystemExit):
        _args("photos", "--out", "x", "--camera-params", "1,abc")
    with pytest.raises(SystemExit):  # one prior at a time
        _args("photos", "--out", "x", "--focal", "100", "--fov", "60")
    root, cams = photos
    out = tmp_path / "scene"
    assert sfm_command.run(_args(str(root), "--out", str(out), "--fov", "60", "--camera-model", "SIMPLE_PINHOLE")) == 0
    text = capsys.readouterr().out
    assert "calibration:" in text and "from --fov" in text and "mean track length" in text


def _jpeg_with_exif(path, size, tags, sub_tags):
    from PIL import Image

    im = Image.new("RGB", size, (120, 90, 60))
    exif = Image.Exif()
    for k, v in tags.items():
        exif[k] = v
    ifd = exif.get_ifd(0x8769)
    for k, v in sub_tags.items():
        ifd[k] = v
    path.parent.mkdir(parents=True, exist_ok=True)
    im.save(path, exif=exif)


def test_exif_focal_length(tmp_path):
    from PIL.TiffImagePlugin import IFDRational

    # 35 mm equivalent: COLMAP's rule, 36 mm across the longest side.
    _jpeg_with_exif(tmp_path / "a.jpg", (400, 300), {}, {0xA405: 28})
    assert exif_focal_px(tmp_path / "a.jpg") == pytest.approx(28 / 36 * 400)
    # Focal length in mm times the sensor's pixels per mm, rescaled to the stored width (resized photo).
    _jpeg_with_exif(tmp_path / "b.jpg", (400, 300), {}, {0x920A: IFDRational(4, 1), 0xA20E: IFDRational(1000, 1),
                                                         0xA210: 4, 0xA002: 4000})
    assert exif_focal_px(tmp_path / "b.jpg") == pytest.approx(4 * 1000 * 400 / 4000)
    _jpeg_with_exif(tmp_path / "c.jpg", (400, 300), {}, {0x920A: IFDRational(4, 1)})  # no sensor size: unknown
    assert exif_focal_px(tmp_path / "c.jpg") is None
    (tmp_path / "d.jpg").write_bytes(b"not a jpeg")
    assert exif_focal_px(tmp_path / "d.jpg") is None
    # Every photo agreeing makes the prior; a photo without EXIF (or another zoom) makes none.
    photos = ["a.jpg"]
    prior, _ = resolve_prior(tmp_path, photos, SfmConfig(), "SIMPLE_RADIAL")
    assert prior.source == "exif" and prior.focal_px == pytest.approx(28 / 36 * 400)
    _jpeg_with_exif(tmp_path / "e.jpg", (400, 300), {}, {})
    prior, notes = resolve_prior(tmp_path, ["a.jpg", "e.jpg"], SfmConfig(), "SIMPLE_RADIAL")
    assert prior is None and "1 of 2" in notes[0]
    _jpeg_with_exif(tmp_path / "f.jpg", (400, 300), {}, {0xA405: 50})
    prior, notes = resolve_prior(tmp_path, ["a.jpg", "f.jpg"], SfmConfig(), "SIMPLE_RADIAL")
    assert prior is None and "differ" in notes[0]
    assert resolve_prior(tmp_path, photos, SfmConfig(use_exif=False), "SIMPLE_RADIAL")[0] is None


def test_auto_model_estimates_no_distortion_from_a_handful_of_photos():
    assert choose_camera_model("auto", FEW_VIEWS - 1)[0] == "SIMPLE_PINHOLE"
    assert choose_camera_model("auto", FEW_VIEWS)[0] == "SIMPLE_RADIAL"
    assert choose_camera_model("OPENCV", 3) == ("OPENCV", "given with --camera-model")


def test_distortion_magnitude_matches_the_radial_model():
    cam = pycolmap.Camera.create_from_model_name(1, "SIMPLE_RADIAL", 100.0, 200, 100)
    assert _distortion(cam) == (0.0, 0.0)
    cam.params = [100.0, 100.0, 50.0, 0.1]
    fraction, px = _distortion(cam)
    # The corner (100, 50) px from the centre is d = (1, 0.5) in distorted normalised units; the undistorted
    # radius s solves s (1 + k s^2) = |d|, and the corner moves by |d| - s of |d|.
    d = np.hypot(1.0, 0.5)
    s = np.roots([0.1, 0, 1, -d]).real[np.abs(np.roots([0.1, 0, 1, -d]).imag) < 1e-9][0]
    assert fraction == pytest.approx((d - s) / d, rel=1e-5) and px == pytest.approx(100 * (d - s), rel=1e-5)
    pinhole = pycolmap.Camera.create_from_model_name(1, "PINHOLE", 100.0, 200, 100)
    assert _distortion(pinhole) == (0.0, 0.0)


def test_umeyama_and_pose_error_recover_a_known_similarity(photos):
    _, cams = photos
    true = [cams[k] for k in sorted(cams)]
    rng = np.random.default_rng(3)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    R = q * np.sign(np.linalg.det(q))  # a proper rotation
    s, t = 0.37, np.array([2.0, -1.0, 5.0])
    # The same rig in another world frame: x' = s R x + t, so each camera's world-to-camera rotation becomes
    # R_wc R^T and its centre s R c + t.
    moved = [c.with_pose(c.world_to_camera[:3, :3] @ R.T, -(c.world_to_camera[:3, :3] @ R.T) @ (s * R @ c.center + t))
             for c in true]
    sim = umeyama(np.stack([c.center for c in true]), np.stack([c.center for c in moved]))
    assert sim.scale == pytest.approx(s) and np.allclose(sim.rotation, R) and np.allclose(sim.translation, t)
    err = pose_error(moved, true)
    assert err.rotation_deg_max < 1e-6 and err.center_max < 1e-9
    # A camera turned by 5 degrees about its axis shows up as 5 degrees (mean over 10 cameras: 0.5).
    c = moved[0]
    turn = np.array([[np.cos(0.0873), -np.sin(0.0873), 0], [np.sin(0.0873), np.cos(0.0873), 0], [0, 0, 1]])
    R_wc = turn @ c.world_to_camera[:3, :3]
    err = pose_error([c.with_pose(R_wc, -R_wc @ c.center)] + moved[1:], true)
    assert err.rotation_deg_max == pytest.approx(np.degrees(0.0873), rel=1e-3)
    assert err.rotation_deg == pytest.approx(np.degrees(0.0873) / len(true), rel=1e-3)
    with pytest.raises(ValueError):
        umeyama(np.zeros((3, 3)), np.ones((3, 3)))


def test_exif_prior_reaches_the_reconstruction(photos, tmp_path):
    """JPEGs stating a 35 mm-equivalent focal length: the prior comes from EXIF and the report compares with it."""
    from PIL import Image

    root, cams = photos
    f35 = round(cams["000.png"].fx / WIDTH * 36)  # the tag is an integer number of millimetres
    (tmp_path / "jpg").mkdir()
    for png in sorted(root.glob("*.png")):
        exif = Image.Exif()
        exif.get_ifd(0x8769)[0xA405] = f35
        Image.open(png).convert("RGB").save(tmp_path / "jpg" / f"{png.stem}.jpg", exif=exif, quality=95)
    cal = run_sfm(tmp_path / "jpg", tmp_path / "scene", single_camera=True).calibration
    assert cal.prior_source == "exif" and cal.prior_focal_px == pytest.approx(f35 / 36 * WIDTH)
    assert cal.focal_vs_prior == pytest.approx(cal.focal_px / cal.prior_focal_px - 1)
    assert abs(cal.focal_vs_prior) < 0.1 and "focal-prior" not in cal.flags


def _handmade_reconstruction():
    """3 images on a line looking at a plane z = 5; points 0-39 seen by images 1 and 2, points 40-59 by 2 and 3."""
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera.create_from_model_name(1, "SIMPLE_PINHOLE", 250.0, 200, 100)
    rec.add_camera_with_trivial_rig(cam)
    rng = np.random.default_rng(0)
    xyz = np.c_[rng.uniform(-1, 1, (60, 2)), np.full(60, 5.0)]
    seen = {1: range(0, 40), 2: range(0, 60), 3: range(40, 60)}
    index = {}
    for image_id, x in zip((1, 2, 3), (-0.5, 0.0, 0.5)):
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(np.eye(3)), np.array([-x, 0.0, 0.0]))
        keypoints = []
        for k, p in enumerate(seen[image_id]):
            c = xyz[p] + [-x, 0, 0]
            keypoints.append([250 * c[0] / c[2] + 100, 250 * c[1] / c[2] + 50])
            index[image_id, p] = k
        image = pycolmap.Image(name=f"{image_id}.png", keypoints=np.array(keypoints), camera_id=1, image_id=image_id)
        rec.add_image_with_trivial_frame(image, pose)
    for p in range(60):
        track = pycolmap.Track([pycolmap.TrackElement(i, index[i, p]) for i in (1, 2, 3) if (i, p) in index])
        rec.add_point3D(xyz[p], track, np.zeros(3, np.uint8))
    return rec


def test_report_measures_tracks_and_overlap_and_flags_them():
    rec = _handmade_reconstruction()
    cal = calibration_report(rec, 4, "SIMPLE_PINHOLE", "test", None, SfmConfig(focal_probe=False))
    assert (cal.registered, cal.total, cal.points, cal.cameras) == (3, 4, 60, 1)
    assert cal.mean_track_length == pytest.approx(2.0)
    assert cal.observations_per_view == pytest.approx((40 + 60 + 20) / 3)
    # best neighbours: image 1 -> 2 (40 shared), 2 -> 1 (40), 3 -> 2 (20)
    assert cal.shared_points_best_neighbour == pytest.approx(100 / 3)
    assert cal.focal_vs_default == pytest.approx(250 / (1.2 * 200))
    assert cal.reprojection_error_px == pytest.approx(0, abs=1e-6) and cal.distortion == 0
    assert set(cal.flags) == {"registered", "short-tracks", "low-overlap"} and len(cal.warnings) == 3
    # A focal length far from 1.2 x the longest side, and a prior it disagrees with, are flagged too.
    rec.cameras[1].params = [90.0, 100.0, 50.0]
    prior = CameraPrior("--focal", 60.0, (60.0, 100.0, 50.0))
    cal = calibration_report(rec, 3, "SIMPLE_PINHOLE", "test", prior, SfmConfig(focal_probe=False))
    assert {"focal-range", "focal-prior"} <= set(cal.flags) and "registered" not in cal.flags
    assert cal.focal_vs_prior == pytest.approx(0.5)


def test_report_json_is_strict_when_the_distortion_does_not_invert():
    """A per-photo camera with a wild distortion term (tabletop, 36 views) made the distortion infinite; the
    manifest must stay strict JSON and the printed report must say what happened."""
    import dataclasses

    cal = calibration_report(_handmade_reconstruction(), 3, "SIMPLE_PINHOLE", "test", None,
                             SfmConfig(focal_probe=False))
    wild = dataclasses.replace(cal, distortion=float("inf"), distortion_px=float("inf"))
    d = wild.to_dict()
    assert d["distortion"] is None and d["distortion_px"] is None
    json.dumps(d, allow_nan=False)
    assert any("does not invert" in line for line in wild.lines())
    cam = pycolmap.Camera.create_from_model_name(1, "SIMPLE_RADIAL", 100.0, 200, 100)
    cam.params = [100.0, 100.0, 50.0, -2.0]  # strong barrel: the corner lies beyond the model's fold
    assert _distortion(cam)[0] > STRONG_DISTORTION


def test_photos_of_one_size_share_a_camera_unless_told_otherwise(photos, tmp_path):
    root, _ = photos
    names = list_photos(root)
    shared, why = choose_camera_sharing(root, names, SfmConfig())
    assert shared and "one shared camera" in why and f"{WIDTH}x{HEIGHT}" in why
    assert choose_camera_sharing(root, names, SfmConfig(single_camera=False)) == (False, "a camera per photo "
                                                                                         "(--camera-per-photo)")
    mixed = tmp_path / "mixed"
    write_image(mixed / "a.png", np.zeros((40, 60, 3), np.float32))
    write_image(mixed / "b.png", np.zeros((30, 60, 3), np.float32))
    assert choose_camera_sharing(mixed, ["a.png", "b.png"], SfmConfig()) == (False, "a camera per photo: the "
                                                                                    "photos have 2 sizes")
    _jpeg_with_exif(tmp_path / "zoom" / "a.jpg", (400, 300), {}, {0xA405: 28})
    _jpeg_with_exif(tmp_path / "zoom" / "b.jpg", (400, 300), {}, {0xA405: 50})
    assert not choose_camera_sharing(tmp_path / "zoom", ["a.jpg", "b.jpg"], SfmConfig())[0]
    assert choose_camera_sharing(tmp_path / "zoom", ["a.jpg", "b.jpg"], SfmConfig(use_exif=False))[0]
    # The default run records the decision; the command's flags map to True / False.
    result = run_sfm(root, tmp_path / "scene", camera_model="SIMPLE_PINHOLE")
    assert result.calibration.cameras == 1 and "one shared camera" in result.calibration.camera_sharing
    assert json.loads((tmp_path / "scene" / "manifest.json").read_text())["sfm_config"]["single_camera"] is True
    assert _args("p", "--out", "o").single_camera is None
    assert _args("p", "--out", "o", "--camera-per-photo").single_camera is False
    assert _args("p", "--out", "o", "--single-camera").single_camera is True
