"""The standard 3DGS ``point_cloud.ply`` (as written by the Inria code and read by splat viewers).

Binary little-endian vertices with float32 properties, in this order:
``x y z nx ny nz f_dc_0..2 f_rest_0..(3*(K-1)-1) opacity scale_0..2 rot_0..3``.
``f_rest`` is stored channel-major (all coefficients of R, then G, then B), opacity
as a logit, scales as logs, rotations as (w, x, y, z) quaternions.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from nimbus.errors import NimbusError
from nimbus.utils.fs import atomic_write_bytes


def ply_property_names(num_sh_coeffs: int) -> list[str]:
    rest = 3 * (num_sh_coeffs - 1)
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
            + [f"f_rest_{i}" for i in range(rest)]
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


def write_gaussian_ply(path: str | os.PathLike, means: np.ndarray, sh: np.ndarray, opacity_logits: np.ndarray,
                       log_scales: np.ndarray, quats_wxyz: np.ndarray) -> Path:
    """Write Gaussians as a 3DGS PLY.

    Parameters
    ----------
    means : (N, 3)  world positions.
    sh : (N, K, 3)  SH coefficients (K = 1, 4, 9 or 16), coefficient 0 is DC.
    opacity_logits : (N,)
    log_scales : (N, 3)
    quats_wxyz : (N, 4)
    """
    n, k = sh.shape[0], sh.shape[1]
    rest = np.transpose(sh[:, 1:, :], (0, 2, 1)).reshape(n, -1)  # channel-major, as Inria's f_rest
    cols = [means, np.zeros((n, 3)), sh[:, 0, :], rest, opacity_logits.reshape(n, 1), log_scales, quats_wxyz]
    data = np.concatenate([np.asarray(c, dtype=np.float32).reshape(n, -1) for c in cols], axis=1)
    names = ply_property_names(k)
    assert data.shape[1] == len(names)
    bad = ~np.isfinite(data)
    if bad.any():
        cols = sorted({names[j] for j in np.nonzero(bad.any(axis=0))[0]}, key=names.index)
        raise NimbusError(f"refusing to write {path}: {int(bad.any(axis=1).sum())} of {n} Gaussians have NaN or "
                          f"infinite values (in {', '.join(cols[:6])}{', ...' if len(cols) > 6 else ''}), which "
                          "splat viewers render as garbage or crash on. Nothing was written")
    header = "ply\nformat binary_little_endian 1.0\n" + f"element vertex {n}\n"
    header += "".join(f"property float {name}\n" for name in names) + "end_header\n"
    return atomic_write_bytes(path, header.encode("ascii") + data.astype("<f4").tobytes())


#: Properties :func:`read_gaussian_ply` needs (``f_rest_*`` are optional: SH degree 0).
REQUIRED_PROPERTIES = ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
                       "rot_0", "rot_1", "rot_2", "rot_3")


def _parse_header(path, raw: bytes) -> tuple[int, list[str], int]:
    """``(vertex count, float property names, offset of the data)`` of a binary little-endian 3DGS PLY.

    Every way the header can be wrong (not a PLY, not ASCII, no / negative / non-integer vertex
    count, properties that are not float32, missing ones) raises :class:`NimbusError`.
    """
    end = raw.find(b"end_header\n")
    if not raw.startswith(b"ply\n") or end < 0:
        raise NimbusError(f"{path} is not a PLY file (no 'ply' / 'end_header' lines); give a point_cloud.ply "
                          "written by nimbus-train or the 3DGS reference code")
    try:
        header = raw[:end].decode("ascii").splitlines()
    except UnicodeDecodeError:
        raise NimbusError(f"{path}: the PLY header is not ASCII text; the file is corrupt") from None
    if "format binary_little_endian 1.0" not in header:
        raise NimbusError(f"{path}: only binary little-endian PLY is supported")
    counts = [line.split() for line in header if line.startswith("element ")]
    if not counts or counts[0][:2] != ["element", "vertex"] or len(counts) > 1:
        raise NimbusError(f"{path}: expected one 'element vertex N' line and no other elements; the file is not "
                          "a 3DGS point cloud")
    try:
        n = int(counts[0][2])
    except (IndexError, ValueError):
        raise NimbusError(f"{path}: 'element vertex' has no integer count; the file is corrupt") from None
    if n < 0:
        raise NimbusError(f"{path}: negative vertex count {n}; the file is corrupt")
    props = [line.split() for line in header if line.startswith("property")]
    if any(len(p) != 3 or p[1] != "float" for p in props):
        raise NimbusError(f"{path}: every property must be 'property float NAME' (3DGS layout); the file is not "
                          "a 3DGS point cloud")
    names = [p[2] for p in props]
    missing = [name for name in REQUIRED_PROPERTIES if name not in names]
    n_rest = sum(1 for name in names if name.startswith("f_rest_"))
    missing += [f"f_rest_{i}" for i in range(n_rest) if f"f_rest_{i}" not in names]
    if missing or n_rest % 3 or len(set(names)) != len(names):
        raise NimbusError(f"{path}: properties {', '.join(missing) or '(duplicated or f_rest not a multiple of 3)'} "
                          "are missing or malformed; the file is not a 3DGS point cloud")
    offset = end + len(b"end_header\n")
    if len(raw) - offset < n * len(names) * 4:
        raise NimbusError(f"{path}: the header declares {n} vertices of {len(names)} floats "
                          f"({n * len(names) * 4} bytes) but the file holds {len(raw) - offset}; it is truncated")
    return n, names, offset


def read_gaussian_ply(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Read a 3DGS PLY written by :func:`write_gaussian_ply` (or the Inria code) into arrays.

    Raises NimbusError for a file that is not one (see :func:`_parse_header`).
    """
    try:
        raw = Path(path).read_bytes()
    except OSError as e:
        raise NimbusError(f"cannot read {path} ({e.strerror or e.__class__.__name__}); check the path") from None
    n, names, offset = _parse_header(path, raw)
    data = np.frombuffer(raw, dtype="<f4", count=n * len(names), offset=offset).reshape(n, len(names))
    col = {name: data[:, i] for i, name in enumerate(names)}
    n_rest = sum(1 for name in names if name.startswith("f_rest_"))
    k = 1 + n_rest // 3
    rest = np.stack([col[f"f_rest_{i}"] for i in range(n_rest)], axis=1).reshape(n, 3, k - 1) if n_rest else \
        np.zeros((n, 3, 0), np.float32)
    sh = np.concatenate([np.stack([col[f"f_dc_{i}"] for i in range(3)], axis=1)[:, None, :],
                         np.transpose(rest, (0, 2, 1))], axis=1)
    return {
        "means": np.stack([col["x"], col["y"], col["z"]], axis=1),
        "sh": sh,
        "opacity_logits": col["opacity"].copy(),
        "log_scales": np.stack([col[f"scale_{i}"] for i in range(3)], axis=1),
        "quats_wxyz": np.stack([col[f"rot_{i}"] for i in range(4)], axis=1),
    }
