"""Nimbus's guided filter (nimbus.utils.guided): OpenCV contrib's filter where that is well conditioned,
the exact filter where contrib's float32 solve is not, and no contrib needed."""

import cv2
import numpy as np
import pytest

from nimbus.utils.guided import guided_filter

has_ximgproc = hasattr(cv2, "ximgproc") and hasattr(cv2.ximgproc, "guidedFilter")


def _box64(a, k):
    return cv2.boxFilter(np.asarray(a, np.float64), -1, (k, k), normalize=True, borderType=cv2.BORDER_REFLECT)


def _reference(guide, src, radius, eps):
    """He et al.'s colour guided filter written out per pixel in float64 (np.linalg.inv, not a batched solve)."""
    k, (h, w) = 2 * radius + 1, src.shape
    mean_i = np.stack([_box64(guide[..., c], k) for c in range(3)], -1)
    mean_p = _box64(src, k)
    corr = np.stack([np.stack([_box64(guide[..., i] * guide[..., j], k) for j in range(3)], -1) for i in range(3)], -2)
    cov = corr - mean_i[..., :, None] * mean_i[..., None, :] + eps * np.eye(3)
    cov_ip = np.stack([_box64(guide[..., c] * src, k) for c in range(3)], -1) - mean_i * mean_p[..., None]
    a = np.empty((h, w, 3))
    for y in range(h):
        for x in range(w):
            a[y, x] = np.linalg.inv(cov[y, x]) @ cov_ip[y, x]
    b = mean_p - (a * mean_i).sum(-1)
    return sum(_box64(a[..., c], k) * guide[..., c] for c in range(3)) + _box64(b, k)


def _smooth_guide(h=48, w=64):
    # strongly correlated channels (as in a hazy image): a near-singular colour covariance per window
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    g = np.stack([np.sin(xx / 7), np.cos(yy / 5), np.sin((xx + yy) / 9)], -1) * 0.5 + 0.5
    src = g.mean(-1) + 0.1 * np.random.default_rng(0).random((h, w))
    return g.astype(np.float32), src.astype(np.float32)


def test_equals_the_float64_filter_on_a_near_singular_guide():
    guide, src = _smooth_guide()
    out = guided_filter(guide, src, 6, 1e-3)
    assert out.shape == src.shape and out.dtype == np.float32
    assert np.abs(out - _reference(guide, src, 6, 1e-3)).max() < 1e-6


@pytest.mark.skipif(not has_ximgproc, reason="OpenCV without contrib: nothing to compare with")
def test_ximgproc_drifts_where_ours_does_not():
    # the reason Nimbus does not call cv2.ximgproc: its float32 solve (seen: 0.019 off here)
    guide, src = _smooth_guide()
    ref = _reference(guide, src, 6, 1e-3)
    assert np.abs(cv2.ximgproc.guidedFilter(guide, src, 6, 1e-3) - ref).max() > 1e-3
    assert np.abs(guided_filter(guide, src, 6, 1e-3) - ref).max() < 1e-6


@pytest.mark.skipif(not has_ximgproc, reason="OpenCV without contrib: nothing to compare with")
@pytest.mark.parametrize("channels", [0, 3])
@pytest.mark.parametrize("radius,eps", [(1, 1e-3), (4, 1e-2), (15, 1e-4)])
def test_equals_ximgproc_where_it_is_well_conditioned(channels, radius, eps):
    rng = np.random.default_rng(radius)
    guide = rng.random((37, 53) + ((channels,) if channels else ()), dtype=np.float32)
    base = guide if guide.ndim == 2 else guide.mean(-1)
    src = (0.7 * base + 0.3 * rng.random((37, 53), dtype=np.float32)).astype(np.float32)
    out = guided_filter(guide, src, radius, eps)
    # float32 rounding inside ximgproc (seen: up to 3.6e-5 on the grey guide)
    assert np.abs(out - cv2.ximgproc.guidedFilter(guide, src, radius, eps)).max() < (1e-5 if channels else 1e-4)


def test_a_flat_guide_gives_the_box_mean():
    # with a constant guide the filter is two box means of the source (a = 0, b = mean)
    src = np.random.default_rng(1).random((20, 30), dtype=np.float32)
    out = guided_filter(np.full((20, 30), 0.5, np.float32), src, 2, 1e-2)
    np.testing.assert_allclose(out, _box64(_box64(src, 5), 5), atol=1e-6)


def test_a_guide_of_other_channels_is_refused():
    with pytest.raises(ValueError, match=r"\[H, W, 3\]"):
        guided_filter(np.zeros((8, 8, 2), np.float32), np.zeros((8, 8), np.float32), 1, 1e-3)
