"""Deterministic files of a degraded dataset: per-view layer archives.

Layer archives are ``.npz`` files (``np.load`` reads them) written by our own
zip writer: every entry has a fixed timestamp (1980-01-01), fixed permissions,
a fixed order and compression level, so the same arrays always give the same
bytes.  (numpy's ``savez_compressed`` happens to be deterministic with the
current numpy and CPython, through ``zipfile``'s defaults, but does not promise it.)
"""

from __future__ import annotations

import io
import os
import zipfile
from pathlib import Path
from typing import Mapping

import numpy as np

from nimbus.errors import NimbusError
from nimbus.utils.fs import atomic_write_bytes

_EPOCH = (1980, 1, 1, 0, 0, 0)


def encode_layers(arrays: Mapping[str, np.ndarray], level: int = 6) -> bytes:
    """The bytes of an ``.npz`` archive of ``arrays`` (names sorted), deterministic."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=level) as zf:
        for name in sorted(arrays):
            arr = np.ascontiguousarray(arrays[name])
            payload = io.BytesIO()
            np.lib.format.write_array(payload, arr, allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=_EPOCH)
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            info.create_system = 3  # Unix, whatever system writes it
            zf.writestr(info, payload.getvalue(), compress_type=zipfile.ZIP_DEFLATED, compresslevel=level)
    return buf.getvalue()


def write_layers(path: str | os.PathLike, arrays: Mapping[str, np.ndarray], level: int = 6) -> bytes:
    """Write :func:`encode_layers` atomically to ``path``; returns the bytes written."""
    data = encode_layers(arrays, level)
    atomic_write_bytes(path, data)
    return data


def read_layers(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """All arrays of a layer archive."""
    path = Path(path)
    if not path.is_file():
        raise NimbusError(f"layer archive {path} does not exist")
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}
