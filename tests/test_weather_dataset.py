"""Degraded benchmark datasets: layout, formats, reproducibility, atomicity and the command line."""

import hashlib
import json
import zipfile
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest

from nimbus.data.builtin import render_builtin
from nimbus.data.camera import Camera
from nimbus.data.images import read_image
from nimbus.data.io import load_scene, write_scene
from nimbus.data.scene import Scene, View
from nimbus.errors import NimbusError
from weather_synth.archive import encode_layers, read_layers
from weather_synth.cli import main as synth_main
from weather_synth.config import protocol_config
from weather_synth.dataset import NO_VIEW_POINT_COLOUR, DegradedPointColours, degrade_scene
from weather_synth.depth import DepthConfig, visible_point_indices
from weather_synth.settings import ALL_SETTING_NAMES, parse_weather
from weather_synth.synth import Synthesizer


@pytest.fixture(scope="module")
def garden():
    """The built-in garden, tiny (64 x 48, 16 views, exact depth, sky mask, sparse points)."""
    return render_builtin("garden", "tiny", seed=0)


def files(root):
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(Path(root).rglob("*")) if p.is_file()}


def cli(*argv):
    """Run nimbus-synth; returns the exit code."""
    with pytest.raises(SystemExit) as e:
        synth_main([str(a) for a in argv])
    return e.value.code


def test_layout_manifest_and_layers(tmp_path, garden, assert_same_scene):
    out = tmp_path / "bench"
    summaries = degrade_scene(garden, out, parse_weather("H,R+S"), protocol_config(seed=2), progress=False)
    assert [s.setting for s in summaries] == ["H", "R+S"]
    assert summaries[0].mean_transmission is not None and summaries[1].mean_transmission is None
    for name in ("H", "R+S"):
        d = out / name
        for sub in ("images", "clean", "sparse/0", "layers", "depths", "sky"):
            assert (d / sub).is_dir(), sub
        assert (d / "manifest.json").is_file() and (d / "train_list.txt").is_file()
        back = load_scene(d)  # trainers read it as any COLMAP scene
        assert_same_scene(replace(garden, colors=back.colors), back, atol=1e-6)  # colours: see below
    index = json.loads((out / "index.json").read_text())
    assert [s["setting"] for s in index["settings"]] == ["H", "R+S"]

    m = json.loads((out / "H" / "manifest.json").read_text())
    assert m["setting"] == "H" and m["protocol"] == "onerestore" and m["seed"] == 2 and m["version"]
    assert m["config"]["haze"]["beta_range"] == [1.0, 2.0]
    assert len(m["views"]) == len(garden)
    for rec, v in zip(m["views"], garden.views):
        assert rec["name"] == v.name and 1 <= rec["haze"]["beta"] <= 2 and rec["seeds"]["haze"] > 0
        img_bytes = (out / "H" / rec["image"]).read_bytes()
        assert hashlib.sha256(img_bytes).hexdigest() == rec["image_sha256"]
        assert hashlib.sha256((out / "H" / rec["clean"]).read_bytes()).hexdigest() == rec["input_sha256"]
    # The degraded image is the haze model applied to the clean image with the saved layers.
    rec = m["views"][3]
    L = read_layers(out / "H" / rec["layers"])
    assert set(L) == {"transmission", "airlight"}
    J = read_image(out / "H" / rec["clean"])
    I = read_image(out / "H" / rec["image"])
    t = L["transmission"][..., None]
    # (Both J and I are 8-bit: half a step each.)
    np.testing.assert_allclose(I, np.clip(J * t + L["airlight"] * (1 - t), 0, 1), atol=1.01 / 255)
    np.testing.assert_allclose(J, garden.views[3].image, atol=0.51 / 255)
    L = read_layers(out / "R+S" / rec["layers"])
    assert set(L) == {"rain", "rain_depth", "snow", "snow_depth"}
    assert L["snow"].max() <= 1 and L["rain"].min() >= 0


def test_same_seed_same_bytes_and_layers_are_deterministic_zips(tmp_path, garden):
    a, b, c = tmp_path / "a", tmp_path / "b", tmp_path / "c"
    degrade_scene(garden, a, parse_weather("all"), protocol_config(seed=5), progress=False)
    degrade_scene(garden, b, parse_weather("all"), protocol_config(seed=5), progress=False)
    fa, fb = files(a), files(b)
    assert sorted({k.split("/")[0] for k in fa}) == sorted(list(ALL_SETTING_NAMES) + ["index.json"])
    assert fa.keys() == fb.keys() and all(fa[k] == fb[k] for k in fa)
    degrade_scene(garden, c, parse_weather("R"), protocol_config(seed=6), progress=False)
    assert files(c)["R/images/001.png"] != fa["R/images/001.png"]
    # A setting's folder, manifest included, does not depend on the other settings of the call: S made alone
    # records no depth source or haze model although "all" built both for its hazy settings.
    d = tmp_path / "d"
    degrade_scene(garden, d, parse_weather("S"), protocol_config(seed=5), progress=False)
    fd = files(d)
    assert {k for k in fd if k.startswith("S/")} == {k for k in fa if k.startswith("S/")}
    assert all(fd[k] == fa[k] for k in fd if k.startswith("S/"))
    scene_keys = json.loads(fa["S/manifest.json"])["scene"].keys()
    assert "haze" not in scene_keys and "haze" in json.loads(fa["H+S/manifest.json"])["scene"]
    # Archives carry fixed timestamps, so their bytes depend only on the arrays.
    arrays = {"t": np.arange(6, dtype=np.float32).reshape(2, 3)}
    assert encode_layers(arrays) == encode_layers(dict(arrays))
    with zipfile.ZipFile(a / "H" / "layers" / "000.npz") as z:
        assert {i.date_time for i in z.infolist()} == {(1980, 1, 1, 0, 0, 0)}


def test_colmap_input_keeps_its_model_and_jpg_names_become_png(tmp_path, make_scene):
    src = make_scene(n_views=4, depth=True)
    # A COLMAP scene whose images are JPEG files.
    jpg_dir = tmp_path / "jpgs"
    jpg_dir.mkdir()
    views = []
    for v in src.views:
        f = jpg_dir / v.name.replace(".png", ".jpg")
        cv2.imwrite(str(f), (v.image[..., ::-1] * 255).astype(np.uint8))
        views.append(View(f.name, v.camera, image_path=f, depth=v.depth))
    scene_dir = write_scene(Scene(tuple(views), frozenset({"000.jpg"}), src.points, src.colors), tmp_path / "scene")
    scene = load_scene(scene_dir)
    out = tmp_path / "out"
    degrade_scene(scene, out, parse_weather("H"), protocol_config(), progress=False)
    back = load_scene(out / "H")
    assert back.names == ["000.png", "001.png", "002.png", "003.png"] and back.test_names == {"000.png"}
    assert sorted(p.name for p in (out / "H" / "clean").iterdir()) == back.names
    np.testing.assert_allclose(read_image(out / "H" / "clean" / "001.png"), scene.views[1].load_image(), atol=1e-6)

    # PNG names: the input's model files (all but the point colours) and images are copied byte for byte.
    png_dir = write_scene(src, tmp_path / "png_scene")
    out2 = tmp_path / "out2"
    degrade_scene(load_scene(png_dir), out2, parse_weather("S,H"), protocol_config(), progress=False)
    for setting in ("S", "H"):
        for f in (png_dir / "sparse" / "0").iterdir():
            same = (out2 / setting / "sparse" / "0" / f.name).read_bytes() == f.read_bytes()
            assert same == (f.name != "points3D.bin"), f.name
        assert (out2 / setting / "clean" / "002.png").read_bytes() == (png_dir / "images" / "002.png").read_bytes()


def test_point_colours_are_means_of_the_degraded_train_views(tmp_path, garden):
    out = tmp_path / "bench"
    config = protocol_config(seed=2)
    degrade_scene(garden, out, parse_weather("H"), config, progress=False)
    colours = load_scene(out / "H").colors.astype(int)
    # Haze lifts the points' colours towards the airlight: far from the clean ones.
    assert np.abs(colours - garden.colors).mean() > 20

    # By hand: the 8-bit degraded pixel under each point, per view.
    seen_in = {}
    for v in garden.views:
        image = cv2.imread(str(out / "H" / "images" / v.name))[..., ::-1].astype(int)
        idx, u, vv, _ = visible_point_indices(v.camera, garden.points, config.depth.occlusion_window,
                                              config.depth.occlusion_tolerance)
        for i, rgb in zip(idx.tolist(), image[vv, u]):
            seen_in.setdefault(i, {})[v.name] = rgb

    def train_mean(i):
        return np.mean([rgb for name, rgb in seen_in[i].items() if name not in garden.test_names], 0)

    # A point that a test view sees too, with a mean that would move by more than 2 levels if it counted.
    i = next(i for i, by in seen_in.items() if by.keys() & garden.test_names and by.keys() - garden.test_names
             and np.abs(np.mean(list(by.values()), 0) - train_mean(i)).max() > 2)
    np.testing.assert_allclose(colours[i], train_mean(i), atol=1)
    seen = sorted(i for i, by in seen_in.items() if by.keys() - garden.test_names)
    np.testing.assert_allclose(colours[seen], [train_mean(i) for i in seen], atol=0.51)
    unseen = np.setdiff1d(np.arange(len(garden.points)), seen)
    assert 0 < len(unseen) < len(seen)
    np.testing.assert_allclose(colours[unseen], np.broadcast_to(colours[seen].mean(0), (len(unseen), 3)), atol=0.51)
    m = json.loads((out / "H" / "manifest.json").read_text())["input"]["point_colours"]
    assert (m["points"], m["points_seen"], m["train_views"]) == (len(garden.points), len(seen), 14)


def test_point_colour_means_without_seen_points_or_views():
    cam = Camera.look_at((0, 0, -4), (0, 0, 0), (0, 1, 0), 8, 6, fov_x_deg=60)
    ahead, behind = [0.0, 0.0, 0.0], [0.0, 0.0, -8.0]
    acc = DegradedPointColours(np.array([ahead, behind]), DepthConfig())
    for red in (10, 13):
        acc.add(cam, np.full((6, 8, 3), (red, 20, 30), np.uint8))
    np.testing.assert_array_equal(acc.colours(), [[12, 20, 30], [12, 20, 30]])  # 11.5 rounds to even
    assert (acc.points_seen, acc.views) == (1, 2)
    nothing_seen = DegradedPointColours(np.array([behind]), DepthConfig())
    nothing_seen.add(cam, np.full((6, 8, 3), (10, 20, 30), np.uint8))
    nothing_seen.add(cam, np.full((6, 8, 3), (20, 20, 31), np.uint8))
    np.testing.assert_array_equal(nothing_seen.colours(), [[15, 20, 30]])  # the images' mean colour
    no_views = DegradedPointColours(np.array([ahead]), DepthConfig())
    np.testing.assert_array_equal(no_views.colours(), [NO_VIEW_POINT_COLOUR])


def write_tracked_colmap_scene(scene, root, text=False):
    """``scene`` as a COLMAP scene whose model has SIMPLE_RADIAL cameras, tracks, errors and shuffled point ids."""
    write_scene(scene, root)
    rec = pycolmap.Reconstruction()
    for image_id, v in enumerate(scene.views, start=1):
        c = v.camera
        rec.add_camera_with_trivial_rig(pycolmap.Camera(model="SIMPLE_RADIAL", width=c.width, height=c.height,
                                                        params=[c.fx, c.cx, c.cy, 0.0], camera_id=image_id))
        uv, _ = c.project(scene.points)
        image = pycolmap.Image(name=v.name, camera_id=image_id, image_id=image_id,
                               points2D=[pycolmap.Point2D(xy) for xy in uv])
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(c.R), c.t))
    ids = np.random.default_rng(0).permutation(len(scene.points)) * 3 + 5
    for j, (pid, xyz, rgb) in enumerate(zip(ids.tolist(), scene.points, scene.colors)):
        track = pycolmap.Track()
        for image_id in range(1, 2 + j % len(scene.views)):
            track.add_element(image_id, j)
        rec.add_point3D_with_id(pid, pycolmap.Point3D(xyz=xyz, color=rgb, track=track, error=0.125 * j))
    sparse = root / "sparse" / "0"
    for f in sparse.iterdir():
        f.unlink()
    rec.write_text(sparse) if text else rec.write(sparse)
    return root


def model_points(sparse):
    rec = pycolmap.Reconstruction(sparse)
    return {pid: (tuple(p.xyz), tuple(p.color), p.error, [(e.image_id, e.point2D_idx) for e in p.track.elements])
            for pid, p in rec.points3D.items()}, {i: c.model_name for i, c in rec.cameras.items()}


@pytest.mark.parametrize("text", [False, True], ids=["bin", "txt"])
def test_colmap_copy_keeps_tracks_and_cameras_and_takes_degraded_colours(tmp_path, make_scene, text):
    root = write_tracked_colmap_scene(make_scene(n_views=4, n_points=60, depth=True), tmp_path / "scene", text)
    scene = load_scene(root)
    out, rewritten = tmp_path / "out", tmp_path / "rewritten"
    degrade_scene(scene, out, parse_weather("H"), protocol_config(), progress=False)
    # The same scene without its folder: the model is rewritten (PINHOLE, no tracks), colours the same way.
    degrade_scene(replace(scene, root=None), rewritten, parse_weather("H"), protocol_config(), progress=False)
    src, dst = root / "sparse" / "0", out / "H" / "sparse" / "0"
    points_file = "points3D.txt" if text else "points3D.bin"
    assert sorted(f.name for f in dst.iterdir()) == sorted(f.name for f in src.iterdir())
    for f in src.iterdir():
        assert ((dst / f.name).read_bytes() == f.read_bytes()) == (f.name != points_file), f.name

    (before, cams_before), (after, cams_after) = model_points(src), model_points(dst)
    assert set(cams_after.values()) == {"SIMPLE_RADIAL"} and cams_after == cams_before
    assert after.keys() == before.keys() and len(after) == 60
    for pid, (xyz, rgb, error, track) in after.items():
        assert (xyz, error, track) == (before[pid][0], before[pid][2], before[pid][3])
    new = load_scene(out / "H").colors
    np.testing.assert_array_equal(new, load_scene(rewritten / "H").colors)
    assert np.abs(new.astype(int) - scene.colors).mean() > 20
    assert {c for *_, c in model_points(rewritten / "H" / "sparse" / "0")[1].items()} == {"PINHOLE"}

    # A scene whose points no longer match its folder's model gets the rewritten model.
    moved = replace(scene, points=scene.points + 1)
    degrade_scene(moved, tmp_path / "moved", parse_weather("H"), protocol_config(), progress=False)
    assert set(model_points(tmp_path / "moved" / "H" / "sparse" / "0")[1].values()) == {"PINHOLE"}


def test_transforms_input_is_written_as_transforms(tmp_path, make_scene):
    src = write_scene(make_scene(n_views=3, depth=True), tmp_path / "scene", format="transforms")
    out = tmp_path / "out"
    degrade_scene(load_scene(src), out, parse_weather("H+R"), protocol_config(), progress=False)
    assert (out / "H+R" / "transforms.json").is_file() and not (out / "H+R" / "sparse").exists()
    assert load_scene(out / "H+R").names == load_scene(src).names


def test_an_interrupted_run_leaves_none_of_its_settings(tmp_path, garden, monkeypatch):
    """Ctrl-C in the second setting: the first, complete, goes too (one setting of three is not the dataset asked
    for; issue 35), and so does the OUT the run made."""
    calls = {"n": 0}
    real = Synthesizer.degrade

    def flaky(self, view, setting, image=None):
        calls["n"] += 1
        if setting.name == "R" and calls["n"] > len(garden) + 3:
            raise KeyboardInterrupt
        return real(self, view, setting, image)

    monkeypatch.setattr(Synthesizer, "degrade", flaky)
    out = tmp_path / "out"
    with pytest.raises(KeyboardInterrupt):
        degrade_scene(garden, out, parse_weather("H,R,S"), protocol_config(), progress=False)
    assert calls["n"] > len(garden)  # H was complete when R was interrupted
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_bad_input_is_refused_before_anything_is_written(tmp_path, garden, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    with pytest.raises(NimbusError, match="not empty.*--overwrite"):
        degrade_scene(garden, out, parse_weather("H"), protocol_config(), progress=False)
    with pytest.raises(NimbusError, match="zero views"):
        degrade_scene(Scene(()), tmp_path / "x", parse_weather("H"), protocol_config(), progress=False)
    degrade_scene(garden, out, parse_weather("H"), protocol_config(), overwrite=True, progress=False)
    assert (out / "keep.txt").read_text() == "mine" and (out / "H" / "manifest.json").is_file()

    scene_dir = write_scene(garden.with_views(garden.views[:3]), tmp_path / "scene")
    fresh = tmp_path / "fresh"
    cases = [
        (["--weather", "H,drizzle"], "unknown weather token 'drizzle'"),
        (["--beta", "-1"], "beta must be >= 0"),
        (["--airlight", "1.5"], "airlight must be"),
        (["--visibility", "10"], "physical haze mode"),
        (["--rain", "torrential"], "unknown rain intensity"),
        (["--set", "haze.nope=1"], "unknown setting"),
    ]
    for extra, message in cases:
        assert cli("degrade", scene_dir, "--out", fresh, "--quiet", *extra) == 2
        err = capsys.readouterr().err
        assert "error: " in err and message in err and "Traceback" not in err
        assert not fresh.exists()
    assert cli("degrade", tmp_path / "missing", "--out", fresh) == 2
    assert "does not exist" in capsys.readouterr().err
    assert cli("degrade", scene_dir, "--out", out, "--quiet") == 2
    assert "not empty" in capsys.readouterr().err


def test_degrade_command_with_physical_protocol_and_estimated_depth(tmp_path, capsys):
    out = tmp_path / "out"
    code = cli("degrade", "builtin:garden:tiny", "--out", out, "--weather", "haze,h+s", "--protocol", "physical",
               "--haze-mode", "heterogeneous", "--depth", "sparse", "--airlight", "0.7,0.75,0.8", "--quiet",
               "--set", "snow.slices=1")
    assert code == 0
    table = capsys.readouterr().out
    assert "setting" in table and "H+S" in table and "mean t" in table
    m = json.loads((out / "H+S" / "manifest.json").read_text())
    assert m["scene"]["haze"]["medium"]["kind"] == "height_fog"
    assert m["scene"]["depth"]["source"] == "sparse" and m["config"]["snow"]["slices"] == 1
    assert m["views"][0]["haze"]["airlight"] == pytest.approx([0.7, 0.75, 0.8])
    L = read_layers(out / "H+S" / m["views"][0]["layers"])
    assert {"transmission", "depth", "snow", "snow_depth"} <= set(L)
    assert np.isfinite(L["transmission"]).all() and 0 < L["transmission"].mean() < 1
    # Depth-aware snow: flake depths are positive and finite where there are flakes.
    sd = L["snow_depth"][L["snow"] > 0.05]
    assert sd.size and np.all((sd > 0) & np.isfinite(sd))


def test_demo_and_preview_write_contact_sheets(tmp_path, capsys):
    out = tmp_path / "demo"
    assert cli("demo", "--out", out, "--size", "tiny", "--quiet", "--views", "4", "--tile-width", "96") == 0
    assert "look at" in capsys.readouterr().out
    sheet = cv2.imread(str(out / "contact_sheet.png"))
    tile_h = 96 * 48 // 64
    assert sheet.shape[0] >= 8 * tile_h and sheet.shape[1] >= 4 * 96  # clean + 7 settings, 4 views
    assert sorted(p.name for p in out.iterdir() if p.is_dir()) == sorted(ALL_SETTING_NAMES)
    png = tmp_path / "sheet.png"
    assert cli("preview", out, "--out", png, "--view", "003.png", "--view", "010.png") == 0
    small = cv2.imread(str(png))
    assert small.shape[1] < sheet.shape[1] and small.shape[0] > sheet.shape[0] * 0.9
    assert cli("preview", out, "--out", png) == 2  # exists
    assert cli("preview", tmp_path / "nothing", "--out", tmp_path / "s.png") == 2
    assert "does not exist" in capsys.readouterr().err
