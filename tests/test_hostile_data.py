"""Hostile or corrupt scene files (issue 14): every one ends in a NimbusError that names the file.

Each test builds its hostile input in tmp_path: names that escape the scene (COLMAP txt / bin,
transforms.json, split lists, links), corrupt COLMAP binary and text models, invalid camera
values, malformed JSON and PLY, and depth maps that are negative, mostly missing or pickled;
issue 35 adds images that declare billions of pixels and damaged images the decoder only warns about.
"""

from __future__ import annotations

import json
import logging
import os
import struct
import subprocess
import sys
import textwrap
import zlib
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest

from nimbus.data.colmap import check_binary_model
from nimbus.data.images import read_depth, write_image
from nimbus.data.io import load_scene, write_scene
from nimbus.data.transforms import read_ply_points
from nimbus.errors import NimbusError

from conftest import make_tiny_scene

ESCAPES = "outside the scene"


def _colmap_scene(tmp_path, text=False, name="scene", **kw) -> Path:
    return write_scene(make_tiny_scene(n_views=3, **kw), tmp_path / name, text=text)


def _outside_image(tmp_path) -> Path:
    """A valid image of the scene's size outside it: what a hostile name would make Nimbus read."""
    f = tmp_path / "outside" / "secret.png"
    write_image(f, np.zeros((24, 32, 3), np.float32))
    return f


# --- 1. names that escape the scene ------------------------------------------------------
@pytest.mark.parametrize("hostile", ["absolute", "../../x/t.png"])
def test_colmap_txt_image_name_outside_the_scene_is_refused(tmp_path, hostile):
    secret = _outside_image(tmp_path)
    root = _colmap_scene(tmp_path, text=True)
    name = str(secret) if hostile == "absolute" else hostile
    images_txt = root / "sparse" / "0" / "images.txt"
    images_txt.write_text(images_txt.read_text().replace(" 000.png", f" {name}"))
    with pytest.raises(NimbusError, match=f"images.txt.*{ESCAPES}"):
        load_scene(root)


@pytest.mark.parametrize("hostile", ["absolute", "../../x/t.png", "sub/../../escape.png"])
def test_colmap_bin_image_name_outside_the_scene_is_refused(tmp_path, hostile):
    secret = _outside_image(tmp_path)
    root = _colmap_scene(tmp_path)
    sparse = root / "sparse" / "0"
    rec = pycolmap.Reconstruction(sparse)
    for im in rec.images.values():
        if im.name == "000.png":
            im.name = str(secret) if hostile == "absolute" else hostile
    rec.write(sparse)
    with pytest.raises(NimbusError, match=f"images.bin.*{ESCAPES}"):
        load_scene(root)


def _transforms_scene(root: Path, frame0=None, top=None) -> Path:
    rng = np.random.default_rng(0)
    frames = []
    for i in range(3):
        write_image(root / "images" / f"{i}.png", rng.random((12, 16, 3), dtype=np.float32))
        c2w = np.eye(4)
        c2w[:3, 3] = [0.2 * i, 0, 3]
        frames.append({"file_path": f"images/{i}.png", "transform_matrix": c2w.tolist()})
    frames[0].update(frame0 or {})
    meta = {"fl_x": 20.0, "fl_y": 20.0, "cx": 8.0, "cy": 6.0, "w": 16, "h": 12, "frames": frames, **(top or {})}
    (root / "transforms.json").write_text(json.dumps(meta))
    return root


@pytest.mark.parametrize("key", ["file_path", "mask_path", "depth_file_path"])
def test_transforms_frame_names_outside_the_scene_are_refused(tmp_path, key):
    secret = _outside_image(tmp_path)
    for i, name in enumerate((str(secret), "../outside/secret.png")):
        root = _transforms_scene(tmp_path / f"s{i}", frame0={key: name})
        with pytest.raises(NimbusError, match=f"transforms.json: frame 0.*{key}.*{ESCAPES}"):
            load_scene(root)


def test_transforms_split_and_ply_names_outside_the_scene_are_refused(tmp_path):
    secret = _outside_image(tmp_path)
    root = _transforms_scene(tmp_path / "a", top={"test_filenames": [str(secret)]})
    with pytest.raises(NimbusError, match=f"test_filenames.*{ESCAPES}"):
        load_scene(root)
    (tmp_path / "outside" / "p.ply").write_text("ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\n"
                                                "property float y\nproperty float z\nend_header\n")
    root = _transforms_scene(tmp_path / "b", top={"ply_file_path": "../outside/p.ply"})
    with pytest.raises(NimbusError, match=f"ply_file_path.*{ESCAPES}"):
        load_scene(root)


@pytest.mark.parametrize("split", ["test_list.txt", "train_list.txt"])
def test_split_list_name_outside_the_scene_is_refused(tmp_path, split):
    root = _colmap_scene(tmp_path)
    (root / "test_list.txt").unlink()
    (root / split).write_text("001.png\n../../etc/passwd\n")
    with pytest.raises(NimbusError, match=f"{split}.*{ESCAPES}"):
        load_scene(root)


def test_symlinks_that_lead_out_of_the_scene_are_refused(tmp_path):
    secret = _outside_image(tmp_path)
    root = _colmap_scene(tmp_path, depth=True)
    link = root / "images" / "001.png"
    link.unlink()
    link.symlink_to(secret)
    with pytest.raises(NimbusError, match="001.png.*leads outside the scene"):
        load_scene(root)
    # transforms.json reader: the same rule
    troot = _transforms_scene(tmp_path / "t")
    (troot / "images" / "2.png").unlink()
    (troot / "images" / "2.png").symlink_to(secret)
    with pytest.raises(NimbusError, match="file_path.*leads outside the scene"):
        load_scene(troot)
    # a depth map linked out of the scene
    root = _colmap_scene(tmp_path, name="depth", depth=True)
    np.save(tmp_path / "outside" / "d.npy", np.ones((24, 32), np.float32))
    (root / "depths" / "002.npy").unlink()
    (root / "depths" / "002.npy").symlink_to(tmp_path / "outside" / "d.npy")
    with pytest.raises(NimbusError, match="depth file of view 002.png.*leads outside the scene"):
        load_scene(root)
    # A link that stays inside the scene is fine.
    inside = _colmap_scene(tmp_path, name="inside")
    (inside / "images" / "000.png").rename(inside / "real.png")
    (inside / "images" / "000.png").symlink_to(inside / "real.png")
    assert load_scene(inside).view("000.png").load_image().shape == (24, 32, 3)


# --- confinement: a scene's own files that are links leading out (issue 35) -----------------------------
SECRET = "SECRET-LINE-of-another-file"


def _link_out(root: Path, name: str) -> None:
    """Move ``root/name`` out of the scene (with a secret added where it is text) and link it back."""
    src, dst = root / name, root.parent / "outside" / name.replace("/", "_")
    dst.parent.mkdir(exist_ok=True)
    if src.is_dir():
        src.rename(dst)
    elif name.endswith(".txt"):
        dst.write_text(src.read_text() + SECRET + "\n")
        src.unlink()
    elif name.endswith(".json"):
        dst.write_text(json.dumps({**json.loads(src.read_text()), "note": SECRET}))
        src.unlink()
    else:
        src.rename(dst)
    src.symlink_to(dst)


# case -> (scene layout, file linked out, what the error names)
SCENE_FILE_ESCAPES = {
    "test_list": ("colmap", "test_list.txt", "split list test_list.txt"),
    "train_list": ("colmap", "train_list.txt", "split list train_list.txt"),
    "sparse": ("colmap", "sparse", "COLMAP model folder"),
    "sparse-0": ("colmap", "sparse/0", "COLMAP model folder"),
    "images.bin": ("colmap", "sparse/0/images.bin", "COLMAP model file"),
    "transforms.json": ("transforms", "transforms.json", "camera file"),
}


@pytest.mark.parametrize("case", list(SCENE_FILE_ESCAPES))
def test_scene_files_linked_out_of_the_scene_are_refused_unread(tmp_path, case):
    layout, name, what = SCENE_FILE_ESCAPES[case]
    root = _colmap_scene(tmp_path) if layout == "colmap" else _transforms_scene(tmp_path / "scene")
    if name == "train_list.txt":
        (root / "test_list.txt").unlink()
        (root / "train_list.txt").write_text("001.png\n002.png\n")
    if name == "sparse":  # a model in sparse/ itself, not sparse/0
        for f in (root / "sparse" / "0").iterdir():
            f.rename(root / "sparse" / f.name)
        (root / "sparse" / "0").rmdir()
    _link_out(root, name)
    with pytest.raises(NimbusError, match=f"{what}.*leads outside the scene") as info:
        load_scene(root)
    assert SECRET not in str(info.value)  # the outside file is never quoted


def test_scene_files_linked_inside_the_scene_are_read(tmp_path):
    root = _colmap_scene(tmp_path)
    (root / "test_list.txt").rename(root / "lists.txt")
    (root / "test_list.txt").symlink_to(root / "lists.txt")
    (root / "sparse" / "0").rename(root / "model")
    (root / "sparse" / "0").symlink_to(root / "model")
    assert load_scene(root).test_names == {"000.png"}


# --- 2. corrupt COLMAP models --------------------------------------------------------------
def _image_count_offset(images_bin: bytes) -> int:
    """Offset of the first image's num_points2D (after id, pose, camera id and the NUL-terminated name)."""
    name_end = images_bin.index(b"\0", 8 + 4 + 56 + 4)
    return name_end + 1


# file -> offset of a variable-length count inside the first record, its format, and the value to plant
VARIABLE_COUNTS = {
    "cameras.bin": (8 + 4, "<i", 999),  # the camera model id decides the number of params
    "images.bin": (None, "<Q", 2**40),  # num_points2D of the first image
    "points3D.bin": (8 + 8 + 24 + 3 + 8, "<Q", 2**40),  # track length of the first point
    "rigs.bin": (8 + 4, "<I", 2**31),  # num_sensors of the first rig
    "frames.bin": (8 + 4 + 4 + 56, "<I", 2**31),  # num_data_ids of the first frame
}


def _corrupt(path: Path, how: str) -> None:
    data = bytearray(path.read_bytes())
    if how == "count":
        data[:8] = struct.pack("<Q", 2**60)
    elif how == "half":
        data = data[: len(data) // 2]
    elif how == "empty":
        data = b""
    else:
        offset, fmt, value = VARIABLE_COUNTS[path.name]
        offset = _image_count_offset(bytes(data)) if offset is None else offset
        data[offset:offset + struct.calcsize(fmt)] = struct.pack(fmt, value)
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("how", ["count", "half", "variable", "empty"])
@pytest.mark.parametrize("name", list(VARIABLE_COUNTS))
def test_corrupt_binary_model_is_refused_naming_the_file(tmp_path, name, how):
    sparse = _colmap_scene(tmp_path) / "sparse" / "0"
    check_binary_model(sparse)  # the intact model passes
    _corrupt(sparse / name, how)
    with pytest.raises(NimbusError, match=rf"{name} is corrupt and unreadable: .*(declares|truncated|unknown|empty)"):
        check_binary_model(sparse)


def test_corrupt_binary_models_fail_through_load_scene_in_bounded_memory(tmp_path):
    """End to end in a child process (memory capped, so a regression cannot take the machine down)."""
    cases = {}
    for name in VARIABLE_COUNTS:
        for how in ("count", "half", "variable"):
            root = _colmap_scene(tmp_path, name=f"{name}-{how}")
            _corrupt(root / "sparse" / "0" / name, how)
            cases[f"{name}-{how}"] = str(root)
    script = textwrap.dedent("""
        import json, resource, sys
        resource.setrlimit(resource.RLIMIT_AS, (2 << 30, 2 << 30))
        from nimbus.data.io import load_scene
        from nimbus.errors import NimbusError
        import pycolmap  # imported before the baseline: only the loads are measured
        cases = json.loads(sys.argv[1])
        base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        out = {}
        for case, root in cases.items():
            try:
                load_scene(root)
                out[case] = ["loaded", ""]
            except NimbusError as e:
                out[case] = ["NimbusError", str(e)]
            except BaseException as e:
                out[case] = [type(e).__name__, str(e)[:200]]
        grown_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - base
        print(json.dumps({"results": out, "grown_mb": grown_kb / 1024}))
    """)
    proc = subprocess.run([sys.executable, "-c", script, json.dumps(cases)], capture_output=True, text=True,
                          timeout=120, cwd=Path(__file__).parent)
    assert proc.returncode == 0, proc.stderr[-2000:]
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    for case, (kind, message) in report["results"].items():
        assert kind == "NimbusError", (case, kind, message)
        assert case.split("-")[0] in message and "corrupt" in message, (case, message)
    assert report["grown_mb"] < 100, report["grown_mb"]


@pytest.mark.parametrize("name", ["cameras.txt", "images.txt", "points3D.txt"])
def test_garbage_line_in_a_text_model_names_the_file_and_line(tmp_path, name):
    sparse = _colmap_scene(tmp_path, text=True) / "sparse" / "0"
    lines = (sparse / name).read_text().splitlines()
    lines.append("this is a garbage line")
    (sparse / name).write_text("\n".join(lines) + "\n")
    with pytest.raises(NimbusError, match=rf"{name} line {len(lines)}: .*garbage"):
        load_scene(sparse.parent.parent)


def test_binary_garbage_in_a_text_model_is_a_clear_error(tmp_path):
    sparse = _colmap_scene(tmp_path, text=True) / "sparse" / "0"
    (sparse / "cameras.txt").write_bytes(b"\xff\xfe\x00garbage\x80" * 10)
    with pytest.raises(NimbusError, match="cameras.txt.*unreadable"):
        load_scene(sparse.parent.parent)


def test_nan_sparse_point_in_a_colmap_model_is_refused(tmp_path):
    sparse = _colmap_scene(tmp_path) / "sparse" / "0"
    data = bytearray((sparse / "points3D.bin").read_bytes())
    data[16:24] = struct.pack("<d", float("nan"))  # x of the first point
    (sparse / "points3D.bin").write_bytes(bytes(data))
    with pytest.raises(NimbusError, match="points3D.bin: 1 of 40 sparse points have NaN"):
        load_scene(sparse.parent.parent)


# --- 3. camera values ------------------------------------------------------------------------
@pytest.mark.parametrize("change, message", [
    ({"cx": float("nan")}, "field 'cx' must be a finite number, got nan"),
    ({"cy": float("inf")}, "field 'cy' must be a finite number, got inf"),
    ({"fl_x": -20.0}, "focal lengths must be positive"),
    ({"fl_x": "abc"}, "field 'fl_x' must be a number or null, got 'abc'"),
    ({"cx": None, "w": 0}, "w must be a positive whole number"),
    ({"w": 16.5}, "w must be a positive whole number"),
    ({"h": True}, "field 'h' must be a number or null, got True"),
    ({"camera_angle_x": 0.0, "fl_x": None}, "camera_angle_x=0 radians"),
    ({"k1": float("nan")}, "field 'k1' must be a finite number"),
])
def test_invalid_camera_values_in_transforms_json_name_the_file_and_frame(tmp_path, change, message):
    frame0 = {k: v for k, v in change.items() if v is not None}
    root = _transforms_scene(tmp_path, frame0=frame0)
    if None in change.values():  # remove the top-level value so the frame's (or a derived one) is used
        meta = json.loads((root / "transforms.json").read_text())
        for k, v in change.items():
            if v is None:
                meta.pop(k)
        (root / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(NimbusError, match=rf"transforms.json: frame 0 \(images/0.png\): .*{message}"):
        load_scene(root)


def test_invalid_pose_in_transforms_json_is_refused(tmp_path):
    bad = np.eye(4)
    bad[0, 3] = np.nan
    root = _transforms_scene(tmp_path / "nan", frame0={"transform_matrix": bad.tolist()})
    with pytest.raises(NimbusError, match=r"frame 0 \(images/0.png\): field 'transform_matrix\[0\]\[3\]' must be"):
        load_scene(root)
    skew = np.eye(4)
    skew[0, 1] = 0.5
    root = _transforms_scene(tmp_path / "skew", frame0={"transform_matrix": skew.tolist()})
    with pytest.raises(NimbusError, match="frame 0.*rotation"):
        load_scene(root)


@pytest.mark.parametrize("field, offset, fmt, value, message", [
    ("cx", 8 + 24 + 16, "<d", float("nan"), "cx must be finite"),
    ("fx", 8 + 24, "<d", float("inf"), "fx must be finite"),
    ("fy", 8 + 24 + 8, "<d", -30.0, "focal lengths must be positive"),
    ("width", 8 + 8, "<Q", 0, "width must be a positive whole number"),
])
def test_invalid_camera_values_in_a_colmap_model_name_the_camera_and_image(tmp_path, field, offset, fmt, value,
                                                                           message):
    sparse = _colmap_scene(tmp_path) / "sparse" / "0"
    data = bytearray((sparse / "cameras.bin").read_bytes())
    data[offset:offset + struct.calcsize(fmt)] = struct.pack(fmt, value)
    (sparse / "cameras.bin").write_bytes(bytes(data))
    with pytest.raises(NimbusError, match=rf"camera 1 in .*sparse/0 \(image '000.png'\): .*{message}"):
        load_scene(sparse.parent.parent)


@pytest.mark.parametrize("legacy", [False, True], ids=["frames.bin", "images.bin"])
def test_nan_pose_in_a_colmap_model_names_the_image(tmp_path, legacy):
    sparse = _colmap_scene(tmp_path) / "sparse" / "0"
    if legacy:  # a model from COLMAP < 3.12: the pose is in images.bin
        (sparse / "rigs.bin").unlink()
        (sparse / "frames.bin").unlink()
        f, offset = sparse / "images.bin", 8 + 4 + 32  # count, image id, quaternion -> tx
    else:  # COLMAP >= 3.12 reads the pose from the image's frame
        f, offset = sparse / "frames.bin", 8 + 4 + 4 + 32  # count, frame id, rig id, quaternion -> tx
    data = bytearray(f.read_bytes())
    data[offset:offset + 8] = struct.pack("<d", float("nan"))
    f.write_bytes(bytes(data))
    with pytest.raises(NimbusError, match=r"\(image '000.png'\): camera pose contains NaN"):
        load_scene(sparse.parent.parent)


# --- 4. malformed JSON and PLY ---------------------------------------------------------------
@pytest.mark.parametrize("value, message", [(None, "field 'file_path' must be a string, got None"),
                                            (5, "field 'file_path' must be a string, got 5"),
                                            (["images/0.png"], r"field 'file_path' must be a string, got \['images"),
                                            ("", "file_path.*not a file name")])
def test_file_path_of_the_wrong_type_is_a_clear_error(tmp_path, value, message):
    root = _transforms_scene(tmp_path, frame0={"file_path": value})
    with pytest.raises(NimbusError, match=f"transforms.json: frame 0.*{message}"):
        load_scene(root)


@pytest.mark.parametrize("key, value, field", [("test_filenames", 5, "test_filenames"),
                                               ("test_filenames", [1, 2], r"test_filenames\[0\]"),
                                               ("train_filenames", {"a": 1}, "train_filenames"),
                                               ("val_filenames", "images/0.png", "val_filenames")])
def test_split_keys_of_the_wrong_type_are_a_clear_error(tmp_path, key, value, field):
    root = _transforms_scene(tmp_path, top={key: value})
    with pytest.raises(NimbusError, match=f"transforms.json: field '{field}' must be a (list|string)"):
        load_scene(root)


# case -> (top-level keys, frame 0's keys, the message after "transforms.json: "); nimbus.schemas.TransformsFile
TRANSFORMS_SCHEMA_CASES = {
    "list-as-file_path": ({}, {"file_path": ["images/0.png"]}, r"frame 0: field 'file_path' must be a string"),
    "string-in-transform_matrix": ({}, {"transform_matrix": [[1, 0, 0, "0"], [0, 1, 0, 0], [0, 0, 1, 3]]},
                                   r"frame 0 \(images/0.png\): field 'transform_matrix\[0\]\[3\]' must be a number"),
    "missing-transform_matrix": ({}, {"transform_matrix": None}, r"frame 0 .*field 'transform_matrix' is missing"),
    "missing-frames": ({"frames": None}, {}, "field 'frames' is missing"),
    "frames-not-a-list": ({"frames": {"0": {}}}, {}, "field 'frames' must be a list"),
    "frame-not-an-object": ({"frames": ["images/0.png"]}, {}, "frame 0: holds a string, not an object"),
    "nan-focal-length": ({"fl_x": float("nan")}, {}, "field 'fl_x' must be a finite number, got nan"),
    "string-as-width": ({"w": "16"}, {}, "field 'w' must be a number or null, got '16'"),
    "list-as-camera_model": ({"camera_model": ["OPENCV"]}, {}, "field 'camera_model' must be a string or null"),
}


@pytest.mark.parametrize("case", list(TRANSFORMS_SCHEMA_CASES))
def test_a_transforms_json_that_does_not_fit_its_schema_names_the_field(tmp_path, case):
    top, frame0, message = TRANSFORMS_SCHEMA_CASES[case]
    root = _transforms_scene(tmp_path, frame0={k: v for k, v in frame0.items() if v is not None},
                             top={k: v for k, v in top.items() if v is not None})
    if None in frame0.values() or None in top.values():  # remove the key instead
        meta = json.loads((root / "transforms.json").read_text())
        for k in [k for k, v in top.items() if v is None]:
            meta.pop(k)
        for k in [k for k, v in frame0.items() if v is None]:
            meta["frames"][0].pop(k)
        (root / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(NimbusError, match="transforms.json: " + message) as e:
        load_scene(root)
    assert "\n" not in str(e.value) and "fix the transforms file" in str(e.value)


def test_deeply_nested_or_non_json_transforms_is_a_clear_error(tmp_path):
    (tmp_path / "deep").mkdir()
    (tmp_path / "deep" / "transforms.json").write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(NimbusError, match="nested too deeply"):
        load_scene(tmp_path / "deep")
    (tmp_path / "digits").mkdir()
    (tmp_path / "digits" / "transforms.json").write_text('{"frames": [], "w": ' + "9" * 5000 + "}")
    with pytest.raises(NimbusError, match="not valid JSON"):
        load_scene(tmp_path / "digits")
    (tmp_path / "bin").mkdir()
    (tmp_path / "bin" / "transforms.json").write_bytes(b"\x89PNG\r\n\x1a\n\xff\xfe")
    with pytest.raises(NimbusError, match="not a UTF-8 text file"):
        load_scene(tmp_path / "bin")


PLY_HEAD = "ply\nformat {fmt} 1.0\n{element}property float x\nproperty float y\nproperty float z\nend_header\n"


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian"])
@pytest.mark.parametrize("element, message", [
    ("", "declares no vertices"),
    ("element vertex\n", "malformed PLY header line"),
    ("element vertex -3\n", "not a whole number"),
    ("element vertex abc\n", "not a whole number"),
    ("element vertex 1000000000000000000000000000000\n", "truncated or its vertex count is wrong"),
    ("element vertex 5\n", "truncated|malformed"),
])
def test_ply_with_a_bad_vertex_count_is_a_clear_error(tmp_path, fmt, element, message):
    body = "1 2 3\n" if fmt == "ascii" else struct.pack("<3f", 1, 2, 3).decode("latin-1")
    ply = tmp_path / "p.ply"
    ply.write_bytes((PLY_HEAD.format(fmt=fmt, element=element) + body).encode("latin-1"))
    with pytest.raises(NimbusError, match=message):
        read_ply_points(ply)
    root = _transforms_scene(tmp_path / "s", top={"ply_file_path": "p.ply"})
    (root / "p.ply").write_bytes(ply.read_bytes())
    with pytest.raises(NimbusError, match=f"p.ply.*({message})"):
        load_scene(root)


def test_ply_without_end_of_header_and_with_nan_points(tmp_path):
    (tmp_path / "a.ply").write_text("ply\nformat ascii 1.0\nelement vertex 1\nend_header")
    with pytest.raises(NimbusError, match="not a PLY file"):
        read_ply_points(tmp_path / "a.ply")
    (tmp_path / "b.ply").write_text(PLY_HEAD.format(fmt="ascii", element="element vertex 2\n") + "1 2 3\nnan 0 0\n")
    with pytest.raises(NimbusError, match="1 of 2 sparse points have NaN"):
        read_ply_points(tmp_path / "b.ply")


# --- 5. depth maps ---------------------------------------------------------------------------
def _depth_scene(tmp_path, depth: np.ndarray, suffix=".npy"):
    root = _colmap_scene(tmp_path, depth=True)
    target = root / "depths" / "001.npy"
    np.save(target, depth.astype(np.float32))
    return load_scene(root).view("001.png")


def test_negative_depth_is_refused(tmp_path):
    d = np.full((24, 32), 3.0)
    d[0, 0] = -1.0
    with pytest.raises(NimbusError, match=r"001.npy has 1 negative value.*flipped sign"):
        _depth_scene(tmp_path, d).load_depth()


@pytest.mark.parametrize("fill", [np.nan, 0.0])
def test_mostly_missing_depth_is_refused_and_a_few_holes_are_sky(tmp_path, fill):
    d = np.full((24, 32), fill)
    with pytest.raises(NimbusError, match=r"001.npy has no depth \(NaN or 0\) at 100%"):
        _depth_scene(tmp_path / "all", d).load_depth()
    d = np.full((24, 32), 2.5)
    d[:3] = fill  # 12.5 % of the pixels: holes, read as "no surface"
    back = _depth_scene(tmp_path / "few", d).load_depth()
    assert np.isinf(back[:3]).all() and (back[3:] == np.float32(2.5)).all()


def test_png_depth_zero_is_a_hole_and_all_zero_is_refused(tmp_path):
    raw = np.full((4, 5), 2500, np.uint16)
    raw[0, 0] = 0
    cv2.imwrite(str(tmp_path / "d.png"), raw)
    d = read_depth(tmp_path / "d.png")
    assert np.isinf(d[0, 0]) and d[1, 1] == pytest.approx(2.5)
    cv2.imwrite(str(tmp_path / "z.png"), np.zeros((4, 5), np.uint16))
    with pytest.raises(NimbusError, match="z.png has no depth"):
        read_depth(tmp_path / "z.png")


def test_all_sky_depth_is_read_with_a_warning(tmp_path, caplog):
    with caplog.at_level(logging.WARNING, logger="nimbus.data.images"):
        d = _depth_scene(tmp_path, np.full((24, 32), np.inf)).load_depth()
    assert np.isinf(d).all()
    assert any("001.npy has no finite depth" in r.getMessage() for r in caplog.records)


class _Payload:
    """Unpickling this would create a file: a depth map must never run code."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (open, (self.marker, "w"))


def test_depth_files_are_never_unpickled_or_allocated_from_their_header(tmp_path):
    marker = tmp_path / "pwned"
    np.save(tmp_path / "p.npy", np.array([_Payload(str(marker))], dtype=object), allow_pickle=True)
    with pytest.raises(NimbusError, match="p.npy is unreadable"):
        read_depth(tmp_path / "p.npy")
    assert not marker.exists()
    with open(tmp_path / "huge.npy", "wb") as f:  # declares 80 GB, holds 16 bytes
        np.lib.format.write_array_header_1_0(f, {"descr": "<f4", "fortran_order": False, "shape": (200000, 100000)})
        f.write(b"\0" * 16)
    with pytest.raises(NimbusError, match="huge.npy is unreadable"):
        read_depth(tmp_path / "huge.npy")
    np.save(tmp_path / "s.npy", np.array(["a", "b"]))
    with pytest.raises(NimbusError, match="s.npy is unreadable"):
        read_depth(tmp_path / "s.npy")
    assert os.path.getsize(tmp_path / "huge.npy") < 1000


# --- images: decompression bombs, headers past OpenCV's limit, damaged files (issue 35) -------------------
def _png_claiming(width: int, height: int) -> bytes:
    """A few hundred bytes of PNG whose header declares ``width`` x ``height`` (its IHDR patched, CRC fixed)."""
    ok, buf = cv2.imencode(".png", np.zeros((4, 4), np.uint8))
    png = bytearray(buf.tobytes())
    png[16:24] = struct.pack(">II", width, height)
    png[29:33] = struct.pack(">I", zlib.crc32(bytes(png[12:29])))
    return bytes(png)


def _never_decoded(monkeypatch) -> list:
    """Record every call of OpenCV's decoder (a refused bomb must be refused from its header alone)."""
    calls = []
    monkeypatch.setattr(cv2, "imdecode", lambda *a, **k: calls.append(a) or None)
    monkeypatch.setattr(cv2, "imread", lambda *a, **k: calls.append(a) or None)
    return calls


def test_a_decompression_bomb_named_by_a_scene_is_refused_from_its_header(tmp_path, monkeypatch):
    """A Blender scene takes its image size from the file: a PNG declaring 30000 x 30000 is refused before
    any pixel is decoded, naming the file, its size and the limit."""
    _blender_bomb = _transforms_scene(tmp_path / "s", top={"w": None, "h": None, "fl_x": None, "camera_angle_x": 0.7})
    bomb = _blender_bomb / "images" / "1.png"
    bomb.write_bytes(_png_claiming(30000, 30000))
    assert bomb.stat().st_size < 1000
    calls = _never_decoded(monkeypatch)
    with pytest.raises(NimbusError) as info:
        scene = load_scene(_blender_bomb)
        for view in scene.views:
            view.load_image()
    message = str(info.value)
    assert str(bomb) in message and "30000x30000" in message and "limit of 100 megapixels" in message
    assert "NIMBUS_MAX_IMAGE_PIXELS" in message
    assert calls == []


@pytest.mark.parametrize("reader", ["image", "mask", "depth"])
def test_every_image_reader_refuses_an_oversized_header_before_decoding(tmp_path, monkeypatch, reader):
    from nimbus.data.images import read_image, read_mask

    path = tmp_path / "big.png"
    path.write_bytes(_png_claiming(40000, 40000))  # past OpenCV's own 2**30 pixels: its error was a traceback
    calls = _never_decoded(monkeypatch)
    read = {"image": read_image, "mask": read_mask, "depth": read_depth}[reader]
    with pytest.raises(NimbusError, match=r"big\.png is 40000x40000 .*limit"):
        read(path)
    assert calls == []


def test_the_pixel_limit_is_overridable_and_opencvs_own_limit_is_one_error_line(tmp_path, monkeypatch):
    from nimbus.data.images import read_image

    small = tmp_path / "small.png"
    write_image(small, np.zeros((12, 16, 3), np.float32))
    monkeypatch.setenv("NIMBUS_MAX_IMAGE_PIXELS", "100")
    with pytest.raises(NimbusError, match=r"small\.png is 16x12 .*limit of 0\.0001 megapixels"):
        read_image(small)
    monkeypatch.setenv("NIMBUS_MAX_IMAGE_PIXELS", "192")
    assert read_image(small).shape == (12, 16, 3)
    monkeypatch.setenv("NIMBUS_MAX_IMAGE_PIXELS", "lots")
    with pytest.raises(NimbusError, match="NIMBUS_MAX_IMAGE_PIXELS='lots' must be a whole number"):
        read_image(small)
    monkeypatch.setenv("NIMBUS_MAX_IMAGE_PIXELS", str(10**10))  # ours allows it; OpenCV's limit still holds
    (tmp_path / "big.png").write_bytes(_png_claiming(40000, 40000))
    with pytest.raises(NimbusError, match=r"big\.png cannot be decoded"):
        read_image(tmp_path / "big.png")


def _jpeg(tmp_path: Path, name: str, damage) -> Path:
    rng = np.random.default_rng(0)
    ok, buf = cv2.imencode(".jpg", (rng.random((48, 64, 3)) * 255).astype(np.uint8))
    path = tmp_path / name
    path.write_bytes(damage(buf.tobytes()))
    return path


def _flip(data: bytes) -> bytes:
    data = bytearray(data)
    data[len(data) // 2] ^= 0xFF
    return bytes(data)


@pytest.mark.parametrize("name, damage, message", [
    ("cut.jpg", lambda d: d[: len(d) // 2] + b"\xff\xd9", "premature end of data segment"),  # end marker re-added
    ("flipped.jpg", _flip, "corrupt JPEG data"),
    ("no_end.jpg", lambda d: d[: len(d) // 2], "truncated"),
])
def test_a_damaged_jpeg_that_the_decoder_only_warns_about_is_refused(tmp_path, capfd, name, damage, message):
    """libjpeg warns on stderr and fills the missing part grey; the image is refused, naming the file."""
    from nimbus.data.images import read_image

    path = _jpeg(tmp_path, name, damage)
    with pytest.raises(NimbusError) as info:
        read_image(path)
    assert str(path) in str(info.value) and message.lower() in str(info.value).lower()
    assert read_image(_jpeg(tmp_path, "whole.jpg", lambda d: d)).shape == (48, 64, 3)
    assert "Corrupt JPEG" not in capfd.readouterr().err  # said once, in the error


def test_a_damaged_png_is_refused_naming_the_file(tmp_path):
    from nimbus.data.images import read_image

    ok, buf = cv2.imencode(".png", (np.random.default_rng(0).random((48, 64, 3)) * 255).astype(np.uint8))
    for name, data in (("crc.png", _flip(buf.tobytes())), ("cut.png", buf.tobytes()[: len(buf) // 2]),
                       ("short.png", _png_claiming(64, 48))):  # valid chunks, too little pixel data
        (tmp_path / name).write_bytes(data)
        with pytest.raises(NimbusError, match=rf"image .*{name} is (unreadable or corrupt|truncated)"):
            read_image(tmp_path / name)


# --- 7. no silent garbage: camera values that load but mean nothing (issue 35, item 7) ----------------------
# A field of view of 180 degrees or more, a focal length in the wrong unit and a quaternion that is no rotation were
# read without a word: pycolmap normalises a zero quaternion into some rotation, and a near-zero focal length renders
# a few pixels of the scene across the whole image.  Each is refused naming the file and the field.
@pytest.mark.parametrize("angle", [np.pi, 3.0, -1.0], ids=["180deg", "172deg-read", "negative"])
def test_a_transforms_field_of_view_of_180_degrees_or_more_is_refused(tmp_path, angle):
    root = _transforms_scene(tmp_path, top={"camera_angle_x": angle})
    meta = json.loads((root / "transforms.json").read_text())
    meta.pop("fl_x"), meta.pop("fl_y")
    (root / "transforms.json").write_text(json.dumps(meta))
    if np.degrees(angle) < 175 and angle > 0:  # wide but a pinhole: read
        assert load_scene(root).views[0].camera.fov_x == pytest.approx(angle)
        return
    with pytest.raises(NimbusError, match=r"transforms.json: frame 0 \(images/0.png\): camera_angle_x=.* not a "
                                          r"pinhole field of view"):
        load_scene(root)


def test_a_transforms_focal_length_that_sees_180_degrees_is_refused(tmp_path):
    root = _transforms_scene(tmp_path, frame0={"fl_y": 1e-6})
    with pytest.raises(NimbusError, match=r"transforms.json: frame 0 \(images/0.png\): fy=1e-06 gives a vertical "
                                          r"field of view of 180 degrees"):
        load_scene(root)


@pytest.mark.parametrize("focal", [1e-9, 0.05])
def test_a_colmap_focal_length_that_sees_180_degrees_is_refused(tmp_path, focal):
    sparse = _colmap_scene(tmp_path) / "sparse" / "0"
    data = bytearray((sparse / "cameras.bin").read_bytes())
    data[8 + 24:8 + 32] = struct.pack("<d", focal)  # fx of camera 1
    (sparse / "cameras.bin").write_bytes(bytes(data))
    with pytest.raises(NimbusError, match=rf"camera 1 in .*sparse/0 \(image '000.png'\): fx={focal:g} gives a "
                                          r"horizontal field of view of 1\d\d(\.\d+)? degrees"):
        load_scene(sparse.parent.parent)


@pytest.mark.parametrize("where", ["frames.bin", "images.bin", "frames.txt", "images.txt"])
@pytest.mark.parametrize("quaternion", [(0, 0, 0, 0), (2, 0, 0, 0)], ids=["zero", "scaled"])
def test_a_colmap_quaternion_that_is_no_rotation_is_refused(tmp_path, where, quaternion):
    text = where.endswith(".txt")
    sparse = _colmap_scene(tmp_path, text=text) / "sparse" / "0"
    f = sparse / where
    if where == "images.bin":  # the legacy layout, where the pose is the image's
        (sparse / "rigs.bin").unlink()
        (sparse / "frames.bin").unlink()
    if text:
        lines = f.read_text().splitlines()
        first = next(i for i, line in enumerate(lines) if line and not line.startswith("#"))
        tokens = lines[first].split()
        at = 1 if where == "images.txt" else 2
        tokens[at:at + 4] = [str(v) for v in quaternion]
        lines[first] = " ".join(tokens)
        f.write_text("\n".join(lines) + "\n")
        match = rf"{where} line {first + 1}: its rotation quaternion .* has norm {np.linalg.norm(quaternion):g}"
    else:
        data = bytearray(f.read_bytes())
        at = 8 + (4 if where == "images.bin" else 8)
        data[at:at + 32] = struct.pack("<4d", *quaternion)
        f.write_bytes(bytes(data))
        match = rf"{where} is corrupt .*(image|frame) 1: its rotation quaternion .* has norm"
    with pytest.raises(NimbusError, match=match):
        load_scene(sparse.parent.parent)


def test_a_colmap_quaternion_rounded_to_a_few_digits_is_read(tmp_path):
    sparse = _colmap_scene(tmp_path, text=True) / "sparse" / "0"
    lines = (sparse / "images.txt").read_text().splitlines()
    first = next(i for i, line in enumerate(lines) if line and not line.startswith("#"))
    tokens = lines[first].split()
    tokens[1:5] = [f"{float(v):.3f}" for v in tokens[1:5]]
    lines[first] = " ".join(tokens)
    (sparse / "images.txt").write_text("\n".join(lines) + "\n")
    assert len(load_scene(sparse.parent.parent).views) == 3


# --- 8. round 2: a duplicated PLY property, names too long for the file system, non-finite exports ----------
@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian"])
def test_a_ply_with_a_duplicated_property_is_refused(tmp_path, fmt):
    """numpy refused the binary record type with a traceback; the ASCII reader silently took the last column."""
    head = PLY_HEAD.format(fmt=fmt, element="element vertex 1\n").replace("property float z\n",
                                                                          "property float z\nproperty float x\n")
    body = "1 2 3 4\n" if fmt == "ascii" else struct.pack("<4f", 1, 2, 3, 4).decode("latin-1")
    (tmp_path / "p.ply").write_bytes((head + body).encode("latin-1"))
    with pytest.raises(NimbusError, match=r"p.ply: the vertex property 'x' is declared more than once"):
        read_ply_points(tmp_path / "p.ply")


@pytest.mark.parametrize("where", ["transforms", "colmap", "split list"])
def test_a_name_longer_than_the_file_system_allows_is_refused(tmp_path, where):
    long = "a" * 300 + ".png"
    if where == "transforms":
        root = _transforms_scene(tmp_path, frame0={"file_path": f"images/{long}"})
        match = r"frame 0 .*file_path name .* has a part of 304 bytes; file systems take at most 255"
    elif where == "colmap":
        sparse = _colmap_scene(tmp_path, text=True) / "sparse" / "0"
        text = (sparse / "images.txt").read_text()
        (sparse / "images.txt").write_text(text.replace(" 000.png", f" {long}", 1))
        root, match = sparse.parent.parent, r"image name in .*images.txt name .* has a part of 304 bytes"
    else:
        root = _colmap_scene(tmp_path)
        (root / "test_list.txt").write_text(long + "\n")
        match = r"test_list.txt.* has a part of 304 bytes"
    with pytest.raises(NimbusError, match=match):
        load_scene(root)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_a_rendered_image_with_non_finite_values_is_not_written(tmp_path, bad):
    """to_uint8 turned NaN into black and inf into white without a word."""
    img = np.full((4, 6, 3), 0.5, np.float32)
    img[1, 2, 0] = bad
    with pytest.raises(NimbusError, match=r"refusing to write image .*r.png: 1 of 72 values are NaN or inf "
                                          r"\(the first at index \(1, 2, 0\)\)"):
        write_image(tmp_path / "r.png", img)
    assert list(tmp_path.iterdir()) == []


def test_a_depth_map_with_nan_is_not_written_and_inf_is_sky(tmp_path):
    from nimbus.data.images import write_depth

    depth = np.ones((4, 6), np.float32)
    depth[0, 0] = np.inf  # sky: kept
    write_depth(tmp_path / "ok.npy", depth)
    assert np.isinf(read_depth(tmp_path / "ok.npy")[0, 0])
    for bad in (np.nan, -np.inf):
        depth[3, 5] = bad
        with pytest.raises(NimbusError, match=r"refusing to write depth map .*bad.npy: 1 of 24 values are NaN or "
                                              r"-inf \(the first at index \(3, 5\)\)"):
            write_depth(tmp_path / "bad.npy", depth)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ok.npy"]


def test_a_write_under_a_name_too_long_is_one_error_and_leaves_nothing(tmp_path):
    from nimbus.utils.fs import atomic_write_bytes

    with pytest.raises(NimbusError, match=r"the file name 'xxx.* is too long for the file system of .* \(300 bytes "
                                          r"in one name; most take 255\)"):
        atomic_write_bytes(tmp_path / ("x" * 300), b"data")
    assert list(tmp_path.iterdir()) == []


def test_a_full_disk_met_outside_the_atomic_writers_is_one_error_line(tmp_path, capsys):
    """A log line, a library's own file: run_cli turns ENOSPC into one line naming the folder (exit 2)."""
    import errno

    from nimbus.cli_util import run_cli

    def main(argv):
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "run" / "train_log.jsonl"))

    assert run_cli(main, []) == 2
    err = capsys.readouterr().err.strip()
    assert err.splitlines() == [err] and err.startswith(f"error: no space left on the device of {tmp_path / 'run'}")

    def bug(argv):
        raise OSError(errno.EIO, "Input/output error")  # not the user's to fix: a traceback as before

    with pytest.raises(OSError):
        run_cli(bug, [])


def test_a_json_output_with_nan_is_not_written_and_an_infinite_psnr_is(tmp_path):
    from nimbus.utils.fs import atomic_write_json

    with pytest.raises(NimbusError, match=r"refusing to write .*results.json: its field per_view.a.psnr is NaN"):
        atomic_write_json(tmp_path / "results.json", {"psnr": 20.0, "per_view": {"a": {"psnr": float("nan")}}})
    assert list(tmp_path.iterdir()) == []
    atomic_write_json(tmp_path / "results.json", {"psnr": float("inf")})  # identical images
    assert json.loads((tmp_path / "results.json").read_text())["psnr"] == float("inf")
