"""The guided filter (He, Sun and Tang, "Guided Image Filtering", 2013), from box means.

OpenCV contrib's ``cv2.ximgproc.guidedFilter`` solves each pixel's 3 x 3 colour system in float32.
Where the guide's colours are strongly correlated (smooth, hazy images: what dehazing feeds it)
that system is near-singular and the float32 solve drifts: on a smooth 64 x 48 colour guide it is
0.019 from a float64 evaluation of the same filter (``tests/test_guided_filter.py``), and on the
tiny garden H views restore-3dgs' refined transmissions differed by 0.13-0.19 between the two.  So
Nimbus computes the filter itself from ``cv2.boxFilter`` means (in every OpenCV build, contrib or
not) with ximgproc's border rule (``BORDER_REFLECT``), all in float64: equal to ximgproc to 1e-5
where its system is well conditioned, the same wherever it runs, and no need of ``cv2.ximgproc``
(plain ``opencv-python(-headless)``, as on many GPU images, is enough).
"""

from __future__ import annotations

import cv2
import numpy as np


def _box(a: np.ndarray, k: int) -> np.ndarray:
    return cv2.boxFilter(a, -1, (k, k), normalize=True, borderType=cv2.BORDER_REFLECT)


def guided_filter(guide: np.ndarray, src: np.ndarray, radius: int, eps: float) -> np.ndarray:
    """``src`` ``[H, W]`` filtered edge-aware by ``guide`` (``[H, W]`` grey or ``[H, W, C]`` colour) -> float32
    ``[H, W]``; window ``2 radius + 1`` (radius at least 1), regulariser ``eps`` (module docstring)."""
    g = np.ascontiguousarray(guide, np.float64)  # float64 throughout: the variances are small differences
    p = np.ascontiguousarray(src, np.float64)
    k = 2 * max(int(radius), 1) + 1
    mp = _box(p, k)
    if g.ndim == 2:
        mg = _box(g, k)
        a = (_box(g * p, k) - mg * mp) / (_box(g * g, k) - mg * mg + eps)
        b = mp - a * mg
        return (_box(a, k) * g + _box(b, k)).astype(np.float32)
    c = g.shape[2]
    chans = [np.ascontiguousarray(g[..., i]) for i in range(c)]
    mg = [_box(ch, k) for ch in chans]
    cov = np.empty(p.shape + (c, c), np.float64)
    for i in range(c):
        for j in range(i, c):
            cov[..., i, j] = cov[..., j, i] = _box(chans[i] * chans[j], k) - mg[i] * mg[j]
        cov[..., i, i] += eps
    cross = np.stack([_box(chans[i] * p, k) - mg[i] * mp for i in range(c)], -1)
    a = np.linalg.solve(cov, cross[..., None])[..., 0]
    b = mp - sum(a[..., i] * mg[i] for i in range(c))
    return (sum(_box(np.ascontiguousarray(a[..., i]), k) * chans[i] for i in range(c)) + _box(b, k)).astype(np.float32)

