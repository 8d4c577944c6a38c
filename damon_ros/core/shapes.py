"""Obstacle shapes shared by scenarios, the tracker, the robot model and the planner.

One small immutable type so that every layer speaks about obstacles the same way: a
scenario's box, a tracked sphere and a point cloud from the camera all become a
:class:`Shape` in the robot base frame, and the robot model turns it into coal geometry.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

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


# --- geometry of a shape: parts, enclosing vertices, volume, inside test, surface samples ---


def compose(position: np.ndarray, orientation: np.ndarray, part: Shape, name: str = "") -> Shape:
    """``part`` (posed in a parent frame) expressed in the frame that holds the parent at
    ``position``/``orientation``: how a compound obstacle's parts reach the base frame."""
    parent = Rotation.from_quat(_unit_quaternion(np.asarray(orientation, dtype=float)))
    q = (parent * Rotation.from_quat(part.orientation)).as_quat()
    position = np.asarray(position, dtype=float) + parent.apply(part.position)
    return Shape(part.kind, part.size, position, q, part.points, name or part.name)


def grown(shape: Shape, grow) -> Shape:
    """A sphere, box or cylinder grown by ``grow`` (m) as the same kind of shape: a box
    face by face (six values: +x, +y, +z, -x, -y, -z, as `fusion.halfspaces` orders its
    faces; one value: all), the others by the largest value."""
    grow = np.maximum(np.atleast_1d(np.asarray(grow, dtype=float)), 0.0)
    if shape.kind == "box" and grow.size == 1:
        grow = np.full(6, grow[0])
    size = np.asarray(shape.size, dtype=float)
    position = np.asarray(shape.position, dtype=float)
    if shape.kind == "box":  # rows: +x, +y, +z, -x, -y, -z faces (`halfspaces`)
        high, low = grow[:3], grow[3:6]
        size = size + high + low
        position = position + shape.rotation() @ (0.5 * (high - low))
    elif shape.kind == "cylinder":
        size = size + np.array([grow.max(), 2.0 * grow.max()])
    else:
        size = size + grow.max()
    return Shape(shape.kind, tuple(size), position, shape.orientation, name=shape.name)


def enclosing_vertices(shape: Shape, sides: int = 12) -> np.ndarray:
    """Base-frame vertices whose convex hull contains ``shape``.

    A box gives its corners; a cylinder a circumscribed ``sides``-gon prism; a sphere the
    circumscribed prism of its bounding cylinder, both at ``r / cos(pi / sides)`` so every
    flat face of the polygon stays outside the circle. The hull of such vertices over all
    parts is the single convex shape that stands for a compound object where one is needed.
    """
    if shape.kind == "points":
        return shape.position + shape.points @ shape.rotation().T
    if shape.kind == "box":
        half = 0.5 * np.asarray(shape.size)
        signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
        local = signs * half
    else:
        r = shape.size[0]
        h = r if shape.kind == "sphere" else 0.5 * shape.size[1]
        angles = 2.0 * np.pi * np.arange(sides) / sides
        ring = r / np.cos(np.pi / sides) * np.column_stack([np.cos(angles), np.sin(angles)])
        local = np.vstack([np.column_stack([ring, np.full(sides, z)]) for z in (-h, h)])
    return shape.position + local @ shape.rotation().T


def volume(shape: Shape) -> float:
    """Volume in m³ (a point set: the volume of its convex hull, 0 when flat)."""
    if shape.kind == "box":
        return float(np.prod(shape.size))
    if shape.kind == "sphere":
        return 4.0 / 3.0 * np.pi * shape.size[0] ** 3
    if shape.kind == "cylinder":
        return float(np.pi * shape.size[0] ** 2 * shape.size[1])
    from scipy.spatial import ConvexHull, QhullError

    try:
        return float(ConvexHull(shape.points).volume)
    except (QhullError, ValueError):
        return 0.0


def contains(shape: Shape, points: np.ndarray, tolerance: float = 0.0) -> np.ndarray:
    """Whether each base-frame point (N×3) lies in ``shape`` (within ``tolerance`` metres).

    A point set is its convex hull (a flat or single-point set contains only points within
    ``tolerance`` of its vertices' bounding box, which is exact enough for evaluation)."""
    p = (np.asarray(points, dtype=float).reshape(-1, 3) - shape.position) @ shape.rotation()
    if shape.kind == "box":
        return np.all(np.abs(p) <= 0.5 * np.asarray(shape.size) + tolerance, axis=1)
    if shape.kind == "sphere":
        return np.linalg.norm(p, axis=1) <= shape.size[0] + tolerance
    if shape.kind == "cylinder":
        return (np.hypot(p[:, 0], p[:, 1]) <= shape.size[0] + tolerance) & (
            np.abs(p[:, 2]) <= 0.5 * shape.size[1] + tolerance)
    from scipy.spatial import ConvexHull, QhullError

    try:
        hull = ConvexHull(shape.points)
    except (QhullError, ValueError):
        low, high = shape.points.min(axis=0), shape.points.max(axis=0)
        return np.all((p >= low - tolerance) & (p <= high + tolerance), axis=1)
    eq = hull.equations  # outward normals n, offsets b: inside where n·p + b <= 0
    return np.all(p @ eq[:, :3].T + eq[:, 3] <= tolerance, axis=1)


def surface_samples(shape: Shape, spacing: float = 0.01) -> np.ndarray:
    """Base-frame points on the surface of a primitive, about ``spacing`` apart (and its
    vertices/rims): what must lie inside an estimate for it to contain the object."""
    if shape.kind == "box":
        half = 0.5 * np.asarray(shape.size)
        axes = [np.linspace(-h, h, max(2, int(np.ceil(2 * h / spacing)) + 1)) for h in half]
        grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        on_face = np.any(np.isclose(np.abs(grid), half), axis=1)
        local = grid[on_face]
    elif shape.kind == "sphere":
        r = shape.size[0]
        n = max(32, int(4 * np.pi * r * r / spacing**2))
        k = np.arange(n) + 0.5
        polar = np.arccos(1 - 2 * k / n)
        azimuth = np.pi * (1 + 5**0.5) * k
        local = r * np.column_stack([np.cos(azimuth) * np.sin(polar),
                                     np.sin(azimuth) * np.sin(polar), np.cos(polar)])
    elif shape.kind == "cylinder":
        r, h = shape.size[0], 0.5 * shape.size[1]
        m = max(16, int(2 * np.pi * r / spacing))
        a = 2 * np.pi * np.arange(m) / m
        zs = np.linspace(-h, h, max(2, int(2 * h / spacing) + 1))
        side = np.column_stack([np.tile(r * np.cos(a), len(zs)), np.tile(r * np.sin(a), len(zs)),
                                np.repeat(zs, m)])
        rings = [np.column_stack([rho * np.cos(a), rho * np.sin(a), np.full(m, z)])
                 for rho in np.linspace(0, r, max(2, int(r / spacing) + 1)) for z in (-h, h)]
        local = np.vstack([side, *rings])
    else:
        return enclosing_vertices(shape)
    return shape.position + local @ shape.rotation().T
