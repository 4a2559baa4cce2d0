"""Image and depth-map IO.

Images cross module boundaries as float32 arrays of shape (H, W, 3), RGB, values
in [0, 1] (display / sRGB-encoded values, as stored in the files).  8-bit and
16-bit PNG and JPEG are read; images are written as 8-bit PNG with
deterministic bytes.  Depth maps are float32 (H, W) z-depths in scene units,
stored as ``.npy``; 16-bit PNG depth (millimetres by default) is also read.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import cv2
import numpy as np

from nimbus.errors import NimbusError
from nimbus.utils.fs import atomic_write_bytes

log = logging.getLogger(__name__)

# Largest share of pixels a depth map may mark as "no depth" (NaN or 0) before it is refused.
MAX_NO_DEPTH_FRACTION = 0.5
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".JPG", ".JPEG", ".PNG", ".tif", ".tiff", ".bmp")


def read_image(path: str | os.PathLike) -> np.ndarray:
    """Read an image file as float32 RGB (H, W, 3) in [0, 1].

    Grey images are repeated to three channels and an alpha channel is dropped.
    A missing, unreadable or truncated file raises :class:`NimbusError` naming it.
    """
    path = Path(path)
    if not path.is_file():
        raise NimbusError(f"image {path} does not exist; check the scene folder or the image list")
    data = np.fromfile(path, dtype=np.uint8)
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if img is None or img.size == 0:
        raise NimbusError(f"image {path} is unreadable or corrupt; replace or remove it")
    if _looks_truncated(path, data):
        raise NimbusError(f"image {path} is truncated (incomplete file); re-copy or re-export it")
    if img.dtype == np.uint8:
        scale = 255.0
    elif img.dtype == np.uint16:
        scale = 65535.0
    elif img.dtype in (np.float32, np.float64):
        scale = 1.0
    else:
        raise NimbusError(f"image {path} has unsupported pixel type {img.dtype}; use 8- or 16-bit PNG/JPEG")
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    elif img.shape[2] == 4:
        img = img[:, :, :3]
    elif img.shape[2] == 1:
        img = np.repeat(img, 3, axis=2)
    rgb = img[:, :, ::-1].astype(np.float32) / np.float32(scale)
    return np.ascontiguousarray(rgb)


def _looks_truncated(path: Path, data: np.ndarray) -> bool:
    """OpenCV decodes some truncated files partially (grey fill); catch the common cases by their end markers."""
    suffix = path.suffix.lower()
    tail = data[-16:].tobytes()
    if suffix == ".png":
        return b"IEND" not in tail
    if suffix in (".jpg", ".jpeg"):
        return not tail.rstrip(b"\x00").endswith(b"\xff\xd9")
    return False


def to_uint8(img: np.ndarray) -> np.ndarray:
    """Quantise a float image in [0, 1] to uint8 with rounding (values outside are clipped)."""
    img = np.nan_to_num(np.asarray(img, dtype=np.float32), nan=0.0, posinf=1.0, neginf=0.0)
    return (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def encode_png(img: np.ndarray) -> bytes:
    """Encode a float RGB image in [0, 1] (or uint8 RGB / grey) as 8-bit PNG bytes (deterministic)."""
    arr = img if img.dtype == np.uint8 else to_uint8(img)
    if arr.ndim == 3:
        arr = np.ascontiguousarray(arr[:, :, ::-1])
    ok, buf = cv2.imencode(".png", arr, [cv2.IMWRITE_PNG_COMPRESSION, 6])
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return buf.tobytes()


def write_image(path: str | os.PathLike, img: np.ndarray) -> Path:
    """Write a float RGB image in [0, 1] (or uint8) as an 8-bit PNG, atomically."""
    return atomic_write_bytes(path, encode_png(img))


def read_depth(path: str | os.PathLike, png_scale: float = 1000.0) -> np.ndarray:
    """Read a z-depth map as float32 (H, W), ``inf`` where there is no surface.

    ``.npy`` holds depth in scene units (loaded with ``allow_pickle=False``: a depth file never
    runs code); a 16-bit PNG holds ``depth * png_scale`` (millimetres for metric scenes).

    What counts as a depth, decided here for every depth file Nimbus reads:

    * ``inf`` is the one "no surface" value (sky, backdrop) and is kept.
    * NaN and 0 mean "no depth here" (a sensor hole; 0 is also the PNG convention): a z-depth
      of 0 cannot be a visible surface.  They are read as ``inf`` when they are a minority of
      the pixels (at most :data:`MAX_NO_DEPTH_FRACTION`).  A map that is mostly NaN / 0 is
      refused: reading it as mostly sky would silently give wrong haze (it is a sparse or
      broken map; densify it, or remove it and use ``--depth sparse``).
    * A negative value (or ``-inf``) is refused: it means a flipped sign convention or a
      disparity / inverse-depth map, not a z-depth.
    * A map with no finite depth at all (every pixel ``inf``) is accepted as all sky, with a
      one-line warning on stderr (logging) naming the file.
    """
    path = Path(path)
    if not path.is_file():
        raise NimbusError(f"depth map {path} does not exist")
    if path.suffix.lower() == ".npy":
        try:
            # Memory-mapped so that a header declaring a huge shape fails on the file size, not on allocation.
            raw = np.load(path, allow_pickle=False, mmap_mode="r")
            if not isinstance(raw, np.ndarray):  # an .npz archive under an .npy name
                raw.close()
                raise ValueError("it is an .npz archive, not one array")
            if raw.dtype.kind not in "biuf":
                raise ValueError(f"it holds {raw.dtype} values, not real numbers")
            d = np.array(np.squeeze(raw), dtype=np.float32)
            del raw
        except (ValueError, OSError, EOFError) as e:
            raise NimbusError(f"depth map {path} is unreadable ({e}); save it with numpy.save as a float "
                              "array") from None
    elif path.suffix.lower() == ".png":
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if raw is None or raw.dtype != np.uint16 or raw.ndim != 2:
            raise NimbusError(f"depth map {path} must be a single-channel 16-bit PNG")
        d = raw.astype(np.float32) / np.float32(png_scale)
    else:
        raise NimbusError(f"depth map {path}: unsupported format; use .npy (float) or 16-bit .png")
    if d.ndim != 2 or d.size == 0:
        raise NimbusError(f"depth map {path} has shape {d.shape}; expected (H, W)")
    return _no_depth_as_inf(d, path)


def _no_depth_as_inf(d: np.ndarray, path: Path) -> np.ndarray:
    """Apply :func:`read_depth`'s rules: refuse negative and mostly-missing maps, NaN / 0 -> inf."""
    negative = d < 0
    if negative.any():
        raise NimbusError(f"depth map {path} has {int(negative.sum())} negative value(s) (min {float(d.min()):g}); "
                          "depths must be z-depths >= 0 in scene units (a negative map is usually a flipped sign "
                          "or a disparity map): fix the file, or remove it and use --depth sparse")
    missing = np.isnan(d) | (d == 0)
    fraction = float(missing.mean())
    if fraction > MAX_NO_DEPTH_FRACTION:
        raise NimbusError(f"depth map {path} has no depth (NaN or 0) at {fraction:.0%} of its pixels; Nimbus needs a "
                          "dense z-depth map (inf = sky): densify it, or remove it and use --depth sparse")
    if missing.any():
        d = np.where(missing, np.float32(np.inf), d)
    if not np.isfinite(d).any():
        log.warning("depth map %s has no finite depth: the whole view is read as sky (no surface)", path)
    return d


def write_depth(path: str | os.PathLike, depth: np.ndarray) -> Path:
    """Write a float32 z-depth map as ``.npy``, atomically."""
    import io

    buf = io.BytesIO()
    np.save(buf, np.asarray(depth, dtype=np.float32), allow_pickle=False)
    return atomic_write_bytes(path, buf.getvalue())


def read_mask(path: str | os.PathLike) -> np.ndarray:
    """Read a single-channel mask PNG as bool (H, W) (non-zero = True).

    Any non-zero value counts, as in nerfstudio: masks are stored as 0/255 or as 0/1.
    """
    path = Path(path)
    raw = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) if path.is_file() else None
    if raw is None:
        raise NimbusError(f"mask {path} is missing or unreadable")
    return raw > 0


def write_mask(path: str | os.PathLike, mask: np.ndarray) -> Path:
    return atomic_write_bytes(path, encode_png(np.where(np.asarray(mask, bool), 255, 0).astype(np.uint8)))
