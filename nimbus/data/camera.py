"""Pinhole cameras in the one convention Nimbus uses everywhere.

Conventions (decided here, once, for the whole project)
-------------------------------------------------------
* **Camera frame**: OpenCV. x points right, y points down, z points forward
  (into the scene).  A point is in front of the camera when its z > 0.
* **Pose**: world-to-camera, ``x_cam = R @ x_world + t`` (the COLMAP
  ``cam_from_world`` transform).  The camera centre is ``-R.T @ t``.
* **Pixels**: the continuous image plane has the *corner* of the top-left
  pixel at (0, 0), so pixel (col u, row v) has its centre at (u + 0.5, v + 0.5).
  This is COLMAP's and gsplat's convention; it makes intrinsics scale exactly
  with the image (``fx, fy, cx, cy`` all times ``s``).
* **Intrinsics**: ``fx, fy, cx, cy`` in pixels; no distortion (distorted
  models are undistorted or refused by the readers).
* **Depth**: "z-depth" is the camera-frame z of the surface; "ray distance" is
  the Euclidean distance from the camera centre, ``z * |(x', y', 1)|`` with
  ``x' = (u + 0.5 - cx) / fx``, ``y' = (v + 0.5 - cy) / fy``
  (:meth:`Camera.ray_distance_from_z`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from nimbus.errors import NimbusError

# How far R @ R.T may be from the identity (entry-wise): rounding in files written with ~7 digits.
ROTATION_TOLERANCE = 1e-5
#: The widest field of view (degrees, horizontal or vertical) a camera read from a scene file may have.  A pinhole
#: image of 180 degrees or more does not exist (the focal length would be 0 or negative), and one this close to it is
#: a focal length typed in the wrong unit: at 175 degrees the focal length is 1/46 of the image width, and the
#: image's edge is stretched radially about 500 times more than its centre (1 / cos^2 of 87.5 degrees).  Undistorted
#: wide-angle captures stay well below (a 120-degree action camera: f = 0.29 x width).
MAX_FIELD_OF_VIEW_DEG = 175.0


def finite_value(value: object, name: str) -> float:
    """``value`` as a finite float; NimbusError naming ``name`` for NaN, inf, a string, a bool or None."""
    if isinstance(value, (str, bytes, bool, np.bool_)) or value is None:
        raise NimbusError(f"camera {name} must be a number, got {value!r}")
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise NimbusError(f"camera {name} must be a number, got {value!r}") from None
    if not np.isfinite(v):
        raise NimbusError(f"camera {name} must be finite, got {v}")
    return v


def image_size_value(value: object, name: str) -> int:
    """``value`` as a positive int pixel count (an integral float such as 640.0 is accepted)."""
    v = finite_value(value, name)
    if v <= 0 or v != int(v):
        raise NimbusError(f"camera {name} must be a positive whole number of pixels, got {value!r}")
    return int(v)


@dataclass(frozen=True, eq=False)
class Camera:
    """A pinhole camera: intrinsics plus a world-to-camera pose.

    Attributes
    ----------
    width, height : int
        Image size in pixels.
    fx, fy, cx, cy : float
        Focal lengths and principal point in pixels (pixel-corner origin, see module doc).
    R : ndarray, shape (3, 3), float64
        World-to-camera rotation.
    t : ndarray, shape (3,), float64
        World-to-camera translation.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    t: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        # Validated here, once, because a NaN principal point or an inf focal length does not fail
        # anywhere later: it renders nothing, trains on nothing and still reports a PSNR.
        object.__setattr__(self, "width", image_size_value(self.width, "width"))
        object.__setattr__(self, "height", image_size_value(self.height, "height"))
        for name in ("fx", "fy", "cx", "cy"):
            object.__setattr__(self, name, finite_value(getattr(self, name), name))
        if not (self.fx > 0 and self.fy > 0):
            raise NimbusError(f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        try:
            R = np.array(self.R, dtype=np.float64).reshape(3, 3)
            t = np.array(self.t, dtype=np.float64).reshape(3)
        except (TypeError, ValueError):
            raise NimbusError("camera pose must be a 3x3 rotation and a 3-vector translation of numbers") from None
        R.setflags(write=False)
        t.setflags(write=False)
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", t)
        if not np.all(np.isfinite(R)) or not np.all(np.isfinite(t)):
            raise NimbusError("camera pose contains NaN or inf")
        if not np.allclose(R @ R.T, np.eye(3), atol=ROTATION_TOLERANCE) or np.linalg.det(R) < 0:
            raise NimbusError("camera rotation is not a proper rotation matrix")

    # --- construction -------------------------------------------------------------
    @classmethod
    def from_K(cls, K: np.ndarray, width: int, height: int, world_to_camera: np.ndarray) -> "Camera":
        """Build from a 3x3 intrinsic matrix and a 3x4 or 4x4 world-to-camera matrix."""
        K = np.asarray(K, dtype=np.float64)
        w2c = np.asarray(world_to_camera, dtype=np.float64)
        return cls(width, height, K[0, 0], K[1, 1], K[0, 2], K[1, 2], w2c[:3, :3], w2c[:3, 3])

    @classmethod
    def look_at(cls, eye, target, up, width: int, height: int, fov_x_deg: float) -> "Camera":
        """A camera at ``eye`` looking at ``target``; ``up`` is the world up direction.

        The image's "down" (camera +y) is aligned with ``-up`` projected on the image plane.
        """
        eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
        z = target - eye
        z /= np.linalg.norm(z)
        x = np.cross(z, up)
        if np.linalg.norm(x) < 1e-9:
            raise NimbusError("look_at: viewing direction is parallel to the up vector")
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        R = np.stack([x, y, z])  # rows: camera axes in world coordinates
        f = 0.5 * width / np.tan(np.radians(fov_x_deg) / 2)
        return cls(width, height, f, f, width / 2, height / 2, R, -R @ eye)

    # --- derived quantities -------------------------------------------------------
    @property
    def K(self) -> np.ndarray:
        """3x3 intrinsic matrix."""
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    @property
    def world_to_camera(self) -> np.ndarray:
        """4x4 world-to-camera matrix."""
        m = np.eye(4)
        m[:3, :3] = self.R
        m[:3, 3] = self.t
        return m

    @property
    def camera_to_world(self) -> np.ndarray:
        """4x4 camera-to-world matrix (OpenCV axes)."""
        m = np.eye(4)
        m[:3, :3] = self.R.T
        m[:3, 3] = self.center
        return m

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates, shape (3,)."""
        return -self.R.T @ self.t

    @property
    def fov_x(self) -> float:
        """Horizontal field of view in radians."""
        return 2 * np.arctan(self.width / (2 * self.fx))

    @property
    def fov_y(self) -> float:
        return 2 * np.arctan(self.height / (2 * self.fy))

    def scaled(self, factor: float, width: int | None = None, height: int | None = None) -> "Camera":
        """The same camera for an image resized by ``factor`` (exact under the pixel-corner convention)."""
        w = width if width is not None else int(round(self.width * factor))
        h = height if height is not None else int(round(self.height * factor))
        sx, sy = w / self.width, h / self.height
        return Camera(w, h, self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, self.R, self.t)

    def with_pose(self, R: np.ndarray, t: np.ndarray) -> "Camera":
        return Camera(self.width, self.height, self.fx, self.fy, self.cx, self.cy, R, t)

    def pixel_rays(self, dtype=np.float32) -> np.ndarray:
        """Camera-frame ray directions through pixel centres, ``(x', y', 1)``, shape (H, W, 3).

        The z component is 1, so ``z_depth * ray`` is the camera-frame surface point.
        """
        u = (np.arange(self.width, dtype=np.float64) + 0.5 - self.cx) / self.fx
        v = (np.arange(self.height, dtype=np.float64) + 0.5 - self.cy) / self.fy
        uu, vv = np.meshgrid(u, v)
        return np.stack([uu, vv, np.ones_like(uu)], axis=-1).astype(dtype)

    def world_rays(self, dtype=np.float32) -> tuple[np.ndarray, np.ndarray]:
        """Unit world-space ray directions (H, W, 3) and the origin (3,) for every pixel centre."""
        d = self.pixel_rays(np.float64)
        d = d / np.linalg.norm(d, axis=-1, keepdims=True)
        return (d @ self.R).astype(dtype), self.center.astype(dtype)

    def ray_distance_from_z(self, z: np.ndarray) -> np.ndarray:
        """Convert a z-depth map (H, W) to the Euclidean distance along each pixel's ray."""
        z = np.asarray(z)
        if z.shape != (self.height, self.width):
            raise NimbusError(f"depth map has shape {z.shape}, camera expects {(self.height, self.width)}")
        norm = np.linalg.norm(self.pixel_rays(np.float64), axis=-1)
        return (z * norm).astype(z.dtype if np.issubdtype(z.dtype, np.floating) else np.float32)

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project world points (N, 3) to continuous pixel coordinates (N, 2) and z-depths (N,)."""
        p = np.asarray(points, dtype=np.float64) @ self.R.T + self.t
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = np.stack([self.fx * p[:, 0] / z + self.cx, self.fy * p[:, 1] / z + self.cy], axis=-1)
        return uv, z

    def project_seen(self, points: np.ndarray, near: float = 1e-6) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`project`, and which points the camera sees (N,) bool: in front of it (``z > near``) and
        inside the image."""
        uv, z = self.project(points)
        with np.errstate(invalid="ignore"):
            seen = (z > near) & np.all(np.isfinite(uv), axis=1)
            seen &= (uv[:, 0] >= 0) & (uv[:, 0] < self.width) & (uv[:, 1] >= 0) & (uv[:, 1] < self.height)
        return uv, z, seen

    def to_dict(self) -> dict:
        return {
            "width": self.width, "height": self.height,
            "fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy,
            "R": self.R.tolist(), "t": self.t.tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict) -> "Camera":
        return cls(d["width"], d["height"], d["fx"], d["fy"], d["cx"], d["cy"], np.array(d["R"]), np.array(d["t"]))


def check_field_of_view(camera: Camera) -> None:
    """Refuse a camera read from a file whose field of view reaches :data:`MAX_FIELD_OF_VIEW_DEG` (NimbusError naming
    the focal length field; the reader adds the file)."""
    for axis, size, focal, fov in (("horizontal", camera.width, "fx", camera.fov_x),
                                   ("vertical", camera.height, "fy", camera.fov_y)):
        if np.degrees(fov) >= MAX_FIELD_OF_VIEW_DEG:
            raise NimbusError(f"{focal}={getattr(camera, focal):.6g} gives a {axis} field of view of "
                              f"{np.degrees(fov):.4g} degrees for an image {size} pixels wide; a pinhole camera "
                              f"sees less than {MAX_FIELD_OF_VIEW_DEG:g} (is the focal length in pixels?)")


def rotation_from_quaternion_wxyz(q: np.ndarray) -> np.ndarray:
    """Rotation matrix from a (w, x, y, z) quaternion (normalised here)."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])
