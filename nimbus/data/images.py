"""Image and depth-map IO.

Images cross module boundaries as float32 arrays of shape (H, W, 3), RGB, values
in [0, 1] (display / sRGB-encoded values, as stored in the files).  8-bit and
16-bit PNG and JPEG are read; images are written as 8-bit PNG with
deterministic bytes.  Depth maps are float32 (H, W) z-depths in scene units,
stored as ``.npy``; 16-bit PNG depth (millimetres by default) is also read.
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from nimbus.errors import NimbusError
from nimbus.utils.fs import atomic_write_bytes

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
    """Read a z-depth map as float32 (H, W).

    ``.npy`` holds depth in scene units; a 16-bit PNG holds ``depth * png_scale``
    (millimetres for metric scenes).  Zero in a PNG means "no depth" and becomes inf.
    """
    path = Path(path)
    if not path.is_file():
        raise NimbusError(f"depth map {path} does not exist")
    if path.suffix.lower() == ".npy":
        try:
            d = np.load(path, allow_pickle=False)
        except (ValueError, OSError) as e:
            raise NimbusError(f"depth map {path} is unreadable ({e}); save it with numpy.save") from None
        d = np.squeeze(d).astype(np.float32)
    elif path.suffix.lower() == ".png":
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if raw is None or raw.dtype != np.uint16 or raw.ndim != 2:
            raise NimbusError(f"depth map {path} must be a single-channel 16-bit PNG")
        d = raw.astype(np.float32) / np.float32(png_scale)
        d[raw == 0] = np.inf
    else:
        raise NimbusError(f"depth map {path}: unsupported format; use .npy (float) or 16-bit .png")
    if d.ndim != 2:
        raise NimbusError(f"depth map {path} has shape {d.shape}; expected (H, W)")
    return d


def write_depth(path: str | os.PathLike, depth: np.ndarray) -> Path:
    """Write a float32 z-depth map as ``.npy``, atomically."""
    import io

    buf = io.BytesIO()
    np.save(buf, np.asarray(depth, dtype=np.float32), allow_pickle=False)
    return atomic_write_bytes(path, buf.getvalue())


def read_mask(path: str | os.PathLike) -> np.ndarray:
    """Read a single-channel mask PNG as bool (H, W) (non-zero = True)."""
    path = Path(path)
    raw = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) if path.is_file() else None
    if raw is None:
        raise NimbusError(f"mask {path} is missing or unreadable")
    return raw > 127


def write_mask(path: str | os.PathLike, mask: np.ndarray) -> Path:
    return atomic_write_bytes(path, encode_png(np.where(np.asarray(mask, bool), 255, 0).astype(np.uint8)))
