"""The controller's JTC semantics, black-box over DDS: tolerances and partial joints.

A mock_panda whose command topic is remapped away, so it publishes joint states of an arm
that never moves (a blocked arm), and a controller with tolerances on (`jtc_loop`): path
tolerance abort-and-hold, goal tolerance with ``goal_time``, partial joints allowed. Its
own module, so that the moving arm of test_node_controller_jtc.py is stopped first.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
import rosutil
from jtc_loop import ACCEPTED, NAMES, REJECTED, Loop, start, stop, trajectory

from damon_ros.ros import topics
from damon_ros.ros.environment import node_environment


@pytest.fixture(scope="module")
def blocked(tmp_path_factory):
    domain = rosutil.next_domain_id(__file__)
    tmp = tmp_path_factory.mktemp("jtc_blocked")
    env = node_environment(domain, tmp)
    # heartbeat watchdog off: it has its own tests (test_node_controller_jtc.py,
    # test_node_controller.py)
    params = {"allow_partial_joints_goal": True, "constraints.panda_joint1.trajectory": 0.05,
              "constraints.panda_joint3.goal": 0.001, "constraints.goal_time": 0.2,
              "planner_heartbeat_timeout_s": 0.0}
    loop = None
    try:
        with rosutil.RosClient(domain) as ros:
            loop = start(ros, env, tmp, "blocked", params,
                          remaps={topics.JOINT_COMMANDS: "/damon_test/nowhere"})
            yield loop
    finally:
        stop(loop)



# ----------------------------------------------------------------------------- blocked

def _desired(loop: Loop) -> np.ndarray:
    return np.array(loop.controller_state.last.position)


def test_path_tolerance_aborts_and_holds_the_measured_position(blocked: Loop):
    for _ in range(5):  # a stale-state stop of a loaded machine pre-empts an attempt
        stale = len(blocked.lines("joint states stale"))
        q = blocked.q()
        line = blocked.send(trajectory([1.0], [q + np.array([0.3, 0, 0, 0, 0, 0, 0])],
                                       [np.zeros(7)]))
        if REJECTED in line and "stale" in line:
            blocked.ros.spin_for(0.5)  # let the states come back (a loaded run: 2 in 12 ms)
            continue
        assert ACCEPTED in line, line
        if blocked.ros.spin_until(lambda: bool(blocked.lines("path tolerance violated")), 6.0) \
                or len(blocked.lines("joint states stale")) == stale:
            break
    assert blocked.lines("path tolerance violated"), blocked.logs()
    assert "panda_joint1" in blocked.lines("path tolerance violated")[-1]
    blocked.ros.spin_for(0.2)
    np.testing.assert_allclose(_desired(blocked), q, atol=1e-6)  # holds where it is


def test_goal_not_reached_within_goal_time_aborts(blocked: Loop):
    q = blocked.q()
    before = len(blocked.lines("goal not reached"))
    sent = time.monotonic()
    line = blocked.send(trajectory([0.3], [q + np.array([0, 0, 0.01, 0, 0, 0, 0])],
                                   [np.zeros(7)]))
    assert ACCEPTED in line, line
    assert blocked.ros.spin_until(lambda: len(blocked.lines("goal not reached")) > before, 3.0)
    assert time.monotonic() - sent > 0.5 - 0.05  # not before the end + goal_time
    assert "panda_joint3" in blocked.lines("goal not reached")[-1]
    blocked.ros.spin_for(0.2)
    np.testing.assert_allclose(_desired(blocked), q, atol=1e-6)


def test_partial_joints_when_allowed_hold_the_others(blocked: Loop):
    q = blocked.q()
    named = [4, 1]
    line = blocked.send(trajectory([1.0], [q[named] + 0.02], [np.zeros(2)],
                                   names=[NAMES[j] for j in named]))
    assert ACCEPTED in line and "2 of 7 joints" in line, line
    target = q[named] + 0.02
    # the desired state of the end (the client may see the controller's states late)
    assert blocked.ros.spin_until(
        lambda: np.max(np.abs(_desired(blocked)[named] - target)) < 1e-6, 5.0), blocked.logs()
    desired = _desired(blocked)
    others = [j for j in range(7) if j not in named]
    # the others hold where the controller measured them when it accepted (within 2 mrad
    # of the test's last state: the two read different messages), the named moved 20 mrad
    np.testing.assert_allclose(desired[others], q[others], atol=2e-3)
    np.testing.assert_allclose(desired[named], target, atol=1e-6)
