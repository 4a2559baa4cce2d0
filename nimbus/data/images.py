"""Image and depth-map IO.

Images cross module boundaries as float32 arrays of shape (H, W, 3), RGB, values
in [0, 1] (display / sRGB-encoded values, as stored in the files).  8-bit and
16-bit PNG and JPEG are read (TIFF and BMP too); images are written as 8-bit PNG with
deterministic bytes.  Depth maps are float32 (H, W) z-depths in scene units,
stored as ``.npy``; 16-bit PNG depth (millimetres by default) is also read.

Every image file is sized from its header before it is decoded (:func:`image_size`) and refused
above :func:`max_image_pixels` (:data:`MAX_IMAGE_PIXELS`, or the environment variable
:data:`MAX_IMAGE_PIXELS_ENV`): a few hundred kilobytes of PNG can declare 30000 x 30000 pixels,
which decode to gigabytes.  A file whose decoder fails, warns of corrupt or missing data (libjpeg
only warns, and fills the rest grey), ends early, or decodes to another size than its header
declares is refused too, naming the file.
"""

from __future__ import annotations

import contextlib
import logging
import os
import struct
import sys
import tempfile
import threading
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from nimbus.errors import NimbusError
from nimbus.utils.fs import atomic_write_bytes

log = logging.getLogger(__name__)

# Largest share of pixels a depth map may mark as "no depth" (NaN or 0) before it is refused.
MAX_NO_DEPTH_FRACTION = 0.5
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".JPG", ".JPEG", ".PNG", ".tif", ".tiff", ".bmp")
#: Largest image (width x height) that is decoded: 100 megapixels, 1.2 GB as float32 RGB, several times a
#: 24-megapixel photo.  :data:`MAX_IMAGE_PIXELS_ENV` replaces it.
MAX_IMAGE_PIXELS = 100_000_000
#: Environment variable holding another pixel limit (a whole number), for a machine with the memory.
MAX_IMAGE_PIXELS_ENV = "NIMBUS_MAX_IMAGE_PIXELS"
#: How libjpeg's warnings of damaged data begin (its JWRN_* messages); it decodes on and fills the rest grey.
CORRUPT_JPEG_WARNINGS = ("Corrupt JPEG data", "Premature end of JPEG file", "Invalid SOS parameters",
                         "Inconsistent progression sequence")


def max_image_pixels() -> int:
    """The pixel limit in force: :data:`MAX_IMAGE_PIXELS_ENV` if set, else :data:`MAX_IMAGE_PIXELS`."""
    raw = os.environ.get(MAX_IMAGE_PIXELS_ENV, "").strip()
    if not raw:
        return MAX_IMAGE_PIXELS
    try:
        value = int(raw.replace("_", ""))
    except ValueError:
        value = 0
    if value < 1:
        raise NimbusError(f"{MAX_IMAGE_PIXELS_ENV}={raw!r} must be a whole number of pixels >= 1 (default "
                          f"{MAX_IMAGE_PIXELS}); fix or unset it")
    return value


def image_size(path: str | os.PathLike) -> tuple[int, int]:
    """``(width, height)`` of an image file from its PNG, JPEG, TIFF or BMP header (nothing is decoded).

    Raises :class:`NimbusError` naming the file when it is missing, is none of those formats, has a
    header without a size, or is larger than :func:`max_image_pixels`.
    """
    path = Path(path)
    try:
        with open(path, "rb") as f:
            head = f.read(1 << 16)
            size = _png_size(head) or _jpeg_size(f, head) or _tiff_size(f, head) or _bmp_size(head)
    except FileNotFoundError:
        raise NimbusError(f"image {path} does not exist; check the scene folder or the image list") from None
    except (OSError, struct.error) as e:
        raise NimbusError(f"image {path} is unreadable ({e}); replace or remove it") from None
    if size is None or min(size) < 1:
        raise NimbusError(f"image {path} is not a PNG, JPEG, TIFF or BMP file with a readable size in its header; "
                          "convert it to PNG, or replace it")
    check_pixel_limit(path, *size)
    return size


def check_pixel_limit(path: str | os.PathLike, width: int, height: int) -> None:
    """Refuse an image of more pixels than :func:`max_image_pixels`, naming the file, its size and the limit."""
    limit = max_image_pixels()
    if width * height > limit:
        raise NimbusError(f"image {path} is {width}x{height} ({width * height / 1e6:.0f} megapixels), more than the "
                          f"limit of {limit / 1e6:g} megapixels; shrink it, or if it is genuine and the machine has "
                          f"the memory, raise the limit with {MAX_IMAGE_PIXELS_ENV}={width * height}")


def _png_size(head: bytes) -> tuple[int, int] | None:
    if head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR" and len(head) >= 24:
        return struct.unpack(">II", head[16:24])
    return None


def _jpeg_size(f, head: bytes) -> tuple[int, int] | None:
    """Walk the JPEG markers to the first start-of-frame segment."""
    if head[:2] != b"\xff\xd8":
        return None
    f.seek(2)
    while True:
        marker = f.read(2)
        if len(marker) < 2 or marker[0] != 0xFF:
            return None
        kind = marker[1]
        if kind == 0xFF:  # fill byte
            f.seek(-1, 1)
            continue
        if kind in (0xD8, 0x01) or 0xD0 <= kind <= 0xD7:  # markers without a length field
            continue
        seg = f.read(2)
        if len(seg) < 2:
            return None
        length = struct.unpack(">H", seg)[0]
        if 0xC0 <= kind <= 0xCF and kind not in (0xC4, 0xC8, 0xCC):
            data = f.read(5)
            if len(data) < 5:
                return None
            h, w = struct.unpack(">HH", data[1:5])
            return w, h
        f.seek(length - 2, 1)


def _tiff_size(f, head: bytes) -> tuple[int, int] | None:
    """ImageWidth (256) and ImageLength (257) of the first image file directory (classic TIFF)."""
    if head[:4] not in (b"II*\x00", b"MM\x00*"):
        return None
    order = "<" if head[:2] == b"II" else ">"
    f.seek(struct.unpack(order + "I", head[4:8])[0])
    count = f.read(2)
    if len(count) < 2:
        return None
    entries = f.read(12 * struct.unpack(order + "H", count)[0])
    found = {}
    for i in range(len(entries) // 12):
        tag, kind = struct.unpack(order + "HH", entries[12 * i:12 * i + 4])
        value = entries[12 * i + 8:12 * i + 12]
        if tag in (256, 257) and kind in (3, 4):  # SHORT or LONG
            found[tag] = struct.unpack(order + "H", value[:2])[0] if kind == 3 else struct.unpack(order + "I", value)[0]
    return (found[256], found[257]) if len(found) == 2 else None


def _bmp_size(head: bytes) -> tuple[int, int] | None:
    if head[:2] != b"BM" or len(head) < 26:
        return None
    if struct.unpack("<I", head[14:18])[0] == 12:  # OS/2 BITMAPCOREHEADER: 16-bit sizes
        return struct.unpack("<HH", head[18:22])
    w, h = struct.unpack("<ii", head[18:26])
    return w, abs(h)  # a negative height is a top-down bitmap


_STDERR_LOCK = threading.Lock()


@contextlib.contextmanager
def _decoder_messages() -> Iterator[list[str]]:
    """The lines written to file descriptor 2 inside the block, where libjpeg prints its warnings (OpenCV
    passes them on to nobody).  One block at a time; lines that are not libjpeg's damage warnings (another
    thread's output) are written back to descriptor 2 afterwards."""
    lines: list[str] = []
    with _STDERR_LOCK, tempfile.TemporaryFile() as capture:
        sys.stderr.flush()
        saved = os.dup(2)
        os.dup2(capture.fileno(), 2)
        try:
            yield lines
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            capture.seek(0)
            lines += capture.read().decode("utf-8", "replace").splitlines(keepends=True)
            other = "".join(line for line in lines if not line.startswith(CORRUPT_JPEG_WARNINGS))
            if other:
                os.write(2, other.encode())


def decode_image_file(path: str | os.PathLike, flags: int = cv2.IMREAD_UNCHANGED, what: str = "image") -> np.ndarray:
    """The pixels of an image file as OpenCV decodes them (``flags``), after :func:`image_size`'s checks.

    Refused with :class:`NimbusError` naming the file (``what`` says what it is): larger than the pixel
    limit, truncated, undecodable, damaged (a libjpeg warning), or decoded to another size than its header's.
    """
    path = Path(path)
    if not path.is_file():
        raise NimbusError(f"{what} {path} does not exist; check the scene folder or the image list")
    width, height = image_size(path)
    data = np.fromfile(path, dtype=np.uint8)
    if _looks_truncated(path, data):
        raise NimbusError(f"{what} {path} is truncated (incomplete file); re-copy or re-export it")
    jpeg = data[:2].tobytes() == b"\xff\xd8"
    try:
        with _decoder_messages() if jpeg else contextlib.nullcontext([]) as messages:
            img = cv2.imdecode(data, flags)
    except cv2.error as e:
        reason = str(e).strip().splitlines()[-1] if str(e).strip() else "OpenCV error"
        raise NimbusError(f"{what} {path} cannot be decoded ({reason}); replace or remove it") from None
    damage = [m.strip() for m in messages if m.startswith(CORRUPT_JPEG_WARNINGS)]
    if damage:
        raise NimbusError(f"{what} {path} is corrupt (the JPEG decoder says: {damage[0]}); re-copy or re-export it")
    if img is None or img.size == 0:
        raise NimbusError(f"{what} {path} is unreadable or corrupt; replace or remove it")
    if img.shape[:2] not in ((height, width), (width, height)):  # turned: OpenCV applies an EXIF orientation
        raise NimbusError(f"{what} {path} decodes to {img.shape[1]}x{img.shape[0]} but its header says "
                          f"{width}x{height}; it is corrupt: re-copy or re-export it")
    return img


def read_image(path: str | os.PathLike) -> np.ndarray:
    """Read an image file as float32 RGB (H, W, 3) in [0, 1].

    Grey images are repeated to three channels and an alpha channel is dropped.  A missing, unreadable,
    truncated, damaged or oversized file raises :class:`NimbusError` naming it (:func:`decode_image_file`).
    """
    path = Path(path)
    img = decode_image_file(path)
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


def refuse_nonfinite(values: np.ndarray, what: str, allow_inf: bool = False) -> None:
    """NimbusError before ``what`` is written when ``values`` hold NaN (or +-inf, unless ``allow_inf``: a depth
    map's ``+inf`` is sky).  :func:`to_uint8` would turn NaN into black and inf into white without a word."""
    values = np.asarray(values)
    if not np.issubdtype(values.dtype, np.floating):
        return
    bad = np.isnan(values) | (np.isneginf(values) if allow_inf else np.isinf(values))
    if bad.any():
        first = tuple(int(i) for i in np.argwhere(bad)[0])
        kinds = "NaN" + ("" if allow_inf else " or inf") + (" or -inf" if allow_inf else "")
        raise NimbusError(f"refusing to write {what}: {int(bad.sum())} of {values.size} values are {kinds} "
                          f"(the first at index {first}); the model or input that made it is broken. "
                          "Nothing was written")


def write_image(path: str | os.PathLike, img: np.ndarray) -> Path:
    """Write a float RGB image in [0, 1] (or uint8) as an 8-bit PNG, atomically; NaN or inf is refused."""
    refuse_nonfinite(img, f"image {path}")
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
        raw = decode_image_file(path, what="depth map")
        if raw.dtype != np.uint16 or raw.ndim != 2:
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
    """Write a float32 z-depth map as ``.npy``, atomically (``+inf`` is sky; NaN and ``-inf`` are refused)."""
    import io

    refuse_nonfinite(depth, f"depth map {path}", allow_inf=True)

    buf = io.BytesIO()
    np.save(buf, np.asarray(depth, dtype=np.float32), allow_pickle=False)
    return atomic_write_bytes(path, buf.getvalue())


def read_mask(path: str | os.PathLike) -> np.ndarray:
    """Read a single-channel mask PNG as bool (H, W) (non-zero = True).

    Any non-zero value counts, as in nerfstudio: masks are stored as 0/255 or as 0/1.
    """
    path = Path(path)
    if not path.is_file():
        raise NimbusError(f"mask {path} is missing or unreadable")
    return decode_image_file(path, cv2.IMREAD_GRAYSCALE, what="mask") > 0


def write_mask(path: str | os.PathLike, mask: np.ndarray) -> Path:
    return atomic_write_bytes(path, encode_png(np.where(np.asarray(mask, bool), 255, 0).astype(np.uint8)))
