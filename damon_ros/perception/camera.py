"""The pinhole camera model shared by the tracker and the mock renderer.

A calibrated RealSense colour stream is a pinhole camera with no distortion plus its pose in
the robot base frame (the hand-eye calibration). The tracker deprojects pixels through it
and the mock renderer casts rays through it, so both read the same calibration file.
Conventions: the optical frame is z forward, x right, y down; a pixel's integer coordinates
are its centre (OpenCV/ROS); depth is the z coordinate in the optical frame.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from damon_ros.core.resources import config_file, read_yaml_section


def pose_matrix(position: Sequence[float], orientation: Sequence[float]) -> np.ndarray:
    """4x4 homogeneous transform from a position and a unit quaternion ``[x, y, z, w]``."""
    q = np.asarray(orientation, dtype=float).reshape(4)
    norm = float(np.linalg.norm(q))
    if not np.isfinite(norm) or abs(norm - 1.0) > 1e-3:
        raise ValueError(f"orientation {q.tolist()} is not a unit quaternion [x, y, z, w]")
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(q / norm).as_matrix()
    T[:3, 3] = np.asarray(position, dtype=float).reshape(3)
    return T


@dataclass(frozen=True, eq=False)
class Camera:
    """A pinhole camera with no distortion and its pose in the robot base frame.

    ``K`` is the 3x3 intrinsic matrix; ``base_T_camera`` the 4x4 pose of the optical frame in
    the base frame (the hand-eye calibration).
    """

    width: int
    height: int
    K: np.ndarray
    base_T_camera: np.ndarray
    fps: float = 30.0
    frame_id: str = "camera_color_optical_frame"
    base_frame: str = "panda_link0"

    def __post_init__(self) -> None:
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ValueError(f"camera size {self.width}x{self.height} must be positive")
        K = np.asarray(self.K, dtype=float).reshape(3, 3)
        if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError(f"camera K {K.tolist()} needs finite, positive fx and fy")
        if not np.allclose(K[2], [0.0, 0.0, 1.0]) or K[1, 0] != 0.0 or K[0, 1] != 0.0:
            raise ValueError(
                f"camera K {K.tolist()} must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew)"
            )
        T = np.asarray(self.base_T_camera, dtype=float).reshape(4, 4)
        R = T[:3, :3]
        if not np.all(np.isfinite(T)) or not np.allclose(R @ R.T, np.eye(3), atol=1e-5) or (
            np.linalg.det(R) < 0.0
        ):
            raise ValueError("camera base_T_camera must be a finite rigid transform (rotation)")
        if self.fps <= 0:
            raise ValueError(f"camera fps {self.fps} must be positive")
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "base_T_camera", T)

    @property
    def rotation(self) -> np.ndarray:
        """Optical frame axes (columns) in the base frame."""
        return self.base_T_camera[:3, :3]

    @property
    def position(self) -> np.ndarray:
        """Optical centre in the base frame."""
        return self.base_T_camera[:3, 3]

    @property
    def orientation(self) -> np.ndarray:
        """Quaternion ``[x, y, z, w]`` of the optical frame in the base frame."""
        return Rotation.from_matrix(self.rotation).as_quat()

    @functools.cached_property
    def ray_x(self) -> np.ndarray:
        """x of the ray ``[x, y, 1]`` through each pixel column (shape ``(width,)``)."""
        return (np.arange(self.width) - self.K[0, 2]) / self.K[0, 0]

    @functools.cached_property
    def ray_y(self) -> np.ndarray:
        """y of the ray ``[x, y, 1]`` through each pixel row (shape ``(height,)``)."""
        return (np.arange(self.height) - self.K[1, 2]) / self.K[1, 1]

    def camera_info(self) -> dict:
        """The fields of a sensor_msgs/CameraInfo, for the node to copy into the message."""
        P = np.zeros((3, 4))
        P[:, :3] = self.K
        return {
            "width": self.width,
            "height": self.height,
            "distortion_model": "plumb_bob",
            "d": [0.0] * 5,
            "k": self.K.reshape(-1).tolist(),
            "r": np.eye(3).reshape(-1).tolist(),
            "p": P.reshape(-1).tolist(),
        }


def camera_from_dict(data: dict, source: str = "<camera>") -> Camera:
    """Build a :class:`Camera` from the ``camera:`` mapping of ``config/camera.yaml``."""
    try:
        pose = data["base_T_camera"]
        K = np.asarray(data["K"], dtype=float)
        if K.size != 9:
            raise ValueError(f"K must have 9 values (row-major 3x3), got {K.size}")
        D = np.asarray(data.get("D", [0.0] * 5), dtype=float)
        if np.any(D != 0.0):
            raise ValueError(f"D {D.tolist()} must be zeros: the renderer and tracker assume a "
                             "rectified image")
        return Camera(
            width=int(data["width"]),
            height=int(data["height"]),
            K=K.reshape(3, 3),
            base_T_camera=pose_matrix(pose["position"], pose["orientation"]),
            fps=float(data.get("fps", 30.0)),
            frame_id=str(data.get("frame_id", "camera_color_optical_frame")),
            base_frame=str(data.get("base_frame", "panda_link0")),
        )
    except KeyError as exc:
        raise ValueError(f"{source}: camera: missing field {exc.args[0]!r}") from exc
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{source}: camera: {exc}") from exc


def camera_file(name: str | os.PathLike | None) -> Path:
    """The camera file ``name``: a path, or the name of a shipped one (``camera_side.yaml``,
    found in the installed share folder too); None or "" = ``config/camera.yaml``."""
    if not name:
        return config_file("camera.yaml")
    path = Path(name)
    if path.is_file() or path.parent != Path("."):
        return path
    try:
        return config_file(str(name))
    except FileNotFoundError:
        return path  # read_yaml_section names it: "cannot be read"


def load_camera(path: str | os.PathLike | None = None) -> Camera:
    """The calibrated camera of ``path`` (see `camera_file`), or of ``config/camera.yaml``."""
    path = camera_file(path)
    return camera_from_dict(read_yaml_section(path, "camera"), str(path))


def load_cameras(files: str | Sequence[str]) -> list[Camera]:
    """Several cameras, from a comma-separated list of camera files (see `camera_file`) or
    a sequence of them: ``"camera.yaml,camera_side.yaml"`` is the front and side pair."""
    names = [f.strip() for f in files.split(",")] if isinstance(files, str) else list(files)
    if not names or not all(names):
        raise ValueError(f"camera list {files!r} must name one or more camera files")
    return [load_camera(name) for name in names]


def to_camera_frame(camera: Camera, points_base: np.ndarray) -> np.ndarray:
    """Points (N, 3) from the base frame into the optical frame."""
    p = np.asarray(points_base, dtype=float).reshape(-1, 3)
    return (p - camera.position) @ camera.rotation


def to_base_frame(camera: Camera, points_camera: np.ndarray) -> np.ndarray:
    """Points (N, 3) from the optical frame into the base frame."""
    p = np.asarray(points_camera, dtype=float).reshape(-1, 3)
    return p @ camera.rotation.T + camera.position


def project(camera: Camera, points_base: np.ndarray) -> np.ndarray:
    """Pixel coordinates (N, 2) as ``(u, v)``; NaN for points not in front of the camera."""
    p = to_camera_frame(camera, points_base)
    z = p[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (p[:, :2] / z[:, None]) @ camera.K[:2, :2].T + camera.K[:2, 2]
    uv[z <= 0.0] = np.nan
    return uv


def deproject(camera: Camera, u: np.ndarray, v: np.ndarray, depth_m: np.ndarray) -> np.ndarray:
    """Optical-frame points (N, 3) of pixels ``(u, v)`` with z-depth ``depth_m`` in metres."""
    z = np.asarray(depth_m, dtype=float).reshape(-1)
    fx, fy, cx, cy = camera.K[0, 0], camera.K[1, 1], camera.K[0, 2], camera.K[1, 2]
    y = (np.asarray(v, dtype=float).reshape(-1) - cy) / fy
    x = (np.asarray(u, dtype=float).reshape(-1) - cx) / fx
    return np.stack([x * z, y * z, z], axis=1)
