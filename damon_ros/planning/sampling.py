"""Sampling-based route search (OMPL) in the planner's configuration space.

One place that sets OMPL up the way this project certifies motions: states within the
joint limits, each valid when the conservative fast model keeps ``margin`` from every
obstacle, motions checked at ≤ ``resolution`` rad steps. Used by the OMPL baselines and by
the graph planner's complete fallback (:meth:`GraphPlanner._fallback`); the caller
certifies what comes back with its own segment rules before anything is executed.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from damon_ros.core.limits import JointLimits
from damon_ros.core.shapes import Shape

ALGORITHMS = {"rrt": "RRT", "rrtstar": "RRTstar", "rrtconnect": "RRTConnect"}


def sampling_route(algorithm: str, robot, limits: JointLimits, q_start: np.ndarray,
                   q_goal: np.ndarray, obstacles: Sequence[Shape], margin: float,
                   resolution: float, budget_s: float, seed: int = 0,
                   range_rad: float = 0.0) -> np.ndarray | None:
    """Simplified waypoints from ``q_start`` to ``q_goal`` (exactly those two at the ends),
    or None when OMPL finds no exact solution within ``budget_s``."""
    from ompl import base as ob
    from ompl import geometric as og
    from ompl import util as ou

    ou.setLogLevel(ou.LogLevel.LOG_NONE)
    ou.RNG.setSeed(int(seed))
    space = ob.RealVectorStateSpace(7)
    bounds = ob.RealVectorBounds(7)
    for i in range(7):
        bounds.setLow(i, float(limits.lower[i]))
        bounds.setHigh(i, float(limits.upper[i]))
    space.setBounds(bounds)
    si = ob.SpaceInformation(space)
    margin = max(0.0, margin)

    obstacles = tuple(obstacles)  # one packing for the whole search (`SphereModel.packed`)

    def valid(state) -> bool:
        q = np.array([state[i] for i in range(7)])
        return not obstacles or robot.state_free(q, obstacles, margin)

    si.setStateValidityChecker(valid)
    # OMPL steps motions by a fraction of the space's extent (L2): ≤ our max-norm step
    si.setStateValidityCheckingResolution(resolution / space.getMaximumExtent())
    si.setup()
    start, goal = space.allocState(), space.allocState()
    for i in range(7):
        start[i], goal[i] = float(q_start[i]), float(q_goal[i])
    pdef = ob.ProblemDefinition(si)
    pdef.setStartAndGoalStates(start, goal)
    planner = getattr(og, ALGORITHMS[algorithm])(si)
    if range_rad:
        planner.setRange(range_rad)
    planner.setProblemDefinition(pdef)
    planner.setup()
    planner.solve(float(budget_s))
    if not pdef.hasExactSolution():
        return None
    path = pdef.getSolutionPath()
    og.PathSimplifier(si).simplifyMax(path)
    waypoints = np.array([[path.getState(k)[i] for i in range(7)]
                          for k in range(path.getStateCount())])
    waypoints[0], waypoints[-1] = q_start, q_goal
    return waypoints
