"""Photos-only regression: a built-in scene's images alone -> ``nimbus-synth sfm`` -> 3DGS, against exact poses.

The built-in ``tiny`` size (64 x 48 px) is too small for SIFT (0 of 16 views register), so the
garden's orbit is rendered at the ``small`` size (240 x 180 px, 40 views, where COLMAP registers
every view) with 2 x 2 supersampling; only the PNGs go to SfM.  Both 3DGS runs use the ``tiny``
preset on half-size training images (``train_downscale=2``) to stay fast, and are scored on the
same held-out views (the LLFF split of the registered names) at full size.
"""

import argparse
import dataclasses
import json

import pytest

from tools.speed.sfm import render_photos
from nimbus.data.align import pose_error
from nimbus.data.io import load_scene
from nimbus.train.config import preset
from nimbus.train.runner import Runner
from weather_synth.commands import sfm as sfm_command

N_VIEWS, WIDTH, HEIGHT = 40, 240, 180
#: Measured on this scene: 40 / 40 registered, 0.3 to 0.45 deg mean rotation error, 0.5 to 1.0 % centre error.
MIN_REGISTERED = 36
MAX_ROTATION_DEG = 2.0
MAX_CENTER_ERROR = 0.04  # RMS centre error / rig extent
#: Measured on this machine: exact poses 17.85 dB, SfM poses 19.18 dB (SfM - exact = +1.33 dB; 18.81 dB with a
#: camera per photo); the exact-pose run with seeds 0, 1, 2 gave 17.85, 17.68, 17.95 dB (0.27 dB spread).  SfM is
#: not worse here: its poses are off by ~0.5 deg, and its test images are the undistorted (resampled, smoother)
#: photos, which a 300-iteration fit matches more easily.  A calibration gone wrong (focal 35 % short, kept fixed: the issue's failure)
#: gave 16.07 dB (-1.8 dB) with 19 deg of rotation error.  The margin, 1.0 dB, leaves ~2 dB of headroom below the
#: measured SfM run (seven times the seed spread) and still fails that wrong calibration; the pose check fails it
#: by far more.
PSNR_MARGIN_DB = 1.0


def _train_psnr(scene, out):
    config = dataclasses.replace(preset("tiny"), train_downscale=2)
    return Runner("3dgs", scene, config, out, seed=0, progress=False).run()["psnr"]


@pytest.mark.slow
def test_photos_only_reconstruction_matches_the_exact_pose_run(tmp_path, capsys):
    exact = render_photos("garden", N_VIEWS, WIDTH, HEIGHT, 0, tmp_path / "photos")
    parser = argparse.ArgumentParser()
    sfm_command.add_arguments(parser)
    assert sfm_command.run(parser.parse_args([str(tmp_path / "photos"), "--out", str(tmp_path / "scene")])) == 0
    printed = capsys.readouterr().out
    assert "calibration:" in printed and "focal length" in printed

    sfm = load_scene(tmp_path / "scene")
    assert len(sfm) >= MIN_REGISTERED
    true = {v.name: v.camera for v in exact.views}
    err = pose_error([v.camera for v in sfm.views], [true[v.name] for v in sfm.views])
    assert err.rotation_deg < MAX_ROTATION_DEG and err.center < MAX_CENTER_ERROR

    # A right calibration raises no warning, and the report is in the manifest.
    calibration = json.loads((tmp_path / "scene" / "manifest.json").read_text())["calibration"]
    assert calibration["registered"] == len(sfm) and calibration["warnings"] == []
    assert calibration["focal_px"] == pytest.approx(true["000.png"].fx, rel=0.03)

    # Exact poses on the same registered views and the same test split.
    exact = exact.with_views([v for v in exact.views if v.name in set(sfm.names)]).with_split(
        [v.name for v in sfm.test_views])
    assert [v.name for v in exact.test_views] == [v.name for v in sfm.test_views] and exact.test_views
    psnr_exact = _train_psnr(exact, tmp_path / "run_exact")
    psnr_sfm = _train_psnr(sfm, tmp_path / "run_sfm")
    print(f"PSNR exact poses {psnr_exact:.2f} dB, SfM poses {psnr_sfm:.2f} dB")
    assert psnr_sfm > psnr_exact - PSNR_MARGIN_DB
