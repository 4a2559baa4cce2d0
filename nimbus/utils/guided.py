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
    """``src`` ``[H, W]`` filtered edge-aware by ``guide`` (``[H, W]`` grey or ``[H, W, 3]`` colour) -> float32
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
    if g.ndim != 3 or g.shape[2] != 3:
        raise ValueError(f"the guide must be [H, W] or [H, W, 3], got {g.shape}")
    c = 3
    chans = [np.ascontiguousarray(g[..., i]) for i in range(c)]
    mg = [_box(ch, k) for ch in chans]
    cross = [_box(chans[i] * p, k) - mg[i] * mp for i in range(c)]
    a00, a01, a02, a11, a12, a22 = (_box(chans[i] * chans[j], k) - mg[i] * mg[j] + (eps if i == j else 0.0)
                                    for i, j in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)))
    # each pixel's symmetric 3 x 3 system by its cofactors, element-wise (np.linalg.solve: 10x slower)
    c00, c01, c02 = a11 * a22 - a12 * a12, a02 * a12 - a01 * a22, a01 * a12 - a02 * a11
    c11, c12, c22 = a00 * a22 - a02 * a02, a01 * a02 - a00 * a12, a00 * a11 - a01 * a01
    det = a00 * c00 + a01 * c01 + a02 * c02
    a = [(c00 * cross[0] + c01 * cross[1] + c02 * cross[2]) / det,
         (c01 * cross[0] + c11 * cross[1] + c12 * cross[2]) / det,
         (c02 * cross[0] + c12 * cross[1] + c22 * cross[2]) / det]
    b = mp - sum(a[i] * mg[i] for i in range(c))
    return (sum(_box(a[i], k) * chans[i] for i in range(c)) + _box(b, k)).astype(np.float32)

