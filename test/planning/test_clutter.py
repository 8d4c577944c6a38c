"""Pieces that make cluttered cells solvable: RRT-Connect keeps the free part of a blocked
step, the compiled shortcut keeps every segment clear, and a goal a few millimetres from an
object (only the meshes accept it) is left along the clearance gradient."""

from __future__ import annotations

import numpy as np
import pytest

from damon_ros.core import sphere_kernels
from damon_ros.core.limits import READY, joint_limits
from damon_ros.core.robot import Robot
from damon_ros.core.shapes import Shape
from damon_ros.learning.bundle import DamonModel
from damon_ros.planning import path_shortcutting, rrt_connect
from damon_ros.planning.graph_planner import GraphPlanner, PlannerConfig


@pytest.fixture(scope="module")
def fast():
    return Robot("fast")


def _wall_in_front(fast: Robot, q: np.ndarray, gap: float) -> Shape:
    """A wall ``gap`` beyond the hand along world x, facing it."""
    x = fast.tcp_pose(q)[0][0]
    return Shape("box", (0.05, 1.5, 1.5), np.array([x + gap + 0.025 + 0.1, 0.0, 0.5]))


def test_a_blocked_step_keeps_its_free_part(fast):
    """From a free state toward one inside a wall: the walk stops just before the first
    state within the margin, so a tree grows into a pocket instead of not at all."""
    robot, wall = tuple(fast.spheres.kernel_args), _wall_in_front(fast, READY, 0.1)
    packed = sphere_kernels.pack_obstacles((wall,))
    b = READY.copy()
    b[1] += 0.8  # leans the arm forward into the wall
    first = sphere_kernels.fixed_groups(robot[5])
    t = rrt_connect._free_prefix(READY, b, 0.01, 0.02, robot, packed, first)
    assert 0.0 < t < 1.0
    steps = int(np.ceil(np.max(np.abs(b - READY)) / 0.02))
    def clear(q):  # the spheres' own verdict, as in the search (no exact band)
        return fast.spheres.segment_clear(q, q, 0, (wall,), 0.01)

    assert clear(READY + t * (b - READY))
    assert not clear(READY + (t + 1.0 / steps) * (b - READY))
    assert rrt_connect._free_prefix(READY, READY, 0.01, 0.02, robot, packed, first) == 1.0


def test_compiled_shortcut_keeps_the_ends_every_segment_clear_and_is_no_longer(fast):
    wall = [Shape("box", (0.05, 1.2, 1.2), np.array([0.45, 0.0, 0.6]))]
    q_start = np.array([-1.2, 0.2, 0.0, -1.8, 0.0, 2.0, 0.8])
    q_goal = np.array([1.2, 0.2, 0.0, -1.8, 0.0, 2.0, 0.8])
    raw = rrt_connect.rrt_connect(fast.spheres, q_start, q_goal, fast.limits.lower,
                                  fast.limits.upper, wall, 0.01, (0.01, 0.01), 0.02, 20.0,
                                  seed=1, step=0.3)
    assert raw is not None and len(raw) > 3
    short = path_shortcutting.shortcut(fast.spheres, raw, wall, 0.01, 0.01, 0.02,
                                       fast.limits.lower, fast.limits.upper)
    np.testing.assert_allclose(short[[0, -1]], raw[[0, -1]])
    assert all(fast.segment_free(a, b, wall, 0.01, resolution=0.02, exact_band=False)
               for a, b in zip(short, short[1:], strict=False))

    def length(p):
        return float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1)))

    assert len(short) <= len(raw) and length(short) <= length(raw) + 1e-9
    # a deadline already past (a moving arm's route after the handover): no pull round
    greedy = path_shortcutting.shortcut(fast.spheres, raw, wall, 0.01, 0.01, 0.02,
                                        fast.limits.lower, fast.limits.upper, deadline=0.0)
    assert all(any(np.array_equal(g, r) for r in raw) for g in greedy)  # waypoints kept
    assert length(short) < length(greedy) - 1e-3  # the pull rounds did shorten it


def _wall_at(x: float) -> Shape:
    return Shape("box", (0.05, 1.5, 1.5), np.array([x + 0.025, 0.0, 0.5]))


def test_a_goal_only_the_meshes_accept_is_left_along_the_clearance_gradient(fast):
    """A wall 6 mm from the hand: the fast model (its spheres bulge up to ~11 mm, + 2 mm)
    refuses the goal, the meshes keep it. The retreat climbs the fast clearance to the
    full margin within a few steps of the goal, and the planner routes into the goal
    through one segment certified on the meshes."""
    mesh = Robot("mesh")
    q_goal = READY.copy()
    x = 1.0
    for _ in range(3):  # slide the wall along x until the meshes keep 6 mm
        x += 0.006 - mesh.clearance(q_goal, [_wall_at(x)]).distance
    wall = _wall_at(x)
    assert 0.004 < mesh.clearance(q_goal, [wall]).distance < 0.008
    assert fast.clearance(q_goal, [wall]).distance <= 0.01
    planner = GraphPlanner(DamonModel.load().graph, fast, joint_limits("panda"),
                           PlannerConfig(time_budget_s=5.0, fallback_budget_s=2.0))
    out = planner._retreat(q_goal, (wall,))
    assert len(out) >= 1
    assert fast.clearance(out[0], [wall]).distance > planner.config.margin
    assert np.max(np.abs(out[0] - q_goal)) < 0.6
    q_start = READY.copy()
    q_start[0] += 0.8
    result = planner.plan(q_start, q_goal, [wall])
    assert result.success, result.reason
    for a, b in zip(result.path, result.path[1:], strict=False):
        states = a + np.linspace(0.0, 1.0, 30)[:, None] * (b - a)
        assert mesh.distances(states, [wall]).min() > 0.0
