"""The guided filter (He, Sun and Tang, "Guided Image Filtering", 2013) with or without OpenCV's contrib modules.

``cv2.ximgproc.guidedFilter`` lives in opencv-contrib, which the install brings; but plain
``opencv-python(-headless)`` is what many environments already hold (a GPU image, a lab's shared
environment, a package that pins it), and the two cannot be installed side by side.  Where
``cv2.ximgproc`` is missing, :func:`guided_filter` computes the same filter from box means
(``cv2.boxFilter``, in every OpenCV build) with ximgproc's border rule (``BORDER_REFLECT``): the
two agree to float rounding (``tests/test_guided_filter.py`` checks it where contrib is installed).
"""

from __future__ import annotations

import cv2
import numpy as np


def has_ximgproc() -> bool:
    """Whether this OpenCV build has the contrib module ``ximgproc``."""
    return hasattr(cv2, "ximgproc") and hasattr(cv2.ximgproc, "guidedFilter")


def _box(a: np.ndarray, k: int) -> np.ndarray:
    return cv2.boxFilter(a, -1, (k, k), normalize=True, borderType=cv2.BORDER_REFLECT)


def guided_filter_box(guide: np.ndarray, src: np.ndarray, radius: int, eps: float) -> np.ndarray:
    """The guided filter from box means alone (what :func:`guided_filter` uses without ``cv2.ximgproc``).

    ``guide`` is ``[H, W]`` (grey) or ``[H, W, C]``; ``src`` is ``[H, W]``; float32 arrays.
    """
    g = np.ascontiguousarray(guide, np.float32)
    p = np.ascontiguousarray(src, np.float32)
    k = 2 * max(int(radius), 1) + 1
    mp = _box(p, k)
    if g.ndim == 2:
        mg = _box(g, k)
        a = (_box(g * p, k) - mg * mp) / (_box(g * g, k) - mg * mg + eps)
        b = mp - a * mg
        return _box(a, k) * g + _box(b, k)
    c = g.shape[2]
    chans = [np.ascontiguousarray(g[..., i]) for i in range(c)]
    mg = [_box(ch, k) for ch in chans]
    cov = np.empty(p.shape + (c, c), np.float64)
    for i in range(c):
        for j in range(i, c):
            cov[..., i, j] = cov[..., j, i] = _box(chans[i] * chans[j], k) - mg[i] * mg[j]
        cov[..., i, i] += eps
    cross = np.stack([_box(chans[i] * p, k) - mg[i] * mp for i in range(c)], -1).astype(np.float64)
    a = np.linalg.solve(cov, cross[..., None])[..., 0].astype(np.float32)
    b = mp - sum(a[..., i] * mg[i] for i in range(c))
    return sum(_box(np.ascontiguousarray(a[..., i]), k) * chans[i] for i in range(c)) + _box(b, k)


def guided_filter(guide: np.ndarray, src: np.ndarray, radius: int, eps: float) -> np.ndarray:
    """``src`` ``[H, W]`` filtered edge-aware by ``guide`` (``[H, W]`` or ``[H, W, 3]``), float32.

    ``cv2.ximgproc.guidedFilter`` where OpenCV has contrib, else :func:`guided_filter_box` (the same
    filter to float rounding).
    """
    g = np.ascontiguousarray(guide, np.float32)
    p = np.ascontiguousarray(src, np.float32)
    r = max(int(radius), 1)
    if has_ximgproc():
        return np.asarray(cv2.ximgproc.guidedFilter(g, p, r, float(eps)), np.float32)
    return guided_filter_box(g, p, r, float(eps)).astype(np.float32)
