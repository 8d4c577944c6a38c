"""Honest refusals: a goal refused only because of the hidden extent of an estimate says so."""

from __future__ import annotations

import numpy as np
import pytest

from damon_ros.core.limits import joint_limits
from damon_ros.core.robot import Robot
from damon_ros.core.scenario import load_public_scenarios
from damon_ros.core.shapes import Shape
from damon_ros.learning.bundle import DamonModel
from damon_ros.perception.unseen import Estimate, unseen_blockers, unseen_reason
from damon_ros.planning.graph_planner import GraphPlanner, PlannerConfig
from damon_ros.simulation.closed_loop import pose_goal

SCENARIO = load_public_scenarios()[0]  # a goal with the hand pointing down


@pytest.fixture(scope="module")
def planner() -> GraphPlanner:
    p = GraphPlanner(DamonModel.load().graph, Robot("fast"), joint_limits("panda"),
                     PlannerConfig(time_budget_s=5.0, handover_s=5.0))
    p.warm_up()
    return p


def _face(y: float) -> Shape:
    """A seen face of 10 x 10 cm, vertical, at ``y``, centred on the goal in x and z."""
    g = SCENARIO.goal.position
    corners = np.array([[dx, 0.0, dz] for dx in (-0.05, 0.05) for dz in (-0.05, 0.05)])
    return Shape("points", (), [g[0], y, g[2]], points=corners)


def test_a_goal_in_the_hidden_extent_names_it_and_one_in_the_seen_surface_does_not(planner):
    g = SCENARIO.goal.position
    # seen: a face 20 cm beyond the goal (away from the robot); the bound reaches back
    # over the goal by the hidden-depth prior
    bound = Shape("box", (0.1, 0.25, 0.1), [g[0], g[1] - 0.075, g[2]])
    goal = pose_goal(SCENARIO)
    refused = planner.plan(SCENARIO.start, goal, [bound])
    assert not refused.success and "goal pose refused" in refused.reason

    def blockers(seen: Shape | None):
        return unseen_blockers(
            lambda obstacles: planner.resolve_goal(goal, SCENARIO.start, obstacles),
            lambda q, shape: float(planner.robot.distances(q[None], [shape])[0]),
            planner.config.margin, [Estimate("red#1", bound, seen),
                                    Estimate("blue#2", Shape("sphere", (0.05,),
                                                             [0.3, 0.5, 0.3]), None)])

    names = blockers(_face(g[1] - 0.2))
    assert names == ["red#1"]
    text = unseen_reason(refused.reason, names)
    assert text.startswith(refused.reason) and "unseen part of red#1" in text
    assert blockers(_face(g[1])) is None  # the seen surface itself is at the goal
    assert blockers(None) is None  # nothing known to be seen: a plain refusal
