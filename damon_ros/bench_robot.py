"""``damon-ros bench-robot``: median µs per robot-model query, printed as a table.

These are the numbers the planner's latency budget is built from: FK, IK, one exact
distance, a batch of fast distances and a certified segment check.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import numpy as np

from damon_ros.robot import READY, Robot
from damon_ros.shapes import Shape


def _median_us(fn: Callable[[], object], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e6 * float(np.median(times))


def measure(repeats: int = 200, seed: int = 0) -> list[tuple[str, float, str]]:
    """(query, median µs, note) rows."""
    rng = np.random.default_rng(seed)
    mesh, fast = Robot("mesh"), Robot("fast")
    lo, hi = fast.limits.lower, fast.limits.upper
    Q = rng.uniform(lo, hi, (1000, 7))
    sphere = Shape("sphere", (0.05,), [0.5, 0.0, 0.4])
    box = Shape("box", (0.1, 0.3, 0.3), [0.5, 0.2, 0.3], [0, 0, 0.2, 0.98])
    free = next(q for q in Q if not mesh.self_collision(q))
    target = fast.tcp_pose(free)
    near = fast.limits.clip(free + 0.2)
    it = iter(range(10**9))

    def q_next() -> np.ndarray:
        return Q[next(it) % len(Q)]

    seg_a, seg_b = READY.copy(), READY.copy()
    seg_a[0], seg_b[0] = -0.5, 0.5  # a 1 rad edge: 51 states at 0.02 rad
    rows = [
        ("FK panda_hand_tcp", _median_us(lambda: fast.fk(q_next()), repeats), "pinocchio"),
        ("IK, warm seed (0.2 rad away)", _median_us(
            lambda: fast.ik(*target, q_near=near), max(20, repeats // 10)), "DLS, limits"),
        ("IK, cold seed (ready pose)", _median_us(
            lambda: fast.ik(*target, q_near=READY), max(20, repeats // 10)), "multi-seed"),
        ("clearance, mesh model, 1 sphere", _median_us(
            lambda: mesh.clearance(q_next(), [sphere]), repeats), "coal GJK, witness points"),
        ("clearance, mesh model, 1 box", _median_us(
            lambda: mesh.clearance(q_next(), [box]), repeats), "coal GJK, witness points"),
        ("clearance, fast model, 1 sphere", _median_us(
            lambda: fast.clearance(q_next(), [sphere]), repeats), "spheres, numpy"),
        ("batch distance, fast, per config (1000 × 2 obst.)", _median_us(
            lambda: fast.distances(Q, [sphere, box]), max(10, repeats // 20)) / len(Q), ""),
        ("batch distance, mesh, per config (20 × 1 obst.)", _median_us(
            lambda: mesh.distances(Q[:20], [sphere]), max(5, repeats // 40)) / 20, ""),
        ("segment check, 1 rad at 0.02 rad, 2 obstacles", _median_us(
            lambda: fast.segment_free(seg_a, seg_b, [sphere, box], 0.02), repeats),
         "51 states, fast model"),
        ("self-collision, mesh model", _median_us(
            lambda: mesh.self_collision(q_next()), repeats), "SRDF pairs"),
    ]
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="damon-ros bench-robot",
                                     description="Median µs per robot-model query.")
    parser.add_argument("--repeats", type=int, default=200, help="timed calls per query")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    rows = measure(args.repeats, args.seed)
    width = max(len(r[0]) for r in rows)
    print(f"{'query':<{width}}  {'median µs':>10}  note")
    for name, us, note in rows:
        print(f"{name:<{width}}  {us:>10.1f}  {note}")
    return 0
