"""The guided filter without OpenCV contrib is the contrib one (nimbus.utils.guided)."""

import numpy as np
import pytest

from nimbus.utils import guided
from nimbus.utils.guided import guided_filter, guided_filter_box, has_ximgproc


def _pair(seed, channels, shape=(37, 53)):
    rng = np.random.default_rng(seed)
    guide = rng.random(shape + ((channels,) if channels else ()), dtype=np.float32)
    # a source correlated with the guide, so the filter has edges to keep
    base = guide if guide.ndim == 2 else guide.mean(-1)
    return guide, (0.7 * base + 0.3 * rng.random(shape, dtype=np.float32)).astype(np.float32)


@pytest.mark.skipif(not has_ximgproc(), reason="OpenCV without contrib: nothing to compare with")
@pytest.mark.parametrize("channels", [0, 3])
@pytest.mark.parametrize("radius,eps", [(1, 1e-3), (4, 1e-2), (15, 1e-4)])
def test_box_means_equal_ximgproc(channels, radius, eps):
    import cv2

    guide, src = _pair(radius, channels)
    ref = cv2.ximgproc.guidedFilter(guide, src, radius, eps)
    out = guided_filter_box(guide, src, radius, eps)
    assert out.shape == src.shape and out.dtype == np.float32
    # float32 rounding: ximgproc forms the grey variance in another order (seen: up to 3.6e-5 here)
    assert np.abs(out - ref).max() < (1e-5 if channels else 1e-4)


def test_without_contrib_the_fallback_runs(monkeypatch):
    guide, src = _pair(0, 3)
    monkeypatch.setattr(guided, "has_ximgproc", lambda: False)
    out = guided_filter(guide, src, 4, 1e-3)
    np.testing.assert_array_equal(out, guided_filter_box(guide, src, 4, 1e-3))
    # edge-aware smoothing: closer to the source's local mean than the source itself, never outside its range
    assert out.min() >= src.min() - 1e-3 and out.max() <= src.max() + 1e-3
    assert np.abs(np.diff(out, axis=1)).mean() < np.abs(np.diff(src, axis=1)).mean()


def test_a_flat_guide_gives_the_box_mean():
    # with a constant guide the filter is two box means of the source (a = 0, b = mean)
    src = np.random.default_rng(1).random((20, 30), dtype=np.float32)
    out = guided_filter_box(np.full((20, 30), 0.5, np.float32), src, 2, 1e-2)
    import cv2
    box = lambda a: cv2.boxFilter(a, -1, (5, 5), borderType=cv2.BORDER_REFLECT)
    np.testing.assert_allclose(out, box(box(src)), atol=1e-6)
