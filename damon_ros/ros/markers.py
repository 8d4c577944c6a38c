"""Obstacle shapes <-> ``visualization_msgs/Marker``, and the table of obstacles a node sees.

The tracker publishes its obstacles as markers on ``/damon/obstacles``, the mock camera its
ground truth on ``/damon/sim/obstacles``, and the planner turns those markers back into
:class:`damon_ros.core.shapes.Shape` objects it certifies paths against. One module does both
directions so that the mapping cannot drift apart:

=========  ==========================  ==================================================
Shape      Marker type                 scale / points
=========  ==========================  ==================================================
sphere     SPHERE                      x = y = z = 2 r
box        CUBE                        full extents, oriented by the pose
cylinder   CYLINDER                    x = y = 2 r, z = length (along the local z axis)
points     POINTS                      points in the marker's frame (the hull is the shape)
=========  ==========================  ==================================================

Reading is strict because a planner that trusts a broken marker can drive the arm into an
obstacle: NaN anywhere, a size <= 0 or > ``MAX_SIZE_M``, a quaternion that is not unit
length, an unknown marker type or a wrong frame raise ``ValueError`` naming the marker and
the problem. Where a marker is more general than a shape, it is read *conservatively*: a
SPHERE with unequal scales (an ellipsoid) becomes the sphere of its largest semi-axis, a
CYLINDER with an elliptic section the cylinder of its largest radius, and a SPHERE_LIST the
hull of a cube around every sphere.

``ObstacleTable`` applies a stream of marker arrays with rviz's semantics (ADD/MODIFY
replace the obstacle with that ``(ns, id)``, DELETE removes it, DELETEALL removes all of
them or those of one ``ns``; ``lifetime`` counted from the receive time, 0 = forever) and
estimates each obstacle's velocity from successive positions, since a marker has no field
for it. One departure from rviz, for safety: an obstacle outlives its lifetime for as long
as no newer marker array has arrived. Silence is a gap in perception (a stalled tracker, a
busy executor), not evidence that the obstacle left; forgetting it there let the planner
route the arm through a box it had seen 0.5 s before (camera demo, D-001). The gap itself
is the perception timeout's to handle (`last_update`). No rclpy here: only message classes,
so the planner core can use it untouched.

What the cameras saw of an obstacle: the tracker adds, per obstacle ``(ns, id)``, a POINTS
marker ``(ns + SEEN_SUFFIX, id)`` holding its visible surface; the rest of the obstacle is
the hidden extent no camera saw. ``ObstacleTable`` keeps those apart (they are not
obstacles; `seen_parts`), so that a refusal can tell which it is caused by.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from builtin_interfaces.msg import Duration, Time
from geometry_msgs.msg import Point
from visualization_msgs.msg import Marker

from damon_ros.core.scenario import COLOR_RGB
from damon_ros.core.shapes import Shape
from damon_ros.perception.velocity import VelocityWindow
from damon_ros.ros.problems import ProblemError, problem_of
from damon_ros.ros.stamps import stamp_seconds, to_duration, to_stamp

MAX_SIZE_M = 3.0
"""Largest size accepted on any axis: nothing that large fits in a Panda's workspace, so a
bigger value is a unit error (mm for m) or garbage, not an obstacle."""

SEEN_SUFFIX = "/seen"
"""Namespace suffix of the markers that show what the cameras saw of an obstacle."""

QUATERNION_TOLERANCE = 1e-3
"""A marker quaternion must have a norm within this of 1 (rviz rejects worse ones too)."""

POINT_WIDTH_M = 0.01
"""Display width of POINTS markers written by `shape_to_marker` (not part of the shape)."""

INT32_MAX = 2**31 - 1

TYPE_NAMES = {
    Marker.ARROW: "ARROW", Marker.CUBE: "CUBE", Marker.SPHERE: "SPHERE",
    Marker.CYLINDER: "CYLINDER", Marker.LINE_STRIP: "LINE_STRIP", Marker.LINE_LIST: "LINE_LIST",
    Marker.CUBE_LIST: "CUBE_LIST", Marker.SPHERE_LIST: "SPHERE_LIST", Marker.POINTS: "POINTS",
    Marker.TEXT_VIEW_FACING: "TEXT_VIEW_FACING", Marker.MESH_RESOURCE: "MESH_RESOURCE",
    Marker.TRIANGLE_LIST: "TRIANGLE_LIST",
}
SHAPE_TYPES = (Marker.SPHERE, Marker.CUBE, Marker.CYLINDER, Marker.POINTS, Marker.SPHERE_LIST)


# --- Shape -> Marker ---------------------------------------------------------------------------


def class_rgba(color: str, alpha: float = 0.8) -> tuple[float, float, float, float]:
    """Display colour of an HSV colour class (the mock camera's albedo); grey if unknown."""
    r, g, b = COLOR_RGB.get(color, (128, 128, 128))
    return (r / 255.0, g / 255.0, b / 255.0, float(alpha))


def _check_header(ns: str, id: int, frame_id: str) -> None:
    if not isinstance(ns, str):
        raise ProblemError(f"marker ns must be a string, got {type(ns).__name__}",
                           "marker.ns_type")
    if isinstance(id, bool) or not isinstance(id, (int, np.integer)) or not (
        -INT32_MAX - 1 <= id <= INT32_MAX
    ):
        raise ProblemError(f"marker id {id!r} must be an int32", "marker.id_range")
    if not isinstance(frame_id, str) or not frame_id:
        raise ProblemError(f"marker frame_id {frame_id!r} must be a non-empty string",
                           "marker.frame_empty")


def _scale(shape: Shape) -> tuple[float, float, float]:
    if shape.kind == "sphere":
        return (2.0 * shape.size[0],) * 3
    if shape.kind == "box":
        return tuple(shape.size)
    if shape.kind == "cylinder":
        return (2.0 * shape.size[0], 2.0 * shape.size[0], shape.size[1])
    return (POINT_WIDTH_M, POINT_WIDTH_M, 0.0)


def _points_extent(points: np.ndarray) -> float:
    return float(np.max(points.max(axis=0) - points.min(axis=0)))


class MarkerRecord(NamedTuple):
    """A marker's values before any message object is built: what `to_marker` makes a
    ``Marker`` of, and `cdr.marker_array_bytes` serialises directly (the tracker's 30 Hz
    arrays, where building the message objects cost more than tracking a ball). Stamps and
    durations are (sec, nanosec); ``points`` N x 3 or None."""

    ns: str
    id: int
    type: int
    action: int
    frame_id: str
    stamp: tuple[int, int]
    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    orientation: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)
    scale: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rgba: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    lifetime: tuple[int, int] = (0, 0)
    points: np.ndarray | None = None
    text: str = ""


def _stamp_of(stamp: Time | float) -> tuple[int, int]:
    t = stamp if isinstance(stamp, Time) else to_stamp(float(stamp))
    return (t.sec, t.nanosec)


def shape_record(
    shape: Shape,
    ns: str,
    id: int,
    frame_id: str,
    stamp: Time | float,
    lifetime_s: float,
    rgba: Sequence[float],
) -> MarkerRecord:
    """An ADD marker drawing ``shape`` (see the module table); ``text`` carries its name.

    ``stamp`` is a ``Time`` message or seconds; ``lifetime_s`` 0 means "until deleted".
    A shape this module would refuse to read back (size > ``MAX_SIZE_M``) is refused here.
    """
    if not isinstance(shape, Shape):
        raise ValueError(f"shape must be a damon_ros.core.shapes.Shape, got {type(shape).__name__}")
    _check_header(ns, id, frame_id)
    color = np.asarray(rgba, dtype=float).reshape(-1)
    if color.shape != (4,) or not np.all((color >= 0.0) & (color <= 1.0)):
        raise ValueError(f"rgba {list(rgba)} must be 4 values in [0, 1]")
    scale = _scale(shape)
    if shape.kind == "points":
        extent = _points_extent(shape.points)
        if extent > MAX_SIZE_M:
            raise ValueError(f"points shape spans {extent:.3f} m, more than {MAX_SIZE_M} m")
    elif max(scale) > MAX_SIZE_M:
        raise ValueError(f"{shape.kind} of scale {list(scale)} exceeds {MAX_SIZE_M} m")
    lifetime = to_duration(float(lifetime_s), "lifetime_s")
    kind = {"sphere": Marker.SPHERE, "box": Marker.CUBE, "cylinder": Marker.CYLINDER,
            "points": Marker.POINTS}[shape.kind]
    return MarkerRecord(
        ns, int(id), kind, Marker.ADD, frame_id, _stamp_of(stamp),
        tuple(float(v) for v in shape.position), tuple(float(v) for v in shape.orientation),
        tuple(float(v) for v in scale), tuple(float(v) for v in color),
        (lifetime.sec, lifetime.nanosec),
        np.asarray(shape.points, dtype=float) if shape.kind == "points" else None, shape.name)


def to_marker(record: MarkerRecord) -> Marker:
    """The ``Marker`` message of a record."""
    r = record
    marker = Marker(ns=r.ns, id=r.id, type=r.type, action=r.action, text=r.text,
                    frame_locked=False, lifetime=Duration(sec=r.lifetime[0],
                                                          nanosec=r.lifetime[1]))
    marker.header.frame_id = r.frame_id
    marker.header.stamp = Time(sec=r.stamp[0], nanosec=r.stamp[1])
    marker.pose.position.x, marker.pose.position.y, marker.pose.position.z = r.position
    o = marker.pose.orientation
    o.x, o.y, o.z, o.w = r.orientation
    marker.scale.x, marker.scale.y, marker.scale.z = r.scale
    c = marker.color
    c.r, c.g, c.b, c.a = r.rgba
    if r.points is not None:
        marker.points = [Point(x=float(x), y=float(y), z=float(z)) for x, y, z in r.points]
    return marker


def shape_to_marker(shape: Shape, ns: str, id: int, frame_id: str, stamp: Time | float,
                    lifetime_s: float, rgba: Sequence[float]) -> Marker:
    """`shape_record` as a ``Marker`` message."""
    return to_marker(shape_record(shape, ns, id, frame_id, stamp, lifetime_s, rgba))


def delete_record(ns: str, id: int, frame_id: str, stamp: Time | float) -> MarkerRecord:
    """A DELETE marker: the obstacle ``(ns, id)`` is gone."""
    _check_header(ns, id, frame_id)
    return MarkerRecord(ns, int(id), Marker.ARROW, Marker.DELETE, frame_id, _stamp_of(stamp))


def delete_marker(ns: str, id: int, frame_id: str, stamp: Time | float) -> Marker:
    """`delete_record` as a ``Marker`` message."""
    return to_marker(delete_record(ns, id, frame_id, stamp))


def delete_all_marker(frame_id: str, stamp: Time | float, ns: str = "") -> Marker:
    """A DELETEALL marker: every obstacle, or every obstacle of ``ns`` when it is given."""
    _check_header(ns, 0, frame_id)
    marker = Marker(ns=ns, id=0, action=Marker.DELETEALL)
    marker.header.frame_id = frame_id
    marker.header.stamp = stamp if isinstance(stamp, Time) else to_stamp(float(stamp))
    return marker


# --- Marker -> Shape ---------------------------------------------------------------------------


def _label(marker: Marker) -> str:
    return f"marker {marker.ns!r}/{marker.id}"


def _pose(marker: Marker) -> tuple[np.ndarray, np.ndarray]:
    p, o = marker.pose.position, marker.pose.orientation
    position = np.array([p.x, p.y, p.z], dtype=float)
    if not np.all(np.isfinite(position)):
        raise ProblemError(f"{_label(marker)}: position {position.tolist()} is not finite",
                           "marker.position_not_finite")
    q = np.array([o.x, o.y, o.z, o.w], dtype=float)
    norm = float(np.linalg.norm(q))
    if not math.isfinite(norm) or abs(norm - 1.0) > QUATERNION_TOLERANCE:
        raise ProblemError(
            f"{_label(marker)}: orientation {q.tolist()} is not a unit quaternion [x, y, z, w] "
            f"(norm {norm:.6g})", "marker.orientation_not_unit"
        )
    return position, q / norm


def _sizes(marker: Marker, values: Sequence[float], what: str) -> np.ndarray:
    s = np.asarray(values, dtype=float)
    if not np.all(np.isfinite(s)):
        raise ProblemError(f"{_label(marker)}: {what} {s.tolist()} is not finite",
                           "marker.size_not_finite")
    if np.any(s <= 0.0):
        raise ProblemError(f"{_label(marker)}: {what} {s.tolist()} must be > 0 m",
                           "marker.size_not_positive")
    if np.any(s > MAX_SIZE_M):
        raise ProblemError(
            f"{_label(marker)}: {what} {s.tolist()} must be <= {MAX_SIZE_M} m (a unit error, "
            "mm for m?)", "marker.size_too_large")
    return s


def _marker_points(marker: Marker) -> np.ndarray:
    if not marker.points:
        raise ProblemError(f"{_label(marker)}: a {TYPE_NAMES[marker.type]} marker needs "
                           "points", "marker.points_missing")
    pts = np.array([[p.x, p.y, p.z] for p in marker.points], dtype=float)
    if not np.all(np.isfinite(pts)):
        raise ProblemError(f"{_label(marker)}: points are not all finite",
                           "marker.points_not_finite")
    extent = _points_extent(pts)
    if extent > MAX_SIZE_M:
        raise ProblemError(f"{_label(marker)}: points span {extent:.3f} m, more than "
                           f"{MAX_SIZE_M} m", "marker.points_too_large")
    return pts


_CUBE_SIGNS = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)


def marker_to_shape(marker: Marker, frame_id: str | None = None) -> Shape:
    """The obstacle an ADD marker describes, in the marker's frame (conservatively; see top).

    ``frame_id``, when given, is the frame the caller works in: a marker in another frame is
    refused rather than silently misplaced (this package does no TF lookups).
    """
    kind = marker.type
    if kind not in SHAPE_TYPES:
        name = TYPE_NAMES.get(kind, "unknown")
        raise ProblemError(
            f"{_label(marker)}: type {kind} ({name}) is not an obstacle shape; expected "
            "SPHERE, CUBE, CYLINDER, POINTS or SPHERE_LIST", "marker.type_unknown"
        )
    if frame_id is not None and marker.header.frame_id != frame_id:
        raise ProblemError(
            f"{_label(marker)}: frame {marker.header.frame_id!r} is not {frame_id!r}",
            "marker.frame_other"
        )
    position, q = _pose(marker)
    scale = (marker.scale.x, marker.scale.y, marker.scale.z)
    name = marker.text
    if kind == Marker.SPHERE:
        radius = 0.5 * float(_sizes(marker, scale, "scale").max())
        return Shape("sphere", (radius,), position, q, name=name)
    if kind == Marker.CUBE:
        return Shape("box", tuple(_sizes(marker, scale, "scale")), position, q, name=name)
    if kind == Marker.CYLINDER:
        s = _sizes(marker, scale, "scale")
        return Shape("cylinder", (0.5 * float(max(s[0], s[1])), float(s[2])), position, q,
                     name=name)
    points = _marker_points(marker)
    if kind == Marker.SPHERE_LIST:
        radius = 0.5 * float(_sizes(marker, scale[:1], "scale.x (sphere diameter)")[0])
        points = (points[:, None, :] + radius * _CUBE_SIGNS[None, :, :]).reshape(-1, 3)
    return Shape("points", (), position, q, points=points, name=name)


# --- the table of current obstacles ----------------------------------------------------------


@dataclass(frozen=True, eq=False)
class TrackedObstacle:
    """One obstacle as last received: shape, estimated velocity (m/s, base frame), times.

    ``stamp`` is the marker's header stamp (when the obstacle was *seen*), ``received`` the
    caller's clock when it arrived, ``expires`` when it will be forgotten (inf: never).
    """

    ns: str
    id: int
    shape: Shape
    velocity: np.ndarray
    stamp: float
    received: float
    expires: float

    def shape_at(self, t: float) -> Shape:
        """The shape moved along its velocity to time ``t`` (same clock as ``stamp``)."""
        return self.shape.moved_to(self.shape.position + self.velocity * (t - self.stamp))


class _Entry:
    """Mutable state of one ``(ns, id)``: the latest obstacle and its recent positions."""

    def __init__(self, window_s: float) -> None:
        self.motion = VelocityWindow(window_s)
        self.obstacle: TrackedObstacle | None = None

    def velocity(self, stamp: float, position: np.ndarray) -> np.ndarray:
        """Least-squares slope of the positions seen in the last window (zero below two)."""
        velocity = self.motion.add(stamp, position)
        return np.zeros(3) if velocity is None else velocity


class ObstacleTable:
    """Current obstacles keyed by ``(ns, id)``, kept up to date from marker arrays.

    ``frame_id``: markers in any other frame are refused (None accepts any frame).
    ``velocity_window_s``: positions within this span (by marker stamp) give the velocity.
    Times passed as ``now`` are the caller's receive clock (e.g. ROS time in seconds); a
    marker with a zero stamp is taken as stamped at ``now``.
    """

    def __init__(self, frame_id: str | None = "panda_link0", velocity_window_s: float = 0.3):
        if not (math.isfinite(velocity_window_s) and velocity_window_s > 0.0):
            raise ValueError(f"velocity_window_s {velocity_window_s} must be a positive number")
        self.frame_id = frame_id
        self.velocity_window_s = float(velocity_window_s)
        self._entries: dict[tuple[str, int], _Entry] = {}
        self._seen: dict[tuple[str, int], Shape] = {}  # keyed by the obstacle's (ns, id)
        self.last_update = -math.inf  # receive time of the last array that said anything valid

    def __len__(self) -> int:
        return sum(1 for e in self._entries.values() if e.obstacle is not None)

    def apply(self, markers: Iterable[Marker], now: float) -> list[str]:
        """Apply markers in order; return one message per marker that was refused.

        A refused marker changes nothing (the previous obstacle with its key stays until it
        expires), so one bad marker cannot erase or corrupt the others of its array.
        """
        if not math.isfinite(now):
            raise ValueError(f"now {now} must be a finite time")
        errors = []
        markers = list(markers)
        for marker in markers:
            try:
                self._apply_one(marker, float(now))
            except ValueError as exc:
                errors.append(problem_of(exc, "marker.invalid"))
        if len(errors) < len(markers) or not markers:  # an empty array says "nothing there"
            self.last_update = float(now)
        return errors

    def _apply_one(self, marker: Marker, now: float) -> None:
        key = (marker.ns, int(marker.id))
        if marker.ns.endswith(SEEN_SUFFIX):
            self._apply_seen(marker, (marker.ns.removesuffix(SEEN_SUFFIX), key[1]))
            return
        if marker.action == Marker.DELETEALL:
            self._entries = {k: e for k, e in self._entries.items()
                             if marker.ns and k[0] != marker.ns}
        elif marker.action == Marker.DELETE:
            self._entries.pop(key, None)
        elif marker.action == Marker.ADD:  # MODIFY has the same value (0) in ROS 2
            self._add(key, marker, now)
        else:
            raise ProblemError(f"{_label(marker)}: unknown action {marker.action}",
                               "marker.action_unknown")

    def _apply_seen(self, marker: Marker, key: tuple[str, int]) -> None:
        """A visible-surface marker: kept beside its obstacle, never an obstacle itself."""
        if marker.action == Marker.ADD:
            self._seen[key] = marker_to_shape(marker, self.frame_id)
        elif marker.action in (Marker.DELETE, Marker.DELETEALL):
            self._seen.pop(key, None)
        else:
            raise ProblemError(f"{_label(marker)}: unknown action {marker.action}",
                               "marker.action_unknown")

    def seen_parts(self, now: float) -> dict[tuple[str, int], Shape]:
        """The visible surface of each live obstacle whose tracker published one."""
        live = {(o.ns, o.id) for o in self.obstacles(now)}
        self._seen = {k: v for k, v in self._seen.items() if k in live}
        return dict(self._seen)

    def _add(self, key: tuple[str, int], marker: Marker, now: float) -> None:
        shape = marker_to_shape(marker, self.frame_id)
        lifetime = stamp_seconds(marker.lifetime)
        if not (math.isfinite(lifetime) and lifetime >= 0.0):
            raise ValueError(f"{_label(marker)}: lifetime {lifetime} s must be >= 0")
        stamp = stamp_seconds(marker.header.stamp) or now
        entry = self._entries.setdefault(key, _Entry(self.velocity_window_s))
        velocity = entry.velocity(stamp, shape.position)
        expires = now + lifetime if lifetime > 0.0 else math.inf
        entry.obstacle = TrackedObstacle(key[0], key[1], shape, velocity, stamp, now, expires)

    def obstacles(self, now: float) -> list[TrackedObstacle]:
        """Live obstacles at ``now``, sorted by key. An expired one is dropped for good, but
        only once a newer array arrived without it (see the module doc)."""
        self._entries = {k: e for k, e in self._entries.items() if e.obstacle is not None and (
            e.obstacle.expires > now or e.obstacle.received >= self.last_update)}
        return [self._entries[k].obstacle for k in sorted(self._entries)]

    def shapes(self, now: float) -> list[Shape]:
        """The live obstacles' shapes as last seen."""
        return [o.shape for o in self.obstacles(now)]
