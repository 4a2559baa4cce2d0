"""``nimbus-bench run --scenes`` on folders: a dataset tree in the NimbusGS authors' layout, a scene folder, a
store refusing two scenes of one name, and the paper's evaluation protocol (float PSNR).

The data is the tiny built-in garden (16 views of 64x48) rendered by the grid's own code; every cell is
3DGS with 5 iterations, run in this process (the CLI's executor replaced by the inline one).
"""

from __future__ import annotations

import html
import json
import os
import shutil

import numpy as np
import pytest

from benchmark.cell import synthesize, write_clean_scene
from benchmark.cli import TOOL
from benchmark.grid import InlineExecutor
from benchmark.html_report import reproduce_commands
from benchmark.scene_sources import resolve_scenes, scene_hash, setting_from_folder
from benchmark.store import ResultsStore, check_scene_hashes, load_results
from nimbus.cli_util import run_cli
from nimbus.data.images import read_image
from nimbus.errors import NimbusError
from nimbus.metrics import peak_signal_noise_ratio as psnr
from nimbus.utils.fs import sha256_file

RUN = ["run", "--methods", "3dgs", "--preset", "tiny", "--set", "iterations=5", "--lpips", "none", "--quiet"]
#: The authors' folder names of the settings the tree gets, and ours.
AUTHORS = {"haze": "H", "haze_rain": "H+R"}


def _files(folder):
    return sorted((str(p.relative_to(folder)), p.stat().st_size, p.stat().st_mtime_ns)
                  for p in folder.rglob("*"))


@pytest.fixture(autouse=True)
def inline(monkeypatch):
    monkeypatch.setattr("benchmark.commands.run.executor_from_args", lambda args: InlineExecutor())


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """The clean tiny garden as a scene folder, and a tree in the authors' layout degraded from it."""
    base = tmp_path_factory.mktemp("scenes")
    clean = base / "mygarden"
    write_clean_scene("garden", "tiny", clean)
    synthesize(clean, base / "ours", list(AUTHORS.values()), progress=False, source="test")
    tree = base / "NimbusGS-Dataset"
    for theirs, ours in AUTHORS.items():
        scene = tree / theirs / "garden"
        for entry in ("images", "sparse", "clean"):
            shutil.copytree(base / "ours" / ours / entry, scene / entry)
        shutil.copytree(scene / "images", scene / "input")  # COLMAP's raw copy: never read
    return clean, tree


def test_setting_folder_names():
    assert setting_from_folder("haze_rain_snow") == "H+R+S"
    assert setting_from_folder("rain-snow") == "R+S"
    assert setting_from_folder("Haze") == "H"
    assert setting_from_folder("H+S") == "H+S"
    assert setting_from_folder("input") is None and setting_from_folder("clean") is None


def test_what_each_folder_is(data, tmp_path, monkeypatch):
    clean, tree = data
    ours = clean.parent / "ours"  # what nimbus-synth degrade wrote
    (src,) = resolve_scenes([str(ours)], "tiny")
    assert (src.kind, src.name, src.size, [s for s, _ in src.settings]) == ("tree", "ours", "images", ["H", "H+R"])
    (src,) = resolve_scenes([str(tree)], "tiny")
    assert (src.kind, src.name, dict(src.settings)) == ("tree", "garden", {
        "H": str(tree.resolve() / "haze" / "garden"), "H+R": str(tree.resolve() / "haze_rain" / "garden")})
    (src,) = resolve_scenes([str(clean)], "tiny")
    assert (src.kind, src.name, src.data_name, src.path) == ("capture", "mygarden", "mygarden", str(clean.resolve()))
    photos = tmp_path / "photos"
    shutil.copytree(clean / "images", photos)
    assert resolve_scenes([str(photos)], "tiny")[0].kind == "photos"
    assert resolve_scenes(["garden"], "small")[0].data_name == "garden-small"
    monkeypatch.chdir(clean.parent)
    assert resolve_scenes(["mygarden"], "tiny")[0].kind == "capture"  # a folder in the working directory
    with pytest.raises(NimbusError, match="has no images_2/"):
        resolve_scenes([str(clean)], "tiny", downscale=2)
    shutil.copytree(clean, tmp_path / "mygarden")
    (tmp_path / "mygarden" / "test_list.txt").write_text("000.png\n")
    with pytest.raises(NimbusError, match="two different scenes 'mygarden'"):
        resolve_scenes([str(clean), str(tmp_path / "mygarden")], "tiny")
    with pytest.raises(NimbusError, match="neither a scene folder"):
        resolve_scenes([str(tmp_path / "mygarden" / "sparse")], "tiny")


@pytest.mark.slow
def test_an_authors_tree_runs_through_run_tables_and_report(data, tmp_path, capsys):
    _, tree = data
    before = _files(tree)
    root = tmp_path / "root"
    assert run_cli(TOOL.run, RUN + ["--scenes", str(tree), "--root", str(root)]) == 0, capsys.readouterr().err
    out, err = capsys.readouterr()
    assert "authors' layout, 1 scene(s) (garden)" in err
    recs = ResultsStore(root).records()
    assert sorted(r["weather"] for r in recs) == ["H", "H+R", "clean"]
    assert all(r["status"] == "ok" and r["scene"] == "garden" for r in recs)
    assert {r["scene_path"] for r in recs} == {str(tree.resolve())}
    assert {r["scene_hash"] for r in recs} == {resolve_scenes([str(tree)], "tiny")[0].scene_hash}
    # Each weather cell trained on the tree's degraded images and was scored against its clean/ images.
    for r in recs:
        if r["weather"] == "clean":
            continue
        theirs = tree / {v: k for k, v in AUTHORS.items()}[r["weather"]] / "garden"
        data_dir = root / "data" / "garden" / r["weather"]
        assert sha256_file(data_dir / "images" / "000.png") == sha256_file(theirs / "images" / "000.png")
        assert r["ground_truth"].startswith("clean/")
        for v in r["per_view"]:
            render = read_image(root / r["run_dir"] / "renders" / "test" / v["name"])
            assert v["psnr"] == pytest.approx(psnr(render, read_image(theirs / "clean" / v["name"])))
        # Its input's own score: the tree's degraded test views against its clean ones.
        assert r["input_psnr"] == pytest.approx(np.mean([psnr(read_image(theirs / "images" / v["name"]),
                                                              read_image(theirs / "clean" / v["name"]))
                                                         for v in r["per_view"]]))
    assert _files(tree) == before  # nothing written into the user's folders

    assert {r["scene_kind"] for r in recs} == {"tree"}
    assert run_cli(TOOL.run, ["tables", "--root", str(root), "--out", str(tmp_path / "tables")]) == 0
    table = (tmp_path / "tables" / "weather_H+R.md").read_text()
    assert "garden PSNR" in table and "garden-images" not in table
    # The tree brought its own degraded images: the table does not claim our synthesis protocol made them.
    assert "dataset tree(s) given to --scenes" in table and "Synthesis protocol: onerestore" not in table
    assert run_cli(TOOL.run, ["report", "--root", str(root), "--out", str(tmp_path / "report")]) == 0
    page = (tmp_path / "report" / "index.html").read_text()
    assert "garden" in page
    # The report's command runs the tree again (its path, not the name of a built-in scene).
    (command,) = reproduce_commands(recs, str(root))
    assert f"--scenes {tree.resolve()} " in command and "--size" not in command
    assert html.escape(command, quote=False) in page or html.escape(command) in page
    capsys.readouterr()


def test_a_scene_folder_is_degraded_under_the_root_and_scored_by_the_paper_protocol(data, tmp_path, capsys):
    clean, _ = data
    before = _files(clean)
    root = tmp_path / "root"
    argv = RUN + ["--scenes", str(clean), "--weathers", "H", "--no-ceiling", "--protocol", "paper",
                  "--root", str(root)]
    assert run_cli(TOOL.run, argv) == 0, capsys.readouterr().err
    capsys.readouterr()
    assert _files(clean) == before  # degraded under the root, never in the scene folder
    manifest = json.loads((root / "data" / "mygarden" / "H" / "manifest.json").read_text())
    assert manifest["config"]["depth"]["source"] == "auto"
    (rec,) = ResultsStore(root).records()
    assert rec["status"] == "ok", rec.get("error")
    assert (rec["scene"], rec["size"], rec["eval_protocol"]) == ("mygarden", "images", "paper")
    assert rec["scene_path"] == str(clean.resolve()) and rec["scene_hash"] == scene_hash(clean)
    assert rec["scene_kind"] == "capture"
    (command,) = reproduce_commands([rec], str(root))  # the folder and the paper protocol, as they were given
    assert f"--scenes {clean.resolve()} " in command and "--protocol paper" in command and "--size" not in command
    assert rec["protocol"]["quantize_8bit"] is False
    # PSNR of the float render against the clean image, not of the 8-bit PNG the run saved.
    run = root / rec["run_dir"]
    rounded = []
    for v in rec["per_view"]:
        stem = os.path.splitext(v["name"])[0]
        pred = np.load(run / "renders_float" / "test" / f"{stem}.npy")
        gt = read_image(root / "data" / "mygarden" / "H" / "clean" / v["name"])
        assert v["psnr"] == pytest.approx(psnr(pred, gt, quantize=False), abs=1e-9)
        rounded.append(psnr(read_image(run / "renders" / "test" / v["name"]), gt))
    assert [v["psnr"] for v in rec["per_view"]] != pytest.approx(rounded, abs=1e-6)
    # The degraded input is an 8-bit PNG: scored without rounding, it scores as the default protocol scores it.
    data = root / "data" / "mygarden" / "H"
    assert rec["input_psnr"] == pytest.approx(np.mean([psnr(read_image(data / "images" / v["name"]),
                                                            read_image(data / "clean" / v["name"]), quantize=False)
                                                       for v in rec["per_view"]]), abs=1e-9)
    # A root keeps one protocol: the same grid scored the default way is refused.
    assert run_cli(TOOL.run, [a for a in argv if a not in ("--protocol", "paper")]) == 2
    assert "--protocol paper" in capsys.readouterr().err


def test_a_store_refuses_two_scenes_of_one_name(data, tmp_path, capsys):
    clean, _ = data
    other = tmp_path / "elsewhere" / clean.name
    shutil.copytree(clean, other)
    (other / "test_list.txt").write_text("000.png\n")  # another split: another scene
    assert scene_hash(other) != scene_hash(clean)
    root = tmp_path / "root"
    root.mkdir()
    cell = {"status": "ok", "scene": "mygarden", "size": "images", "method": "3dgs", "preset": "tiny", "seed": 0}
    ResultsStore(root).append({**cell, "cell_id": "mygarden_H_3dgs_tiny_s0", "weather": "H",
                               "scene_path": str(clean), "scene_hash": scene_hash(clean)})
    before = (root / "results.jsonl").read_bytes()
    assert run_cli(TOOL.run, RUN + ["--scenes", str(other), "--weathers", "H", "--root", str(root)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "already holds a scene named 'mygarden'" in err and "Traceback" not in err
    assert (root / "results.jsonl").read_bytes() == before and not (root / "data").exists()
    # A store that mixes them anyway (records merged by hand) is refused by every reader.
    ResultsStore(root).append({**cell, "cell_id": "mygarden_R_3dgs_tiny_s0", "weather": "R",
                               "scene_path": str(other), "scene_hash": scene_hash(other)})
    with pytest.raises(NimbusError, match="mixes two scenes named 'mygarden'"):
        load_results(root)
    check_scene_hashes(ResultsStore(root).records()[:1], "one record")  # one scene alone is fine


@pytest.mark.parametrize("scenes, message", [
    ("/no/such/folder", "does not exist"),
    ("nosuchscene", "unknown"),
])
def test_a_bad_scene_is_one_clear_error(scenes, message, tmp_path, capsys):
    assert run_cli(TOOL.run, RUN + ["--scenes", scenes, "--root", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error:") and message in err and "Traceback" not in err
    assert not (tmp_path / "r").exists()


def test_a_photo_folder_runs_through_sfm_degrade_train_score_and_tables(tmp_path, capsys):
    """Photos only (no poses): ``nimbus-bench run --scenes PHOTOS`` poses them by SfM under the root, degrades the
    posed scene, trains, scores against its clean images and tables it; the photo folder is not written."""
    from nimbus.data.builtin import get_scene
    from nimbus.data.builtin.raycast import RenderSettings, render_view
    from nimbus.data.images import write_image

    photos = tmp_path / "myphotos"
    config = get_scene("garden").config
    world = config.world(0)
    # 14 neighbouring views of the 40-view orbit (9 degrees apart) at 240 x 180: SIFT needs this size and overlap.
    for i, cam in enumerate(config.cameras(40, 240, 180, 0)[:14]):
        write_image(photos / f"{i:03d}.png", render_view(world, cam, RenderSettings(samples_per_axis=1)).image)
    before = _files(photos)
    root = tmp_path / "root"
    argv = RUN + ["--scenes", str(photos), "--weathers", "H", "--no-ceiling", "--root", str(root)]
    assert run_cli(TOOL.run, argv) == 0, capsys.readouterr().err
    _, err = capsys.readouterr()
    assert "has no poses: running SfM" in err and "sfm: registered" in err
    (rec,) = ResultsStore(root).records()
    assert rec["status"] == "ok", rec.get("error")
    assert rec["scene"] == "myphotos" and rec["scene_kind"] == "photos" and rec["scene_path"] == str(photos.resolve())
    assert np.isfinite(rec["psnr"]) and rec["per_view"] and rec["ground_truth"].startswith("clean/")
    assert _files(photos) == before  # posed and degraded under the root only
    assert [p.name for p in (root / "sfm").iterdir()] == [f"myphotos-{rec['scene_hash'][:12]}"]
    # A second run reuses the SfM and the cell.
    assert run_cli(TOOL.run, argv) == 0
    assert "running SfM" not in capsys.readouterr().err
    assert run_cli(TOOL.run, ["tables", "--root", str(root), "--out", str(tmp_path / "tables")]) == 0
    assert "myphotos PSNR" in (tmp_path / "tables" / "weather_H.md").read_text()
    capsys.readouterr()
