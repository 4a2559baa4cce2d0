"""Blender / nerfstudio ``transforms.json`` scenes.

Reading
-------
* ``ROOT/transforms.json`` (nerfstudio, Instant-NGP) or Blender synthetic's
  ``transforms_train.json`` + ``transforms_test.json`` (``transforms_val.json`` is
  not used, as in 3DGS); a path to one ``.json`` file reads just that file.
* ``transform_matrix`` is an OpenGL camera-to-world matrix (x right, y up,
  z backward); it is converted to the OpenCV world-to-camera pose of
  :mod:`nimbus.data.camera` by flipping the y and z axes and inverting.
* Intrinsics ``fl_x, fl_y, cx, cy, w, h`` per frame or at the top level (frame
  values win); or Blender's ``camera_angle_x`` (``fl = w / 2 / tan(angle / 2)``,
  square pixels, centred principal point) with the size read from the image.
* ``file_path`` relative to ROOT, with or without an extension (Blender
  omits ``.png``); like every name read from the file it must stay inside
  ROOT (:func:`nimbus.data.scene.scene_file`: no absolute path, no ``..``, no
  link leading out).  View names are these paths with a folder shared by all of
  them removed (``images/frame_00001.png`` -> ``frame_00001.png``).  With
  ``downscale=d`` that shared folder ``X`` is replaced by ``X_d`` (nerfstudio's
  ``images_2/4/8``) and the cameras are scaled to the files' true sizes.
* Lens distortion (the instant-ngp / nerfstudio keys ``k1, k2, k3, k4, p1, p2``, per
  frame or at the top level): with ``camera_model`` ``OPENCV`` (or none, ``PINHOLE``,
  ``SIMPLE_PINHOLE``, ``PERSPECTIVE``) the coefficients are OpenCV's ``(k1, k2, p1, p2, k3)``
  (a non-zero ``k4``, nerfstudio's r^8 term, has no OpenCV counterpart and is refused, as
  nerfstudio's own undistortion does); with ``OPENCV_FISHEYE`` they are OpenCV's fisheye
  ``(k1, k2, k3, k4)`` (``p1, p2`` must be 0).  Such views are undistorted on load into
  pinhole views whose files live in the cache (:mod:`nimbus.data.undistort`).  Other models
  (``EQUIRECTANGULAR``, ...) are refused.
* ``ply_file_path`` (nerfstudio) gives the sparse points; otherwise there are none.
* Split: ``train_list.txt`` / ``test_list.txt`` if present; else Blender's
  test file; else nerfstudio's ``test_filenames``; else the LLFF rule.
* nerfstudio's per-frame ``mask_path`` is the view's validity mask (non-zero = the
  pixel counts, as in nerfstudio); with ``downscale=d`` it is read from the mask's folder
  with ``_d`` appended (``masks/x.png`` -> ``masks_d/x.png``, nerfstudio's rule).  It wins over a
  ``masks/`` file of the same view.  ``depth_file_path`` is ignored (nerfstudio's depth
  units differ from Nimbus's), but a name that leads outside ROOT is still refused;
  ``depths/``, ``masks/`` and ``sky/`` folders are attached as for every layout (:mod:`nimbus.data.io`).
* The file, then each frame as it is reached, is checked against its declared schema
  (:class:`nimbus.schemas.TransformsFile`, :class:`~nimbus.schemas.TransformsFrame`): a key of the
  wrong type (a number as ``file_path``, a string or NaN in ``transform_matrix``, a split list that
  is no list of names) raises NimbusError naming the file, the frame and the field.
* Every camera value is checked (:class:`nimbus.data.camera.Camera`): finite
  numbers, positive focal lengths, whole positive sizes, a finite rotation; a
  bad one raises NimbusError naming the file and the frame.
* A frame that lists an image an earlier frame listed is refused when it is read, naming both
  frames, before the frames after it are resolved.  A long load (a file of 100,000 frames) shows
  its progress on stderr after 2 s (:mod:`nimbus.utils.progress`).

Writing
-------
``transforms.json`` (OpenGL camera-to-world, per-frame ``fl_x, fl_y, cx, cy,
w, h``, ``camera_model: OPENCV``), ``images/``, ``sparse_pc.ply`` (binary PLY,
double xyz + uchar rgb) when there are points, ``depths/``, ``masks/`` and the
split lists.  nerfstudio reads it as it is.
"""

from __future__ import annotations

import json
import os
from dataclasses import replace
from pathlib import Path, PurePosixPath

import numpy as np

from nimbus.data.camera import MAX_FIELD_OF_VIEW_DEG, Camera, check_field_of_view, finite_value, image_size_value
from nimbus.data.images import IMAGE_EXTENSIONS
from nimbus.data.scene_files import (
    attach_aux_files,
    check_image_sizes,
    check_points_finite,
    format_names,
    image_size,
    scaled_to_image,
    write_view_files,
)
from nimbus.data.scene import Scene, View, llff_test_names, read_split_lists, scene_file
from nimbus.data.undistort import Lens, undistort_views
from nimbus.errors import NimbusError
from nimbus.schemas import TransformsFile, TransformsFrame, check
from nimbus.utils.fs import atomic_write_bytes, atomic_write_json
from nimbus.utils.progress import note_if_slow, slow_progress

# OpenGL <-> OpenCV camera axes: flip y and z.
GL_TO_CV = np.diag([1.0, -1.0, -1.0])
DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
# camera_model values of a perspective camera (the OpenCV / Brown model when k1.. are given) and of a fisheye.
PERSPECTIVE_CAMERA_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "PERSPECTIVE")
FISHEYE_CAMERA_MODELS = ("OPENCV_FISHEYE",)
# Colour given to PLY points that carry none (mid-grey).
DEFAULT_POINT_COLOR = 128
WRITTEN_PLY = "sparse_pc.ply"
# What a transforms file must say, whatever reads it (nimbus.schemas.TransformsFile / TransformsFrame).
FIX = "fix the transforms file"
# Per-frame file names Nimbus does not read but still keeps inside the scene.
IGNORED_FRAME_FILES = ("depth_file_path",)


def read_json(path: Path) -> dict:
    """Parse a JSON object from ``path``; NimbusError with the position of a syntax error."""
    try:
        with note_if_slow(f"nimbus: parsing {path} ..."):
            meta = json.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise NimbusError(f"{path} does not exist") from None
    except UnicodeDecodeError:
        raise NimbusError(f"{path} is not a UTF-8 text file; it should be a transforms.json") from None
    except json.JSONDecodeError as e:
        raise NimbusError(f"{path} is not valid JSON ({e.msg} at line {e.lineno}, column {e.colno}); "
                          "fix or re-export it") from None
    except RecursionError:
        raise NimbusError(f"{path} is nested too deeply to be a transforms.json; fix or re-export it") from None
    except ValueError as e:  # e.g. an integer literal longer than Python's digit limit
        raise NimbusError(f"{path} is not valid JSON ({e}); fix or re-export it") from None
    except OSError as e:
        raise NimbusError(f"{path} cannot be read ({e.strerror}); check the file") from None
    if not isinstance(meta, dict):
        raise NimbusError(f"{path} must hold a JSON object with a \"frames\" list")
    return meta


def _transforms_files(path: Path) -> tuple[Path, list[tuple[Path, bool]]]:
    """The scene root and the (json file, is_test_file) pairs to read."""
    if path.is_file():
        return path.parent, [(path, False)]
    if (path / "transforms.json").is_file():
        return path, [(path / "transforms.json", False)]
    if (path / "transforms_train.json").is_file():
        files = [(path / "transforms_train.json", False)]
        if (path / "transforms_test.json").is_file():
            files.append((path / "transforms_test.json", True))
        return path, files
    raise NimbusError(f"{path} has no transforms.json (or Blender transforms_train.json)")


def _resolve_image(root: Path, file_path: object, what: str) -> Path | None:
    """The image file a ``file_path`` names: as given, or with an image extension added.

    The name and the file found are both confined to ``root`` (:func:`scene_file`).
    """
    p = scene_file(root, file_path, what)
    if p.is_file():
        return p
    for ext in dict.fromkeys(e.lower() for e in IMAGE_EXTENSIONS):
        for candidate in (p.with_name(p.name + ext), p.with_name(p.name + ext.upper())):
            if candidate.is_file():
                return scene_file(root, f"{file_path}{candidate.suffix}", what)
    return None


def _check_listed_once(listed: dict[str, str], key: str, where: str) -> None:
    """Record that ``where`` lists the image ``key``; NimbusError if a frame read before it did."""
    if key in listed:
        raise NimbusError(f"{where} lists the same image as {listed[key]}; a scene lists each image once: remove "
                          "one of the two frames")
    listed[key] = where


def transforms_lens(model: object, values: dict) -> Lens | None:
    """The lens of a frame from its ``camera_model`` and distortion keys (None: no distortion).

    ``values`` maps the keys of :data:`DISTORTION_KEYS` that are present to their values.
    Raises NimbusError for a non-finite or non-number coefficient, an unsupported model, and
    coefficients the model does not have (see the module docstring).
    """
    name = "OPENCV" if model is None else str(model).upper()
    k = {key: finite_value(values[key], key) if values.get(key) is not None else 0.0 for key in DISTORTION_KEYS}
    if name in FISHEYE_CAMERA_MODELS:
        if k["p1"] or k["p2"]:
            raise NimbusError(f"camera_model {model} has no tangential distortion, but p1={k['p1']:g}, "
                              f"p2={k['p2']:g} are set; remove them or use camera_model OPENCV")
        return Lens(name, True, (k["k1"], k["k2"], k["k3"], k["k4"]))
    if name not in PERSPECTIVE_CAMERA_MODELS:
        raise NimbusError(f"camera_model {model} is not supported; Nimbus reads perspective cameras "
                          f"({', '.join(PERSPECTIVE_CAMERA_MODELS)}, with k1, k2, k3, p1, p2 distortion) and "
                          f"{', '.join(FISHEYE_CAMERA_MODELS)} (k1-k4); convert the images to one of these first")
    if k["k4"]:
        raise NimbusError(f"k4={k['k4']:g} with camera_model {name}: a fourth radial term (r^8) has no OpenCV "
                          "counterpart and Nimbus cannot undistort it (nerfstudio cannot either); recalibrate with "
                          "k1, k2, k3, p1, p2, or use camera_model OPENCV_FISHEYE if it is a fisheye lens")
    lens = Lens(name, False, (k["k1"], k["k2"], k["p1"], k["p2"], k["k3"]))
    return None if lens.is_identity else lens


def _intrinsics(meta: dict, frame: dict, full_image: Path,
                where: str) -> tuple[int, int, float, float, float, float, Lens | None]:
    """(w, h, fx, fy, cx, cy, lens) of a frame, frame keys over top-level ones."""
    def get(key):
        return frame.get(key, meta.get(key))

    lens = transforms_lens(get("camera_model"), {key: get(key) for key in DISTORTION_KEYS})
    w, h = get("w"), get("h")
    if w is None or h is None:
        if full_image is None or not full_image.is_file():
            raise NimbusError(f"{where}: no image size (w, h) and no image file to read it from")
        w, h = image_size(full_image)
    w, h = image_size_value(w, "w"), image_size_value(h, "h")
    fx, fy = get("fl_x"), get("fl_y")
    with np.errstate(divide="ignore", invalid="ignore"):  # a zero or NaN angle is refused as a focal length
        if fx is None:
            if get("camera_angle_x") is None:
                raise NimbusError(f"{where}: no focal length (fl_x or camera_angle_x); add it to the file")
            fx = 0.5 * w / np.tan(0.5 * _angle(get("camera_angle_x"), "camera_angle_x"))
        if fy is None:
            fy = (0.5 * h / np.tan(0.5 * _angle(get("camera_angle_y"), "camera_angle_y"))
                  if get("camera_angle_y") is not None else fx)
    cx = get("cx") if get("cx") is not None else w / 2
    cy = get("cy") if get("cy") is not None else h / 2
    return (w, h, finite_value(fx, "fl_x"), finite_value(fy, "fl_y"), finite_value(cx, "cx"),
            finite_value(cy, "cy"), lens)


def _angle(value: object, name: str) -> float:
    """A field of view in radians from the file, refused at 0 or below and at 180 degrees (pi) or more."""
    v = finite_value(value, name)
    if not 0 < v < np.radians(MAX_FIELD_OF_VIEW_DEG):
        raise NimbusError(f"{name}={v:g} radians ({np.degrees(v):.4g} degrees) is not a pinhole field of view: it "
                          f"must be above 0 and below {MAX_FIELD_OF_VIEW_DEG:g} degrees "
                          f"({np.radians(MAX_FIELD_OF_VIEW_DEG):.4f} radians)")
    return v


def _mask_file(root: Path, name: object, downscale: int, what: str) -> Path:
    """The validity mask a frame's ``mask_path`` names (``downscale=d``: in ``<its folder>_d``), kept in ROOT."""
    path = scene_file(root, name, what)
    if downscale > 1:
        rel = PurePosixPath(name)
        if len(rel.parts) < 2:
            raise NimbusError(f"{what}: {name!r} is not in a folder, so there is no downscaled copy to read with "
                              f"downscale={downscale}; put the masks in masks/ with a masks_{downscale}/ copy, or "
                              "use downscale=1")
        folder = f"{rel.parts[0]}_{downscale}"
        path = scene_file(root, PurePosixPath(*rel.parts[1:]).as_posix(), f"{what} (downscaled)", folder=folder)
    if not path.is_file():
        raise NimbusError(f"{what}: mask {path} does not exist; restore it or remove the frame's mask_path"
                          + (f" (with downscale={downscale} the masks come from {path.parent.name}/)"
                             if downscale > 1 else ""))
    return path


def opengl_c2w_to_w2c(c2w: np.ndarray) -> np.ndarray:
    """OpenGL camera-to-world (3x4 or 4x4) -> OpenCV world-to-camera 4x4."""
    m = np.eye(4)
    m[:3, :4] = np.asarray(c2w, dtype=np.float64)[:3, :4]
    m[:3, :3] = m[:3, :3] @ GL_TO_CV
    R = m[:3, :3].T
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ m[:3, 3]
    return w2c


def camera_to_opengl_c2w(camera: Camera) -> np.ndarray:
    """A camera's pose as the OpenGL camera-to-world 4x4 matrix transforms.json stores."""
    c2w = camera.camera_to_world
    c2w[:3, :3] = c2w[:3, :3] @ GL_TO_CV
    return c2w


def read_transforms(path: str | os.PathLike, downscale: int = 1, cache_dir: str | os.PathLike | None = None) -> Scene:
    """Read a Blender / nerfstudio ``transforms.json`` scene (see the module docstring).

    Parameters
    ----------
    path : path
        Scene folder, or a ``.json`` file in it.
    downscale : int
        1, or ``d`` to read images from ``<image folder>_d`` with scaled cameras.
    cache_dir : path, optional
        Where views of distorted cameras are undistorted to (default: the user cache,
        :func:`nimbus.data.undistort.default_cache_dir`).

    Returns
    -------
    Scene
        ``source_format="transforms"``; distorted views undistorted (``metadata["undistorted"]``).
    """
    path = Path(path)
    if not path.exists():
        raise NimbusError(f"scene folder {path} does not exist; check the path")
    root, files = _transforms_files(path)
    for file, _ in files:  # one linked from elsewhere would be read (and quoted in errors) as this scene's
        scene_file(root, file.name, "camera file")
    records = []  # (relative image path, full image path, camera, is_test, lens, mask_path)
    missing, test_filenames, metas = [], [], []
    # Where each image was first listed: by the name as written (checked before the frame is resolved), and by
    # the file it resolved to ("a" and "a.png" name one file).
    listed: dict[str, str] = {}
    for file, is_test in files:
        meta = check(TransformsFile, read_json(file), str(file), FIX)
        metas.append(meta)
        frames = meta["frames"]
        test_filenames += meta.get("test_filenames", [])
        for i, frame in enumerate(slow_progress(frames, f"reading {file.name}", len(frames), "frame")):
            # Each frame as it is reached: a file of a million frames is never held twice.
            named = isinstance(frame, dict) and isinstance(frame.get("file_path"), str)
            check(TransformsFrame, frame, f"{file}: frame {i}" + (f" ({frame['file_path']})" if named else ""), FIX)
            where = f"{file}: frame {i} ({frame['file_path']})"
            if isinstance(frame["file_path"], str):
                _check_listed_once(listed, "name:" + PurePosixPath(frame["file_path"]).as_posix(), where)
            for key in IGNORED_FRAME_FILES:
                if frame.get(key) is not None:
                    scene_file(root, frame[key], f"{where}: {key}")
            mask = frame.get("mask_path")
            if mask is not None:
                mask = _mask_file(root, mask, downscale, f"{where}: mask_path")
            image = _resolve_image(root, frame["file_path"], f"{where}: file_path")
            if image is None:
                missing.append(str(frame["file_path"]))
                continue
            _check_listed_once(listed, "file:" + Path(os.path.relpath(image, root)).as_posix(), where)
            try:
                w, h, fx, fy, cx, cy, lens = _intrinsics(meta, frame, image, where)
                c2w = np.asarray(frame["transform_matrix"], dtype=np.float64)
                if c2w.shape not in ((4, 4), (3, 4)):
                    raise NimbusError(f"transform_matrix must be 4x4 or 3x4, got shape {c2w.shape}")
                cam = Camera.from_K(np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]]), w, h, opengl_c2w_to_w2c(c2w))
                check_field_of_view(cam)
            except NimbusError as e:
                raise NimbusError(e.args[0] if str(e).startswith(where) else f"{where}: {e}") from None
            except (TypeError, ValueError) as e:
                raise NimbusError(f"{where}: malformed value ({e}); fix the transforms file") from None
            records.append((Path(os.path.relpath(image, root)).as_posix(), image, cam, is_test, lens, mask))
    if missing:
        raise NimbusError(f"{len(missing)} image(s) listed in the transforms file(s) are missing under {root}: "
                          f"{format_names(missing)}; restore them or remove their frames")

    rel = [r[0] for r in records]
    parts = [r.split("/") for r in rel]
    prefix = parts[0][0] if all(len(p) > 1 and p[0] == parts[0][0] for p in parts) else ""
    names = ["/".join(p[1:]) if prefix else r for p, r in zip(parts, rel)]
    if downscale > 1 and not prefix:
        raise NimbusError(f"downscale={downscale} needs the images in one folder (e.g. images/) with a "
                          f"downscaled copy beside it (images_{downscale}/); {root} has none; use downscale=1")
    views = []
    for name, (_, image, cam, _, _, _) in zip(names, records):
        if downscale > 1:
            image = scene_file(root, name, f"downscaled image of {name}", folder=f"{prefix}_{downscale}")
            if not image.is_file():
                raise NimbusError(f"downscaled image {image} does not exist; make {prefix}_{downscale}/ by "
                                  f"resizing {prefix}/ by 1/{downscale}, or use downscale=1")
        views.append(View(name, cam, image_path=image))
    if downscale == 1:
        check_image_sizes(views, "fix w/h in the transforms file or use the matching images")
    else:
        views = [scaled_to_image(v, downscale) for v in views]
    views = attach_aux_files(root, views, downscale)
    views = [replace(v, mask_path=r[5]) if r[5] is not None else v for v, r in zip(views, records)]
    views, undistorted = undistort_views(views, [r[4] for r in records], cache_dir, where=str(root))

    test = read_split_lists(root, names)
    if test is None and len(files) > 1:
        test = {n for n, r in zip(names, records) if r[3]}
    if test is None and test_filenames:
        by_path = {r[1].resolve(): n for n, r in zip(names, records)}
        test = set()
        for f in test_filenames:
            image = _resolve_image(root, f, "test_filenames entry")
            if image is None or image.resolve() not in by_path:
                raise NimbusError(f"test_filenames entry {f!r} is not a frame of the scene; fix the transforms file")
            test.add(by_path[image.resolve()])
    if test is None:
        test = llff_test_names(names)

    points, colors = np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
    ply_file = metas[0].get("ply_file_path")
    if ply_file not in (None, ""):
        ply = scene_file(root, ply_file, f"{files[0][0]}: ply_file_path")
        if not ply.is_file():
            raise NimbusError(f"ply_file_path {ply} does not exist; restore it or remove the key")
        points, colors = read_ply_points(ply)
    metadata = {"transforms_files": [f.name for f, _ in files], "image_dir": prefix, "downscale": downscale}
    if undistorted is not None:
        metadata["undistorted"] = undistorted
    return Scene(tuple(views), frozenset(test), points, colors, root=root, source_format="transforms",
                 metadata=metadata)


def write_transforms(scene: Scene, directory: str | os.PathLike) -> None:
    """Write ``scene`` as a nerfstudio ``transforms.json`` scene into the existing folder ``directory``.

    Use :func:`nimbus.data.io.write_scene` for an atomic write to a new folder.
    """
    if not scene.views:
        raise NimbusError("the scene has no views; nothing to write")
    directory = Path(directory)
    names = write_view_files(scene, directory)
    frames = []
    for v in scene.views:
        c = v.camera
        frames.append({
            "file_path": f"images/{names[v.name]}",
            "transform_matrix": camera_to_opengl_c2w(c).tolist(),
            "fl_x": c.fx, "fl_y": c.fy, "cx": c.cx, "cy": c.cy, "w": c.width, "h": c.height,
        })
    meta = {"camera_model": "OPENCV", "frames": frames}
    if len(scene.points):
        write_ply_points(directory / WRITTEN_PLY, scene.points, scene.colors)
        meta["ply_file_path"] = WRITTEN_PLY
    atomic_write_json(directory / "transforms.json", meta)


# --- PLY point clouds ------------------------------------------------------------------
_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


def read_ply_points(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Vertices of a PLY file (ASCII or binary) as xyz float64 (N, 3) and rgb uint8 (N, 3).

    The vertex element must come first and have x, y, z; colours are
    ``red, green, blue`` (uchar, or float in [0, 1]); without them points are grey.
    A malformed header, a vertex count that is missing, negative or larger than the
    file holds, and non-finite coordinates raise NimbusError naming the file.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as e:
        raise NimbusError(f"PLY file {path} cannot be read ({e.strerror}); check ply_file_path") from None
    end = data.find(b"end_header")
    newline = data.find(b"\n", end) if end >= 0 else -1
    if not data.startswith(b"ply") or newline < 0:
        raise NimbusError(f"{path} is not a PLY file (no 'ply' ... 'end_header' header); re-export the points")
    header = data[:end].decode("ascii", "replace").splitlines()
    body_start = newline + 1
    fmt, count, props, in_vertex, seen_element = None, None, [], False, False
    for line in header:
        tok = line.split()
        if not tok:
            continue
        if tok[0] == "format" and len(tok) >= 2:
            fmt = tok[1]
        elif tok[0] == "element":
            if len(tok) != 3:
                raise NimbusError(f"{path}: malformed PLY header line {line.strip()!r} "
                                  "(expected 'element NAME COUNT'); re-export the points")
            if not seen_element and tok[1] != "vertex":
                raise NimbusError(f"{path}: the first PLY element must be 'vertex'")
            in_vertex, seen_element = tok[1] == "vertex", True
            if in_vertex:
                if not tok[2].isdigit():  # also refuses a negative count
                    raise NimbusError(f"{path}: the vertex count {tok[2]!r} is not a whole number >= 0; "
                                      "re-export the points")
                count = int(tok[2])
        elif tok[0] == "property" and in_vertex:
            if len(tok) != 3 or tok[1] not in _PLY_TYPES:
                raise NimbusError(f"{path}: unsupported vertex property {' '.join(tok[1:])!r}")
            props.append((tok[2], _PLY_TYPES[tok[1]]))
    if count is None:
        raise NimbusError(f"{path}: the PLY header declares no vertices ('element vertex COUNT'); re-export the points")
    names = [p[0] for p in props]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:  # which column is "x" would be a guess (numpy refuses the record type; the ASCII path took the last)
        raise NimbusError(f"{path}: the vertex property {', '.join(map(repr, twice[:4]))} is declared more than once; "
                          "each property names one column: re-export the points")
    if not {"x", "y", "z"} <= set(names):
        raise NimbusError(f"{path}: vertices have no x, y, z")
    if fmt == "ascii":
        if count > len(data) - body_start:  # every vertex takes more than one byte
            raise NimbusError(f"{path} is truncated or its vertex count is wrong ({count} vertices declared, "
                              f"{len(data) - body_start} bytes of vertex data)")
        rows = data[body_start:].decode("ascii", "replace").split("\n", count)[:count]
        try:
            table = np.array([r.split()[: len(props)] for r in rows], dtype=np.float64).reshape(count, len(props))
        except ValueError:
            raise NimbusError(f"{path}: malformed or truncated ASCII vertex list ({count} vertices declared)") from None
        col = {n: table[:, i] for i, n in enumerate(names)}
    elif fmt in ("binary_little_endian", "binary_big_endian"):
        order = "<" if fmt == "binary_little_endian" else ">"
        dtype = np.dtype([(n, order + t) for n, t in props])
        if len(data) - body_start < dtype.itemsize * count:
            raise NimbusError(f"{path} is truncated or its vertex count is wrong ({count} vertices of "
                              f"{dtype.itemsize} bytes declared, {len(data) - body_start} bytes present)")
        arr = np.frombuffer(data, dtype=dtype, count=count, offset=body_start)
        col = {n: arr[n] for n in names}
    else:
        raise NimbusError(f"{path}: unknown PLY format {fmt!r}")
    xyz = np.stack([col["x"], col["y"], col["z"]], axis=1).astype(np.float64).reshape(count, 3)
    check_points_finite(xyz, path)
    if {"red", "green", "blue"} <= set(names):
        rgb = np.stack([col["red"], col["green"], col["blue"]], axis=1)
        if np.issubdtype(np.asarray(rgb).dtype, np.floating) and rgb.size and rgb.max() <= 1.0:
            rgb = rgb * 255.0
        rgb = np.clip(np.nan_to_num(np.round(rgb)), 0, 255).astype(np.uint8)
    else:
        rgb = np.full((count, 3), DEFAULT_POINT_COLOR, np.uint8)
    return xyz, rgb


def write_ply_points(path: str | os.PathLike, points: np.ndarray, colors: np.ndarray) -> Path:
    """Write points (N, 3) and uint8 colours (N, 3) as a binary little-endian PLY (double xyz), atomically."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    colors = np.asarray(colors, dtype=np.uint8).reshape(-1, 3)
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(points)}\n"
        "property double x\nproperty double y\nproperty double z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
    )
    table = np.empty(len(points), dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8"),
                                         ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    for i, k in enumerate("xyz"):
        table[k] = points[:, i]
    for i, k in enumerate(("red", "green", "blue")):
        table[k] = colors[:, i]
    return atomic_write_bytes(path, header.encode("ascii") + table.tobytes())
