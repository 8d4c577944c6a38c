"""Compiled shortcutting of a sampled route on the fast model's kernels.

Why compiled: a route from RRT-Connect among MotionBenchMaker's shelves has tens of
waypoints, and the greedy shortcut plus the pull toward the neighbours' midpoints asks a few
hundred segment questions; asked one by one from Python they cost 8-18 ms a plan, more than
the search that found the route. Here the same questions (same states, same resolution,
same margins as :meth:`GraphPlanner._shortcut`) run in one loop.

Only obstacle clearance is checked here. Self-collision on the meshes and the planner's
certification rules (exact meshes into a goal close to an object) stay with the caller,
which certifies the result and falls back to its own shortcut when that refuses it.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence

import numpy as np
from numba import njit

from damon_ros.core import sphere_kernels
from damon_ros.core.shapes import Shape

_clear = sphere_kernels.motion_clear

PULL_FRACTIONS = (1.0, 0.5, 0.25, 0.1)
"""How far toward the neighbours' midpoint a waypoint is tried, largest first."""


@njit(cache=True)
def _greedy(path, first_margin, margin, resolution, robot, obstacles):
    """Indices kept: from each kept waypoint, the farthest later one reachable straight."""
    n = path.shape[0]
    keep = np.empty(n, np.int64)
    keep[0] = 0
    count, i = 1, 0
    while i < n - 1:
        j = n - 1
        while j > i + 1:
            m = first_margin if i == 0 else margin
            if _clear(path[i], path[j], m, resolution, robot, obstacles):
                break
            j -= 1
        keep[count] = j
        count += 1
        i = j
    return keep[:count]


@njit(cache=True)
def _pull_round(path, first_margin, margin, resolution, lower, upper, fractions, robot,
                obstacles):
    """One round: each interior waypoint moves (in place) toward its neighbours' midpoint
    as far as both of its segments stay clear. Returns the largest move (rad)."""
    n, dims = path.shape
    candidate = np.empty(dims)
    moved = 0.0
    for i in range(1, n - 1):
        for f in fractions:
            inside = True
            for a in range(dims):
                candidate[a] = path[i, a] + f * (0.5 * (path[i - 1, a] + path[i + 1, a])
                                                 - path[i, a])
                inside = inside and lower[a] <= candidate[a] <= upper[a]
            if not inside:
                continue
            m = first_margin if i == 1 else margin
            if _clear(path[i - 1], candidate, m, resolution, robot, obstacles) and \
                    _clear(candidate, path[i + 1], margin, resolution, robot, obstacles):
                step = 0.0
                for a in range(dims):
                    step = max(step, abs(candidate[a] - path[i, a]))
                    path[i, a] = candidate[a]
                moved = max(moved, step)
                break
    return moved


def shortcut(spheres, path: np.ndarray, obstacles: Sequence[Shape], first_margin: float,
             margin: float, resolution: float, lower: np.ndarray, upper: np.ndarray,
             rounds: int = 3, deadline: float = math.inf) -> np.ndarray:
    """``path`` (N, 7) shortened: greedy shortcuts, then the pull toward the midpoints, at
    most ``rounds`` rounds, until one moves no waypoint by 0.01 rad, and none begun after
    ``deadline`` (`time.perf_counter`; the pull only shortens a route that is already
    clear); the first segment keeps
    ``first_margin``, every other ``margin``, on the fast model ``spheres`` against
    ``obstacles``. Self-collision is not checked (the caller's)."""
    path = np.ascontiguousarray(path, dtype=float)
    if len(path) < 3 or not obstacles:
        return path[[0, -1]] if not obstacles else path
    robot = tuple(spheres.kernel_args)
    packed = spheres.packed(tuple(obstacles))
    keep = _greedy(path, first_margin, margin, resolution, robot, packed)
    path = path[keep].copy()
    bounds = (np.asarray(lower, float), np.asarray(upper, float))
    fractions = np.array(PULL_FRACTIONS)
    for _ in range(rounds):  # a round a call: the deadline is checked between rounds
        if time.perf_counter() > deadline:
            break
        if _pull_round(path, first_margin, margin, resolution, *bounds, fractions, robot,
                       packed) < 0.01:
            break
    return path


def warm_up(spheres) -> None:
    """Compile (or load from the disk cache) the kernels before a node needs them."""
    probe = (Shape("sphere", (0.05,), np.array([2.0, 2.0, 2.0])),)
    path = np.array([np.zeros(7), np.full(7, 0.1), np.full(7, 0.2)])
    shortcut(spheres, path, probe, 0.0, 0.0, 0.02, np.full(7, -1.0), np.full(7, 1.0))
