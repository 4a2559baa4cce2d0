"""Read and write scenes in any supported layout: :func:`load_scene` and :func:`write_scene`.

Supported layouts
-----------------
``"colmap"``
    ``images/`` + ``sparse/0`` (or ``sparse/``) with ``.bin`` or ``.txt`` files
    (:mod:`nimbus.data.colmap`).  Mip-NeRF360's ``images_2/4/8`` folders are used
    with ``downscale=2/4/8``.  Built-in scenes written by ``nimbus-synth scene``
    and scenes made by ``nimbus-synth sfm`` use this layout.
``"transforms"``
    Blender / nerfstudio ``transforms.json`` (or Blender's
    ``transforms_train.json`` + ``transforms_test.json``) (:mod:`nimbus.data.transforms`).

Both layouts may carry, beside the images, optional per-view z-depth maps
``depths/<name without extension>.npy`` and masks ``masks/<name without
extension>.png`` (``depths_<d>`` / ``masks_<d>`` with ``downscale=d``), and the
split lists ``train_list.txt`` / ``test_list.txt``.  Without split lists the
LLFF rule (every 8th view is a test view) applies, except for Blender's own
train/test files.

What both layouts' readers and writers share (the view images, depths and masks
beside the camera model) is in :mod:`nimbus.data.scene_files`.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from nimbus.data.scene import Scene
from nimbus.data.scene_files import list_images
from nimbus.errors import NimbusError
from nimbus.utils.fs import atomic_dir

SCENE_FORMATS = ("colmap", "transforms")


# --- loading ---------------------------------------------------------------------------
def detect_format(path: str | os.PathLike) -> str:
    """Which layout the scene at ``path`` uses: ``"colmap"`` or ``"transforms"``.

    A folder with ``sparse/0`` or ``sparse/`` holding a COLMAP model is ``"colmap"``
    (checked first); a ``transforms.json`` / ``transforms_train.json`` (or a path to
    a ``.json`` file) is ``"transforms"``.  A folder of photos only, a missing path
    or anything else raises :class:`NimbusError` saying what to do.
    """
    path = Path(path)
    if not path.exists():
        raise NimbusError(f"scene folder {path} does not exist; check the path")
    if path.is_file():
        if path.suffix.lower() == ".json":
            return "transforms"
        raise NimbusError(f"{path} is a file; give a scene folder (COLMAP images/ + sparse/0, or transforms.json)")
    from nimbus.data.colmap import find_sparse_dir

    if find_sparse_dir(path) is not None:
        return "colmap"
    if (path / "transforms.json").is_file() or (path / "transforms_train.json").is_file():
        return "transforms"
    if list_images(path):
        photos = path / "images" if list_images(path / "images") else path
        raise NimbusError(
            f"{path} holds photos but no camera poses (no sparse/0 model and no transforms.json); "
            f"recover them first with: nimbus-synth sfm {photos} --out SCENE_DIR"
        )
    raise NimbusError(
        f"{path} is not a scene folder: expected a COLMAP model (images/ + sparse/0) or a transforms.json; "
        "make one with `nimbus-synth scene` or from photos with `nimbus-synth sfm PHOTOS --out SCENE_DIR`"
    )


def load_scene(path: str | os.PathLike, downscale: int = 1, format: str = "auto",
               cache_dir: str | os.PathLike | None = None) -> Scene:
    """Read a scene in any supported layout (see the module docstring).

    Parameters
    ----------
    path : path
        The scene folder (or a ``transforms*.json`` file).
    downscale : int
        1, or a factor ``d`` for which the scene has an ``images_<d>`` folder
        (Mip-NeRF360 / nerfstudio); cameras are scaled to the actual image sizes.
    format : str
        ``"auto"`` (detect), ``"colmap"`` or ``"transforms"``.
    cache_dir : path, optional
        Where views of distorted cameras are undistorted to (default: the user cache,
        :mod:`nimbus.data.undistort`).

    Returns
    -------
    Scene
        Views sorted by name with image paths (images are loaded lazily), the
        split, the sparse points and colours (possibly none), ``root`` and
        ``source_format`` set.
    """
    if not isinstance(downscale, (int, np.integer)) or downscale < 1:
        raise NimbusError(f"downscale must be a positive integer (1, 2, 4, 8), got {downscale!r}")
    if format == "auto":
        format = detect_format(path)
    elif not Path(path).exists():
        raise NimbusError(f"scene folder {path} does not exist; check the path")
    if format == "colmap":
        from nimbus.data.colmap import read_colmap

        return read_colmap(path, downscale=int(downscale), cache_dir=cache_dir)
    if format == "transforms":
        from nimbus.data.transforms import read_transforms

        return read_transforms(path, downscale=int(downscale), cache_dir=cache_dir)
    raise NimbusError(f"unknown scene format {format!r}; use one of {('auto',) + SCENE_FORMATS}")


# --- writing ---------------------------------------------------------------------------
def write_scene(scene: Scene, out: str | os.PathLike, format: str = "colmap", overwrite: bool = False,
                text: bool = False) -> Path:
    """Write ``scene`` to a new folder ``out`` atomically (nothing is left behind on failure).

    Parameters
    ----------
    format : str
        ``"colmap"`` (``images/`` + ``sparse/0``, readable by COLMAP, 3DGS and gsplat)
        or ``"transforms"`` (nerfstudio ``transforms.json``).
    overwrite : bool
        Replace a non-empty ``out``.  The scene's own input folder is never replaced.
    text : bool
        COLMAP only: write ``.txt`` instead of ``.bin`` model files.
    """
    _check_format(format)
    out = Path(out)
    check_not_input(scene, out)
    with atomic_dir(out, overwrite=overwrite) as tmp:
        write_scene_into(scene, tmp, format=format, text=text)
    return out


def write_scene_into(scene: Scene, directory: str | os.PathLike, format: str = "colmap", text: bool = False) -> None:
    """Write ``scene`` into an existing (usually temporary) ``directory``.

    For callers that add their own files inside one atomic write
    (``with atomic_dir(out) as tmp: write_scene_into(scene, tmp); ...``).
    """
    _check_format(format)
    directory = Path(directory)
    if not directory.is_dir():
        raise NimbusError(f"{directory} is not a directory")
    if format == "colmap":
        from nimbus.data.colmap import write_colmap

        write_colmap(scene, directory, text=text)
    else:
        from nimbus.data.transforms import write_transforms

        write_transforms(scene, directory)


def _check_format(format: str) -> None:
    if format not in SCENE_FORMATS:
        raise NimbusError(f"unknown scene format {format!r}; use one of {SCENE_FORMATS}")


def check_not_input(scene: Scene, out: str | os.PathLike) -> None:
    """Refuse an output folder that is, or contains, the scene's own input files."""
    out = Path(out).resolve()
    inputs = [scene.root] if scene.root is not None else []
    for v in scene.views:
        inputs += [p for p in (v.image_path, v.depth_path, v.mask_path, v.sky_path) if p is not None]
    for p in inputs:
        p = Path(p).resolve()
        if p == out or out in p.parents:
            raise NimbusError(f"output {out} would replace the scene's own input ({p}); choose another --out")
