""".splat export (nimbus/train/splat.py, ``nimbus-bench export``): byte layout, viewer order, round trip."""

from __future__ import annotations

import numpy as np
import pytest

from benchmark.cli import TOOL
from nimbus.cli_util import run_cli
from nimbus.errors import NimbusError
from nimbus.train.ply import read_gaussian_ply, write_gaussian_ply
from nimbus.train.splat import SH_C0, encode_splat, read_splat, write_splat


def gaussians(n=200, k=4, seed=0):
    rng = np.random.default_rng(seed)
    return dict(means=rng.normal(size=(n, 3)).astype(np.float32),
                sh=rng.normal(scale=0.8, size=(n, k, 3)).astype(np.float32),
                opacity_logits=rng.normal(scale=2.0, size=n).astype(np.float32),
                log_scales=rng.uniform(-6, 0, size=(n, 3)).astype(np.float32),
                quats_wxyz=rng.normal(size=(n, 4)).astype(np.float32))


def viewer_order(g):
    """The splat viewer's order: descending exp(s0) exp(s1) exp(s2) sigmoid(opacity)."""
    size = np.exp(g["log_scales"].astype(np.float64)).prod(axis=1)
    return np.argsort(-(size / (1 + np.exp(-g["opacity_logits"].astype(np.float64)))), kind="stable")


def test_layout_of_one_splat_by_hand(tmp_path):
    q = np.array([[0.0, 0.0, 0.0, 2.0]])  # not normalised: (0, 0, 0, 1) after normalising
    raw = encode_splat([[1.0, -2.0, 3.5]], np.array([[[0.0, 1.0, -10.0]]]), [0.0], [[0.0, np.log(2.0), -1.0]], q)
    assert len(raw) == 32
    pos = np.frombuffer(raw[:12], "<f4")
    scale = np.frombuffer(raw[12:24], "<f4")
    np.testing.assert_array_equal(pos, [1.0, -2.0, 3.5])
    np.testing.assert_allclose(scale, [1.0, 2.0, np.exp(-1.0)], rtol=1e-7)
    # R = 0.5 * 255 = 127.5 -> 128 (ties to even), G = (0.5 + C0) * 255, B below 0 -> 0; A = sigmoid(0) = 127.5 -> 128
    assert list(raw[24:28]) == [128, round((0.5 + SH_C0) * 255), 0, 128]
    assert list(raw[28:32]) == [128, 128, 128, 255]  # 1 * 128 + 128 = 256, clipped


def test_round_trip_through_the_reader(tmp_path):
    g = gaussians()
    path = write_splat(tmp_path / "a.splat", **g)
    assert path.stat().st_size == 32 * len(g["means"])
    back = read_splat(path)
    order = viewer_order(g)
    np.testing.assert_array_equal(back["means"], g["means"][order])  # positions exact
    np.testing.assert_allclose(np.exp(back["log_scales"].astype(np.float64)),
                               np.exp(g["log_scales"][order].astype(np.float64)), rtol=2e-7)  # float32 scales
    colour = np.clip(0.5 + SH_C0 * g["sh"][order, 0].astype(np.float64), 0, 1)
    np.testing.assert_allclose(0.5 + SH_C0 * back["sh"][:, 0].astype(np.float64), colour, atol=0.5 / 255 + 1e-6)
    alpha = 1 / (1 + np.exp(-g["opacity_logits"][order].astype(np.float64)))
    alpha_back = 1 / (1 + np.exp(-back["opacity_logits"].astype(np.float64)))
    np.testing.assert_allclose(alpha_back, np.clip(alpha, 0.5 / 255, 1 - 0.5 / 255), atol=0.5 / 255 + 1e-6)
    q = g["quats_wxyz"][order].astype(np.float64)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    stored = np.clip(q * 128 + 128, 0, 255)
    # Each component within half a byte (plus the clip at 255 for a component of +1); the read-back
    # quaternion is renormalised, so compare the stored bytes, then the rotation it stands for.
    np.testing.assert_allclose(back["rotation"], stored, atol=0.5 + 1e-9)
    dots = np.abs(np.sum(back["quats_wxyz"] * q, axis=1))
    assert dots.min() > 0.99
    # The viewer's order: non-increasing size x opacity (of the exact values, before quantisation).
    size_opacity = np.exp(g["log_scales"][order].astype(np.float64)).prod(axis=1) * alpha
    assert np.all(np.diff(size_opacity) <= 0)


def test_reader_refuses_a_truncated_file(tmp_path):
    bad = tmp_path / "bad.splat"
    bad.write_bytes(b"\0" * 33)
    with pytest.raises(NimbusError, match="multiple of 32"):
        read_splat(bad)


def test_export_verb_from_a_run_folder(tmp_path, capsys):
    g = gaussians(n=50, k=4)
    run = tmp_path / "run"
    write_gaussian_ply(run / "point_cloud.ply", **g)
    out = tmp_path / "scene.splat"
    assert run_cli(TOOL.run, ["export", str(run), "--format", "splat", "--out", str(out)]) == 0
    assert "50 Gaussians" in capsys.readouterr().out
    ply = read_gaussian_ply(run / "point_cloud.ply")
    np.testing.assert_array_equal(read_splat(out)["means"], ply["means"][viewer_order(ply)])
    assert sorted(p.name for p in run.iterdir()) == ["point_cloud.ply"]  # the run folder is only read
    assert run_cli(TOOL.run, ["export", str(run), "--out", str(out)]) == 2  # exists, no --overwrite
    assert "--overwrite" in capsys.readouterr().err
    assert run_cli(TOOL.run, ["export", str(tmp_path / "nowhere"), "--out", str(tmp_path / "x.splat")]) == 2
    assert "does not exist" in capsys.readouterr().err
