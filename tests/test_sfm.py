"""Structure from motion on small synthetic photos of a textured room corner, and the `sfm` command."""

import argparse

import cv2
import numpy as np
import pycolmap
import pytest

from nimbus.cli_util import run_cli
from nimbus.data.camera import Camera
from nimbus.data.images import write_image
from nimbus.data.io import load_scene
from nimbus.data.sfm import run_sfm
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
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    u, sig, vt = np.linalg.svd(b.T @ a)
    d = np.diag([1, 1, np.sign(np.linalg.det(u @ vt))])
    R = u @ d @ vt
    s = np.trace(np.diag(sig) @ d) / (a ** 2).sum()
    res = b - s * a @ R.T
    return np.sqrt((res ** 2).sum(1).mean()) / np.sqrt((b ** 2).sum(1).mean())


def test_sfm_registers_the_photos_and_recovers_the_camera_path(photos, tmp_path):
    root, cams = photos
    result = run_sfm(root, tmp_path / "scene", seed=0)
    scene, registered, total = result
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
