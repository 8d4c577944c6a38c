"""Shapes survive the trip through markers; bad markers are refused; the table follows rviz."""

from __future__ import annotations

import math

import numpy as np
import pytest
from geometry_msgs.msg import Point
from hypothesis import given, settings
from hypothesis import strategies as st
from visualization_msgs.msg import Marker

from damon_ros.core.shapes import Shape
from damon_ros.ros.markers import (
    MAX_SIZE_M,
    ObstacleTable,
    class_rgba,
    delete_all_marker,
    delete_marker,
    marker_to_shape,
    shape_to_marker,
    stamp_seconds,
    to_stamp,
)

FRAME = "panda_link0"
RGBA = (0.1, 0.8, 0.2, 0.7)
Q = np.array([0.1, -0.2, 0.3, 0.9]) / np.linalg.norm([0.1, -0.2, 0.3, 0.9])


def marker(shape: Shape, ns: str = "green", id: int = 3, stamp: float = 10.0,
           lifetime_s: float = 0.5) -> Marker:
    return shape_to_marker(shape, ns, id, FRAME, stamp, lifetime_s, RGBA)


def assert_same_shape(a: Shape, b: Shape) -> None:
    assert a.kind == b.kind and a.name == b.name
    assert np.allclose(a.size, b.size, atol=1e-12)
    assert np.allclose(a.position, b.position, atol=1e-12)
    # q and -q are the same rotation
    assert np.allclose(a.rotation(), b.rotation(), atol=1e-9)
    if a.kind == "points":
        assert np.allclose(a.points, b.points, atol=1e-12)


@pytest.mark.parametrize("shape", [
    Shape("sphere", (0.075,), [0.409, 0.051, 0.386], name="ball"),
    Shape("box", (0.13, 0.151, 0.226), [0.564, -0.045, 0.381], Q, name="block"),
    Shape("cylinder", (0.058, 0.244), [0.487, 0.04, 0.429], Q, name="pole"),
    Shape("points", (), [0.5, 0.0, 0.3], Q, points=[[0, 0, 0], [0.1, 0, 0], [0, 0.2, 0.05]]),
])
def test_round_trip_of_every_kind(shape):
    m = marker(shape)
    assert m.action == Marker.ADD and m.ns == "green" and m.id == 3
    assert m.header.frame_id == FRAME and stamp_seconds(m.header.stamp) == pytest.approx(10.0)
    assert stamp_seconds(m.lifetime) == pytest.approx(0.5)
    assert (m.color.r, m.color.g, m.color.b, m.color.a) == pytest.approx(RGBA)
    assert_same_shape(marker_to_shape(m, FRAME), shape)


def test_marker_types_and_scales_follow_ros_conventions():
    sphere = marker(Shape("sphere", (0.05,), [0, 0, 0]))
    assert sphere.type == Marker.SPHERE
    assert (sphere.scale.x, sphere.scale.y, sphere.scale.z) == pytest.approx((0.1, 0.1, 0.1))
    cyl = marker(Shape("cylinder", (0.05, 0.3), [0, 0, 0]))
    assert cyl.type == Marker.CYLINDER
    assert (cyl.scale.x, cyl.scale.y, cyl.scale.z) == pytest.approx((0.1, 0.1, 0.3))
    assert marker(Shape("box", (0.1, 0.2, 0.3), [0, 0, 0])).type == Marker.CUBE
    assert marker(Shape("points", (), [0, 0, 0], points=[[0, 0, 0]])).type == Marker.POINTS


@settings(max_examples=60, deadline=None, derandomize=True)
@given(
    radius=st.floats(0.001, 1.5),
    position=st.lists(st.floats(-5, 5), min_size=3, max_size=3),
    quat=st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(
        lambda q: np.linalg.norm(q) > 0.1),
    length=st.floats(0.001, 3.0),
)
def test_round_trip_property(radius, position, quat, length):
    q = np.asarray(quat) / np.linalg.norm(quat)
    for shape in (Shape("sphere", (radius,), position, q),
                  Shape("cylinder", (radius, length), position, q),
                  Shape("box", (2 * radius, length, radius), position, q)):
        assert_same_shape(marker_to_shape(marker(shape)), shape)


def test_general_markers_are_read_conservatively():
    m = marker(Shape("sphere", (0.05,), [0, 0, 0]))
    m.scale.y = 0.3  # an ellipsoid: bounded by the sphere of its largest semi-axis
    assert marker_to_shape(m).size == (0.15,)
    c = marker(Shape("cylinder", (0.05, 0.3), [0, 0, 0]))
    c.scale.x = 0.2
    assert marker_to_shape(c).size == pytest.approx((0.1, 0.3))
    s = Marker(type=Marker.SPHERE_LIST, ns="blue", id=1)
    s.header.frame_id = FRAME
    s.pose.orientation.w = 1.0
    s.scale.x = s.scale.y = s.scale.z = 0.1
    s.points = [Point(x=0.0, y=0.0, z=0.0), Point(x=1.0, y=0.0, z=0.0)]
    shape = marker_to_shape(s, FRAME)
    assert shape.kind == "points"
    low, high = shape.points.min(axis=0), shape.points.max(axis=0)
    assert low == pytest.approx([-0.05, -0.05, -0.05]) and high == pytest.approx([1.05, .05, .05])


def _bad(mutate) -> Marker:
    m = marker(Shape("box", (0.1, 0.2, 0.3), [0.5, 0.0, 0.3]))
    mutate(m)
    return m


@pytest.mark.parametrize(("mutate", "words"), [
    (lambda m: setattr(m.pose.position, "x", math.nan), "position .* not finite"),
    (lambda m: setattr(m.scale, "y", math.inf), "scale .* not finite"),
    (lambda m: setattr(m.scale, "z", math.nan), "scale .* not finite"),
    (lambda m: setattr(m.scale, "x", 0.0), r"must be > 0 m"),
    (lambda m: setattr(m.scale, "x", -0.1), r"must be > 0 m"),
    (lambda m: setattr(m.scale, "z", MAX_SIZE_M + 0.01), r"must be <= 3.0 m"),
    (lambda m: setattr(m.pose.orientation, "w", 0.0), "not a unit quaternion"),
    (lambda m: setattr(m.pose.orientation, "x", 0.5), "not a unit quaternion"),
    (lambda m: setattr(m.pose.orientation, "z", math.nan), "not a unit quaternion"),
    (lambda m: setattr(m, "type", Marker.ARROW), r"type 0 \(ARROW\) is not an obstacle shape"),
    (lambda m: setattr(m, "type", 42), r"type 42 \(unknown\)"),
    (lambda m: setattr(m.header, "frame_id", "world"), "frame 'world' is not 'panda_link0'"),
    (lambda m: (setattr(m, "type", Marker.POINTS), setattr(m, "points", [])), "needs points"),
    (lambda m: (setattr(m, "type", Marker.POINTS),
                setattr(m, "points", [Point(), Point(x=math.nan)])), "not all finite"),
    (lambda m: (setattr(m, "type", Marker.POINTS),
                setattr(m, "points", [Point(), Point(x=4.0)])), "span 4.000 m"),
])
def test_bad_markers_are_refused_with_a_clear_message(mutate, words):
    with pytest.raises(ValueError, match=words) as info:
        marker_to_shape(_bad(mutate), FRAME)
    assert "marker 'green'/3" in str(info.value)


@pytest.mark.parametrize(("call", "words"), [
    (lambda: marker(Shape("sphere", (1.6,), [0, 0, 0])), "exceeds 3.0 m"),
    (lambda: marker(Shape("sphere", (0.1,), [0, 0, 0]), lifetime_s=-1.0), "lifetime_s"),
    (lambda: marker(Shape("sphere", (0.1,), [0, 0, 0]), id=2**31), "int32"),
    (lambda: marker(Shape("sphere", (0.1,), [0, 0, 0]), stamp=math.nan), "stamp"),
    (lambda: shape_to_marker(Shape("sphere", (0.1,), [0, 0, 0]), "g", 1, "", 0.0, 0.0, RGBA),
     "frame_id"),
    (lambda: shape_to_marker(Shape("sphere", (0.1,), [0, 0, 0]), "g", 1, FRAME, 0.0, 0.0,
                             (1, 1, 1)), "rgba"),
    (lambda: shape_to_marker("ball", "g", 1, FRAME, 0.0, 0.0, RGBA), "Shape"),
])
def test_bad_arguments_are_refused(call, words):
    with pytest.raises(ValueError, match=words):
        call()


def test_helpers():
    assert stamp_seconds(to_stamp(1234.5678)) == pytest.approx(1234.5678, abs=1e-9)
    assert class_rgba("red")[:3] == pytest.approx((210 / 255, 35 / 255, 35 / 255))
    assert class_rgba("purple", 0.5) == pytest.approx((128 / 255,) * 3 + (0.5,))
    d = delete_marker("red", 7, FRAME, 1.0)
    assert (d.action, d.ns, d.id) == (Marker.DELETE, "red", 7)
    assert delete_all_marker(FRAME, 1.0).action == Marker.DELETEALL


# --- ObstacleTable ---------------------------------------------------------------------------


def ball(x: float, ns: str = "green", id: int = 0, stamp: float = 10.0,
         lifetime_s: float = 0.5) -> Marker:
    return marker(Shape("sphere", (0.05,), [x, 0.0, 0.3]), ns, id, stamp, lifetime_s)


def test_table_adds_replaces_and_expires_by_receive_time():
    table = ObstacleTable(FRAME)
    assert table.apply([ball(0.5), ball(0.7, "red", 1, lifetime_s=0.0)], now=100.0) == []
    assert len(table) == 2
    table.apply([ball(0.6, stamp=10.1)], now=100.1)  # same key: replaced, not added
    live = table.obstacles(100.2)
    assert [(o.ns, o.id) for o in live] == [("green", 0), ("red", 1)]
    assert live[0].shape.position[0] == pytest.approx(0.6)
    assert live[0].expires == pytest.approx(100.6) and math.isinf(live[1].expires)
    # Without newer data nothing is forgotten: silence is a perception gap, not absence.
    assert len(table.obstacles(100.61)) == 2
    table.apply([ball(0.8, "blue", 2, lifetime_s=0.0)], now=100.3)  # newer data
    # Expiry counts from the receive time (100.1 + 0.5), not from the stamp.
    assert [(o.ns, o.id) for o in table.obstacles(100.59)] == [
        ("blue", 2), ("green", 0), ("red", 1)]
    assert [(o.ns, o.id) for o in table.obstacles(100.61)] == [("blue", 2), ("red", 1)]
    assert len(table.shapes(1e6)) == 2  # lifetime 0: forever
    assert table.last_update == 100.3


def test_only_valid_data_counts_as_an_update():
    table = ObstacleTable(FRAME)
    table.apply([ball(0.5)], now=1.0)
    bad = ball(0.6, "red", 1)
    bad.scale.x = math.nan
    assert len(table.apply([bad], now=2.0)) == 1  # refused: perception said nothing valid
    assert table.last_update == 1.0 and len(table.obstacles(5.0)) == 1
    table.apply([], now=3.0)  # an empty array: "nothing there", so the old ball may go
    assert table.last_update == 3.0 and table.obstacles(5.0) == []


def test_table_delete_and_delete_all():
    table = ObstacleTable(FRAME)
    table.apply([ball(0.5, "green", 0), ball(0.6, "green", 1), ball(0.7, "red", 0)], now=0.0)
    table.apply([delete_marker("green", 1, FRAME, 0.0), delete_marker("blue", 9, FRAME, 0.0)],
                now=0.1)
    assert [(o.ns, o.id) for o in table.obstacles(0.1)] == [("green", 0), ("red", 0)]
    table.apply([delete_all_marker(FRAME, 0.0, ns="red")], now=0.2)
    assert [(o.ns, o.id) for o in table.obstacles(0.2)] == [("green", 0)]
    table.apply([ball(0.9, "blue", 2), delete_all_marker(FRAME, 0.0), ball(0.4, "red", 5)],
                now=0.3)
    assert [(o.ns, o.id) for o in table.obstacles(0.3)] == [("red", 5)]


def test_a_bad_marker_is_reported_and_leaves_the_others_alone():
    table = ObstacleTable(FRAME)
    table.apply([ball(0.5, "green", 0)], now=0.0)
    bad = ball(0.55, "green", 0)
    bad.scale.x = math.nan
    arrow = ball(0.3, "red", 1)
    arrow.type = Marker.ARROW
    errors = table.apply([bad, arrow, ball(0.8, "blue", 2)], now=0.1)
    assert len(errors) == 2 and "not finite" in errors[0] and "ARROW" in errors[1]
    live = {(o.ns, o.id): o for o in table.obstacles(0.1)}
    assert set(live) == {("green", 0), ("blue", 2)}
    assert live[("green", 0)].shape.position[0] == pytest.approx(0.5)  # kept the good one
    other_frame = ball(0.1, "red", 3)
    other_frame.header.frame_id = "world"
    assert "frame 'world'" in table.apply([other_frame], now=0.2)[0]
    unknown_action = ball(0.1, "red", 4)
    unknown_action.action = 7
    assert "unknown action 7" in table.apply([unknown_action], now=0.2)[0]


def test_velocity_from_successive_positions():
    table = ObstacleTable(FRAME, velocity_window_s=0.3)
    rng = np.random.default_rng(0)
    v = np.array([0.2, -0.1, 0.05])
    for k in range(10):
        t = 5.0 + k / 30.0
        p = np.array([0.5, 0.0, 0.3]) + v * (t - 5.0) + rng.normal(0.0, 1e-4, 3)
        m = marker(Shape("sphere", (0.05,), p), "yellow", 1, t)
        table.apply([m], now=100.0 + k / 30.0)
    (obstacle,) = table.obstacles(100.3)
    assert obstacle.velocity == pytest.approx(v, abs=0.01)
    assert obstacle.stamp == pytest.approx(5.3)
    ahead = obstacle.shape_at(5.8)
    assert ahead.position == pytest.approx(obstacle.shape.position + 0.5 * v, abs=0.01)


def test_velocity_restarts_after_a_gap_or_a_clock_jump_and_ignores_repeats():
    table = ObstacleTable(FRAME, velocity_window_s=0.3)
    table.apply([ball(0.50, stamp=1.0, lifetime_s=0.0)], now=1.0)
    table.apply([ball(0.51, stamp=1.1, lifetime_s=0.0)], now=1.1)
    assert table.obstacles(1.1)[0].velocity[0] == pytest.approx(0.1)
    table.apply([ball(0.51, stamp=1.1, lifetime_s=0.0)], now=1.12)  # republished: same view
    assert table.obstacles(1.12)[0].velocity[0] == pytest.approx(0.1)
    table.apply([ball(0.90, stamp=2.0, lifetime_s=0.0)], now=2.0)  # away for 0.9 s > window
    assert np.all(table.obstacles(2.0)[0].velocity == 0.0)
    table.apply([ball(0.20, stamp=0.5, lifetime_s=0.0)], now=2.1)  # clock went back
    assert np.all(table.obstacles(2.1)[0].velocity == 0.0)


def test_zero_stamp_uses_the_receive_time_and_bad_arguments_are_refused():
    table = ObstacleTable(None)
    m = ball(0.5)
    m.header.stamp = to_stamp(0.0)
    m.header.frame_id = "anything"  # frame_id None accepts any frame
    table.apply([m], now=42.0)
    assert table.obstacles(42.0)[0].stamp == 42.0
    with pytest.raises(ValueError, match="velocity_window_s"):
        ObstacleTable(FRAME, velocity_window_s=0.0)
    with pytest.raises(ValueError, match="now"):
        table.apply([], now=math.nan)


RGBA = (1.0, 0.0, 0.0, 1.0)


def test_seen_surface_markers_are_kept_beside_their_obstacle_not_as_obstacles():
    from damon_ros.ros.markers import SEEN_SUFFIX, delete_marker

    box = Shape("box", (0.1, 0.2, 0.3), [0.5, 0.0, 0.4])
    face = Shape("points", (), [0.45, 0.0, 0.4],
                 points=np.array([[0, -0.1, -0.15], [0, 0.1, -0.15], [0, 0.0, 0.15]]))
    table = ObstacleTable()
    assert not table.apply([shape_to_marker(box, "red", 3, "panda_link0", 1.0, 0.5, RGBA),
                            shape_to_marker(face, "red" + SEEN_SUFFIX, 3, "panda_link0", 1.0,
                                            0.5, RGBA)], now=1.0)
    assert [o.ns for o in table.obstacles(1.0)] == ["red"]  # the surface is no obstacle
    (seen,) = table.seen_parts(1.0).items()
    assert seen[0] == ("red", 3) and np.allclose(seen[1].points + seen[1].position,
                                                 face.points + face.position)
    table.apply([delete_marker("red", 3, "panda_link0", 1.1)], now=1.1)
    assert table.seen_parts(1.1) == {}  # gone with its obstacle
