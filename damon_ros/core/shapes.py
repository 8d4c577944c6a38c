"""Obstacle shapes shared by scenarios, the tracker, the robot model and the planner.

One small immutable type so that every layer speaks about obstacles the same way: a
scenario's box, a tracked sphere and a point cloud from the camera all become a
:class:`Shape` in the robot base frame, and the robot model turns it into coal geometry.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

KINDS = ("box", "sphere", "cylinder", "points")
"""Shape kinds. ``points`` is a convex point set (its hull); one point is a point obstacle."""

SIZE_LENGTH = {"box": 3, "sphere": 1, "cylinder": 2, "points": 0}
"""How many size values each kind takes: box full extents x y z; sphere radius;
cylinder radius and length (along its local z axis); points none."""


def _unit_quaternion(q: np.ndarray) -> np.ndarray:
    norm = float(np.linalg.norm(q))
    if not np.isfinite(norm) or norm < 1e-9:
        raise ValueError(f"orientation {q.tolist()} is not a valid quaternion")
    return q / norm


@dataclass(frozen=True)
class Shape:
    """An obstacle in the robot base frame.

    ``orientation`` is a quaternion ``[x, y, z, w]``; ``points`` (only for kind ``points``)
    are given in the shape's own frame, so a point set can move by changing its pose.
    """

    kind: str
    size: tuple[float, ...] = ()
    position: np.ndarray = field(default_factory=lambda: np.zeros(3))
    orientation: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 0.0, 1.0]))
    points: np.ndarray | None = None
    name: str = ""

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"unknown shape kind {self.kind!r}; expected one of {KINDS}")
        size = tuple(float(s) for s in self.size)
        if len(size) != SIZE_LENGTH[self.kind]:
            raise ValueError(
                f"{self.kind} takes {SIZE_LENGTH[self.kind]} size values, got {len(size)}"
            )
        if not all(np.isfinite(size)) or any(s <= 0.0 for s in size):
            raise ValueError(f"{self.kind} size {list(size)} must be finite and positive")
        position = np.asarray(self.position, dtype=float).reshape(3)
        if not np.all(np.isfinite(position)):
            raise ValueError(f"position {position.tolist()} is not finite")
        orientation = _unit_quaternion(np.asarray(self.orientation, dtype=float).reshape(4))
        points = None
        if self.kind == "points":
            if self.points is None:
                raise ValueError("a points shape needs points")
            points = np.asarray(self.points, dtype=float).reshape(-1, 3)
            if len(points) == 0 or not np.all(np.isfinite(points)):
                raise ValueError("points must be a non-empty finite N×3 array")
        object.__setattr__(self, "size", size)
        object.__setattr__(self, "position", position)
        object.__setattr__(self, "orientation", orientation)
        object.__setattr__(self, "points", points)

    def moved_to(self, position: np.ndarray) -> Shape:
        """The same shape at another position (obstacle motion is translation only)."""
        return Shape(self.kind, self.size, position, self.orientation, self.points, self.name)

    def rotation(self) -> np.ndarray:
        """3×3 rotation matrix of the shape's frame in the base frame."""
        x, y, z, w = self.orientation
        return np.array(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
            ]
        )

    def bounding_radius(self) -> float:
        """Radius of a sphere about ``position`` that contains the shape."""
        if self.kind == "sphere":
            return self.size[0]
        if self.kind == "box":
            return 0.5 * float(np.linalg.norm(self.size))
        if self.kind == "cylinder":
            return float(np.hypot(self.size[0], 0.5 * self.size[1]))
        return float(np.max(np.linalg.norm(self.points, axis=1)))


def point(position: np.ndarray, name: str = "") -> Shape:
    """A point obstacle: a one-point convex set."""
    position = np.asarray(position, dtype=float)
    return Shape("points", (), position, points=np.zeros((1, 3)), name=name)
