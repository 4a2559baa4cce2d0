"""Similarity alignment of two camera rigs: how far recovered poses are from the true ones.

Structure from motion recovers cameras up to an unknown similarity (rotation,
translation and scale of the whole world), so recovered poses are compared with
true ones only after the best similarity is fitted between the camera centres
(Umeyama's closed form) and applied to the recovered rotations too.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from nimbus.data.camera import Camera


@dataclass(frozen=True)
class Similarity:
    """``x -> scale * rotation @ x + translation``.

    Attributes
    ----------
    scale : float
        Positive.
    rotation : ndarray
        (3, 3) float64 proper rotation (determinant +1).
    translation : ndarray
        (3,) float64.
    """

    scale: float
    rotation: np.ndarray
    translation: np.ndarray

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Map (N, 3) points."""
        return self.scale * np.asarray(points, np.float64) @ self.rotation.T + self.translation


def umeyama(src: np.ndarray, dst: np.ndarray) -> Similarity:
    """The similarity that maps ``src`` onto ``dst`` with the least squared error (Umeyama 1991).

    Parameters
    ----------
    src, dst : ndarray
        (N, 3) corresponding points, N >= 3 and not all collinear.

    Returns
    -------
    Similarity
        Minimises ``sum |dst_i - (s R src_i + t)|^2``; a reflection is never returned.
    """
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise ValueError(f"umeyama needs two (N, 3) arrays with N >= 3, got {src.shape} and {dst.shape}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    var_a = (a ** 2).sum()
    if var_a <= 0:
        raise ValueError("umeyama: the source points all coincide")
    u, sig, vt = np.linalg.svd(b.T @ a)
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt)) or 1.0])
    rotation = u @ d @ vt
    scale = float(np.trace(np.diag(sig) @ d) / var_a)
    return Similarity(scale, rotation, mu_d - scale * rotation @ mu_s)


@dataclass(frozen=True)
class PoseError:
    """Recovered cameras against true ones after a similarity fit of the centres.

    Attributes
    ----------
    rotation_deg : float
        Mean angle, in degrees, between each aligned recovered camera orientation and the true one.
    rotation_deg_max : float
        The largest of those angles.
    center : float
        RMS distance between aligned recovered and true centres, relative to the scene extent
        (the RMS distance of the true centres from their mean): 0.01 is 1 % of the rig's size.
    center_max : float
        The largest centre distance, relative to the same extent.
    similarity : Similarity
        The fitted map from the recovered world to the true one.
    """

    rotation_deg: float
    rotation_deg_max: float
    center: float
    center_max: float
    similarity: Similarity


def pose_error(recovered: Sequence[Camera], true: Sequence[Camera]) -> PoseError:
    """Compare corresponding cameras (same order) after aligning ``recovered`` to ``true`` with :func:`umeyama`.

    Parameters
    ----------
    recovered, true : sequence of Camera
        At least 3 of each, in corresponding order, centres not collinear.
    """
    if len(recovered) != len(true):
        raise ValueError(f"pose_error: {len(recovered)} recovered cameras for {len(true)} true ones")
    est = np.stack([c.center for c in recovered]).astype(np.float64)
    ref = np.stack([c.center for c in true]).astype(np.float64)
    sim = umeyama(est, ref)
    extent = float(np.sqrt(((ref - ref.mean(0)) ** 2).sum(1).mean()))
    dist = np.linalg.norm(sim.apply(est) - ref, axis=1) / extent
    angles = []
    for r, t in zip(recovered, true):
        # camera-to-world rotation of the recovered camera, carried into the true world
        r_c2w = sim.rotation @ np.asarray(r.camera_to_world, np.float64)[:3, :3]
        t_c2w = np.asarray(t.camera_to_world, np.float64)[:3, :3]
        cos = (np.trace(t_c2w.T @ r_c2w) - 1.0) / 2.0
        angles.append(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
    return PoseError(float(np.mean(angles)), float(np.max(angles)), float(np.sqrt((dist ** 2).mean())),
                     float(dist.max()), sim)


__all__ = ["PoseError", "Similarity", "pose_error", "umeyama"]
