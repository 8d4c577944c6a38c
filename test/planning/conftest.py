"""Fixtures of the space-time and certified-stop tests: the fast robot model and a graph
planner on the shipped model (modules that need others define their own)."""

from __future__ import annotations

import pytest

from damon_ros.core.limits import joint_limits
from damon_ros.core.robot import Robot
from damon_ros.learning.bundle import DamonModel
from damon_ros.planning.graph_planner import GraphPlanner, PlannerConfig

CONFIG = PlannerConfig(time_budget_s=5.0, handover_s=5.0)  # see test_planner.TEST_CONFIG


@pytest.fixture(scope="module")
def fast() -> Robot:
    return Robot("fast")


@pytest.fixture(scope="module")
def planner(fast) -> GraphPlanner:
    p = GraphPlanner(DamonModel.load().graph, fast, joint_limits("panda"), CONFIG)
    p.warm_up()
    return p
