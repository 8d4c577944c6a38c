"""OMPL baselines (RRT, RRT*, RRTConnect) behind the planner's own interface.

They subclass :class:`damon_ros.planning.graph_planner.GraphPlanner` and replace only
the route search, so the runtime loop, goal resolution (the same IK), certification rules
(the same conservative fast model, margin and first-segment rule), self-collision rule,
shortcutting, time parameterisation and controller are identical: what differs is how a
route is found. Re-planning from the current state when the path is threatened (the runtime
loop) is the honest stand-in for Dynamic RRT*.
"""

from __future__ import annotations

import time

from damon_ros.core.limits import JointLimits
from damon_ros.planning.graph_planner import GraphPlanner, PlannerConfig, PlanResult, Scene, _Query
from damon_ros.planning.sampling import ALGORITHMS, sampling_route


class OmplPlanner(GraphPlanner):
    """A sampling-based planner from OMPL; ``solve_time`` bounds one route search (s).
    RRT* uses the whole budget to improve its path; RRT and RRTConnect stop at the first
    solution."""

    def __init__(self, algorithm: str, robot, limits: JointLimits,
                 config: PlannerConfig | None = None, solve_time: float = 1.0,
                 range_rad: float = 0.0, seed: int = 0) -> None:
        if algorithm not in ALGORITHMS:
            raise ValueError(f"unknown OMPL planner {algorithm!r}; expected one of "
                             f"{sorted(ALGORITHMS)}")
        from dataclasses import replace

        # the search budget is the OMPL solve time (RRT* spends all of it improving its path)
        config = replace(config or PlannerConfig(), time_budget_s=solve_time)
        super().__init__(None, robot, limits, config)
        self.algorithm = algorithm
        self.solve_time = solve_time
        self.range_rad = range_rad
        self.seed = seed

    def settings(self) -> dict:
        return {"algorithm": ALGORITHMS[self.algorithm], "solve_time_s": self.solve_time,
                "range_rad": self.range_rad or "OMPL default",
                "motion_check_step_rad": self.config.resolution, "simplify": True,
                "margin_m": self.config.margin}

    def _route(self, q_start, q_goal, scene: Scene) -> PlanResult:
        t0 = time.perf_counter()
        # one margin for every state OMPL checks; never below zero (the planner's "may only
        # move away" rule for a start inside the conservative envelope needs segment order)
        margin = min(self.config.margin, self._start_margin(q_start, scene.now))
        waypoints = sampling_route(self.algorithm, self.robot, self.limits, q_start, q_goal,
                                   scene.ahead, margin, self.config.resolution,
                                   self.solve_time, self.seed, self.range_rad)
        result = PlanResult(False, "", goal_q=q_goal)
        name = ALGORITHMS[self.algorithm]
        if waypoints is None:
            result.reason = f"{name} found no route in {self.solve_time:.2f} s; holding position"
        elif self._certified(waypoints, _Query(self, q_start, q_goal, scene)):
            result.success, result.path = True, waypoints
            result.trajectory = self._time_parameterize(waypoints)
        else:
            result.reason = f"{name} path fails certification (self-collision or margin); holding"
        result.timing_ms["search"] = 1e3 * (time.perf_counter() - t0)
        return result
