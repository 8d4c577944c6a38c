"""``damon-ros bench-robot``: median µs per robot-model query, and the fast-model margin.

The table holds the numbers the planner's latency budget is built from: FK, IK, one exact
distance, a batch of fast distances and certified segment checks. ``--margin N`` instead
measures, on N random configurations each with a random obstacle near the arm, how far the
un-inflated sphere model's distance can exceed the exact mesh distance — the measurement
behind :data:`damon_ros.robot.FAST_MODEL_MARGIN`.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from damon_ros.robot import FAST_MODEL_MARGIN, READY, Robot, local_vertices
from damon_ros.shapes import Shape


def _median_us(fn: Callable[[], object], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e6 * float(np.median(times))


def _cycle(items: list) -> Callable[[], object]:
    """A function returning the items in turn, so repeated calls do not hit one cached case."""
    state = {"i": -1}

    def nxt():
        state["i"] = (state["i"] + 1) % len(items)
        return items[state["i"]]

    return nxt


def measure(repeats: int = 200, seed: int = 0) -> list[tuple[str, float, str]]:
    """(query, median µs, note) rows."""
    rng = np.random.default_rng(seed)
    mesh, fast = Robot("mesh"), Robot("fast")
    lo, hi = fast.limits.lower, fast.limits.upper
    Q = rng.uniform(lo, hi, (1000, 7))
    free = [q for q in Q[:200] if not mesh.self_collision(q)]
    q_next = _cycle(free)
    sphere = Shape("sphere", (0.05,), [0.5, 0.0, 0.4])
    box = Shape("box", (0.1, 0.3, 0.3), [0.5, 0.2, 0.3], [0, 0, 0.2, 0.98])
    far = Shape("sphere", (0.05,), [-0.6, 0.0, 1.2])
    goals = [(fast.tcp_pose(q), fast.limits.clip(q + rng.normal(scale=0.1, size=7)))
             for q in free[:40]]
    warm, cold = _cycle(goals), _cycle(goals)
    seg_a, seg_b = READY.copy(), READY.copy()
    seg_a[0], seg_b[0] = -0.5, 0.5  # a 1 rad edge: 51 states at 0.02 rad
    seg_states = fast.steps(seg_a, seg_b, 0.02) + 1
    fast.segment_free(seg_a, seg_b, [sphere])  # compile the kernels outside the timing

    def ik_warm():
        (p, o), near = warm()
        return fast.ik(p, o, q_near=near)

    def ik_cold():
        (p, o), _ = cold()
        return fast.ik(p, o, q_near=READY, rng=rng)

    few = max(20, repeats // 5)
    return [
        ("FK panda_hand_tcp", _median_us(lambda: fast.fk(q_next()), repeats), "pinocchio"),
        ("IK, warm seed (~0.1 rad away)", _median_us(ik_warm, few), "LM, joint limits"),
        ("IK, cold (ready-pose seed, then random)", _median_us(ik_cold, few), "multi-seed"),
        ("clearance, mesh model, 1 sphere", _median_us(
            lambda: mesh.clearance(q_next(), [sphere]), repeats), "coal GJK, witness points"),
        ("clearance, mesh model, 1 box", _median_us(
            lambda: mesh.clearance(q_next(), [box]), repeats), "coal GJK, witness points"),
        ("clearance, fast model, 1 sphere", _median_us(
            lambda: fast.clearance(q_next(), [sphere]), repeats), "spheres, witness points"),
        ("batch distance, fast, per config (1000 × 2 obst.)", _median_us(
            lambda: fast.distances(Q, [sphere, box]), max(10, repeats // 20)) / len(Q), "numba"),
        ("batch distance, mesh, per config (20 × 1 obst.)", _median_us(
            lambda: mesh.distances(Q[:20], [sphere]), max(5, repeats // 40)) / 20, "coal"),
        ("segment_free per state, 2 obst. near (free)", _median_us(
            lambda: fast.segment_free(seg_a, seg_b, [sphere, box], 0.02), repeats) / seg_states,
         f"{seg_states} states, 1 rad edge"),
        ("segment_free per state, 1 obst. far", _median_us(
            lambda: fast.segment_free(seg_a, seg_b, [far], 0.02), repeats) / seg_states,
         f"{seg_states} states, 1 rad edge"),
        ("self-collision, mesh model", _median_us(
            lambda: mesh.self_collision(q_next()), repeats), "SRDF pairs, convex GJK"),
    ]


@dataclass(frozen=True)
class MarginReport:
    """How the un-inflated sphere model's distance relates to the exact mesh distance."""

    samples: int
    excess_max: float  # max(fast_raw - mesh) where the meshes are apart from the obstacle
    excess_p99: float
    excess_median: float
    penetrating: int  # samples where the meshes touch or penetrate the obstacle
    raw_max_when_penetrating: float  # the fast model must not say "free" on those
    required: float  # inflation making "fast > 0 ⇒ mesh > 0" and fast ≤ mesh (when apart)


def _random_obstacle(rng: np.random.Generator, anchor: np.ndarray, spread: float) -> Shape:
    """A sphere or box of random size and orientation whose centre lies within ``spread`` m
    (plus its own size) of ``anchor``."""
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    if rng.random() < 0.5:
        radius = rng.uniform(0.01, 0.1)
        return Shape("sphere", (radius,), anchor + direction * (radius + rng.uniform(-0.02,
                                                                                    spread)))
    size = rng.uniform(0.02, 0.2, 3)
    offset = 0.5 * float(np.min(size)) + rng.uniform(-0.02, spread)
    return Shape("box", tuple(size), anchor + direction * offset, rng.normal(size=4))


def measure_margin(samples: int = 10_000, seed: int = 7, spread: float = 0.15) -> MarginReport:
    """Compare the un-inflated sphere model with the meshes on random configurations, each
    with one random obstacle placed near a random mesh vertex of the arm."""
    rng = np.random.default_rng(seed)
    mesh = Robot("mesh")
    raw = Robot("fast", fast_margin=0.0)
    objects = mesh.mesh_geom.geometryObjects
    vertices = [local_vertices(o.geometry) for o in objects]
    excess, raw_when_hit = [], [-np.inf]
    for _ in range(samples):
        q = rng.uniform(mesh.limits.lower, mesh.limits.upper)
        i = int(rng.integers(len(objects)))
        obstacles = [_random_obstacle(rng, _world_vertex(mesh, q, i, vertices, rng), spread)]
        d_mesh = mesh.clearance(q, obstacles).distance
        d_raw = float(raw.distances(q[None], obstacles)[0])
        if d_mesh > 0.0:
            excess.append(d_raw - d_mesh)
        else:
            raw_when_hit.append(d_raw)
    excess = np.array(excess)
    required = max(float(excess.max()), float(max(raw_when_hit)), 0.0)
    return MarginReport(samples, float(excess.max()), float(np.percentile(excess, 99)),
                        float(np.median(excess)), len(raw_when_hit) - 1, float(max(raw_when_hit)),
                        required)


def _world_vertex(robot: Robot, q: np.ndarray, i: int, vertices: list[np.ndarray],
                  rng: np.random.Generator) -> np.ndarray:
    pin.updateGeometryPlacements(robot.model, robot.data, robot.mesh_geom, robot.mesh_data, q)
    v = vertices[i][rng.integers(len(vertices[i]))]
    return robot.mesh_data.oMg[i].act(v)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="damon-ros bench-robot",
                                     description="Median µs per robot-model query.")
    parser.add_argument("--repeats", type=int, default=200, help="timed calls per query")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--margin", type=int, default=0, metavar="N",
                        help="instead: measure the fast-model margin on N random samples")
    args = parser.parse_args(argv)
    if args.repeats < 1 or args.margin < 0:
        parser.error("--repeats must be ≥ 1 and --margin ≥ 0")
    if args.margin:
        r = measure_margin(args.margin, seed=args.seed or 7)
        print(f"samples {r.samples}, meshes touching the obstacle in {r.penetrating}")
        print(f"un-inflated fast − mesh distance (meshes apart): max {r.excess_max * 1e3:+.1f} mm, "
              f"p99 {r.excess_p99 * 1e3:+.1f} mm, median {r.excess_median * 1e3:+.1f} mm")
        print(f"largest un-inflated fast distance while the meshes touch: "
              f"{r.raw_max_when_penetrating * 1e3:+.1f} mm")
        print(f"inflation required: {r.required * 1e3:.1f} mm; FAST_MODEL_MARGIN is "
              f"{FAST_MODEL_MARGIN * 1e3:.1f} mm -> "
              f"{'conservative' if FAST_MODEL_MARGIN >= r.required else 'NOT conservative'}")
        return 0 if FAST_MODEL_MARGIN >= r.required else 1
    rows = measure(args.repeats, args.seed)
    width = max(len(r[0]) for r in rows)
    print(f"{'query':<{width}}  {'median µs':>10}  note")
    for name, us, note in rows:
        print(f"{name:<{width}}  {us:>10.1f}  {note}")
    return 0
