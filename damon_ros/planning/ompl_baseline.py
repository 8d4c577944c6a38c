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

import numpy as np

from damon_ros.core.limits import JointLimits
from damon_ros.planning.graph_planner import GraphPlanner, PlannerConfig, PlanResult, Scene, _Query

ALGORITHMS = {"rrt": "RRT", "rrtstar": "RRTstar", "rrtconnect": "RRTConnect"}


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
        from ompl import base as ob
        from ompl import geometric as og
        from ompl import util as ou

        t0 = time.perf_counter()
        ou.setLogLevel(ou.LogLevel.LOG_NONE)
        ou.RNG.setSeed(self.seed)
        space = ob.RealVectorStateSpace(7)
        bounds = ob.RealVectorBounds(7)
        for i in range(7):
            bounds.setLow(i, float(self.limits.lower[i]))
            bounds.setHigh(i, float(self.limits.upper[i]))
        space.setBounds(bounds)
        si = ob.SpaceInformation(space)
        # one margin for every state OMPL checks; never below zero (the planner's "may only
        # move away" rule for a start inside the conservative envelope needs segment order)
        margin = max(0.0, min(self.config.margin, self._start_margin(q_start, scene.now)))
        obstacles = scene.ahead
        robot = self.robot

        def valid(state) -> bool:
            q = np.array([state[i] for i in range(7)])
            return not obstacles or bool(robot.distances(q[None], obstacles)[0] > margin)

        si.setStateValidityChecker(valid)
        # OMPL steps motions by a fraction of the space's extent (L2): ≤ our max-norm step
        si.setStateValidityCheckingResolution(self.config.resolution / space.getMaximumExtent())
        si.setup()
        start, goal = space.allocState(), space.allocState()
        for i in range(7):
            start[i], goal[i] = float(q_start[i]), float(q_goal[i])
        pdef = ob.ProblemDefinition(si)
        pdef.setStartAndGoalStates(start, goal)
        planner = getattr(og, ALGORITHMS[self.algorithm])(si)
        if self.range_rad:
            planner.setRange(self.range_rad)
        planner.setProblemDefinition(pdef)
        planner.setup()
        budget = self.solve_time
        planner.solve(budget)
        result = PlanResult(False, "", goal_q=q_goal)
        if pdef.hasExactSolution():
            path = pdef.getSolutionPath()
            og.PathSimplifier(si).simplifyMax(path)
            waypoints = np.array([[path.getState(k)[i] for i in range(7)]
                                  for k in range(path.getStateCount())])
            waypoints[0], waypoints[-1] = q_start, q_goal
            query = _Query(self, q_start, q_goal, scene)  # the planner's own certification
            last = len(waypoints) - 2
            if all(query.segment_certified(a, b, first=i == 0, last=i == last)
                   and self.robot.segment_self_collision_free(a, b)
                   for i, (a, b) in enumerate(zip(waypoints, waypoints[1:], strict=False))):
                result.success, result.path = True, waypoints
                result.trajectory = self._time_parameterize(waypoints)
            else:
                result.reason = (f"{ALGORITHMS[self.algorithm]} path fails certification "
                                 "(self-collision or margin); holding")
        else:
            result.reason = (f"{ALGORITHMS[self.algorithm]} found no route in "
                             f"{budget:.2f} s; holding position")
        result.timing_ms["search"] = 1e3 * (time.perf_counter() - t0)
        return result
