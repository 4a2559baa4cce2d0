"""COLMAP scenes: ``images/`` + ``sparse/0`` (binary or text), read and written through pycolmap.

Layout read
-----------
``ROOT/images/<name>``, the model in ``ROOT/sparse/0`` (or directly in
``ROOT/sparse``, as ``colmap image_undistorter`` writes it), ``.bin`` or
``.txt``.  With ``downscale=d`` the images come from Mip-NeRF360's
``ROOT/images_<d>`` and each camera is scaled to its file's true size.  Optional
``depths/``, ``masks/``, ``sky/``, ``train_list.txt`` / ``test_list.txt`` (see
:mod:`nimbus.data.io`).

Files received from elsewhere are not trusted: every image name must stay inside
the scene folder (:func:`nimbus.data.scene.scene_file`), a binary model's
structure is checked against its file sizes before pycolmap reads it
(:func:`check_binary_model`), every camera value and pose is validated
(:class:`nimbus.data.camera.Camera`) and the sparse points must be finite.

Camera models: ``SIMPLE_PINHOLE`` and ``PINHOLE`` are read as they are, and so are
``SIMPLE_RADIAL``, ``RADIAL``, ``OPENCV`` and ``FULL_OPENCV`` when all their distortion
parameters are zero.  With distortion, these and the fisheye models
``SIMPLE_RADIAL_FISHEYE``, ``RADIAL_FISHEYE``, ``OPENCV_FISHEYE``, ``SIMPLE_FISHEYE`` and
``FISHEYE`` are undistorted on load into pinhole views whose files live in the cache
(:mod:`nimbus.data.undistort`; :data:`COLMAP_LENSES` maps each onto OpenCV's models).
The other models (``FOV``, the thin-prism fisheyes, ``DIVISION``, ``EUCM``,
``EQUIRECTANGULAR``) are refused with the command that undistorts the scene.

Layout written
--------------
``images/`` (source files copied byte for byte, in-memory images as PNG),
``sparse/0`` with one ``PINHOLE`` camera per distinct intrinsics, the poses,
and the sparse points with their colours.  Points are written with empty
tracks (COLMAP, pycolmap, 3DGS and gsplat read them; the 3DGS initialisation
needs only xyz and colour).  Also ``depths/``, ``masks/``, ``sky/`` and the split lists.
"""

from __future__ import annotations

import functools
import logging
import mmap
import os
import struct
from pathlib import Path

import numpy as np
import pycolmap

from nimbus.data.camera import Camera, check_field_of_view
from nimbus.data.scene_files import (
    attach_aux_files,
    check_image_sizes,
    check_points_finite,
    format_names,
    list_images,
    scaled_to_image,
    write_view_files,
)
from nimbus.data.scene import Scene, View, llff_test_names, read_split_lists, scene_file
from nimbus.data.undistort import Lens, undistort_views
from nimbus.errors import NimbusError

log = logging.getLogger(__name__)

PINHOLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")
# COLMAP model -> (fisheye, the index in the model's params of each OpenCV distortion coefficient,
# None = 0).  COLMAP's perspective models are OpenCV's (k1, k2, p1, p2[, k3, k4, k5, k6]) with terms
# left out; its fisheye models are OpenCV's equidistant (k1, k2, k3, k4) one, so a fisheye with zero
# coefficients still needs resampling.  Checked against pycolmap's img_from_cam in tests/test_undistort.py.
COLMAP_LENSES: dict[str, tuple[bool, tuple[int | None, ...]]] = {
    "SIMPLE_RADIAL": (False, (3, None, None, None)),
    "RADIAL": (False, (3, 4, None, None)),
    "OPENCV": (False, (4, 5, 6, 7)),
    "FULL_OPENCV": (False, (4, 5, 6, 7, 8, 9, 10, 11)),
    "SIMPLE_RADIAL_FISHEYE": (True, (3, None, None, None)),
    "RADIAL_FISHEYE": (True, (3, 4, None, None)),
    "OPENCV_FISHEYE": (True, (4, 5, 6, 7)),
    "SIMPLE_FISHEYE": (True, (None, None, None, None)),
    "FISHEYE": (True, (None, None, None, None)),
}


def find_sparse_dir(root: str | os.PathLike) -> Path | None:
    """``ROOT/sparse/0`` or ``ROOT/sparse`` when it holds a COLMAP model (cameras.bin/.txt), else None."""
    root = Path(root)
    for d in (root / "sparse" / "0", root / "sparse"):
        if (d / "cameras.bin").is_file() or (d / "cameras.txt").is_file():
            return d
    return None


def model_suffix(sparse_dir: str | os.PathLike) -> str:
    """``".bin"`` when pycolmap will read the binary files (all three exist), else ``".txt"``."""
    return ".bin" if all((Path(sparse_dir) / f"{n}.bin").is_file() for n in ("cameras", "images", "points3D")) \
        else ".txt"


def read_reconstruction(sparse_dir: str | os.PathLike) -> pycolmap.Reconstruction:
    """Load a COLMAP model folder; unreadable files raise NimbusError naming the file.

    A binary model is checked against its file sizes first (:func:`check_binary_model`):
    pycolmap trusts the counts in the files and would allocate whatever a corrupt one declares.
    """
    sparse_dir = Path(sparse_dir)
    binary = model_suffix(sparse_dir) == ".bin"
    if binary:
        check_binary_model(sparse_dir)
    else:
        check_text_quaternions(sparse_dir)
    try:
        return pycolmap.Reconstruction(sparse_dir)
    except Exception as e:  # pycolmap raises assorted C++ exceptions (ValueError, RuntimeError, IndexError)
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        where = None if binary else locate_text_model_error(sparse_dir)
        if where is not None:
            raise NimbusError(f"COLMAP model file {where} is unreadable; fix that line or re-export the model "
                              "from COLMAP") from None
        raise NimbusError(f"COLMAP model in {sparse_dir} is unreadable ({first}); re-export it from COLMAP") from None


# --- binary model check ----------------------------------------------------------------
# Fixed bytes of one record (ids, poses, counts) in COLMAP's binary files; see COLMAP's
# src/colmap/scene/reconstruction_io_binary.cc.
_POSE_BYTES = 7 * 8  # quaternion wxyz + translation, float64
_CAMERA_BYTES = 4 + 4 + 8 + 8  # camera_id u32, model_id i32, width u64, height u64 (+ params f64)
_IMAGE_BYTES = 4 + _POSE_BYTES + 4  # image_id, cam_from_world, camera_id (+ name, NUL, count, points)
_POINT2D_BYTES = 8 + 8 + 8  # x, y f64, point3D_id u64
_POINT3D_BYTES = 8 + 3 * 8 + 3 + 8  # point3D_id u64, xyz f64, rgb u8, error f64 (+ track length u64)
_TRACK_ELEMENT_BYTES = 4 + 4  # image_id u32, point2D_idx u32
_RIG_BYTES = 4 + 4  # rig_id, num_sensors (+ sensors)
_SENSOR_BYTES = 4 + 4  # sensor type i32, sensor id u32
_FRAME_BYTES = 4 + 4 + _POSE_BYTES + 4  # frame_id, rig_id, rig_from_world, num_data_ids (+ data ids)
_DATA_ID_BYTES = 4 + 4 + 8  # sensor type, sensor id, data id u64
_U8, _U32, _I32, _U64 = (struct.Struct(f) for f in ("<B", "<I", "<i", "<Q"))


@functools.cache
def camera_model_num_params() -> dict[int, int]:
    """COLMAP camera model id -> number of parameters, as the installed pycolmap defines them."""
    table = {}
    for model in pycolmap.CameraModelId.__members__.values():
        if int(model) >= 0:
            table[int(model)] = len(pycolmap.Camera.create_from_model_id(1, model, 1.0, 1, 1).params)
    return table


class _Corrupt(Exception):
    """A structural problem found by :class:`_RecordReader`; turned into a NimbusError naming the file."""


class _RecordReader:
    """A bounds-checked cursor over a COLMAP binary file that reads only headers and counts.

    Every count is checked against the bytes left before anything is skipped, so a corrupt
    file costs neither memory nor time (the file is memory-mapped, never read whole).
    """

    def __init__(self, buf) -> None:
        self.buf, self.pos, self.size = buf, 0, len(buf)

    def left(self) -> int:
        return self.size - self.pos

    def skip(self, n: int, what: str) -> None:
        if n > self.left():
            raise _Corrupt(f"{what} needs {n} bytes but only {self.left()} are left (the file is truncated)")
        self.pos += n

    def read(self, fmt: struct.Struct, what: str) -> int:
        start = self.pos
        self.skip(fmt.size, what)
        return fmt.unpack_from(self.buf, start)[0]

    def count(self, fmt: struct.Struct, min_bytes: int, what: str) -> int:
        """A declared number of records of at least ``min_bytes`` each, refused when they cannot fit."""
        n = self.read(fmt, f"the number of {what}")
        if n * min_bytes > self.left():
            raise _Corrupt(f"declares {n} {what} (at least {n * min_bytes} bytes) but only {self.left()} bytes "
                           "follow (a corrupt count or a truncated file)")
        return n

    def name(self, what: str) -> None:
        end = self.buf.find(b"\0", self.pos)
        if end < 0:
            raise _Corrupt(f"{what} has no terminating NUL byte (the file is truncated)")
        self.pos = end + 1


#: How far a pose quaternion's norm may be from 1: COLMAP writes unit quaternions, and a file rounded to 3 digits
#: stays within this.  A zero (or wildly scaled) quaternion is no rotation; pycolmap would normalise it into some
#: rotation and the view would be trained at a pose nobody measured.
QUATERNION_NORM_TOLERANCE = 0.01


def quaternion_problem(q) -> str | None:
    """What is wrong with a pose quaternion (QW, QX, QY, QZ) read from a model, or None.  A non-finite one is left to
    the camera check (:class:`~nimbus.data.camera.Camera` refuses a NaN pose naming the image)."""
    q = np.asarray(q, dtype=np.float64)
    norm = float(np.linalg.norm(q))
    if np.all(np.isfinite(q)) and not abs(norm - 1) <= QUATERNION_NORM_TOLERANCE:
        return (f"its rotation quaternion (QW QX QY QZ) = {' '.join(f'{v:g}' for v in q)} has norm {norm:.4g}, "
                f"not 1 (within {QUATERNION_NORM_TOLERANCE:g}): it is no rotation")
    return None


def _check_quaternion(r: _RecordReader, offset: int, what: str) -> None:
    if r.left() >= offset + 32:
        problem = quaternion_problem(struct.unpack_from("<4d", r.buf, r.pos + offset))
        if problem:
            raise _Corrupt(f"{what}: {problem}")


def _walk_cameras(r: _RecordReader) -> None:
    num_params = camera_model_num_params()
    for i in range(r.count(_U64, _CAMERA_BYTES, "cameras")):
        r.skip(4, f"camera {i + 1}")
        model = r.read(_I32, f"camera {i + 1}")
        if model not in num_params:
            raise _Corrupt(f"camera {i + 1} has an unknown camera model id {model}")
        r.skip(16 + 8 * num_params[model], f"camera {i + 1}")


def _walk_images(r: _RecordReader) -> None:
    for i in range(r.count(_U64, _IMAGE_BYTES + 1 + 8, "images")):
        _check_quaternion(r, 4, f"image {i + 1}")  # after image_id
        r.skip(_IMAGE_BYTES, f"image {i + 1}")
        r.name(f"the name of image {i + 1}")
        n = r.count(_U64, _POINT2D_BYTES, f"2D points of image {i + 1}")
        r.pos += n * _POINT2D_BYTES


def _walk_points3d(r: _RecordReader) -> None:
    # Hot loop (a model can hold millions of points): inlined rather than through the helpers.
    n = r.count(_U64, _POINT3D_BYTES + 8, "3D points")
    buf, pos, size, unpack = r.buf, r.pos, r.size, _U64.unpack_from
    for i in range(n):
        if pos + _POINT3D_BYTES + 8 > size:
            r.pos = pos
            raise _Corrupt(f"3D point {i + 1} of {n} is cut off (the file is truncated)")
        track = unpack(buf, pos + _POINT3D_BYTES)[0]
        pos += _POINT3D_BYTES + 8
        if track * _TRACK_ELEMENT_BYTES > size - pos:
            raise _Corrupt(f"3D point {i + 1} declares a track of {track} observations "
                           f"({track * _TRACK_ELEMENT_BYTES} bytes) but only {size - pos} bytes follow")
        pos += track * _TRACK_ELEMENT_BYTES
    r.pos = pos


def _walk_rigs(r: _RecordReader) -> None:
    for i in range(r.count(_U64, _RIG_BYTES, "rigs")):
        r.skip(4, f"rig {i + 1}")
        sensors = r.read(_U32, f"the number of sensors of rig {i + 1}")
        if sensors == 0:
            continue
        r.skip(_SENSOR_BYTES, f"the reference sensor of rig {i + 1}")
        # The other sensors: type, id and a has-pose byte each (+ a pose when that byte is set).
        if (sensors - 1) * (_SENSOR_BYTES + 1) > r.left():
            raise _Corrupt(f"rig {i + 1} declares {sensors} sensors (at least {(sensors - 1) * (_SENSOR_BYTES + 1)} "
                           f"bytes) but only {r.left()} bytes follow (a corrupt count or a truncated file)")
        for _ in range(sensors - 1):
            r.skip(_SENSOR_BYTES, f"a sensor of rig {i + 1}")
            if r.read(_U8, f"a sensor of rig {i + 1}"):
                r.skip(_POSE_BYTES, f"a sensor pose of rig {i + 1}")


def _walk_frames(r: _RecordReader) -> None:
    for i in range(r.count(_U64, _FRAME_BYTES, "frames")):
        _check_quaternion(r, 8, f"frame {i + 1}")  # after frame_id, rig_id
        r.skip(_FRAME_BYTES - 4, f"frame {i + 1}")
        n = r.count(_U32, _DATA_ID_BYTES, f"data ids of frame {i + 1}")
        r.pos += n * _DATA_ID_BYTES


_BINARY_WALKERS = {"rigs.bin": _walk_rigs, "cameras.bin": _walk_cameras, "frames.bin": _walk_frames,
                   "images.bin": _walk_images, "points3D.bin": _walk_points3d}


def check_binary_model(sparse_dir: str | os.PathLike) -> None:
    """Walk every binary file of a COLMAP model and check its structure against its size.

    Reads only the record headers and the variable-length counts (a camera model's number of
    parameters, an image's NUL-terminated name and ``num_points2D * 24`` bytes, a point's
    ``track_length * 8`` bytes, a rig's sensors, a frame's data ids).  A declared count that
    cannot fit in the bytes left, a record cut off by the end of the file or an unknown camera
    model raises NimbusError naming the file, in well under a second and without allocating
    more than the walk itself needs, before pycolmap would try to allocate what the file declares.
    Bytes after the last record are ignored, as COLMAP does.
    """
    sparse_dir = Path(sparse_dir)
    for name, walk in _BINARY_WALKERS.items():
        path = sparse_dir / name
        if not path.is_file():
            continue
        try:
            with open(path, "rb") as f:
                if os.fstat(f.fileno()).st_size == 0:
                    raise _Corrupt("the file is empty")
                try:
                    buf = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
                except OSError:  # a file system without mmap: read it (bounded by its size, not its counts)
                    buf = f.read()
                try:
                    walk(_RecordReader(buf))
                finally:
                    if isinstance(buf, mmap.mmap):
                        buf.close()
        except _Corrupt as e:
            raise NimbusError(f"COLMAP model file {path} is corrupt and unreadable: {e}; re-export the model "
                              "from COLMAP (or restore the file from a backup)") from None
        except OSError as e:
            raise NimbusError(f"COLMAP model file {path} cannot be read ({e.strerror}); check the file") from None


# --- text model errors -----------------------------------------------------------------
def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def _text_line_problem(kind: str, tokens: list[str]) -> str | None:
    """What is wrong with one data line of a text model file, or None (a light check for messages)."""
    if kind == "cameras":
        if len(tokens) < 4 or not all(t.isdigit() for t in (tokens[0], tokens[2], tokens[3])):
            return "expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS..."
        if not all(_is_number(t) for t in tokens[4:]):
            return "camera parameters must be numbers"
        if not all(np.isfinite(float(t)) for t in tokens[4:]):
            return "camera parameters must be finite (no nan or inf)"
        model = getattr(pycolmap.CameraModelId, tokens[1], None)
        if model is None:
            return f"unknown camera model {tokens[1]!r}"
        expected = camera_model_num_params()[int(model)]
        if len(tokens) - 4 != expected:
            return f"the {tokens[1]} model takes {expected} parameters, the line has {len(tokens) - 4}"
    elif kind == "images":
        if len(tokens) < 10 or not all(_is_number(t) for t in tokens[:9]):
            return "expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME"
    elif kind == "points2D":
        if len(tokens) % 3 or not all(_is_number(t) for t in tokens):
            return "expected the image's 2D points as X Y POINT3D_ID triples"
    elif kind == "points3D":
        if len(tokens) < 8 or (len(tokens) - 8) % 2 or not all(_is_number(t) for t in tokens):
            return "expected POINT3D_ID X Y Z R G B ERROR TRACK[] as (IMAGE_ID, POINT2D_IDX) pairs"
    return None


def check_text_quaternions(sparse_dir: str | os.PathLike) -> None:
    """Refuse a text model whose ``images.txt`` or ``frames.txt`` holds a pose quaternion that is no rotation
    (:func:`quaternion_problem`), naming the file and line; pycolmap would normalise it silently."""
    sparse_dir = Path(sparse_dir)
    for kind, first in (("images", 1), ("frames", 2)):  # QW is the 2nd token of an image line, 3rd of a frame's
        path = sparse_dir / f"{kind}.txt"
        try:
            lines = path.read_text(encoding="utf-8").splitlines()
        except (OSError, UnicodeDecodeError):
            continue  # pycolmap reads (or refuses) it next
        expect_points = False
        for number, line in enumerate(lines, 1):
            stripped = line.strip()
            if expect_points:  # an image's 2D points: the line after its pose line, empty or not
                expect_points = False
                continue
            if not stripped or stripped.startswith("#"):
                continue
            tokens = stripped.split()
            try:
                q = [float(t) for t in tokens[first:first + 4]]
            except ValueError:
                q = []
            problem = quaternion_problem(q) if len(q) == 4 else None
            if problem:
                raise NimbusError(f"COLMAP model file {path} line {number}: {problem}; fix the pose or re-export "
                                  "the model from COLMAP")
            expect_points = kind == "images"


def locate_text_model_error(sparse_dir: str | os.PathLike) -> str | None:
    """``"FILE line N: problem ('line')"`` for the first malformed line of a text model, or None.

    Used only to explain a model pycolmap refused, so the message names the file and line.
    """
    sparse_dir = Path(sparse_dir)
    for kind in ("cameras", "images", "points3D"):
        path = sparse_dir / f"{kind}.txt"
        try:
            lines = path.read_text(encoding="utf-8").splitlines()
        except UnicodeDecodeError:
            return f"{path} (not a UTF-8 text file)"
        except OSError:
            continue
        expect_points = False
        for number, line in enumerate(lines, start=1):
            stripped = line.strip()
            if kind == "images" and expect_points:  # the line after a pose line, empty or not
                problem, expect_points = _text_line_problem("points2D", stripped.split()), False
            elif not stripped or stripped.startswith("#"):
                continue
            else:
                problem = _text_line_problem(kind, stripped.split())
                expect_points = kind == "images"
            if problem:
                return f"{path} line {number}: {problem} (got {stripped[:80]!r})"
    return None


def colmap_lens(cam: pycolmap.Camera, sparse_dir: Path | str = "") -> Lens | None:
    """The lens distortion of a pycolmap camera (None for a pinhole model or zero distortion).

    Raises NimbusError naming the camera and the model folder for a non-finite coefficient and
    for a model Nimbus cannot undistort (with the COLMAP command that does).
    """
    model = cam.model_name
    if model in PINHOLE_MODELS:
        return None
    if model not in COLMAP_LENSES:
        root = Path(sparse_dir).parent.parent if Path(sparse_dir).name == "0" else Path(sparse_dir).parent
        raise NimbusError(
            f"camera {cam.camera_id} in {sparse_dir} uses the {model} camera model, which Nimbus cannot undistort "
            f"(it undistorts {', '.join(COLMAP_LENSES)}). Undistort the scene with COLMAP first: "
            f"`colmap image_undistorter --image_path {root}/images --input_path {sparse_dir} "
            f"--output_path {root}_undistorted` (or in Python: pycolmap.undistort_images("
            f"'{root}_undistorted', '{sparse_dir}', '{root}/images')), then load {root}_undistorted")
    fisheye, index = COLMAP_LENSES[model]
    params = [float(p) for p in cam.params]
    names = [n.strip() for n in cam.params_info.split(",")]
    for i in (i for i in index if i is not None):
        if not np.isfinite(params[i]):
            raise NimbusError(f"camera {cam.camera_id} in {sparse_dir}: the {model} distortion parameter "
                              f"{names[i]} must be finite, got {params[i]}; fix the model (or re-export it from "
                              "COLMAP)")
    lens = Lens(model, fisheye, tuple(0.0 if i is None else params[i] for i in index))
    return None if lens.is_identity else lens


def camera_from_colmap(cam: pycolmap.Camera, cam_from_world: np.ndarray, sparse_dir: Path | str = "",
                       image_name: str | None = None) -> tuple[Camera, Lens | None]:
    """A Nimbus camera and its lens from a pycolmap camera and a 3x4 world-to-camera matrix.

    For a distorted model the camera is the pinhole part (``fx, fy, cx, cy``) and the lens is
    :func:`colmap_lens` (None without distortion).  Raises NimbusError for a model Nimbus cannot
    undistort (checked first: pycolmap crashes when asked for the focal length of a model
    without one, such as ``EQUIRECTANGULAR``) and for an invalid camera (non-finite or
    non-positive intrinsics, a size of 0, a pose that is not finite or not a rotation), naming
    the model folder, the camera and ``image_name``.
    """
    lens = colmap_lens(cam, sparse_dir)
    m = np.asarray(cam_from_world, dtype=np.float64)
    try:
        camera = Camera(cam.width, cam.height, cam.focal_length_x, cam.focal_length_y,
                        cam.principal_point_x, cam.principal_point_y, m[:3, :3], m[:3, 3])
        check_field_of_view(camera)
    except NimbusError as e:
        image = f" (image {image_name!r})" if image_name is not None else ""
        raise NimbusError(f"camera {cam.camera_id} in {sparse_dir}{image}: {e}; fix the model (or re-export it "
                          "from COLMAP)") from None
    return camera, lens


def _cam_from_world(image: pycolmap.Image) -> np.ndarray:
    pose = image.cam_from_world
    pose = pose() if callable(pose) else pose  # a method since pycolmap 3.12, a property before
    return np.asarray(pose.matrix())


def _check_model_inside(root: Path, sparse: Path) -> None:
    """Refuse a model folder, or a model file in it, that is a link leading out of the scene: another
    folder's model would be read (and quoted in errors) as this scene's (:func:`scene_file`)."""
    rel = sparse.relative_to(root).as_posix()
    scene_file(root, rel, "COLMAP model folder")
    for f in sorted(sparse.iterdir()):
        if f.suffix in (".bin", ".txt"):
            scene_file(root, f"{rel}/{f.name}", "COLMAP model file")


def read_colmap(root: str | os.PathLike, downscale: int = 1, cache_dir: str | os.PathLike | None = None) -> Scene:
    """Read a COLMAP scene folder (see the module docstring for the layout and accepted models).

    Parameters
    ----------
    root : path
        Folder with ``images/`` and ``sparse/0``.
    downscale : int
        Use ``images_<downscale>`` and scale the cameras to its images (1 = ``images/``).
    cache_dir : path, optional
        Where views of distorted cameras are undistorted to (default: the user cache,
        :func:`nimbus.data.undistort.default_cache_dir`).

    Returns
    -------
    Scene
        ``source_format="colmap"``; the registered images as views (pinhole; distorted ones
        undistorted, with ``metadata["undistorted"]``); sparse points and colours; the split
        from ``train_list.txt`` / ``test_list.txt`` or the LLFF rule.

    Raises
    ------
    NimbusError
        Missing folder or model, empty model, a camera model Nimbus cannot undistort,
        registered images missing on disk (named), images of the wrong size (named).
        Images on disk but not in the model are only logged as a warning.
    """
    root = Path(root)
    if not root.is_dir():
        raise NimbusError(f"scene folder {root} does not exist; check the path")
    sparse = find_sparse_dir(root)
    if sparse is None:
        raise NimbusError(f"{root} has no COLMAP model (expected sparse/0/cameras.bin or .txt); "
                          f"to make one from photos run: nimbus-synth sfm PHOTOS --out {root}")
    _check_model_inside(root, sparse)
    rec = read_reconstruction(sparse)
    images = sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)
    if not images:
        raise NimbusError(f"the COLMAP model in {sparse} has no registered images; "
                          "re-run SfM (nimbus-synth sfm) with more overlapping photos")
    image_dir = root / ("images" if downscale == 1 else f"images_{downscale}")
    if not image_dir.is_dir():
        hint = ("" if downscale == 1 else
                f"; make it by resizing images/ by 1/{downscale} (e.g. `mogrify -path {image_dir} "
                f"-resize {100 / downscale:g}% {root}/images/*`) or load with downscale=1")
        raise NimbusError(f"image folder {image_dir} does not exist{hint}")

    images_file = sparse / f"images{model_suffix(sparse)}"
    views, lenses = [], {}
    for im in images:
        # The name decides what is read now and, as the view name, what writers create later.
        path = scene_file(root, im.name, f"image name in {images_file}", folder=image_dir.name)
        cam, lenses[im.name] = camera_from_colmap(rec.cameras[im.camera_id], _cam_from_world(im), sparse,
                                                  image_name=im.name)
        views.append(View(im.name, cam, image_path=path))
    missing = [v.name for v in views if not v.image_path.is_file()]
    if missing:
        raise NimbusError(f"{len(missing)} image(s) of the COLMAP model are missing from {image_dir}: "
                          f"{format_names(missing)}; restore them or remove them from the model")
    unregistered = sorted(set(list_images(image_dir)) - {v.name for v in views})
    if unregistered:
        log.warning("%d image(s) in %s are not registered in the COLMAP model and are ignored: %s",
                    len(unregistered), image_dir, format_names(unregistered))
    if downscale == 1:
        check_image_sizes(views, "use the images the COLMAP model was made from "
                                 "(a downscaled folder needs downscale=d and images_<d>/)")
    else:
        views = [scaled_to_image(v, downscale) for v in views]
    views = attach_aux_files(root, views, downscale)
    views, undistorted = undistort_views(views, [lenses[v.name] for v in views], cache_dir, where=str(root))

    point_ids = sorted(rec.points3D)
    points = np.array([rec.points3D[i].xyz for i in point_ids], dtype=np.float64).reshape(-1, 3)
    colors = np.array([rec.points3D[i].color for i in point_ids], dtype=np.uint8).reshape(-1, 3)
    check_points_finite(points, sparse / f"points3D{model_suffix(sparse)}")
    names = [v.name for v in views]
    test = read_split_lists(root, names)
    if test is None:
        test = llff_test_names(names)
    metadata = {"sparse_dir": str(sparse.relative_to(root)), "image_dir": image_dir.name, "downscale": downscale}
    if undistorted is not None:
        metadata["undistorted"] = undistorted
    return Scene(tuple(views), frozenset(test), points, colors, root=root, source_format="colmap",
                 metadata=metadata)


def scene_to_reconstruction(scene: Scene, names: dict[str, str] | None = None) -> pycolmap.Reconstruction:
    """A pycolmap model of the scene: PINHOLE cameras (one per distinct intrinsics), poses, points.

    ``names`` maps view names to the image names to record (default: unchanged).
    Image ids follow the sorted view names from 1; points get empty tracks.
    """
    rec = pycolmap.Reconstruction()
    camera_ids: dict[tuple, int] = {}
    for image_id, v in enumerate(scene.views, start=1):
        c = v.camera
        key = (c.width, c.height, c.fx, c.fy, c.cx, c.cy)
        if key not in camera_ids:
            camera_ids[key] = len(camera_ids) + 1
            rec.add_camera_with_trivial_rig(pycolmap.Camera(
                model="PINHOLE", width=c.width, height=c.height, params=[c.fx, c.fy, c.cx, c.cy],
                camera_id=camera_ids[key]))
        image = pycolmap.Image(name=(names or {}).get(v.name, v.name), camera_id=camera_ids[key], image_id=image_id)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(c.R), c.t))
    for xyz, rgb in zip(scene.points, scene.colors):
        rec.add_point3D(xyz, pycolmap.Track(), rgb)
    return rec


def write_colmap(scene: Scene, directory: str | os.PathLike, text: bool = False) -> None:
    """Write ``scene`` as a COLMAP scene into the existing folder ``directory``.

    Use :func:`nimbus.data.io.write_scene` for an atomic write to a new folder.
    ``text=True`` writes ``.txt`` model files instead of ``.bin``.
    """
    if not scene.views:
        raise NimbusError("the scene has no views; nothing to write")
    directory = Path(directory)
    names = write_view_files(scene, directory)
    sparse = directory / "sparse" / "0"
    sparse.mkdir(parents=True, exist_ok=True)
    rec = scene_to_reconstruction(scene, names)
    if text:
        rec.write_text(sparse)
    else:
        rec.write(sparse)
