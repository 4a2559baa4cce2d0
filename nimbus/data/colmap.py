"""COLMAP scenes: ``images/`` + ``sparse/0`` (binary or text), read and written through pycolmap.

Layout read
-----------
``ROOT/images/<name>``, the model in ``ROOT/sparse/0`` (or directly in
``ROOT/sparse``, as ``colmap image_undistorter`` writes it), ``.bin`` or
``.txt``.  With ``downscale=d`` the images come from Mip-NeRF360's
``ROOT/images_<d>`` and each camera is scaled to its file's true size.  Optional
``depths/``, ``masks/``, ``train_list.txt`` / ``test_list.txt`` (see
:mod:`nimbus.data.io`).

Camera models: ``SIMPLE_PINHOLE`` and ``PINHOLE`` are read as they are;
``SIMPLE_RADIAL``, ``RADIAL``, ``OPENCV`` and ``FULL_OPENCV`` only when all their
distortion parameters are zero.  Anything else is refused with the command that
undistorts the scene (Nimbus renders pinhole cameras only).

Layout written
--------------
``images/`` (source files copied byte for byte, in-memory images as PNG),
``sparse/0`` with one ``PINHOLE`` camera per distinct intrinsics, the poses,
and the sparse points with their colours.  Points are written with empty
tracks (COLMAP, pycolmap, 3DGS and gsplat read them; the 3DGS initialisation
needs only xyz and colour).  Also ``depths/``, ``masks/`` and the split lists.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np
import pycolmap

from nimbus.data.camera import Camera
from nimbus.data.io import (
    attach_aux_files,
    check_image_sizes,
    format_names,
    list_images,
    scaled_to_image,
    write_view_files,
)
from nimbus.data.scene import Scene, View, llff_test_names, read_split_lists
from nimbus.errors import NimbusError

log = logging.getLogger(__name__)

PINHOLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")
# Perspective models that reduce to a pinhole when every distortion parameter is zero.
# (Fisheye models do not: zero coefficients still mean an equidistant projection.)
ZERO_DISTORTION_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV")


def find_sparse_dir(root: str | os.PathLike) -> Path | None:
    """``ROOT/sparse/0`` or ``ROOT/sparse`` when it holds a COLMAP model (cameras.bin/.txt), else None."""
    root = Path(root)
    for d in (root / "sparse" / "0", root / "sparse"):
        if (d / "cameras.bin").is_file() or (d / "cameras.txt").is_file():
            return d
    return None


def read_reconstruction(sparse_dir: str | os.PathLike) -> pycolmap.Reconstruction:
    """Load a COLMAP model folder; unreadable files raise NimbusError naming the folder."""
    sparse_dir = Path(sparse_dir)
    try:
        return pycolmap.Reconstruction(sparse_dir)
    except Exception as e:  # pycolmap raises assorted C++ exceptions (ValueError, RuntimeError)
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise NimbusError(f"COLMAP model in {sparse_dir} is unreadable ({first}); re-export it from COLMAP") from None


def camera_from_colmap(cam: pycolmap.Camera, cam_from_world: np.ndarray, sparse_dir: Path | str = "") -> Camera:
    """A Nimbus camera from a pycolmap camera and a 3x4 world-to-camera matrix.

    Raises NimbusError for a distorted or non-perspective model, saying how to undistort.
    """
    model = cam.model_name
    params = np.asarray(cam.params, dtype=np.float64)
    if model not in PINHOLE_MODELS:
        extra = params[list(cam.extra_params_idxs())]
        if model not in ZERO_DISTORTION_MODELS or np.any(extra != 0):
            root = Path(sparse_dir).parent.parent if Path(sparse_dir).name == "0" else Path(sparse_dir).parent
            raise NimbusError(
                f"camera {cam.camera_id} in {sparse_dir} uses the {model} model with lens distortion "
                f"(params {params.tolist()}); Nimbus needs undistorted pinhole images. Undistort the scene first: "
                f"`colmap image_undistorter --image_path {root}/images --input_path {sparse_dir} "
                f"--output_path {root}_undistorted` (or in Python: pycolmap.undistort_images("
                f"'{root}_undistorted', '{sparse_dir}', '{root}/images')), then load {root}_undistorted"
            )
    m = np.asarray(cam_from_world, dtype=np.float64)
    return Camera(cam.width, cam.height, cam.focal_length_x, cam.focal_length_y,
                  cam.principal_point_x, cam.principal_point_y, m[:3, :3], m[:3, 3])


def _cam_from_world(image: pycolmap.Image) -> np.ndarray:
    pose = image.cam_from_world
    pose = pose() if callable(pose) else pose  # a method since pycolmap 3.12, a property before
    return np.asarray(pose.matrix())


def read_colmap(root: str | os.PathLike, downscale: int = 1) -> Scene:
    """Read a COLMAP scene folder (see the module docstring for the layout and accepted models).

    Parameters
    ----------
    root : path
        Folder with ``images/`` and ``sparse/0``.
    downscale : int
        Use ``images_<downscale>`` and scale the cameras to its images (1 = ``images/``).

    Returns
    -------
    Scene
        ``source_format="colmap"``; the registered images as views; sparse points
        and colours; the split from ``train_list.txt`` / ``test_list.txt`` or the LLFF rule.

    Raises
    ------
    NimbusError
        Missing folder or model, empty model, distorted camera, registered images
        missing on disk (named), images of the wrong size (named).
        Images on disk but not in the model are only logged as a warning.
    """
    root = Path(root)
    if not root.is_dir():
        raise NimbusError(f"scene folder {root} does not exist; check the path")
    sparse = find_sparse_dir(root)
    if sparse is None:
        raise NimbusError(f"{root} has no COLMAP model (expected sparse/0/cameras.bin or .txt); "
                          f"to make one from photos run: nimbus-synth sfm PHOTOS --out {root}")
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

    views = [View(im.name, camera_from_colmap(rec.cameras[im.camera_id], _cam_from_world(im), sparse),
                  image_path=image_dir / im.name) for im in images]
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

    point_ids = sorted(rec.points3D)
    points = np.array([rec.points3D[i].xyz for i in point_ids], dtype=np.float64).reshape(-1, 3)
    colors = np.array([rec.points3D[i].color for i in point_ids], dtype=np.uint8).reshape(-1, 3)
    names = [v.name for v in views]
    test = read_split_lists(root, names)
    if test is None:
        test = llff_test_names(names)
    return Scene(tuple(views), frozenset(test), points, colors, root=root, source_format="colmap",
                 metadata={"sparse_dir": str(sparse.relative_to(root)), "image_dir": image_dir.name,
                           "downscale": downscale})


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
