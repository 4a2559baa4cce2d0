"""``nimbus-bench score`` / score_renders: matching renders to views, ground-truth sources, errors, results file."""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest

from benchmark.cli import TOOL
from benchmark.score import score_renders
from nimbus.cli_util import run_cli
from nimbus.data import load_scene, write_scene
from nimbus.data.images import read_image, write_image
from nimbus.errors import NimbusError
from nimbus.metrics import LPIPS, peak_signal_noise_ratio, random_state_dict, structural_similarity
from nimbus.utils.fs import sha256_file

TEST = ["000.png", "003.png"]


@pytest.fixture
def bench(tmp_path, make_scene, monkeypatch):
    """A scene on disk (6 views of 48x36, test views 000 and 003) and noisy renders of every view."""
    monkeypatch.setenv("NIMBUS_CACHE", str(tmp_path / "empty-cache"))  # no LPIPS weights unless a test adds them
    scene_dir, renders = tmp_path / "scene", tmp_path / "renders"
    write_scene(make_scene(n_views=6, width=48, height=36, test_names=TEST), scene_dir)
    rng = np.random.default_rng(0)
    for v in load_scene(scene_dir).views:
        img = v.load_image()
        write_image(renders / f"{v.stem}.png", np.clip(img + rng.normal(0, 0.05, img.shape), 0, 1))
    return scene_dir, renders


def cli(argv: list[str]) -> int:
    return run_cli(TOOL.run, argv)


def test_scores_test_views_with_hashes(bench):
    scene_dir, renders = bench
    res = score_renders(renders, scene_dir, lpips_net=None)
    assert [r["name"] for r in res["per_view"]] == TEST and res["views"] == 2 and res["split"] == "test"
    for r in res["per_view"]:
        pred, gt = read_image(r["pred"]), read_image(r["gt"])
        assert r["gt"] == str(scene_dir / "images" / r["name"])
        assert r["psnr"] == pytest.approx(peak_signal_noise_ratio(pred, gt))
        assert r["ssim"] == pytest.approx(structural_similarity(pred, gt))
        assert r["pred_sha256"] == sha256_file(r["pred"]) and r["gt_sha256"] == sha256_file(r["gt"])
    assert res["mean"]["psnr"] == pytest.approx(np.mean([r["psnr"] for r in res["per_view"]]))
    assert res["protocol"]["ssim"] == "3dgs" and res["protocol"]["lpips"] is None
    assert any("4 image(s)" in n for n in res["notes"])  # the train renders were not scored
    assert {"nimbus", "torch", "numpy"} <= set(res["versions"])


def test_split_all_jpeg_renders_and_lpips_instance(bench):
    scene_dir, renders = bench
    (renders / "001.png").unlink()
    cv2.imwrite(str(renders / "001.jpg"), np.full((36, 48, 3), 128, np.uint8))
    lp = LPIPS("vgg", state_dict=random_state_dict("vgg"))
    res = score_renders(renders, scene_dir, split="all", ssim_protocol="skimage", lpips_net=lp)
    assert len(res["per_view"]) == 6 and res["per_view"][1]["pred"].endswith("001.jpg")
    assert all(r["lpips"] > 0 for r in res["per_view"]) and res["protocol"]["ssim"] == "skimage"


def test_degraded_setting_folder_is_scored_against_clean(bench, tmp_path):
    scene_dir, renders = bench
    # A weather_synth setting folder: images/ degraded, clean/ the ground truth.
    shutil.copytree(scene_dir / "images", scene_dir / "clean")
    for f in (scene_dir / "images").iterdir():
        write_image(f, np.zeros((36, 48, 3), np.float32))
    res = score_renders(renders, scene_dir, lpips_net=None)
    assert res["per_view"][0]["gt"] == str(scene_dir / "clean" / "000.png") and res["mean"]["psnr"] > 20
    assert res["ground_truth"].startswith("clean/")
    # --gt-dir overrides clean/
    res2 = score_renders(renders, scene_dir, lpips_net=None, gt_dir=scene_dir / "images")
    assert res2["mean"]["psnr"] < res["mean"]["psnr"] - 5


def test_nerfbaselines_color_folder(bench, tmp_path):
    scene_dir, renders = bench
    nb = tmp_path / "nb"
    shutil.copytree(renders, nb / "color")
    res = score_renders(nb, scene_dir, lpips_net=None)
    assert res["per_view"][0]["pred"] == str(nb / "color" / "000.png")


def test_missing_mis_sized_and_ambiguous_renders_are_clear_errors(bench, tmp_path):
    scene_dir, renders = bench
    (renders / "003.png").unlink()
    with pytest.raises(NimbusError, match=r"1 of 2 views have no render in .*: 003.png"):
        score_renders(renders, scene_dir, lpips_net=None)
    write_image(renders / "003.png", np.zeros((18, 24, 3), np.float32))
    with pytest.raises(NimbusError, match="003.png is 24x18, ground truth 48x36"):
        score_renders(renders, scene_dir, lpips_net=None)
    (renders / "003.png").unlink()
    for ext in (".jpg", ".jpeg"):
        cv2.imwrite(str(renders / f"003{ext}"), np.zeros((36, 48, 3), np.uint8))
    with pytest.raises(NimbusError, match="several images for view 003.png"):
        score_renders(renders, scene_dir, lpips_net=None)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(NimbusError, match="holds no images"):
        score_renders(empty, scene_dir, lpips_net=None)


def test_dataset_root_is_refused_with_a_hint(bench, tmp_path):
    scene_dir, renders = bench
    root = tmp_path / "degraded"
    shutil.copytree(scene_dir, root / "H")
    (root / "H" / "clean").mkdir()
    (root / "index.json").write_text("{}")
    with pytest.raises(NimbusError, match=r"one scene per weather setting \(H\); pass one of them"):
        score_renders(renders, root, lpips_net=None)


def test_cli_writes_json_and_reports_missing_lpips(bench, tmp_path, capsys):
    scene_dir, renders = bench
    out = tmp_path / "results.json"
    assert cli(["score", "--pred", str(renders), "--gt", str(scene_dir), "--ssim", "dmpix", "--out", str(out)]) == 0
    captured = capsys.readouterr()
    assert "mean" in captured.out and "n/a" in captured.out and "dmpix" in captured.out
    assert "nimbus-bench setup-weights" in captured.err
    res = json.loads(out.read_text())  # strict JSON: parses without inf / NaN
    assert res["format"] == "nimbus-bench-score/1" and res["mean"]["lpips"] is None
    assert "nimbus-bench setup-weights" in res["lpips_missing"]
    assert [r["name"] for r in res["per_view"]] == TEST
    # an existing --out is kept unless --overwrite
    assert cli(["score", "--pred", str(renders), "--gt", str(scene_dir), "--out", str(out), "--lpips", "none"]) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert cli(["score", "--pred", str(renders), "--gt", str(scene_dir), "--out", str(out), "--lpips", "none",
                "--overwrite"]) == 0


def test_cli_errors_exit_2_without_traceback(bench, tmp_path, capsys):
    scene_dir, renders = bench
    assert cli(["score", "--pred", str(tmp_path / "nope"), "--gt", str(scene_dir)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: renders folder") and "Traceback" not in err
    with pytest.raises(SystemExit) as e:
        cli(["score", "--pred", str(renders), "--gt", str(scene_dir), "--ssim", "ms-ssim"])
    assert e.value.code == 2
