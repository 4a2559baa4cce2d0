"""The similarity frame training runs in (centred on the cameras, extent 1)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch

from nimbus.data import Scene
from nimbus.render.gaussians import Gaussians


@dataclasses.dataclass(frozen=True)
class SceneFrame:
    """The similarity frame training runs in: ``x_train = (x_world - center) / scale``.

    ``center`` is the mean camera centre and ``scale`` the scene extent
    (:attr:`nimbus.data.Scene.extent`), so every scene trains centred with extent 1,
    whatever the units and the origin of its reconstruction (gsplat's
    ``normalize_world_space``, nerfstudio's ``auto_scale_poses``).  Without it the
    settings that are lengths (``near_plane``, the initial scale floor) meant different
    things in a scene reconstructed in millimetres or kilometres, and a geo-referenced
    scene (coordinates ~1e6) lost its detail to float32 rounding of the means.
    Projections, and so every render and score, are unchanged by the frame; only lengths
    inside the trainer (depth renders, NimbusGS's extinction) are in extent units.

    Attributes
    ----------
    center : tuple of 3 float
        World point that becomes the origin.
    scale : float
        World length that becomes 1 (> 0).
    """

    center: tuple[float, float, float]
    scale: float

    @classmethod
    def of(cls, scene: Scene) -> "SceneFrame":
        centers = scene.camera_centers
        center = centers.mean(0) if len(centers) else np.zeros(3)
        return cls(tuple(float(x) for x in center), float(scene.extent))

    def camera(self, camera):
        """``camera`` posed in this frame (same image: the camera-space scale does not change projections)."""
        c = np.asarray(self.center, dtype=np.float64)
        return camera.with_pose(camera.R, (np.asarray(camera.t, dtype=np.float64) + camera.R @ c) / self.scale)

    def points(self, points: np.ndarray) -> np.ndarray:
        return (np.asarray(points, dtype=np.float64) - np.asarray(self.center)) / self.scale

    def scene(self, scene: Scene) -> Scene:
        """``scene`` in this frame.  Depth maps are dropped: no trainer reads them, and they hold world lengths."""
        views = tuple(dataclasses.replace(v, camera=self.camera(v.camera), depth=None, depth_path=None)
                      for v in scene.views)
        return dataclasses.replace(scene, views=views, points=self.points(scene.points))

    def to_world(self, g: Gaussians) -> Gaussians:
        """Gaussians of this frame in world coordinates (centres and scales; rotations and colours are the same)."""
        c = torch.as_tensor(self.center, dtype=torch.float64, device=g.means.device)
        means = (g.means.to(torch.float64) * self.scale + c).to(g.means.dtype)
        return dataclasses.replace(g, means=means, log_scales=g.log_scales + math.log(self.scale))

    def as_list(self) -> list[float]:
        return [*self.center, self.scale]
