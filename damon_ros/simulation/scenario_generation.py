"""Fresh scenario files like the public families, from a seed.

Benchmarks and the runtime model must be judged on scenes nobody tuned for, so this writes
new format-1 scenarios (../shared/scenarios/FORMAT.md) family by family:

===  ==========================================  =======================================
A    one static box                               B  one static sphere
C    static box and sphere                        D  static box and a sweeping sphere
E    two static boxes and a sweeping sphere       F  one static tilted cylinder
G    cylinder and a diving sphere
===  ==========================================  =======================================

A task moves the hand across the front of the robot, from one side to the other, past the
obstacles placed between; movers cross that region at a speed drawn from a band. Every
scenario is checked before it is kept: start and goal are IK solutions out of self-contact
and at least ``min_clearance`` from every obstacle *at every instant* (exact meshes), and
the file parses with the project's own reader. The same seed writes the same files.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from damon_ros.core.limits import READY
from damon_ros.core.scenario import Scenario, parse_scenario
from damon_ros.core.shapes import Shape

FAMILIES = {
    "A": "one static box",
    "B": "one static sphere",
    "C": "static box and sphere",
    "D": "static box and a sweeping sphere",
    "E": "two static boxes and a sweeping sphere",
    "F": "one static tilted cylinder",
    "G": "cylinder and a diving sphere",
}


@dataclass(frozen=True)
class GenerationConfig:
    """Ranges the scenes are drawn from (SI units)."""

    speed: tuple[float, float] = (0.15, 0.35)  # m/s of the movers
    min_clearance: float = 0.05  # m, start and goal from every obstacle at every instant
    time_limit: float = 30.0
    attempts: int = 200  # draws per scenario before giving up (with a clear error)


def _down_orientation(rng: np.random.Generator) -> list[float]:
    """The hand pointing down, yawed a little: [x, y, z, w] of a half turn about a
    horizontal axis."""
    yaw = rng.uniform(-0.35, 0.1)
    return [math.cos(yaw), math.sin(yaw), 0.0, 0.0]


def _yaw_quaternion(yaw: float) -> list[float]:
    return [0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)]


def _box(name: str, color: str, rng: np.random.Generator, centre: np.ndarray) -> dict:
    size = [rng.uniform(0.06, 0.14), rng.uniform(0.14, 0.28), rng.uniform(0.15, 0.33)]
    return {"name": name, "shape": "box", "size": _round(size), "color": color,
            "pose": {"position": _round(centre),
                     "orientation": _round(_yaw_quaternion(rng.uniform(-0.4, 0.4)))}}


def _sphere(name: str, color: str, rng: np.random.Generator, centre: np.ndarray) -> dict:
    return {"name": name, "shape": "sphere", "size": _round([rng.uniform(0.04, 0.08)]),
            "color": color, "pose": {"position": _round(centre),
                                     "orientation": [0.0, 0.0, 0.0, 1.0]}}


def _cylinder(name: str, color: str, rng: np.random.Generator, centre: np.ndarray) -> dict:
    tilt = rng.uniform(0.3, 1.3) * rng.choice([-1.0, 1.0])
    return {"name": name, "shape": "cylinder",
            "size": _round([rng.uniform(0.04, 0.06), rng.uniform(0.16, 0.25)]), "color": color,
            "pose": {"position": _round(centre),
                     "orientation": _round([math.sin(tilt / 2), 0.0, 0.0, math.cos(tilt / 2)])}}


def _mover(sphere: dict, start: np.ndarray, end: np.ndarray, t0: float,
           rng: np.random.Generator, config: GenerationConfig) -> dict:
    """A sphere that waits ``t0`` s at ``start`` then moves in a straight line to ``end`` at
    a speed from the band, and stays there."""
    speed = rng.uniform(*config.speed)
    t1 = t0 + float(np.linalg.norm(end - start)) / speed
    sphere["pose"]["position"] = _round(start)
    sphere["motion"] = {"type": "waypoints", "waypoints": [
        _round([0.0, *start]), _round([t0, *start]), _round([t1, *end])]}
    return sphere


def _sweeping(rng: np.random.Generator, side: float, config: GenerationConfig,
              color: str) -> dict:
    """Across the front of the robot, from the goal's side to the start's (or back)."""
    x = rng.uniform(0.45, 0.75)
    start = np.array([x, -0.72 * side, rng.uniform(0.35, 0.70)])
    end = np.array([x + rng.uniform(-0.15, 0.15), 0.72 * side, rng.uniform(0.30, 0.65)])
    ball = _sphere("ball", color, rng, start)
    return _mover(ball, start, end, rng.uniform(0.3, 2.5), rng, config)


def _diving(rng: np.random.Generator, middle: np.ndarray, config: GenerationConfig,
            color: str) -> dict:
    """From above and behind the work area down through the middle of the hand's way."""
    start = np.array([rng.uniform(0.6, 0.75), middle[1] + rng.uniform(0.2, 0.4),
                      rng.uniform(0.6, 0.8)])
    end = np.array([rng.uniform(0.35, 0.5), middle[1] - rng.uniform(0.1, 0.25),
                    rng.uniform(0.3, 0.42)])
    ball = _sphere("ball2", color, rng, start)
    return _mover(ball, start, end, rng.uniform(0.3, 1.5), rng, config)


def _obstacles(family: str, rng: np.random.Generator, middle: np.ndarray, side: float,
               config: GenerationConfig) -> list[dict]:
    def near(dx: tuple[float, float] = (0.05, 0.2), dz: tuple[float, float] = (-0.1, 0.1)):
        return middle + [rng.uniform(*dx), rng.uniform(-0.1, 0.1), rng.uniform(*dz)]

    if family == "A":
        return [_box("block", "red", rng, near())]
    if family == "B":
        return [_sphere("ball", "green", rng, near())]
    if family == "C":
        return [_box("block", "red", rng, near()), _sphere("ball", "green", rng,
                                                          near((0.0, 0.15), (0.05, 0.25)))]
    if family == "D":
        return [_box("block", "red", rng, near()), _sweeping(rng, side, config, "green")]
    if family == "E":
        floor_box = _box("block2", "yellow", rng, near((0.05, 0.2), (-0.4, -0.25)))
        return [_box("block", "red", rng, near((0.15, 0.3))), floor_box,
                _sweeping(rng, side, config, "green")]
    if family == "F":
        return [_cylinder("pole", "blue", rng, near())]
    if family == "G":
        return [_cylinder("pole", "blue", rng, near((0.0, 0.15), (-0.2, 0.0))),
                _diving(rng, middle, config, "yellow")]
    raise ValueError(f"unknown family {family!r}; choose from {''.join(FAMILIES)}")


def _round(values, digits: int = 4) -> list[float]:
    return [round(float(v), digits) for v in values]


@dataclass(frozen=True)
class Generated:
    """A generated scenario: the document to write and the scenario it parses to."""

    data: dict
    scenario: Scenario

    def yaml(self) -> str:
        import yaml

        return yaml.safe_dump(self.data, sort_keys=False, default_flow_style=None)


class ScenarioGenerator:
    """Draws valid scenarios; ``robot`` must be the exact-mesh model (``Robot("mesh")``)."""

    def __init__(self, robot, config: GenerationConfig | None = None) -> None:
        self.robot = robot
        self.config = config or GenerationConfig()

    def generate(self, family: str, name: str, rng: np.random.Generator) -> Generated:
        """One scenario of ``family``; raises RuntimeError if no valid draw was found."""
        if family not in FAMILIES:
            raise ValueError(f"unknown family {family!r}; choose from {''.join(FAMILIES)}")
        for _ in range(self.config.attempts):
            data = self._draw(family, name, rng)
            if data is not None:
                return Generated(data, parse_scenario(data, f"<generated {name}>"))
        raise RuntimeError(f"{name}: no valid {family} scenario in {self.config.attempts} draws")

    def _draw(self, family: str, name: str, rng: np.random.Generator) -> dict | None:
        side = float(rng.choice([-1.0, 1.0]))
        a = np.array([rng.uniform(0.30, 0.55), side * rng.uniform(0.20, 0.42),
                      rng.uniform(0.25, 0.50)])
        b = np.array([rng.uniform(0.30, 0.60), -side * rng.uniform(0.20, 0.42),
                      rng.uniform(0.25, 0.50)])
        obstacles = _obstacles(family, rng, (a + b) / 2, side, self.config)
        draft = parse_scenario(self._document(family, name, READY, b, [1, 0, 0, 0],
                                              None, obstacles), "<draft>")
        start = self._clear_ik(a, _down_orientation(rng), draft, rng)
        if start is None:
            return None
        orientation = _down_orientation(rng)
        goal = self._clear_ik(b, orientation, draft, rng, q_near=start)
        if goal is None:
            return None
        return self._document(family, name, start, b, orientation, goal, obstacles)

    def _clear_ik(self, position, orientation, draft: Scenario, rng,
                  q_near: np.ndarray | None = None) -> np.ndarray | None:
        result = self.robot.ik(position, orientation, q_near=q_near, rng=rng, n_seeds=12,
                               max_solutions=1)
        if not result.success or not self._clear_at_all_times(result.q, draft):
            return None
        return result.q

    def _clear_at_all_times(self, q: np.ndarray, draft: Scenario) -> bool:
        """≥ min_clearance from every obstacle at 20 ms steps over all motion (a sphere
        moving at 1.5 m/s goes 3 cm between checks, so the margin keeps a 2 cm guard)."""
        end = max((float(o.waypoints[-1, 0]) for o in draft.obstacles if o.is_dynamic),
                  default=0.0)
        static: list[Shape] = [s for o in draft.obstacles if not o.is_dynamic
                               for s in o.parts_at(0.0)]
        if static and self.robot.clearance(q, static).distance < self.config.min_clearance:
            return False
        movers = [o for o in draft.obstacles if o.is_dynamic]
        for t in np.arange(0.0, end + 0.02, 0.02):
            shapes = [s for o in movers for s in o.parts_at(float(t))]
            if shapes and self.robot.clearance(q, shapes).distance < self.config.min_clearance:
                return False
        return True

    def _document(self, family: str, name: str, start, position, orientation, goal,
                  obstacles: list[dict]) -> dict:
        data = {
            "format": 1, "name": name, "description": f"generated: {FAMILIES[family]}",
            "robot": "panda", "start": {"joints": _round(start)},
            "goal": {"pose": {"position": _round(position), "orientation": _round(orientation)},
                     "position_tolerance": 0.01, "orientation_tolerance": 0.05},
            "obstacles": obstacles, "time_limit": self.config.time_limit,
        }
        if goal is not None:
            data["goal"]["joints"] = _round(goal)
        return data


def generate_family(generator: ScenarioGenerator, family: str, count: int, seed: int,
                    progress: Callable[[str], None] | None = None) -> list[Generated]:
    """``count`` scenarios named ``<family>-s<seed>-<i>``; scenario ``i`` has its own
    random stream (seed, family, i), so asking for more keeps the first ones unchanged."""
    out = []
    for i in range(count):
        rng = np.random.default_rng([seed, ord(family), i])
        out.append(generator.generate(family, f"{family}-s{seed}-{i:03d}", rng))
        if progress is not None:
            progress(out[-1].scenario.name)
    return out


def write_scenarios(generator: ScenarioGenerator, out: Path, families: str, count: int,
                    seed: int, overwrite: bool = False,
                    progress: Callable[[str], None] | None = None) -> tuple[list[Path], int]:
    """``count`` scenario files spread over ``families`` (the first families get one more
    when it does not divide) into ``out``; an existing file is kept unless ``overwrite``.
    Returns every file's path and how many were written."""
    out.mkdir(parents=True, exist_ok=True)
    per_family = [count // len(families) + (i < count % len(families))
                  for i in range(len(families))]
    files, written = [], 0
    for family, n in zip(families, per_family, strict=True):
        for item in generate_family(generator, family, n, seed, progress):
            path = out / f"{item.scenario.name}.yaml"
            if overwrite or not path.exists():
                path.write_text(item.yaml(), encoding="utf-8")
                written += 1
            files.append(path)
    return files, written
