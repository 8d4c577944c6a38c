"""Scenario files (format 1, ../shared/scenarios/FORMAT.md) as typed, validated objects.

The benchmark, the demo, the mock camera and the tests all read scenarios, including files
this project has never seen, so every field is checked and a bad file is rejected with one
message naming the file, the field and the problem.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from damon_ros.core.resources import public_scenarios_dir
from damon_ros.core.shapes import SIZE_LENGTH, Shape, compose, enclosing_vertices

FORMAT_VERSION = 1
COLORS = ("red", "green", "blue", "yellow")
COLOR_RGB = {
    "red": (210, 35, 35),
    "green": (40, 190, 60),
    "blue": (35, 75, 215),
    "yellow": (225, 205, 30),
}
"""Base albedo of each colour class (the mock camera's paint, the markers' colour).
Lambertian shading only scales RGB, which keeps hue and saturation and lowers value, so a
shaded pixel stays inside its HSV class."""

SHAPES = ("box", "sphere", "cylinder", "compound")
PART_SHAPES = ("box", "sphere", "cylinder")
NAME_PATTERN = re.compile(r"^[A-Za-z0-9_.-]+$")
BASE_FRAMES = ("panda_link0", "fr3_link0")


class ScenarioError(ValueError):
    """A scenario file is invalid; the message reads ``<file>: <field>: <problem>``."""

    def __init__(self, source: str, field: str, problem: str) -> None:
        super().__init__(f"{source}: {field}: {problem}")
        self.source = source
        self.field = field
        self.problem = problem


@dataclass(frozen=True)
class Goal:
    """An end-effector (``panda_hand_tcp``) target, with an optional joint solution."""

    position: np.ndarray
    orientation: np.ndarray
    joints: np.ndarray | None
    position_tolerance: float = 0.01
    orientation_tolerance: float = 0.05


@dataclass(frozen=True)
class Obstacle:
    """A named, coloured obstacle; ``waypoints`` rows are ``[t, x, y, z]`` (None = static).

    ``parts`` are the exact primitives in the base frame at the obstacle's pose: one (the
    shape itself) for box, sphere and cylinder; several for a ``compound`` (an amorphous
    object), whose ``shape`` is then the convex point set enclosing all parts — the one
    convex shape that stands for it where a single shape is needed. Contact scoring and
    rendering use the parts (:meth:`parts_at`), never that hull.
    """

    name: str
    color: str
    shape: Shape
    waypoints: np.ndarray | None = None
    parts: tuple[Shape, ...] = ()

    def __post_init__(self) -> None:
        if not self.parts:
            object.__setattr__(self, "parts", (self.shape,))

    @property
    def is_compound(self) -> bool:
        return len(self.parts) > 1 or self.parts[0] is not self.shape

    @property
    def is_dynamic(self) -> bool:
        return self.waypoints is not None

    def position_at(self, t: float) -> np.ndarray:
        """Piecewise-linear position; before the first and after the last waypoint it holds."""
        if self.waypoints is None:
            return self.shape.position
        times = self.waypoints[:, 0]
        return np.array([np.interp(t, times, self.waypoints[:, 1 + i]) for i in range(3)])

    def velocity_at(self, t: float) -> np.ndarray:
        """Velocity of the piecewise-linear motion (zero outside the waypoints' span)."""
        if self.waypoints is None:
            return np.zeros(3)
        times = self.waypoints[:, 0]
        k = int(np.searchsorted(times, t, side="right"))
        if k == 0 or k >= len(times):
            return np.zeros(3)
        dt = times[k] - times[k - 1]
        return (self.waypoints[k, 1:] - self.waypoints[k - 1, 1:]) / dt

    def shape_at(self, t: float) -> Shape:
        return self.shape if self.waypoints is None else self.shape.moved_to(self.position_at(t))

    def parts_at(self, t: float) -> list[Shape]:
        """The exact primitives at time ``t`` (motion translates the whole object)."""
        if self.waypoints is None:
            return list(self.parts)
        offset = self.position_at(t) - self.shape.position
        return [p.moved_to(p.position + offset) for p in self.parts]


@dataclass(frozen=True)
class Scenario:
    """A start state, a goal and obstacles that may move."""

    name: str
    description: str
    robot: str
    start: np.ndarray
    goal: Goal
    obstacles: tuple[Obstacle, ...]
    time_limit: float
    source: str = "<memory>"

    @property
    def is_dynamic(self) -> bool:
        return any(o.is_dynamic for o in self.obstacles)

    @property
    def family(self) -> str:
        """The letter before the first '-' of the name (A–G for the public set)."""
        return self.name.split("-", 1)[0]

    def obstacles_at(self, t: float) -> list[Shape]:
        """Every obstacle's exact primitives at ``t`` (a compound contributes its parts)."""
        return [p for o in self.obstacles for p in o.parts_at(t)]


class _Reader:
    """Typed access to a YAML mapping that raises :class:`ScenarioError` naming the field."""

    def __init__(self, source: str) -> None:
        self.source = source

    def fail(self, field: str, problem: str) -> ScenarioError:
        return ScenarioError(self.source, field, problem)

    def mapping(self, data: object, field: str) -> dict:
        if not isinstance(data, dict):
            raise self.fail(field, f"must be a mapping, got {type(data).__name__}")
        return data

    def require(self, data: dict, key: str, field: str) -> object:
        if key not in data or data[key] is None:
            raise self.fail(f"{field}.{key}" if field else key, "missing")
        return data[key]

    def number(self, value: object, field: str, positive: bool = False) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.fail(field, f"must be a number, got {value!r}")
        value = float(value)
        if not math.isfinite(value):
            raise self.fail(field, f"must be finite, got {value}")
        if positive and value <= 0.0:
            raise self.fail(field, f"must be positive, got {value}")
        return value

    def vector(self, value: object, field: str, length: int | None, positive: bool = False):
        if not isinstance(value, (list, tuple)):
            raise self.fail(field, f"must be a list of numbers, got {type(value).__name__}")
        if length is not None and len(value) != length:
            raise self.fail(field, f"must have {length} values, got {len(value)}")
        return np.array([self.number(v, f"{field}[{i}]", positive) for i, v in enumerate(value)])

    def quaternion(self, value: object, field: str) -> np.ndarray:
        q = self.vector(value, field, 4)
        norm = float(np.linalg.norm(q))
        if abs(norm - 1.0) > 1e-2:
            raise self.fail(field, f"must be a unit quaternion [x, y, z, w], norm is {norm:.4f}")
        return q / norm


def _joint_limits() -> tuple[np.ndarray, np.ndarray]:
    from damon_ros.core.limits import joint_limits

    limits = joint_limits("panda")
    return limits.lower, limits.upper


def _joints(r: _Reader, value: object, field: str) -> np.ndarray:
    q = r.vector(value, field, 7)
    lower, upper = _joint_limits()
    for i in range(7):
        if not lower[i] - 1e-6 <= q[i] <= upper[i] + 1e-6:
            raise r.fail(
                f"{field}[{i}]", f"{q[i]} is outside joint {i + 1}'s limits "
                f"[{lower[i]:.4f}, {upper[i]:.4f}]"
            )
    return q


def _goal(r: _Reader, data: object) -> Goal:
    data = r.mapping(data, "goal")
    pose = r.mapping(r.require(data, "pose", "goal"), "goal.pose")
    position = r.vector(r.require(pose, "position", "goal.pose"), "goal.pose.position", 3)
    orientation = r.quaternion(
        r.require(pose, "orientation", "goal.pose"), "goal.pose.orientation"
    )
    joints = data.get("joints")
    return Goal(
        position=position,
        orientation=orientation,
        joints=None if joints is None else _joints(r, joints, "goal.joints"),
        position_tolerance=r.number(
            data.get("position_tolerance", 0.01), "goal.position_tolerance", positive=True
        ),
        orientation_tolerance=r.number(
            data.get("orientation_tolerance", 0.05), "goal.orientation_tolerance", positive=True
        ),
    )


def _waypoints(r: _Reader, motion: object, field: str) -> np.ndarray:
    motion = r.mapping(motion, field)
    kind = r.require(motion, "type", field)
    if kind != "waypoints":
        raise r.fail(f"{field}.type", f"unknown motion type {kind!r}; expected 'waypoints'")
    rows = r.require(motion, "waypoints", field)
    if not isinstance(rows, list) or not rows:
        raise r.fail(f"{field}.waypoints", "must be a non-empty list of [t, x, y, z]")
    table = np.array([r.vector(row, f"{field}.waypoints[{i}]", 4) for i, row in enumerate(rows)])
    if np.any(np.diff(table[:, 0]) <= 0.0):
        raise r.fail(f"{field}.waypoints", "times must be strictly increasing")
    return table


def _obstacle(r: _Reader, data: object, index: int) -> Obstacle:
    field = f"obstacles[{index}]"
    data = r.mapping(data, field)
    name = r.require(data, "name", field)
    if not isinstance(name, str) or not name:
        raise r.fail(f"{field}.name", "must be a non-empty string")
    kind = r.require(data, "shape", field)
    if kind not in SHAPES:
        raise r.fail(f"{field}.shape", f"unknown shape {kind!r}; expected one of {SHAPES}")
    if kind != "compound":
        size = r.vector(r.require(data, "size", field), f"{field}.size", SIZE_LENGTH[kind],
                        True)
    elif data.get("size") is not None:
        raise r.fail(f"{field}.size", "must be absent for a compound (its parts have sizes)")
    color = r.require(data, "color", field)
    if color not in COLORS:
        raise r.fail(f"{field}.color", f"unknown color {color!r}; expected one of {COLORS}")
    pose = r.mapping(r.require(data, "pose", field), f"{field}.pose")
    position = r.vector(r.require(pose, "position", f"{field}.pose"), f"{field}.pose.position", 3)
    orientation = r.quaternion(
        r.require(pose, "orientation", f"{field}.pose"), f"{field}.pose.orientation"
    )
    motion = data.get("motion")
    waypoints = None if motion is None else _waypoints(r, motion, f"{field}.motion")
    if kind == "compound":
        parts = tuple(compose(position, orientation, part, name)
                      for part in _parts(r, data, field))
        hull = np.vstack([enclosing_vertices(p) for p in parts]) - position
        shape = Shape("points", (), position, points=hull, name=name)
        return Obstacle(name=name, color=color, shape=shape, waypoints=waypoints, parts=parts)
    shape = Shape(kind, tuple(size), position, orientation, name=name)
    return Obstacle(name=name, color=color, shape=shape, waypoints=waypoints)


def _parts(r: _Reader, data: dict, field: str) -> list[Shape]:
    """The primitives of a compound, each posed in the obstacle's frame."""
    parts = r.require(data, "parts", field)
    if not isinstance(parts, list) or not parts:
        raise r.fail(f"{field}.parts", "must be a non-empty list of box/sphere/cylinder parts")
    out = []
    for i, part in enumerate(parts):
        pf = f"{field}.parts[{i}]"
        part = r.mapping(part, pf)
        kind = r.require(part, "shape", pf)
        if kind not in PART_SHAPES:
            raise r.fail(f"{pf}.shape", f"unknown part shape {kind!r}; expected one of "
                         f"{PART_SHAPES}")
        size = r.vector(r.require(part, "size", pf), f"{pf}.size", SIZE_LENGTH[kind], True)
        position = r.vector(r.require(part, "position", pf), f"{pf}.position", 3)
        orientation = r.quaternion(r.require(part, "orientation", pf), f"{pf}.orientation")
        out.append(Shape(kind, tuple(size), position, orientation))
    return out


def parse_scenario(data: object, source: str = "<memory>") -> Scenario:
    """Validate a scenario mapping (already parsed YAML) into a :class:`Scenario`."""
    r = _Reader(source)
    data = r.mapping(data, "<root>")
    version = r.require(data, "format", "")
    if version != FORMAT_VERSION:
        raise r.fail("format", f"unsupported format {version!r}; this reader knows 1")
    name = r.require(data, "name", "")
    if not isinstance(name, str) or not NAME_PATTERN.match(name):
        raise r.fail("name", f"{name!r} must match [A-Za-z0-9_.-]+")
    robot = data.get("robot", "panda")
    if robot != "panda":
        raise r.fail("robot", f"unknown robot {robot!r}; only 'panda' is supported")
    start = r.mapping(r.require(data, "start", ""), "start")
    obstacles = data.get("obstacles") or []
    if not isinstance(obstacles, list):
        raise r.fail("obstacles", "must be a list")
    parsed = tuple(_obstacle(r, o, i) for i, o in enumerate(obstacles))
    names = [o.name for o in parsed]
    if len(set(names)) != len(names):
        raise r.fail("obstacles", f"obstacle names must be unique, got {names}")
    return Scenario(
        name=name,
        description=str(data.get("description", "")),
        robot=robot,
        start=_joints(r, r.require(start, "joints", "start"), "start.joints"),
        goal=_goal(r, r.require(data, "goal", "")),
        obstacles=parsed,
        time_limit=r.number(r.require(data, "time_limit", ""), "time_limit", positive=True),
        source=source,
    )


def load_scenario(path: str | os.PathLike) -> Scenario:
    """Read and validate one scenario file."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ScenarioError(str(path), "<file>", f"cannot be read: {exc.strerror}") from exc
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ScenarioError(str(path), "<file>", f"is not valid YAML: {exc}") from exc
    return parse_scenario(data, str(path))


def scenario_files(paths: Iterable[str | os.PathLike]) -> list[Path]:
    """Expand directories into their ``*.yaml`` files, sorted; files pass through."""
    files: list[Path] = []
    for p in map(Path, paths):
        files.extend(sorted(p.glob("*.yaml")) if p.is_dir() else [p])
    return files




def load_public_scenarios(names: Sequence[str] | None = None) -> list[Scenario]:
    """All public scenarios (or those named), for tests, the demo and the benchmark."""
    files = scenario_files([public_scenarios_dir()])
    scenarios = [load_scenario(f) for f in files]
    return scenarios if names is None else [s for s in scenarios if s.name in names]
