"""RRT-Connect compiled with numba over the fast model's kernels: the planner's complete search.

Why our own: OMPL's Python bindings call back into Python for every state they check (an
array copy, a kernel call and the binding's overhead per state), so among MotionBenchMaker's
shelves a route took 0.2-5 s and often none came within the budget. Here the sampling,
the nearest-neighbour scan and every motion check (`sphere_kernels.segment_clear`, the same
states at the same resolution as every other certified check) run in one compiled loop.

The trees live in arrays owned by :class:`RrtConnect`, so the search runs in slices of
iterations and the caller's wall-clock budget is honoured between them. What it returns is
a raw waypoint path; the caller shortcuts and certifies it with its own rules (start and
goal margins, self-collision on the meshes, exact decisions near contact) before anything
moves.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence

import numpy as np
from numba import njit

from damon_ros.core import sphere_kernels
from damon_ros.core.shapes import Shape

ADVANCED, REACHED, TRAPPED = 0, 1, 2

SLICE = 256
"""Iterations per compiled call between two looks at the clock (~1-5 ms)."""


@njit(cache=True)
def _free_prefix(a, b, margin, resolution, robot, obstacles, first):
    """How far (0-1) from ``a`` toward ``b`` the states at ``resolution`` keep ``margin``,
    walked in order from ``a`` (a tree node). Groups before ``first`` are not checked: the
    base's, when they keep every margin of the search (`_first_group`). A tree grows into
    a narrow pocket only this way: from a grasp goal inside a shelf, almost every full step
    toward a random sample hits the shelf, and all-or-nothing extension left that tree at
    2-50 nodes while the other grew to thousands."""
    steps = sphere_kernels.motion_steps(a, b, resolution)
    if steps == 0:
        return 1.0
    jr, jp, sj, sc, sr, gj, gs, ge, gc, gr, jb = robot
    kind, pos, rot, params, hull = obstacles
    fr = np.empty((jr.shape[0] + 1, 3, 3))
    fp = np.empty((jr.shape[0] + 1, 3))
    q = np.empty(a.shape[0])
    where = np.empty(2, np.int64)
    for k in range(1, steps + 1):
        t = k / steps
        for i in range(a.shape[0]):
            q[i] = a[i] + (b[i] - a[i]) * t
        if sphere_kernels._distance_below(q, margin + 1e-12, jr, jp, sj, sc, sr, gj, gs, ge, gc,
                                          gr, jb, kind, pos, rot, params, hull, fr, fp,
                                          where, margin, first) <= margin:
            return (k - 1) / steps
    return 1.0


@njit(cache=True)
def _nearest(nodes, count, q):
    best, best_d = 0, np.inf
    for i in range(count):
        d = 0.0
        for a in range(q.shape[0]):
            x = nodes[i, a] - q[a]
            d += x * x
        if d < best_d:
            best, best_d = i, d
    return best


@njit(cache=True)
def _steer(frm, to, step):
    d = math.sqrt(np.sum((to - frm) ** 2))
    if d <= step:
        return to.copy(), True
    return frm + (to - frm) * (step / d), False


@njit(cache=True)
def _margin_of(tree, parent_index, margins):
    """Edges leaving a root (the start or the goal) keep that end's margin; others λ."""
    return margins[tree] if parent_index == 0 else margins[2]


@njit(cache=True)
def _extend(nodes, parents, counts, tree, target, step, margins, resolution, robot, obstacles,
            first):
    """One step of tree ``tree`` toward ``target``: (new index or -1, status): a full step
    (ADVANCED), the target itself (REACHED), the free part of a blocked step (TRAPPED), or
    nothing (-1, TRAPPED)."""
    near = _nearest(nodes[tree], counts[tree], target)
    new, reached = _steer(nodes[tree, near], target, step)
    margin = _margin_of(tree, near, margins)
    t = _free_prefix(nodes[tree, near], new, margin, resolution, robot, obstacles, first)
    if t <= 0.0:
        return -1, TRAPPED
    status = REACHED if reached else ADVANCED
    if t < 1.0:  # blocked on the way: keep the free part
        new = nodes[tree, near] + t * (new - nodes[tree, near])
        status = TRAPPED
    k = counts[tree]
    if k >= nodes.shape[1]:
        return -1, TRAPPED
    nodes[tree, k] = new
    parents[tree, k] = near
    counts[tree] = k + 1
    return k, status


LOCAL_RAD = 0.3
"""Half-width (rad per joint) of the box around a node of the smaller tree that half of its
samples come from while it is under a tenth of the other's size."""


@njit(cache=True)
def _target(nodes, counts, tree, lower, upper):
    """A sample for ``tree``: uniform in the joint box, or, while the tree is stuck in a
    pocket (under a tenth of the other tree's nodes), half the time near one of its nodes.
    A grasp goal between shelf boards grew 14 nodes in 33,000 uniform samples: from there
    almost every direction hits a board within the first step."""
    n = lower.shape[0]
    if counts[tree] * 10 < counts[1 - tree] and np.random.random() < 0.5:
        base = nodes[tree, np.random.randint(counts[tree])]
        out = np.empty(n)
        for i in range(n):
            x = base[i] + (2.0 * np.random.random() - 1.0) * LOCAL_RAD
            out[i] = min(max(x, lower[i]), upper[i])
        return out
    return lower + np.random.random(n) * (upper - lower)


@njit(cache=True)
def _search(nodes, parents, counts, lower, upper, step, margins, resolution, iterations, state,
            robot, obstacles, first):
    """``iterations`` rounds of RRT-Connect; returns (start-tree node, goal-tree node) of
    the connection, or (-1, -1). ``state[0]`` is the tree that extends next."""
    for _ in range(iterations):
        a = state[0]
        b = 1 - a
        state[0] = b
        target = _target(nodes, counts, a, lower, upper)
        new, _ = _extend(nodes, parents, counts, a, target, step, margins, resolution, robot,
                         obstacles, first)
        if new < 0:
            continue
        goal = nodes[a, new].copy()
        while True:  # connect: tree b steps toward the new node until it arrives or is blocked
            k, status = _extend(nodes, parents, counts, b, goal, step, margins, resolution,
                                robot, obstacles, first)
            if status == REACHED:
                return (new, k) if a == 0 else (k, new)
            if status != ADVANCED:
                break
    return -1, -1


@njit(cache=True)
def _seed(seed):
    np.random.seed(seed)


def _first_group(robot: tuple, packed: tuple, margin: float) -> int:
    """The first sphere group the search must check: past the base's, when the base (which
    never moves) keeps ``margin`` from every obstacle; otherwise all of them."""
    _, _, sj, sc, sr, gj = robot[:6]
    if sphere_kernels.fixed_clearance(sj, sc, sr, *packed) > margin:
        return int(sphere_kernels.fixed_groups(gj))
    return 0


def _branch(nodes: np.ndarray, parents: np.ndarray, index: int) -> list[np.ndarray]:
    out = [nodes[index]]
    while index != 0:
        index = int(parents[index])
        out.append(nodes[index])
    return out


def rrt_connect(spheres, q_start: np.ndarray, q_goal: np.ndarray, lower: np.ndarray,
                upper: np.ndarray, obstacles: Sequence[Shape], margin: float,
                end_margins: tuple[float, float], resolution: float, budget_s: float,
                seed: int = 0, step: float = 1.0, max_nodes: int = 50_000
                ) -> np.ndarray | None:
    """Waypoints from ``q_start`` to ``q_goal`` whose segments keep ``margin`` on the fast
    model ``spheres`` (those leaving the start or the goal keep ``end_margins``), or None
    when none is found within ``budget_s`` s. ``step``: rad (L2) per tree extension."""
    deadline = time.perf_counter() + budget_s
    nodes = np.zeros((2, max_nodes, 7))
    parents = np.zeros((2, max_nodes), np.int64)
    nodes[0, 0], nodes[1, 0] = q_start, q_goal
    counts = np.ones(2, np.int64)
    margins = np.array([end_margins[0], end_margins[1], margin], float)
    packed = spheres.packed(tuple(obstacles))
    robot = tuple(spheres.kernel_args)
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    if sphere_kernels.motion_clear(nodes[0, 0], nodes[1, 0], min(end_margins), resolution,
                                   robot, packed):
        return np.array([q_start, q_goal])
    _seed(int(seed))
    state = np.zeros(1, np.int64)
    first = _first_group(robot, packed, float(margins.max()))
    while time.perf_counter() < deadline and counts.max() < max_nodes:
        i, j = _search(nodes, parents, counts, lower, upper, step, margins, resolution, SLICE,
                       state, robot, packed, first)
        if i >= 0:
            # the connection point is in both trees: once
            path = _branch(nodes[0], parents[0], i)[::-1] + _branch(nodes[1], parents[1], j)[1:]
            return np.array(path)
    return None


def warm_up(spheres) -> None:
    """Compile (or load from the disk cache) every kernel of the search, so that the first
    fallback of a running node does not spend seconds compiling while the arm holds."""
    probe = (Shape("sphere", (0.05,), np.array([2.0, 2.0, 2.0])),)
    q = np.zeros(7)
    nodes, parents = np.zeros((2, 2, 7)), np.zeros((2, 2), np.int64)
    _seed(0)
    _search(nodes, parents, np.ones(2, np.int64), q - 1.0, q + 1.0, 1.0,
            np.zeros(3), 0.02, 0, np.zeros(1, np.int64), tuple(spheres.kernel_args),
            sphere_kernels.pack_obstacles(probe), 0)
    _first_group(tuple(spheres.kernel_args), sphere_kernels.pack_obstacles(probe), 0.0)
    sphere_kernels.motion_clear(q, q + 0.01, 0.0, 0.02, tuple(spheres.kernel_args),
                                sphere_kernels.pack_obstacles(probe))  # the direct try
