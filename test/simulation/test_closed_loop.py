"""The closed-loop simulation acts on a threat as the planner node does."""

from __future__ import annotations

import time

import numpy as np
import yaml

from damon_ros.core.resources import public_scenarios_dir
from damon_ros.core.robot import Robot
from damon_ros.core.scenario import parse_scenario
from damon_ros.learning.bundle import DamonModel
from damon_ros.planning.graph_planner import GraphPlanner, PlanResult
from damon_ros.planning.reactive import ReactivePlanner
from damon_ros.simulation import closed_loop
from damon_ros.simulation.closed_loop import SimConfig, pose_goal, run_scenario

SLOW_S = 1.0
"""Wall time every re-route takes in the test: long past a brake (~0.3 s from 2 rad/s)."""


class _SlowReroute(GraphPlanner):
    """Re-routes take `SLOW_S` and find nothing (a fallback search that runs out)."""

    def replan(self, *args, **kwargs) -> PlanResult:
        time.sleep(SLOW_S)
        return PlanResult(False, "no route (slow on purpose)")


def test_a_threat_stops_the_arm_before_a_slow_reroute_is_decided(monkeypatch):
    """The node sends a stop the moment it finds a threat (`on_threat`), then re-routes; the
    simulation did nothing until the re-route was decided, so the arm coasted on into the
    threat for the whole search (a hold after a 0.1 s fallback search, on the stress bench)."""
    speeds: list[tuple[float, float]] = []

    class Recorded(closed_loop.ArmSim):
        def step(self, dt, t):
            q, qd = super().step(dt, t)
            speeds.append((t, float(np.max(np.abs(qd)))))
            return q, qd

    monkeypatch.setattr(closed_loop, "ArmSim", Recorded)
    fast, mesh = Robot("fast"), Robot("mesh")
    planner = _SlowReroute(DamonModel.load().graph, fast, fast.limits)
    planner.warm_up()
    data = yaml.safe_load((public_scenarios_dir() / "A-001.yaml").read_text())
    first = planner.plan(parse_scenario(data).start, pose_goal(parse_scenario(data)),
                         parse_scenario(data).obstacles_at(0.0)).trajectory
    # a ball rolls in from the side (1 m/s) to where the hand will be 60 % into its move
    k = int(np.searchsorted(first.times, 0.6 * first.times[-1]))
    target = fast.tcp_positions(first.positions[k][None])[0]
    far = target + [0.0, 0.8, 0.0]
    data["obstacles"].append({
        "name": "roller", "shape": "sphere", "size": [0.04], "color": "blue",
        "pose": {"position": far.tolist(), "orientation": [0.0, 0.0, 0.0, 1.0]},
        "motion": {"type": "waypoints",
                   "waypoints": [[0.0, *far], [0.4, *far], [1.2, *target]]}})
    data["time_limit"] = 2.0
    runtime = ReactivePlanner(planner)
    found: list[float] = []
    update = runtime.update

    def recorded_update(t, *args, **kwargs):
        found.append(t)
        return update(t, *args, **kwargs)

    threats: list[float] = []
    runtime.update = recorded_update
    runtime.on_threat = lambda why: threats.append(found[-1])
    run_scenario(parse_scenario(data), runtime, "damon", mesh, fast, SimConfig())
    assert threats, "the rolling ball never threatened the trajectory"
    times, speed = np.array(speeds).T
    at_threat = speed[np.searchsorted(times, threats[0])]
    assert at_threat > 1.0  # the arm was moving fast when the threat was found
    # the re-route is decided SLOW_S after the threat; the stop has acted long before that
    later = np.searchsorted(times, threats[0] + 0.3 * SLOW_S)
    assert later < len(times), "the run ended (contact?) before the stop could act"
    assert speed[later] < 0.25 * at_threat, (at_threat, speed[later])
