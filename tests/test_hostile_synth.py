"""Hostile and faulty inputs to ``nimbus-synth``: every write stays inside ``--out``, inputs are never modified,
nothing is left behind, and each refusal is one ``error:`` line with exit code 2 (issue 14).

Every hostile input is built here, in ``tmp_path``; the scenes are tiny (3-4 views of 32 x 24 pixels).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from conftest import make_tiny_scene

from nimbus.cli_util import MAX_SEED
from nimbus.data.images import encode_png
from nimbus.data.io import write_scene
from nimbus.errors import NimbusError
from weather_synth import dataset as dataset_module
from weather_synth.cli import main as synth_main
from weather_synth.config import protocol_config
from weather_synth.dataset import degrade_scene
from weather_synth.settings import parse_weather
from weather_synth.synth import Synthesizer


# --- helpers ---------------------------------------------------------------------------------------------
def cli(capsys, *argv) -> tuple[int, str]:
    """Run nimbus-synth; returns the exit code and stderr."""
    with pytest.raises(SystemExit) as e:
        synth_main([str(a) for a in argv])
    return e.value.code, capsys.readouterr().err


def assert_one_error(code: int, err: str, *phrases: str) -> None:
    """Exit 2, exactly one ``error:`` line holding every phrase, no traceback."""
    assert code == 2, err
    lines = [line for line in err.splitlines() if line.startswith("error:")]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    for phrase in phrases:
        assert phrase in lines[0], lines[0]


def snapshot(root: Path) -> dict[str, bytes | None]:
    """Every file (bytes) and folder (None) under ``root``, hidden ones included."""
    return {p.relative_to(root).as_posix(): (p.read_bytes() if p.is_file() else None)
            for p in sorted(Path(root).rglob("*"))}


def tiny_scene(n_views: int = 3):
    return make_tiny_scene(n_views=n_views, depth=True)


def write_photos(folder: Path, n: int = 3) -> Path:
    folder.mkdir(parents=True)
    rng = np.random.default_rng(0)
    for i in range(n):
        (folder / f"p{i}.png").write_bytes(encode_png(rng.integers(0, 256, (24, 32, 3), dtype=np.uint8)))
    return folder


def dead_pid() -> int:
    """The pid of a process that has exited (what a killed run leaves in its ``.owner`` file)."""
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """A COLMAP scene folder, a photo folder and a degraded dataset (setting H), built once."""
    root = tmp_path_factory.mktemp("inputs")
    scene_dir = write_scene(tiny_scene(), root / "scene")
    photos = write_photos(root / "photos")
    dataset = root / "dataset"
    degrade_scene(tiny_scene(), dataset, parse_weather("H"), protocol_config(), progress=False)
    return {"scene": scene_dir, "photos": photos, "dataset": dataset}


# --- 1. view names cannot write outside the output ---------------------------------------------------
@pytest.mark.parametrize("bypass_precheck", [False, True], ids=["checked", "write-time-only"])
@pytest.mark.parametrize("kind", ["absolute", "relative"])
def test_hostile_view_name_writes_nothing_outside_out(tmp_path, monkeypatch, kind, bypass_precheck):
    """A view named ``/abs/t.png`` or ``../../../victim/t.png`` (a scene reader that let it through): the
    dataset writer used to overwrite the target with a hazed image and put ``t.npz`` beside it."""
    work = tmp_path / "work"
    victim = work / "victim" / "t.png"
    victim.parent.mkdir(parents=True)
    victim.write_bytes(b"precious")
    out = work / "out"
    # Where the degraded image and the layers of "../../../victim/t.png" used to land from out/.H.tmp-*/...
    name = str(victim) if kind == "absolute" else "../../../victim/t.png"
    scene = tiny_scene()
    scene = replace(scene, views=(scene.views[0], replace(scene.views[1], name=name), scene.views[2]))
    if bypass_precheck:  # the up-front name check off: each write must still be confined on its own
        monkeypatch.setattr(dataset_module, "check_view_names", lambda scene, out: None)
    before = snapshot(tmp_path)
    with pytest.raises(NimbusError, match="outside"):
        degrade_scene(scene, out, parse_weather("H"), protocol_config(), progress=False)
    assert victim.read_bytes() == b"precious" and not victim.with_suffix(".npz").exists()
    assert snapshot(tmp_path) == before  # nothing written anywhere, and no OUT left behind


def test_view_names_that_collide_after_normalising_are_refused(tmp_path):
    scene = tiny_scene()
    scene = replace(scene, views=(scene.views[0], replace(scene.views[1], name="sub/../001.png"), scene.views[2]))
    scene = replace(scene, views=scene.views + (replace(scene.views[1], name="001.png"),))
    with pytest.raises(NimbusError, match="'..'|share"):
        degrade_scene(scene, tmp_path / "out", parse_weather("H"), protocol_config(), progress=False)
    assert not (tmp_path / "out").exists()


def test_preview_reads_only_inside_the_dataset(tmp_path, capsys, inputs):
    """A received dataset whose manifest names an image outside it: preview must not read (show) that file."""
    dataset = tmp_path / "dataset"
    shutil.copytree(inputs["dataset"], dataset)
    secret = tmp_path / "secret.png"
    secret.write_bytes((dataset / "H" / "images" / "000.png").read_bytes())
    manifest = dataset / "H" / "manifest.json"
    m = json.loads(manifest.read_text())
    m["views"][0]["image"] = str(secret)
    manifest.write_text(json.dumps(m))
    code, err = cli(capsys, "preview", dataset, "--out", tmp_path / "sheet.png", "--view", "000.png")
    assert_one_error(code, err, "outside")
    assert not (tmp_path / "sheet.png").exists()


# case -> how the H setting's manifest is spoiled, words its one error line must hold (nimbus.schemas.SettingManifest)
MANIFEST_CASES = {
    "list-as-view-name": (lambda m: m["views"][0].update(name=["000.png"]), "field 'views[0].name' must be a string"),
    "string-as-seed": (lambda m: m.update(seed="0"), "field 'seed' must be an integer or null, got '0'"),
    "missing-views": (lambda m: m.pop("views"), "field 'views' is missing"),
    "nested-200k-deep": ("[" * 200_000 + "]" * 200_000, "is not valid JSON (nested too deeply)"),
    "non-object": ('["H"]', "holds a list, not an object"),
    "nan-seed": (lambda m: m.update(seed=float("nan")), "field 'seed' must be an integer or null, got nan"),
    "unknown-split": (lambda m: m["views"][0].update(split="val"), "field 'views[0].split' must be 'train' or 'test'"),
}


@pytest.mark.parametrize("case", list(MANIFEST_CASES))
def test_preview_of_a_manifest_that_does_not_fit_is_one_error_naming_the_field(tmp_path, capsys, inputs, case):
    dataset = tmp_path / "dataset"
    shutil.copytree(inputs["dataset"], dataset)
    spoil, words = MANIFEST_CASES[case]
    manifest = dataset / "H" / "manifest.json"
    if isinstance(spoil, str):
        manifest.write_text(spoil)
    else:
        m = json.loads(manifest.read_text())
        spoil(m)
        manifest.write_text(json.dumps(m))
    code, err = cli(capsys, "preview", dataset, "--out", tmp_path / "sheet.png")
    assert_one_error(code, err, "manifest.json", words, "nimbus-synth degrade")
    assert not (tmp_path / "sheet.png").exists()


# --- 2. an output may not be, contain or lie inside an input ------------------------------------------
@pytest.mark.parametrize("where", ["is", "inside", "contains"])
@pytest.mark.parametrize("command", ["degrade", "sfm"])
def test_output_overlapping_an_input_is_refused_and_the_input_kept(tmp_path, capsys, inputs, command, where):
    """``--out`` equal to, inside or above the folder a command reads, with --overwrite (which would replace
    it): refused before anything is read or written.  ``scene`` and ``demo`` read no files, so they have no
    input to overlap."""
    parent = tmp_path / "parent"
    src = parent / "input"
    shutil.copytree(inputs["scene" if command == "degrade" else "photos"], src)
    out = {"is": src, "inside": src / "out", "contains": parent}[where]
    extra = ["--weather", "H", "--quiet"] if command == "degrade" else []
    before = snapshot(tmp_path)
    code, err = cli(capsys, command, src, "--out", out, "--overwrite", *extra)
    assert_one_error(code, err, "the input", "choose an output")
    assert snapshot(tmp_path) == before


@pytest.mark.parametrize("where", ["is", "inside"])
def test_preview_refuses_a_sheet_inside_the_dataset(tmp_path, capsys, inputs, where):
    """A sheet written into the dataset (or over it) would change what trainers read."""
    dataset = tmp_path / ("dataset.png" if where == "is" else "dataset")
    shutil.copytree(inputs["dataset"], dataset)
    out = dataset if where == "is" else dataset / "H" / "sheet.png"
    before = snapshot(tmp_path)
    code, err = cli(capsys, "preview", dataset, "--out", out, "--overwrite")
    assert_one_error(code, err, "the input", "choose an output")
    assert snapshot(tmp_path) == before


# --- 3. an unusable --out is one error line ----------------------------------------------------------
@pytest.fixture
def read_only(tmp_path, monkeypatch):
    """A read-only folder; as root (who may write anywhere) ``os.access`` reports it read-only, as it would
    be to anyone else."""
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    if os.geteuid() == 0:
        real = os.access
        monkeypatch.setattr(os, "access", lambda p, mode, **kw: False if Path(p).resolve() == ro.resolve()
                            and mode & os.W_OK else real(p, mode, **kw))
    yield ro
    ro.chmod(0o755)


@pytest.mark.parametrize("kind", ["file", "under-file", "read-only"])
@pytest.mark.parametrize("command", ["scene", "sfm", "degrade", "demo", "preview"])
def test_unusable_out_is_one_error_line(tmp_path, capsys, inputs, read_only, command, kind):
    """A --out that is a file, lies under a file, or is in a read-only folder: no PermissionError or
    NotADirectoryError traceback, and nothing created."""
    file = tmp_path / "file.png"
    file.write_bytes(b"not a folder")
    leaf = "sheet.png" if command == "preview" else "out"
    out = {"file": file, "under-file": file / leaf, "read-only": read_only / leaf}[kind]
    if command == "preview" and kind == "file":
        out = tmp_path / "folder.png"  # preview's --out is a file; the unusable one is a folder
        out.mkdir()
    argv = {
        "scene": ["scene", "garden", "--size", "tiny"],
        "sfm": ["sfm", inputs["photos"]],
        "degrade": ["degrade", inputs["scene"], "--weather", "H", "--quiet"],
        "demo": ["demo", "--size", "tiny", "--weather", "H", "--quiet"],
        "preview": ["preview", inputs["dataset"], "--overwrite"],
    }[command]
    before = snapshot(tmp_path)
    code, err = cli(capsys, *argv, "--out", out)
    assert_one_error(code, err, "choose another")
    assert snapshot(tmp_path) == before


# --- 4. no leftovers -------------------------------------------------------------------------------------
def test_degrade_removes_what_a_killed_run_left(tmp_path, capsys, inputs):
    """``.SETTING.tmp-*`` folders whose owner process is dead (a killed degrade) are removed by the next run,
    which then finds OUT empty; a live run's folder is left alone (and OUT is then not empty)."""
    out = tmp_path / "out"
    stale = [out / ".H.tmp-abc", out / ".S.tmp-k1ll3d", out / ".depth-cache.tmp-x"]
    for s in stale:
        (s / "images.degraded").mkdir(parents=True)
        (s / ".owner").write_text(str(dead_pid()))
    code, err = cli(capsys, "degrade", inputs["scene"], "--out", out, "--weather", "H", "--quiet")
    assert code == 0, err
    assert not any(s.exists() for s in stale)
    assert sorted(p.name for p in out.iterdir()) == ["H", "index.json"]

    busy = tmp_path / "busy"
    live = busy / ".H.tmp-live"
    live.mkdir(parents=True)
    (live / ".owner").write_text(str(os.getpid()))
    code, err = cli(capsys, "degrade", inputs["scene"], "--out", busy, "--weather", "H", "--quiet")
    assert_one_error(code, err, "not empty")
    assert (live / ".owner").is_file()

    # A folder with other files is refused without --overwrite: nothing in it is touched.
    theirs = tmp_path / "theirs"
    (theirs / ".H.tmp-old").mkdir(parents=True)
    (theirs / ".H.tmp-old" / ".owner").write_text(str(dead_pid()))
    (theirs / "notes.txt").write_text("mine")
    before = snapshot(theirs)
    code, err = cli(capsys, "degrade", inputs["scene"], "--out", theirs, "--weather", "H", "--quiet")
    assert_one_error(code, err, "not empty")
    assert snapshot(theirs) == before


def test_estimated_depth_cache_stays_in_out_and_a_killed_runs_cache_is_removed(tmp_path, monkeypatch):
    """The depth cache of ``--depth sparse`` is written inside OUT (not the system temp folder) and carries
    its owner's pid, so what a killed run left there is removed by the next run."""
    system_tmp = tmp_path / "system-tmp"
    system_tmp.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(system_tmp))
    scene = make_tiny_scene(n_views=4, n_points=200)
    config = protocol_config()
    config = replace(config, depth=replace(config.depth, source="sparse"))
    out = tmp_path / "out"
    monkeypatch.setattr(Synthesizer, "close", lambda self: None)  # killed: the cache is never cleaned up
    degrade_scene(scene, out, parse_weather("H"), config, progress=False)
    monkeypatch.undo()
    assert list(system_tmp.iterdir()) == []
    (cache,) = out.glob(".depth-cache.tmp-*")
    assert list(cache.glob("*.npy")) and (cache / ".owner").read_text() == str(os.getpid())
    (cache / ".owner").write_text(str(dead_pid()))  # its process is gone now
    degrade_scene(scene, out, parse_weather("H"), config, overwrite=True, progress=False)
    assert sorted(p.name for p in out.iterdir()) == ["H", "index.json"]


def test_failed_degrade_leaves_no_output_folder(tmp_path, capsys):
    """A scene whose third image is corrupt behind a valid header (it loads, then fails mid-way through the
    first setting): the run fails with one error line and leaves no OUT, nor the parents it made."""
    scene_dir = write_scene(make_tiny_scene(n_views=4, depth=True), tmp_path / "scene")
    image = scene_dir / "images" / "002.png"
    data = bytearray(image.read_bytes())
    data[50:-20] = bytes(len(data) - 70)  # IHDR intact, pixel data zeroed: the checksum fails on decode
    image.write_bytes(bytes(data))
    before = snapshot(scene_dir)
    code, err = cli(capsys, "degrade", scene_dir, "--out", tmp_path / "new" / "deeper" / "out",
                    "--weather", "H,R", "--quiet")
    assert_one_error(code, err, "002.png", "corrupt")
    assert not (tmp_path / "new").exists()
    assert snapshot(scene_dir) == before


def test_failed_demo_leaves_no_output_folder(tmp_path, capsys, monkeypatch):
    def broken(*args, **kwargs):
        raise NimbusError("synthetic failure after the dataset was written")

    monkeypatch.setattr("weather_synth.contact_sheet.dataset_contact_sheet", broken)
    code, err = cli(capsys, "demo", "--size", "tiny", "--weather", "H", "--quiet", "--out", tmp_path / "demo")
    assert_one_error(code, err, "synthetic failure")
    assert list(tmp_path.iterdir()) == []


# --- 5. no silently ignored options; one seed rule -----------------------------------------------------
@pytest.mark.parametrize("spec,extra,message", [
    ("builtin:garden:tiny", ["--downscale", "2"], "--downscale 2"),
    ("builtin:garden:tiny:extra", [], "builtin:NAME[:SIZE]"),
    ("builtin:", [], "builtin:NAME[:SIZE]"),
])
def test_builtin_scene_refuses_what_it_would_ignore(tmp_path, capsys, spec, extra, message):
    """``--downscale`` was ignored for built-in scenes yet recorded in the manifest; refuse it instead."""
    code, err = cli(capsys, "degrade", spec, "--out", tmp_path / "out", "--weather", "H", "--quiet", *extra)
    assert_one_error(code, err, message)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("seed", ["-1", str(10**20), str(MAX_SEED + 1), "1.5"])
@pytest.mark.parametrize("command", ["scene", "sfm", "degrade", "demo"])
def test_seed_out_of_range_is_one_error_line(tmp_path, capsys, inputs, command, seed):
    """One seed rule for every command: an integer in [0, 2**32 - 1].  A huge seed used to end in an
    OverflowError (scene, demo) or a pybind TypeError (sfm) traceback."""
    argv = {
        "scene": ["scene", "garden", "--size", "tiny"],
        "sfm": ["sfm", inputs["photos"]],
        "degrade": ["degrade", "builtin:garden:tiny", "--quiet"],
        "demo": ["demo", "--size", "tiny", "--quiet"],
    }[command]
    code, err = cli(capsys, *argv, "--out", tmp_path / "out", "--seed", seed)
    assert_one_error(code, err, "seed")
    assert list(tmp_path.iterdir()) == []


def test_largest_seed_is_accepted(tmp_path, capsys):
    code, err = cli(capsys, "degrade", "builtin:garden:tiny", "--out", tmp_path / "out", "--weather", "H",
                    "--quiet", "--seed", str(MAX_SEED))
    assert code == 0, err
    assert json.loads((tmp_path / "out" / "H" / "manifest.json").read_text())["seed"] == MAX_SEED


# --- 6. issue 35, round 2: a full disk, a dangling --out, absurd weather amounts ---------------------------------
def test_a_full_disk_in_a_later_setting_leaves_no_setting_behind(tmp_path, capsys, inputs, disk_full):
    """The disk fills while the third setting is written: none of the settings this run wrote stays (one setting
    of seven is not the dataset asked for), nor a temporary folder; one error line names the folder."""
    failed = disk_full("/.R+S.tmp-")  # the third of H, R, S, H+R, ...: after two complete settings
    out = tmp_path / "new" / "bench"
    code, err = cli(capsys, "degrade", inputs["scene"], "--out", out, "--weather", "all", "--quiet")
    assert failed, "the third setting was never written"
    assert_one_error(code, err, "no space left on the device of", "bytes free")
    assert list(tmp_path.iterdir()) == []


def test_a_full_disk_with_overwrite_keeps_the_settings_it_did_not_write(tmp_path, capsys, inputs, disk_full):
    out = tmp_path / "bench"
    assert cli(capsys, "degrade", inputs["scene"], "--out", out, "--weather", "H,S", "--quiet")[0] == 0
    before = snapshot(out / "S")
    disk_full("/.R.tmp-")
    code, err = cli(capsys, "degrade", inputs["scene"], "--out", out, "--weather", "H,R", "--quiet", "--overwrite")
    assert_one_error(code, err, "no space left on the device of")
    assert sorted(p.name for p in out.iterdir()) == ["H", "S", "index.json"]  # R, which this run began, is gone
    assert snapshot(out / "S") == before


@pytest.mark.parametrize("command", ["degrade", "demo"])
def test_out_given_as_a_dangling_link_is_one_error_line(tmp_path, capsys, inputs, command):
    link = tmp_path / "out"
    link.symlink_to(tmp_path / "missing")
    args = [inputs["scene"]] if command == "degrade" else ["--size", "tiny"]
    code, err = cli(capsys, command, *args, "--out", link, "--weather", "H", "--quiet")
    assert_one_error(code, err, "is a link to", "does not exist")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"] and link.is_symlink()


@pytest.mark.parametrize("flag, value, words", [
    ("--rain", "1e6", "--rain 1e6: the amount must be a number in [0, 10]"),
    ("--snow", "1e4", "--snow 1e4: the amount must be a number in [0, 250]"),
])
def test_a_weather_amount_beyond_its_bound_is_one_error_line(tmp_path, capsys, inputs, flag, value, words):
    code, err = cli(capsys, "degrade", inputs["scene"], "--out", tmp_path / "out", "--weather", "R,S", "--quiet",
                    flag, value)
    assert_one_error(code, err, words)
    assert list(tmp_path.iterdir()) == []


def test_a_degraded_image_with_nan_is_not_written(tmp_path, capsys, inputs, monkeypatch):
    real = Synthesizer.degrade

    def broken(self, view, setting, image=None):
        res = real(self, view, setting, image)
        res.image[0, 0, 0] = np.nan  # what a NaN depth or a broken medium would make
        return res

    monkeypatch.setattr(Synthesizer, "degrade", broken)
    code, err = cli(capsys, "degrade", inputs["scene"], "--out", tmp_path / "out", "--weather", "H", "--quiet")
    assert_one_error(code, err, "refusing to write the degraded view", "of setting H", "NaN")
    assert list(tmp_path.iterdir()) == []
