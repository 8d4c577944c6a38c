"""Fresh scenario files like the public families, from a seed.

Benchmarks and the runtime model must be judged on scenes nobody tuned for, so this writes
new format-1 scenarios (../shared/scenarios/FORMAT.md) family by family:

===  ==========================================  =======================================
A    one static box                               B  one static sphere
C    static box and sphere                        D  static box and a sweeping sphere
E    two static boxes and a sweeping sphere       F  one static tilted cylinder
G    cylinder and a diving sphere                S  stress: 1-3 crossing movers + boxes
===  ==========================================  =======================================

A task moves the hand across the front of the robot, from one side to the other, past the
obstacles placed between; movers cross that region at a speed drawn from a band. Every
scenario is checked before it is kept: start and goal are IK solutions out of self-contact
and at least ``min_clearance`` from every obstacle *at every instant* (exact meshes), and
the file parses with the project's own reader. The same seed writes the same files.

Family S (stress) is not one of the public families: 1–3 movers — spheres, boxes and
``compound`` objects (a tool, a hand, a clump; rigid parts in one colour) — each crossing
the hand's straight way at a random time and speed from the band, plus 1–2 static boxes,
every obstacle in its own colour class. Its names carry the band
(``S-v0.6-1-s7-000``) so the bands of one seed sit side by side in one folder, and the
random stream does not depend on the band: scenario ``i`` of each band is the same draw
with other speeds wherever the draw is accepted in both.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from damon_ros.core.limits import READY
from damon_ros.core.scenario import COLORS, Scenario, parse_scenario
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
"""The families like the public ones (the default of ``damon-ros scenarios generate``)."""

STRESS = "S"
ALL_FAMILIES = {**FAMILIES, STRESS: "stress: 1-3 movers (sphere, box, compound) crossing "
                                    "the hand's way at random times, and static boxes"}

STRESS_BANDS = ((0.1, 0.3), (0.3, 0.6), (0.6, 1.0), (1.0, 1.5))
"""Mover speed bands (m/s) of the stress bench: a slow cart to a fast human hand."""


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


def _obstacles(family: str, rng: np.random.Generator, a: np.ndarray, b: np.ndarray,
               side: float, config: GenerationConfig, movers: int = 1) -> list[dict]:
    middle = (a + b) / 2

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
    if family == STRESS:  # the static part; movers are added one by one (_draw_stress)
        colors = [str(c) for c in rng.permutation(COLORS)]
        return _stress_statics(rng, near, colors, int(rng.integers(1, min(2, 4 - movers) + 1)))
    raise ValueError(f"unknown family {family!r}; choose from {''.join(ALL_FAMILIES)}")


def _stress_statics(rng: np.random.Generator, near: Callable[..., np.ndarray],
                    colors: list[str], n_static: int) -> list[dict]:
    """1–2 static boxes: one beyond the hand's way, one low under it (as in family E)."""
    spots = [near((0.15, 0.3)), near((0.05, 0.2), (-0.4, -0.25))]
    return [_box(f"block{i + 1}", colors.pop(), rng, spots[i]) for i in range(n_static)]


_MOVER_MAKERS = ("sphere", "box", "compound")


def _stress_mover(name: str, color: str, a: np.ndarray, b: np.ndarray,
                  rng: np.random.Generator, config: GenerationConfig) -> dict:
    """A sphere, a carried box or a compound object crossing the hand's way."""
    kind = str(rng.choice(_MOVER_MAKERS))
    make = {"sphere": _sphere, "box": _small_box, "compound": _compound}[kind]
    return _crossing(make(name, color, rng, np.zeros(3)), a, b, rng, config)


def _random_quaternion(rng: np.random.Generator) -> list[float]:
    q = rng.normal(size=4)
    return _round(q / np.linalg.norm(q), 6)


def _small_box(name: str, color: str, rng: np.random.Generator, centre: np.ndarray) -> dict:
    """A carried box (a parcel, a tray) in any orientation."""
    return {"name": name, "shape": "box", "size": _round(rng.uniform(0.05, 0.15, 3)),
            "color": color, "pose": {"position": _round(centre),
                                     "orientation": _random_quaternion(rng)}}


def _part(shape: str, size, position, orientation=(0.0, 0.0, 0.0, 1.0)) -> dict:
    return {"shape": shape, "size": _round(size), "position": _round(position),
            "orientation": _round(orientation, 6)}


def _compound(name: str, color: str, rng: np.random.Generator, centre: np.ndarray) -> dict:
    """A rigid object no single primitive describes: a tool (handle, head, knob), a hand
    (palm, four fingers, thumb) or a clump of 2–4 spheres (a bag), in any orientation."""
    kind = str(rng.choice(["tool", "hand", "clump"]))
    if kind == "tool":
        length, head = rng.uniform(0.14, 0.24), rng.uniform(0.10, 0.16)
        parts = [_part("box", [length, 0.035, 0.035], [0.0, 0.0, 0.0]),
                 _part("box", [0.04, 0.04, head], [length / 2 - 0.02, 0.0, head / 2 - 0.02]),
                 _part("sphere", [rng.uniform(0.025, 0.04)], [-length / 2, 0.0, 0.0])]
    elif kind == "hand":
        palm = rng.uniform(0.08, 0.10)
        finger = rng.uniform(0.06, 0.085)
        down = [math.sin(math.pi / 4), 0.0, 0.0, math.cos(math.pi / 4)]  # z axis along -y
        parts = [_part("box", [palm, 0.03, palm], [0.0, 0.0, 0.0])]
        parts += [_part("cylinder", [0.01, finger], [x, 0.0, palm / 2 + finger / 2],
                        [0.0, 0.0, 0.0, 1.0]) for x in np.linspace(-0.03, 0.03, 4)]
        parts.append(_part("cylinder", [0.011, 0.06], [palm / 2 + 0.02, -0.015, 0.0], down))
    else:
        parts = [_part("sphere", [rng.uniform(0.03, 0.06)], rng.uniform(-0.05, 0.05, 3))
                 for _ in range(int(rng.integers(2, 5)))]
    return {"name": name, "shape": "compound", "color": color, "parts": parts,
            "pose": {"position": _round(centre), "orientation": _random_quaternion(rng)}}


def _crossing(obstacle: dict, a: np.ndarray, b: np.ndarray, rng: np.random.Generator,
              config: GenerationConfig) -> dict:
    """Moves ``obstacle`` in a straight line at a speed from the band through a point of
    the hand's straight way from ``a`` to ``b``, reaching it ``t_cross`` s into the run
    (0.2–1.8 s: while a typical 1–1.5 s move is under way): from 0.45–0.7 m before that
    point (it waits there if it starts early, or is already on its way at t = 0 if the
    crossing is too soon to come from that far) to 0.45–0.7 m past it, where it stays.
    Its direction is mostly across the way, mostly horizontal: a hand reaching over the
    table, a cart passing, a thrown object."""
    way = (b - a) / np.linalg.norm(b - a)
    cross = a + rng.uniform(0.3, 0.7) * (b - a) + [rng.uniform(-0.05, 0.1),
                                                   rng.uniform(-0.05, 0.05),
                                                   rng.uniform(0.0, 0.12)]
    across = np.cross([0.0, 0.0, 1.0], way)
    across /= np.linalg.norm(across)
    heading = rng.uniform(-0.6, 0.6) + rng.choice([0.0, math.pi])  # rad off square across
    elevation = rng.uniform(-0.6, 0.6)
    d = math.cos(elevation) * (math.cos(heading) * across + math.sin(heading) * way)
    d = d + [0.0, 0.0, math.sin(elevation)]
    d /= np.linalg.norm(d)  # the way may climb: across and way are not both horizontal
    speed = rng.uniform(*config.speed)
    t_cross = rng.uniform(0.2, 1.8)
    before, after = rng.uniform(0.45, 0.7), rng.uniform(0.45, 0.7)
    before = min(before, speed * t_cross)
    floor = 0.05  # m: neither end below the table top
    if d[2] > 0:
        before = min(before, (cross[2] - floor) / d[2])
    elif d[2] < 0:
        after = min(after, (cross[2] - floor) / -d[2])
    start, end = cross - before * d, cross + after * d
    t_move, t_end = t_cross - before / speed, t_cross + after / speed
    rows = [[0.0, *start]] + ([[t_move, *start]] if t_move > 1e-3 else []) + [[t_end, *end]]
    obstacle["pose"]["position"] = _round(start)
    obstacle["motion"] = {"type": "waypoints", "waypoints": [_round(r) for r in rows]}
    return obstacle


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
        if family not in ALL_FAMILIES:
            raise ValueError(f"unknown family {family!r}; choose from {''.join(ALL_FAMILIES)}")
        # the stress family's mover count is drawn once, not per attempt: scenes with more
        # movers are refused more often, and redrawing it would favour a single mover
        movers = int(rng.integers(1, 4)) if family == STRESS else 1
        for _ in range(self.config.attempts):
            data = self._draw(family, name, rng, movers)
            if data is not None:
                return Generated(data, parse_scenario(data, f"<generated {name}>"))
        raise RuntimeError(f"{name}: no valid {family} scenario in {self.config.attempts} draws")

    def _draw(self, family: str, name: str, rng: np.random.Generator,
              movers: int = 1) -> dict | None:
        side = float(rng.choice([-1.0, 1.0]))
        a = np.array([rng.uniform(0.30, 0.55), side * rng.uniform(0.20, 0.42),
                      rng.uniform(0.25, 0.50)])
        b = np.array([rng.uniform(0.30, 0.60), -side * rng.uniform(0.20, 0.42),
                      rng.uniform(0.25, 0.50)])
        obstacles = _obstacles(family, rng, a, b, side, self.config, movers)
        draft = parse_scenario(self._document(family, name, READY, b, [1, 0, 0, 0],
                                              None, obstacles), "<draft>")
        start = self._clear_ik(a, _down_orientation(rng), draft, rng)
        if start is None:
            return None
        orientation = _down_orientation(rng)
        goal = self._clear_ik(b, orientation, draft, rng, q_near=start)
        if goal is None:
            return None
        if family == STRESS and not self._add_movers(obstacles, movers, a, b, start, goal,
                                                     rng):
            return None
        return self._document(family, name, start, b, orientation, goal, obstacles)

    def _add_movers(self, obstacles: list[dict], count: int, a: np.ndarray, b: np.ndarray,
                    start: np.ndarray, goal: np.ndarray, rng: np.random.Generator,
                    tries: int = 40) -> bool:
        """Adds ``count`` crossing movers to the stress scene, each redrawn (up to ``tries``
        times) until start and goal stay clear of it at every instant: one refusal costs
        one mover, not the whole scene, so three movers are as reachable as one."""
        used = {o["color"] for o in obstacles}
        colors = [c for c in COLORS if c not in used]
        for k in range(count):
            for _ in range(tries):
                mover = _stress_mover(f"mover{k + 1}", colors[k], a, b, rng, self.config)
                alone = parse_scenario(self._document(STRESS, "mover", READY, b, [1, 0, 0, 0],
                                                      None, [mover]), "<draft>")
                if all(self._clear_at_all_times(q, alone) for q in (start, goal)):
                    obstacles.insert(k, mover)
                    break
            else:
                return False
        return True

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
            "format": 1, "name": name, "description": f"generated: {ALL_FAMILIES[family]}",
            "robot": "panda", "start": {"joints": _round(start)},
            "goal": {"pose": {"position": _round(position), "orientation": _round(orientation)},
                     "position_tolerance": 0.01, "orientation_tolerance": 0.05},
            "obstacles": obstacles, "time_limit": self.config.time_limit,
        }
        if goal is not None:
            data["goal"]["joints"] = _round(goal)
        return data


def mover_speed(scenario: Scenario) -> float:
    """The fastest straight-line speed (m/s) of any mover of ``scenario`` (0 if static):
    what puts a scenario, generated here or not, into a speed band."""
    speeds = []
    for o in scenario.obstacles:
        if o.is_dynamic and len(o.waypoints) > 1:
            w = o.waypoints
            steps = np.linalg.norm(np.diff(w[:, 1:], axis=0), axis=1) / np.diff(w[:, 0])
            speeds.append(float(steps.max()))
    return max(speeds, default=0.0)


def speed_band(speed: float, bands=STRESS_BANDS) -> tuple[float, float] | None:
    """The band holding ``speed`` (a small tolerance for rounded waypoints), or None."""
    for low, high in bands:
        if low - 1e-3 <= speed <= high + 1e-3:
            return low, high
    return None


def band_tag(speed: tuple[float, float]) -> str:
    """``v0.6-1`` for the band 0.6–1.0 m/s: the part of a name that says the movers' band."""
    return f"v{speed[0]:g}-{speed[1]:g}"


def generate_family(generator: ScenarioGenerator, family: str, count: int, seed: int,
                    progress: Callable[[str], None] | None = None,
                    tag_band: bool = False) -> list[Generated]:
    """``count`` scenarios named ``<family>-s<seed>-<i>`` (``<family>-<band>-s<seed>-<i>``
    for the stress family or when ``tag_band``); scenario ``i`` has its own random stream
    (seed, family, i), so asking for more keeps the first ones unchanged."""
    out = []
    prefix = family
    if tag_band or family == STRESS:
        prefix = f"{family}-{band_tag(generator.config.speed)}"
    for i in range(count):
        rng = np.random.default_rng([seed, ord(family), i])
        out.append(generator.generate(family, f"{prefix}-s{seed}-{i:03d}", rng))
        if progress is not None:
            progress(out[-1].scenario.name)
    return out


def write_scenarios(generator: ScenarioGenerator, out: Path, families: str, count: int,
                    seed: int, overwrite: bool = False,
                    progress: Callable[[str], None] | None = None,
                    tag_band: bool = False) -> tuple[list[Path], int]:
    """``count`` scenario files spread over ``families`` (the first families get one more
    when it does not divide) into ``out``; an existing file is kept unless ``overwrite``.
    Returns every file's path and how many were written."""
    out.mkdir(parents=True, exist_ok=True)
    per_family = [count // len(families) + (i < count % len(families))
                  for i in range(len(families))]
    files, written = [], 0
    for family, n in zip(families, per_family, strict=True):
        for item in generate_family(generator, family, n, seed, progress, tag_band):
            path = out / f"{item.scenario.name}.yaml"
            if overwrite or not path.exists():
                path.write_text(item.yaml(), encoding="utf-8")
                written += 1
            files.append(path)
    return files, written
