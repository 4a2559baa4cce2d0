"""Shared test fixtures: small, generic, fast."""

from __future__ import annotations

import os

# As the command-line tools do (nimbus.cli): passive OpenMP waits, before torch loads in this process.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from nimbus.data.camera import Camera  # noqa: E402
from nimbus.data.scene import Scene, View  # noqa: E402


def make_tiny_scene(n_views: int = 5, width: int = 32, height: int = 24, n_points: int = 40, seed: int = 0,
                    depth: bool = False, mask: bool = False, sky: bool = False, test_names=None) -> Scene:
    """An in-memory scene: look-at cameras on a ring around the origin, random images and points.

    Parameters
    ----------
    depth, mask, sky : bool
        Also give every view a random z-depth map (float32 (H, W), in [1, 5]) / bool validity mask / sky mask.
    test_names : iterable of str, optional
        The test split (default: the first view, ``"000.png"``).
    """
    rng = np.random.default_rng(seed)
    views = []
    for i in range(n_views):
        a = 2 * np.pi * i / n_views
        eye = (4 * np.cos(a), 4 * np.sin(a), 1.0 + 0.2 * i)
        cam = Camera.look_at(eye, (0, 0, 0), (0, 0, 1), width, height, fov_x_deg=55)
        views.append(View(
            f"{i:03d}.png", cam,
            image=rng.random((height, width, 3), dtype=np.float32),
            depth=rng.uniform(1, 5, (height, width)).astype(np.float32) if depth else None,
            mask=rng.random((height, width)) > 0.5 if mask else None,
            sky=rng.random((height, width)) > 0.7 if sky else None,
        ))
    points = rng.normal(size=(n_points, 3))
    colors = rng.integers(0, 256, (n_points, 3), dtype=np.uint8)
    test = {"000.png"} if test_names is None else set(test_names)
    return Scene(tuple(views), frozenset(test), points, colors)


@pytest.fixture
def make_scene():
    """Factory fixture: ``make_scene(n_views=5, width=32, height=24, ...)`` -> in-memory Scene (see make_tiny_scene)."""
    return make_tiny_scene


def _assert_same_scene(a: Scene, b: Scene, atol: float = 1e-9) -> None:
    """Same names, split, intrinsics, poses (to ``atol``), points and colours."""
    assert a.names == b.names
    assert a.test_names == b.test_names
    for va, vb in zip(a.views, b.views):
        ca, cb = va.camera, vb.camera
        assert (ca.width, ca.height) == (cb.width, cb.height)
        np.testing.assert_allclose([ca.fx, ca.fy, ca.cx, ca.cy], [cb.fx, cb.fy, cb.cx, cb.cy], atol=atol)
        np.testing.assert_allclose(ca.world_to_camera, cb.world_to_camera, atol=atol)
    np.testing.assert_allclose(a.points, b.points, atol=atol)
    np.testing.assert_array_equal(a.colors, b.colors)


@pytest.fixture
def assert_same_scene():
    """``assert_same_scene(a, b, atol=1e-9)``: two scenes have the same views, cameras, split and points."""
    return _assert_same_scene


def _interrupt_and_resume(make_runner, after: int):
    """``make_runner()`` run until Ctrl-C after step ``after`` (between checkpoints: the interrupt saves the
    state), then a fresh ``make_runner()`` loaded from that checkpoint (the same run folder): the resumed runner."""
    from nimbus.train.checkpoint import CHECKPOINT

    half = make_runner()
    step = half.method.train_iteration

    def interrupted(it):
        if it == after + 1:
            raise KeyboardInterrupt
        return step(it)

    half.method.train_iteration = interrupted
    with pytest.raises(KeyboardInterrupt):
        half.run()
    resumed = make_runner()
    resumed.load_checkpoint(half.out / CHECKPOINT)
    return resumed


@pytest.fixture
def interrupt_and_resume():
    """``interrupt_and_resume(make_runner, after)``: a run interrupted after step ``after``, resumed (see above)."""
    return _interrupt_and_resume


def _fill_disk_for(monkeypatch, pattern: str, after_bytes: int = 0) -> list:
    """Make every file opened for writing through ``os.fdopen`` (what the atomic writers use) whose path holds
    ``pattern`` fail with ENOSPC once ``after_bytes`` are written, as a full disk does, without filling one.
    Returns the list of paths that failed."""
    import errno
    import os

    real = os.fdopen
    failed = []

    class Full:
        def __init__(self, f, path):
            self._f, self._path = f, path

        def write(self, data):
            self._f.write(bytes(data)[:after_bytes])
            failed.append(self._path)
            raise OSError(errno.ENOSPC, "No space left on device")

        def __getattr__(self, name):
            return getattr(self._f, name)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self._f.close()
            return False

    def fdopen(fd, mode="r", *args, **kwargs):
        f = real(fd, mode, *args, **kwargs)
        if "w" not in mode and "a" not in mode:
            return f
        try:
            path = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            return f
        return Full(f, path) if pattern in path else f

    monkeypatch.setattr(os, "fdopen", fdopen)
    return failed


@pytest.fixture
def disk_full(monkeypatch):
    """``disk_full(pattern)``: writes to files whose path holds ``pattern`` end in ENOSPC (see _fill_disk_for)."""
    return lambda pattern, after_bytes=0: _fill_disk_for(monkeypatch, pattern, after_bytes)
