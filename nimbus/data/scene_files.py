"""The files beside a scene's camera model, shared by every layout's reader and writer.

Per view: the image (``images/<name>``), an optional z-depth map (``depths/<stem>.npy``), a
validity mask (``masks/<stem>.png``) and a sky mask (``sky/<stem>.png``); with ``downscale=d``
the ``images_<d>`` / ``depths_<d>`` / ... folders (Mip-NeRF360).  Readers find, attach and check
them (:func:`attach_aux_files`, :func:`check_image_sizes`, :func:`scaled_to_image`); writers copy
or encode them into the output folder (:func:`write_view_files`).  The readers
(:mod:`nimbus.data.colmap`, :mod:`nimbus.data.transforms`) and :mod:`nimbus.data.io`, which
dispatches to them, import this module; it imports none of them.
"""

from __future__ import annotations

import logging
import os
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np

from nimbus.data.images import IMAGE_EXTENSIONS, image_size, write_depth, write_image, write_mask
from nimbus.data.scene import Scene, View, scene_file, write_split_lists
from nimbus.errors import NimbusError
from nimbus.utils.progress import slow_progress

log = logging.getLogger(__name__)

DEPTH_DIR, MASK_DIR, SKY_DIR = "depths", "masks", "sky"
# How many names an error or warning lists before it just counts the rest.
MAX_LISTED_NAMES = 10


def list_images(folder: str | os.PathLike) -> list[str]:
    """Image files under ``folder`` (recursive), as sorted posix paths relative to it; [] if no folder."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    names = []
    for dirpath, dirnames, filenames in os.walk(folder):
        dirnames[:] = [d for d in dirnames if not d.startswith(".")]
        for f in filenames:
            if not f.startswith(".") and Path(f).suffix in IMAGE_EXTENSIONS:
                names.append((Path(dirpath) / f).relative_to(folder).as_posix())
    return sorted(names)


def format_names(names: list[str]) -> str:
    """``a.png, b.png, ... (and 12 more)`` for messages."""
    names = sorted(names)
    head = ", ".join(names[:MAX_LISTED_NAMES])
    return head + (f" (and {len(names) - MAX_LISTED_NAMES} more)" if len(names) > MAX_LISTED_NAMES else "")


def aux_dirs(downscale: int) -> tuple[str, str, str]:
    """Folder names of depth maps, validity masks and sky masks for a downscale factor (``depths`` or
    ``depths_4``...)."""
    if downscale == 1:
        return DEPTH_DIR, MASK_DIR, SKY_DIR
    return f"{DEPTH_DIR}_{downscale}", f"{MASK_DIR}_{downscale}", f"{SKY_DIR}_{downscale}"


def aux_name(name: str, suffix: str) -> str:
    """Depth / mask file name of a view: its name with the extension replaced."""
    return Path(name).with_suffix(suffix).as_posix()


def attach_aux_files(root: Path, views: list[View], downscale: int) -> list[View]:
    """Attach ``depths/<stem>.npy``, ``masks/<stem>.png`` and ``sky/<stem>.png`` to the views that have them.

    A folder that exists but lacks some views' files gets a warning naming them.  A file
    that leads outside the scene (a link, or a folder linked elsewhere) is refused
    (:func:`nimbus.data.scene.scene_file`).
    """
    depth_dir, mask_dir, sky_dir = (root / d for d in aux_dirs(downscale))
    out = []
    missing: dict[str, list[str]] = {depth_dir.name: [], mask_dir.name: [], sky_dir.name: []}
    for v in views:
        changes = {}
        for folder, suffix, field in ((depth_dir, ".npy", "depth_path"), (mask_dir, ".png", "mask_path"),
                                      (sky_dir, ".png", "sky_path")):
            if not folder.is_dir():
                continue
            f = folder / aux_name(v.name, suffix)
            if f.is_file():
                changes[field] = scene_file(root, aux_name(v.name, suffix), f"{field[:-5]} file of view {v.name}",
                                            folder=folder.name)
            else:
                missing[folder.name].append(v.name)
        out.append(replace(v, **changes) if changes else v)
    for folder, names in missing.items():
        if names:
            log.warning("%s/%s has no file for %d view(s): %s", root, folder, len(names), format_names(names))
    return out


def check_points_finite(points: np.ndarray, source: str | os.PathLike) -> None:
    """Refuse sparse points with NaN or inf coordinates (they would seed NaN Gaussians), naming the file."""
    bad = ~np.isfinite(np.asarray(points, dtype=np.float64)).all(axis=-1)
    if bad.any():
        raise NimbusError(f"{source}: {int(bad.sum())} of {len(bad)} sparse points have NaN or infinite "
                          "coordinates; remove them or re-export the points")


def check_image_sizes(views: list[View], hint: str) -> None:
    """Check every view's image file against its camera size; NimbusError naming the first mismatches."""
    bad = []
    for v in slow_progress(views, "checking image sizes", len(views), "image"):
        w, h = image_size(v.image_path)
        if (w, h) != (v.camera.width, v.camera.height):
            bad.append(f"{v.image_path} is {w}x{h}, camera {v.camera.width}x{v.camera.height}")
    if bad:
        raise NimbusError(f"{len(bad)} image(s) do not match their camera size: {'; '.join(bad[:3])}; {hint}")


def scaled_to_image(view: View, downscale: int) -> View:
    """The view with its camera scaled to its ``images_<d>`` file's true size (Mip-NeRF360 layout).

    The file must be within one pixel of ``camera size / downscale`` in each
    direction (downscalers round differently); otherwise NimbusError names it.
    """
    cam = view.camera
    w, h = image_size(view.image_path)
    ew, eh = cam.width / downscale, cam.height / downscale
    if abs(w - ew) > 1 or abs(h - eh) > 1:
        raise NimbusError(
            f"image {view.image_path} is {w}x{h} but a {downscale}x downscale of its "
            f"{cam.width}x{cam.height} camera should be about {ew:g}x{eh:g}; "
            f"regenerate {view.image_path.parent.name}/ from the full-size images or use another downscale"
        )
    return replace(view, camera=cam.scaled(1.0 / downscale, width=w, height=h))


def output_image_name(view: View) -> str:
    """Name a view's image gets in a written scene.

    Files are copied under their own name; an in-memory image is encoded as PNG,
    so a name with another extension gets ``.png`` (read_image checks file
    endings by suffix, so PNG bytes must not hide behind ``.jpg``), and so does a
    PNG file under such a name (a JPEG photo undistorted into the cache).
    """
    if view.image is None and view.image_path is not None:
        if Path(view.image_path).suffix.lower() == ".png" and Path(view.name).suffix.lower() != ".png":
            return aux_name(view.name, ".png")
        return view.name
    return view.name if Path(view.name).suffix == ".png" else aux_name(view.name, ".png")


def write_view_files(scene: Scene, directory: Path, image_dir: str = "images") -> dict[str, str]:
    """Write every view's image, depth and mask, and the split lists, into ``directory``.

    Image files are copied byte for byte (no re-encoding); in-memory images are
    written as 8-bit PNG.  Depths go to ``depths/<stem>.npy`` and masks to
    ``masks/<stem>.png`` for the views that have them.

    Returns
    -------
    dict
        View name -> the image name used in the written scene (see :func:`output_image_name`).
    """
    directory = Path(directory)
    names = {v.name: output_image_name(v) for v in scene.views}
    unsafe = [n for n in names.values() if Path(n).is_absolute() or ".." in Path(n).parts]
    if unsafe:
        raise NimbusError(f"view names must be relative paths inside the image folder: {format_names(unsafe)}")
    if len(set(names.values())) != len(names):
        raise NimbusError("views would share an image file name once written as PNG; rename them")
    for v in scene.views:
        name = names[v.name]
        # The image's name was chosen to fit its file (output_image_name): any ending is copied.
        _copy_or_write(v.image, v.image_path, directory / image_dir / name, None, "image", v.load_image, write_image)
        for array, path, folder, ending, what, load, write in (
                (v.depth, v.depth_path, DEPTH_DIR, ".npy", "depth map", v.load_depth, write_depth),
                (v.mask, v.mask_path, MASK_DIR, ".png", "mask", v.load_mask, write_mask),
                (v.sky, v.sky_path, SKY_DIR, ".png", "sky mask", v.load_sky, write_mask)):
            if array is not None or path is not None:
                _copy_or_write(array, path, directory / folder / aux_name(name, ending), ending, what, load, write)
    written = Scene(views=tuple(View(names[v.name], v.camera) for v in scene.views),
                    test_names=frozenset(names[n] for n in scene.test_names))
    write_split_lists(written, directory)
    return names


def _copy_or_write(array, path, dst: Path, ending: str | None, what: str, load, write) -> None:
    """Copy ``path`` byte for byte when the view holds no ``array`` and the file is already in the
    written format (its suffix is ``ending``; None: any), else write ``load()`` with ``write``."""
    if array is None and path is not None and (ending is None or Path(path).suffix == ending):
        _copy(path, dst, what)
    else:
        write(dst, load())


def _copy(src: Path, dst: Path, what: str) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    try:
        shutil.copyfile(src, dst)
    except OSError as e:
        raise NimbusError(f"cannot copy {what} {src}: {e.strerror}; check the scene's files") from None
