"""Every validator at a node's door: named cases, then properties over arbitrary input.

The properties are the safety contract of issue 6: whatever a message holds, a validator
either returns usable (finite, in-range) values or refuses with a one-line reason; it never
raises anything else, so a node's callback cannot die on a bad message.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from geometry_msgs.msg import PoseStamped
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from sensor_msgs.msg import JointState
from visualization_msgs.msg import Marker

from damon_ros.core.limits import READY as READY_Q
from damon_ros.core.limits import joint_limits
from damon_ros.planning.follower import validate_trajectory
from damon_ros.ros.inputs import CLOCK_RESET_S, InputError, JointStateReader, goal_problem
from damon_ros.ros.markers import MAX_SIZE_M, ObstacleTable
from damon_ros.ros.problems import ProblemLog

READY = READY_Q.tolist()  # a list: the cases below splice it
NAMES = [f"panda_joint{i}" for i in range(1, 8)]
LIM = joint_limits("panda")
FRAME = "panda_link0"
any_float = st.floats(allow_nan=True, allow_infinity=True, width=64)
PROPERTY = settings(max_examples=150, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.too_slow])


def pose(x=0.4, y=0.0, z=0.4, q=(1.0, 0.0, 0.0, 0.0), frame=FRAME) -> PoseStamped:
    msg = PoseStamped()
    msg.header.frame_id = frame
    msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = x, y, z
    o = msg.pose.orientation
    o.x, o.y, o.z, o.w = q
    return msg


def joint_state(names=NAMES, positions=READY, stamp=1.0) -> JointState:
    msg = JointState(name=list(names), position=[float(p) for p in positions])
    sec = int(stamp)
    msg.header.stamp = Time(sec=sec, nanosec=int(round((stamp - sec) * 1e9)))
    return msg


# ----------------------------------------------------------------------------- goals

@pytest.mark.parametrize(("msg", "words"), [
    (pose(), ""),
    (pose(frame=""), ""),  # empty frame = the base frame
    (pose(frame="world"), "frame_id 'world' is not the base frame 'panda_link0'"),
    (pose(x=math.nan), "pose holds NaN or inf"),
    (pose(z=math.inf), "pose holds NaN or inf"),
    (pose(q=(0.0, 0.0, 0.0, 0.0)), "not a unit quaternion (norm 0.0000)"),
    (pose(q=(1.0, 1.0, 0.0, 0.0)), "not a unit quaternion (norm 1.4142)"),
])
def test_goal_problems_are_named(msg, words):
    problem = goal_problem(msg, FRAME)
    assert words in problem and (problem == "") == (words == "")


@PROPERTY
@given(values=st.lists(any_float, min_size=7, max_size=7),
       frame=st.sampled_from(["", FRAME, "world", "panda_hand"]))
def test_a_goal_passes_only_when_finite_unit_and_in_the_base_frame(values, frame):
    problem = goal_problem(pose(*values[:3], q=values[3:], frame=frame), FRAME)
    assert isinstance(problem, str) and "\n" not in problem
    usable = (frame in ("", FRAME) and all(math.isfinite(v) for v in values)
              and abs(math.hypot(*values[3:]) - 1.0) <= 1e-3)
    assert (problem == "") == usable


# ----------------------------------------------------------------------------- joint states

def test_joint_states_any_order_with_extra_joints_are_read_by_name():
    reader = JointStateReader(NAMES)
    names = ["panda_finger_joint1"] + NAMES[::-1]
    q = reader.read(joint_state(names, [0.04] + READY[::-1]))
    np.testing.assert_array_equal(q, READY)


@pytest.mark.parametrize(("msg", "words"), [
    (joint_state(NAMES[:6], READY[:6]), r"lacks \['panda_joint7'\]"),
    (joint_state(NAMES, READY[:6]), "7 names but 6 positions"),
    (joint_state(NAMES, READY[:3] + [math.nan] + READY[4:]), "NaN or inf"),
    (joint_state(NAMES, READY[:3] + [-math.inf] + READY[4:]), "NaN or inf"),
])
def test_bad_joint_states_are_refused(msg, words):
    with pytest.raises(InputError, match=words):
        JointStateReader(NAMES).read(msg)


def test_joint_state_stamps_must_not_go_backwards_except_for_a_clock_reset():
    reader = JointStateReader(NAMES)
    reader.read(joint_state(stamp=10.0))
    reader.read(joint_state(stamp=10.0))  # a repeat is harmless
    with pytest.raises(InputError, match=r"goes backwards \(5.0 ms older"):
        reader.read(joint_state(stamp=9.995))
    reader.read(joint_state(stamp=10.001))
    assert reader.clock_resets == 0
    reader.read(joint_state(stamp=10.001 - CLOCK_RESET_S - 0.5))  # a simulator restart
    assert reader.clock_resets == 1
    reader.read(joint_state(stamp=0.0))  # unstamped: no order to check
    with pytest.raises(InputError, match="backwards"):
        reader.read(joint_state(stamp=10.001 - CLOCK_RESET_S - 0.5 - 0.01))


@PROPERTY
@given(order=st.permutations(range(9)), keep=st.integers(5, 9),
       positions=st.lists(st.one_of(any_float, st.floats(-3.0, 3.0)), min_size=0, max_size=10),
       stamps=st.lists(st.floats(0.0, 5.0), min_size=1, max_size=4))
def test_a_joint_state_is_read_by_name_and_finite_or_refused(order, keep, positions, stamps):
    pool = NAMES + ["panda_finger_joint1", "panda_finger_joint2"]
    names = [pool[k] for k in order[:keep]]
    reader = JointStateReader(NAMES)
    for stamp in stamps:
        msg = joint_state(names, positions, stamp)
        try:
            q = reader.read(msg)
        except InputError as exc:
            assert "\n" not in str(exc)
            continue
        assert q.shape == (7,) and np.all(np.isfinite(q))
        assert list(q) == [positions[names.index(n)] for n in NAMES]


# ----------------------------------------------------------------------------- trajectories

@PROPERTY
@given(names=st.lists(st.sampled_from(NAMES + ["elbow", ""]), min_size=0, max_size=8),
       times=st.lists(any_float, min_size=0, max_size=4),
       rows=st.lists(st.lists(st.one_of(any_float, st.floats(-3.0, 3.0)), max_size=8),
                     max_size=4),
       velocities=st.one_of(st.none(), st.lists(st.lists(any_float, max_size=8), max_size=4)),
       start=st.one_of(st.none(), st.floats(0.0, 100.0)))
def test_a_trajectory_is_accepted_only_when_every_point_is_finite_and_in_limits(
        names, times, rows, velocities, start):
    reason = validate_trajectory(names, NAMES, times, rows, velocities, None, LIM,
                                 start_time=start, now=50.0)
    if reason is not None:
        assert isinstance(reason, str) and reason and "\n" not in reason
        return
    assert sorted(names) == sorted(NAMES)  # every joint once, in any order
    if not times:
        return  # no points: "stop and hold"
    order = [names.index(n) for n in NAMES]
    pos = np.asarray(rows, dtype=float)[:, order]
    assert np.all(np.isfinite(times)) and times[0] >= 0.0 and np.all(np.diff(times) > 0)
    assert np.all((pos >= LIM.lower - 1e-6) & (pos <= LIM.upper + 1e-6))
    if velocities:
        vel = np.array([v for v in velocities if v], dtype=float).reshape(-1, 7)[:, order]
        assert np.all(np.abs(vel) <= LIM.velocity + 1e-6)


# ----------------------------------------------------------------------------- markers

@PROPERTY
@given(kind=st.sampled_from([Marker.SPHERE, Marker.CUBE, Marker.CYLINDER, Marker.ARROW,
                             Marker.TEXT_VIEW_FACING, Marker.MESH_RESOURCE, 99]),
       action=st.sampled_from([Marker.ADD, Marker.DELETE, Marker.DELETEALL, 7]),
       numbers=st.lists(st.one_of(any_float, st.floats(-5.0, 5.0)), min_size=10,
                        max_size=10),
       frame=st.sampled_from([FRAME, "", "camera_link"]))
def test_a_marker_becomes_a_sane_obstacle_or_a_one_line_refusal(kind, action, numbers, frame):
    m = Marker(ns="red", id=1, type=kind, action=action)
    m.header.frame_id = frame
    p, o, s = m.pose.position, m.pose.orientation, m.scale
    p.x, p.y, p.z, o.x, o.y, o.z, o.w, s.x, s.y, s.z = numbers
    table = ObstacleTable(FRAME)
    errors = table.apply([m], now=1.0)
    assert all(isinstance(e, str) and "\n" not in e for e in errors)
    for obstacle in table.obstacles(1.0):
        shape = obstacle.shape
        assert np.all(np.isfinite(shape.position)) and np.all(np.isfinite(obstacle.velocity))
        assert 0.0 < shape.bounding_radius() <= MAX_SIZE_M


# ----------------------------------------------------------------------------- logging

def test_problem_log_logs_each_kind_at_once_and_counts_repeats():
    lines, now = [], [0.0]
    log = ProblemLog(lines.append, every_s=5.0, clock=lambda: now[0])
    for _ in range(3):
        log.report("ignored joint state: joint state holds NaN or inf positions")
    log.report("ignored joint state: joint state stamp goes backwards (1.0 ms older ...)")
    assert len(lines) == 2  # two kinds, one line each; the repeats are counted
    now[0] = 6.0
    log.report("ignored joint state: joint state holds NaN or inf positions")
    assert lines[-1].endswith("(2 more since)")
