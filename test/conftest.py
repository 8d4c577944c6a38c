"""Suite-wide set-up: the compiled kernels exist on disk before any node process starts.

numba caches a kernel beside its module the first time it is compiled. In a fresh clone
that first time was inside whichever test came first — for the planner's RRT-Connect, a
planner node's start-up (11 s of compiling on a quiet core, more on a busy one), within the
bound that test gives the node to come up. Compiling once here makes every start-up load them.
"""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session", autouse=True)
def compiled_kernels():
    from damon_ros.core.limits import joint_limits
    from damon_ros.core.robot import Robot
    from damon_ros.perception import colour_classes, fit_kernels
    from damon_ros.planning import path_shortcutting, rrt_connect, space_time
    from damon_ros.planning.follower import CommandShaper

    robot = Robot("fast")
    spheres = robot.spheres
    rrt_connect.warm_up(spheres)
    path_shortcutting.warm_up(spheres)
    space_time.warm_up(robot)
    CommandShaper(joint_limits("fr3"))  # its kernels and the FR3's velocity bounds
    fit_kernels.warm_up()  # the tracker's shape fits
    colour_classes.warm_up()  # and its colour segmentation
