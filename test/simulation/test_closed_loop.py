"""The closed-loop simulation acts on a threat as the planner node does."""

from __future__ import annotations

import numpy as np

from damon_ros.core.robot import Robot
from damon_ros.core.scenario import load_public_scenarios
from damon_ros.learning.bundle import DamonModel
from damon_ros.planning.graph_planner import GraphPlanner
from damon_ros.planning.reactive import Event, ReactivePlanner
from damon_ros.simulation import closed_loop
from damon_ros.simulation.closed_loop import SimConfig, run_scenario

SLOW_MS = 1000.0
"""How long the re-route after the threat takes (charged as its decision time): long past a
brake from full speed (~0.3 s)."""
FAST_RAD_S = 1.5


class _ThreatAtSpeed(ReactivePlanner):
    """The first update that finds the arm at `FAST_RAD_S` finds a threat (`on_threat`, as
    `ReactivePlanner.update` calls it) and then takes `SLOW_MS` to decide on a hold: a
    fallback search that runs out. Triggered by the arm's speed, not the clock, so that a
    late start on a loaded machine does not move it."""

    threat_at: float | None = None

    def update(self, t, q_now, obstacles, perception_age_s=0.0, qd_now=None) -> Event | None:
        if self.threat_at is None and qd_now is not None and np.max(np.abs(qd_now)) > FAST_RAD_S:
            self.threat_at = t
            if self.on_threat is not None:  # as ReactivePlanner.update calls it
                self.on_threat("a threat (test)")
            return self._hold("a threat (test); no route (test)", None, SLOW_MS)
        return super().update(t, q_now, obstacles, perception_age_s, qd_now)


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
    planner = GraphPlanner(DamonModel.load().graph, fast, fast.limits)
    planner.warm_up()
    runtime = _ThreatAtSpeed(planner)
    run_scenario(load_public_scenarios(["A-001"])[0], runtime, "damon", mesh, fast, SimConfig())
    assert runtime.threat_at is not None, "the arm never reached full speed"
    times, speed = np.array(speeds).T
    later = np.searchsorted(times, runtime.threat_at + 0.3)  # the hold acts after 1 s
    assert speed[later] < 0.2 * FAST_RAD_S, speed[later]  # coasting on: ~2 rad/s
