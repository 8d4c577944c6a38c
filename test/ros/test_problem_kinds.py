"""Each message problem of the README's safety table has its own log line and a throttled
count: a property test over the validators (markers, goals, joint states) and `ProblemLog`."""

from __future__ import annotations

import math

from geometry_msgs.msg import PoseStamped
from hypothesis import given, settings
from hypothesis import strategies as st
from sensor_msgs.msg import JointState
from visualization_msgs.msg import Marker

from damon_ros.core.shapes import Shape
from damon_ros.ros.inputs import InputError, JointStateReader, goal_problem
from damon_ros.ros.markers import MAX_SIZE_M, ObstacleTable, shape_to_marker
from damon_ros.ros.problems import ProblemLog

FRAME = "panda_link0"
NAMES = [f"panda_joint{i}" for i in range(1, 8)]
finite = st.floats(-10.0, 10.0, allow_nan=False)


def _marker() -> Marker:
    return shape_to_marker(Shape("sphere", (0.05,), [0.3, 0.5, 0.8]), "t", 1, FRAME, 1.0, 0.5,
                           (1.0, 0.0, 0.0, 1.0))


def _set_scale(m: Marker, v: float) -> None:
    m.scale.x = m.scale.y = m.scale.z = v


# defect name -> (strategy for its parameter, how to apply it, the kind it must report)
MARKER_DEFECTS = {
    "nan position": (st.sampled_from([math.nan, math.inf, -math.inf]),
                     lambda m, v: setattr(m.pose.position, "y", v), "marker.position_not_finite"),
    "bad quaternion": (st.floats(0.0, 0.9), lambda m, v: setattr(m.pose.orientation, "w", v),
                       "marker.orientation_not_unit"),
    "size <= 0": (st.floats(-5.0, 0.0), _set_scale, "marker.size_not_positive"),
    "size > 3 m": (st.floats(MAX_SIZE_M + 1e-3, 1e6), _set_scale, "marker.size_too_large"),
    "nan size": (st.just(math.nan), _set_scale, "marker.size_not_finite"),
    "unknown type": (st.sampled_from([Marker.TEXT_VIEW_FACING, Marker.ARROW, 99]),
                     lambda m, v: setattr(m, "type", v), "marker.type_unknown"),
    "unknown action": (st.sampled_from([1, 4, 7]), lambda m, v: setattr(m, "action", v),
                       "marker.action_unknown"),
    "other frame": (st.sampled_from(["world", "fr3_link0", "map"]),
                    lambda m, v: setattr(m.header, "frame_id", v), "marker.frame_other"),
}


def _goal() -> PoseStamped:
    g = PoseStamped()
    g.header.frame_id = FRAME
    g.pose.position.x, g.pose.position.z = 0.4, 0.5
    g.pose.orientation.w = 1.0
    return g


GOAL_DEFECTS = {
    "nan pose": (st.sampled_from([math.nan, math.inf]),
                 lambda g, v: setattr(g.pose.position, "x", v), "goal.not_finite"),
    "bad quaternion": (st.floats(0.0, 0.99), lambda g, v: setattr(g.pose.orientation, "w", v),
                       "goal.orientation_not_unit"),
    "other frame": (st.sampled_from(["world", "map"]),
                    lambda g, v: setattr(g.header, "frame_id", v), "goal.frame_other"),
}


def _joint_state(stamp: float = 10.0) -> JointState:
    js = JointState(name=list(NAMES), position=[0.1] * 7)
    js.header.stamp.sec = int(stamp)
    return js


JOINT_DEFECTS = {
    "joint missing": (st.integers(0, 6), lambda js, k: js.name.__setitem__(k, "finger"),
                      "joint_state.joints_missing"),
    "lengths": (st.integers(1, 6), lambda js, k: setattr(js, "position", [0.1] * k),
                "joint_state.lengths"),
    "nan": (st.sampled_from([math.nan, math.inf]),
            lambda js, v: setattr(js, "position", [v] + [0.1] * 6), "joint_state.not_finite"),
}


def _marker_kind(name: str, value) -> str:
    _, apply, _ = MARKER_DEFECTS[name]
    m = _marker()
    apply(m, value)
    errors = ObstacleTable(FRAME).apply([m], 1.0)
    assert len(errors) == 1, (name, value)
    return errors[0].kind


def _goal_kind(name: str, value) -> str:
    g = _goal()
    GOAL_DEFECTS[name][1](g, value)
    problem = goal_problem(g, FRAME)
    assert problem, (name, value)
    return problem.kind


def _joint_kind(name: str, value) -> str:
    js = _joint_state()
    JOINT_DEFECTS[name][1](js, value)
    try:
        JointStateReader(NAMES).read(js)
    except InputError as exc:
        return exc.kind
    raise AssertionError(f"{name} {value} accepted")


def _defect(table):
    return st.sampled_from(sorted(table)).flatmap(
        lambda name: st.tuples(st.just(name), table[name][0]))


ANY_DEFECT = st.one_of(
    _defect(MARKER_DEFECTS).map(lambda d: ("marker", *d)),
    _defect(GOAL_DEFECTS).map(lambda d: ("goal", *d)),
    _defect(JOINT_DEFECTS).map(lambda d: ("joint", *d)),
)
KIND_OF = {"marker": _marker_kind, "goal": _goal_kind, "joint": _joint_kind}
TABLES = {"marker": MARKER_DEFECTS, "goal": GOAL_DEFECTS, "joint": JOINT_DEFECTS}


def test_the_valid_messages_pass():
    assert ObstacleTable(FRAME).apply([_marker()], 1.0) == []
    assert goal_problem(_goal(), FRAME) == ""
    JointStateReader(NAMES).read(_joint_state())


def test_stamp_going_back_is_its_own_kind():
    reader = JointStateReader(NAMES)
    reader.read(_joint_state(10.0))
    try:
        reader.read(_joint_state(9.5))
    except InputError as exc:
        assert exc.kind == "joint_state.stamp_backwards"
    else:
        raise AssertionError("an older stamp was accepted")


def test_every_defect_has_a_kind_of_its_own():
    kinds = [table[name][2] for table in TABLES.values() for name in table]
    assert len(set(kinds)) == len(kinds)


@settings(max_examples=60, deadline=None)
@given(ANY_DEFECT)
def test_each_defect_reports_its_own_kind_whatever_its_numbers(defect):
    source, name, value = defect
    assert KIND_OF[source](name, value) == TABLES[source][name][2]


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(ANY_DEFECT, st.floats(0.0, 3.0)), min_size=1, max_size=40))
def test_each_kind_has_its_first_line_at_once_and_then_a_throttled_count(stream):
    """Whatever the mix and timing: a kind's first message is logged when it occurs (no
    other kind can hide it), repeats within ``every_s`` are not, and the next line of the
    kind carries the exact count of those left out."""
    now, lines = [0.0], []
    log = ProblemLog(lines.append, every_s=5.0, clock=lambda: now[0])
    last_logged: dict[str, float] = {}
    left_out: dict[str, int] = {}
    for (source, name, value), gap in stream:
        now[0] += gap
        kind = TABLES[source][name][2]
        message = f"{source} refused: {name} {value!r}"
        before = len(lines)
        logged = log.report(message, kind)
        due = kind not in last_logged or now[0] - last_logged[kind] >= 5.0
        assert logged == due and len(lines) == before + due
        if due:
            count = left_out.pop(kind, 0)
            assert lines[-1] == (message if not count else f"{message} ({count} more since)")
            last_logged[kind] = now[0]
        else:
            left_out[kind] = left_out.get(kind, 0) + 1
            assert log.suppressed(kind) == left_out[kind]


def test_a_huge_marker_is_not_hidden_behind_a_size_zero_one():
    lines: list[str] = []
    log = ProblemLog(lines.append, every_s=5.0, clock=lambda: 0.0)
    table = ObstacleTable(FRAME)
    for size in (0.0, 100.0, 0.0, 100.0):
        m = _marker()
        _set_scale(m, size)
        (error,) = table.apply([m], 1.0)
        log.report(f"obstacle marker refused: {error}", error.kind)
    assert len(lines) == 2 and "> 0 m" in lines[0] and "<= 3.0 m" in lines[1]
