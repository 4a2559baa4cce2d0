"""The ``.splat`` file of web Gaussian-splat viewers (antimatter15/splat and the viewers that read it).

No header; 32 bytes per splat, little-endian, in this order::

    position   3 x float32   world x, y, z
    scale      3 x float32   linear standard deviations (exp of the PLY's log scales)
    colour     4 x uint8     R, G, B = (0.5 + SH_C0 * f_dc) * 255, A = sigmoid(opacity) * 255
    rotation   4 x uint8     the unit quaternion (w, x, y, z as in the PLY) as q * 128 + 128

Bytes are rounded to nearest (ties to even) and clipped to [0, 255], as the viewer's
``Uint8ClampedArray`` does when it converts a PLY itself.  Splats are stored by descending
``scale_x * scale_y * scale_z * opacity`` (the viewer's order: the big, opaque ones load first).

What the format drops: the higher SH bands (view-dependent colour), colours outside [0, 1],
and precision (8 bits for colour, opacity and rotation).  :func:`read_splat` therefore returns
the Gaussians at that precision, in the arrays :func:`nimbus.train.ply.read_gaussian_ply` returns.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from nimbus.errors import NimbusError
from nimbus.utils.fs import atomic_write_bytes

#: The DC band's constant: colour = 0.5 + SH_C0 * f_dc (the 3DGS convention).
SH_C0 = 0.28209479177387814
SPLAT_DTYPE = np.dtype([("position", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rotation", "u1", 4)])
assert SPLAT_DTYPE.itemsize == 32


def _to_byte(x: np.ndarray) -> np.ndarray:
    """Float values on the 0..255 scale as uint8: rounded to nearest (ties to even), clipped."""
    return np.clip(np.rint(x), 0, 255).astype(np.uint8)


def encode_splat(means: np.ndarray, sh: np.ndarray, opacity_logits: np.ndarray, log_scales: np.ndarray,
                 quats_wxyz: np.ndarray) -> bytes:
    """Gaussians as ``.splat`` bytes (arguments as :func:`nimbus.train.ply.write_gaussian_ply` takes them).

    Parameters
    ----------
    means : (N, 3)  world positions.
    sh : (N, K, 3)  SH coefficients; only the DC band (``sh[:, 0]``) is kept.
    opacity_logits : (N,)
    log_scales : (N, 3)
    quats_wxyz : (N, 4)  rotations, any norm (normalised here; a zero quaternion becomes the identity).
    """
    means = np.asarray(means, np.float64).reshape(-1, 3)
    n = len(means)
    sh = np.asarray(sh, np.float64).reshape(n, -1, 3)
    opacity = 1.0 / (1.0 + np.exp(-np.asarray(opacity_logits, np.float64).reshape(n)))
    scales = np.exp(np.asarray(log_scales, np.float64).reshape(n, 3))
    q = np.asarray(quats_wxyz, np.float64).reshape(n, 4)
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    q = np.where(norm > 0, q / np.where(norm > 0, norm, 1.0), [1.0, 0.0, 0.0, 0.0])
    # A stable sort keeps equal splats in their PLY order, so one model always gives the same file.
    order = np.argsort(-(scales.prod(axis=1) * opacity), kind="stable")
    out = np.empty(n, SPLAT_DTYPE)
    out["position"] = means[order]
    out["scale"] = scales[order]
    out["rgba"][:, :3] = _to_byte((0.5 + SH_C0 * sh[order, 0, :]) * 255.0)
    out["rgba"][:, 3] = _to_byte(opacity[order] * 255.0)
    out["rotation"] = _to_byte(q[order] * 128.0 + 128.0)
    return out.tobytes()


def write_splat(path: str | os.PathLike, means: np.ndarray, sh: np.ndarray, opacity_logits: np.ndarray,
                log_scales: np.ndarray, quats_wxyz: np.ndarray) -> Path:
    """Write Gaussians as a ``.splat`` file, atomically (see :func:`encode_splat`)."""
    return atomic_write_bytes(path, encode_splat(means, sh, opacity_logits, log_scales, quats_wxyz))


def read_splat(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Read a ``.splat`` file into the arrays :func:`~nimbus.train.ply.read_gaussian_ply` returns.

    Returns
    -------
    dict
        ``means`` (N, 3) and ``log_scales`` (N, 3) float32 (the log of the stored scales);
        ``sh`` (N, 1, 3) the DC band of the stored colour; ``opacity_logits`` (N,), an opacity of
        0 or 255 read as 0.5 / 255 from the end (a logit must be finite); ``quats_wxyz`` (N, 4)
        normalised; and ``rgba`` / ``rotation`` (N, 4) uint8, the bytes as stored.  In file order
        (the viewer's, not the PLY's).

    Raises
    ------
    NimbusError
        The file cannot be read or its size is not a multiple of 32 bytes.
    """
    try:
        raw = Path(path).read_bytes()
    except OSError as e:
        raise NimbusError(f"cannot read {path} ({e.strerror or e.__class__.__name__}); check the path") from None
    if len(raw) % SPLAT_DTYPE.itemsize:
        raise NimbusError(f"{path} holds {len(raw)} bytes, not a multiple of {SPLAT_DTYPE.itemsize}; it is not a "
                          ".splat file or it is truncated")
    data = np.frombuffer(raw, SPLAT_DTYPE)
    rgba = data["rgba"].astype(np.float64) / 255.0
    alpha = np.clip(rgba[:, 3], 0.5 / 255.0, 1.0 - 0.5 / 255.0)
    q = (data["rotation"].astype(np.float64) - 128.0) / 128.0
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    q = np.where(norm > 0, q / np.where(norm > 0, norm, 1.0), [1.0, 0.0, 0.0, 0.0])
    with np.errstate(divide="ignore"):  # a zero scale is -inf in log space, as the PLY would hold it
        log_scales = np.log(data["scale"])
    return {
        "means": data["position"].copy(),
        "sh": ((rgba[:, None, :3] - 0.5) / SH_C0).astype(np.float32),
        "opacity_logits": np.log(alpha / (1.0 - alpha)).astype(np.float32),
        "log_scales": log_scales.astype(np.float32),
        "quats_wxyz": q.astype(np.float32),
        "rgba": data["rgba"].copy(),
        "rotation": data["rotation"].copy(),
    }
