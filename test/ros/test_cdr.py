"""The 1 kHz messages and the planner's trajectories as CDR bytes (`damon_ros.ros.cdr`) mean
exactly what rclpy's own serialisation makes of them: written bytes read back by rclpy,
rclpy's bytes read here, for any names and values; a stream's layout cache never reads a
changed message wrongly; bytes nobody can read raise ValueError."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import Image, JointState
from std_msgs.msg import Float64MultiArray, MultiArrayDimension
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint
from visualization_msgs.msg import MarkerArray

from damon_ros.core.shapes import Shape
from damon_ros.ros.cdr import (
    Float64ArrayDecoder,
    Float64ArrayWriter,
    JointStateDecoder,
    JointStateWriter,
    JointTrajectoryWriter,
    header_stamp,
    image_bytes,
    marker_array_bytes,
)
from damon_ros.ros.inputs import InputError, JointStateReader
from damon_ros.ros.markers import delete_record, shape_record, to_marker

NAMES = [f"panda_joint{i}" for i in range(1, 8)]
values = st.floats(allow_nan=False, allow_infinity=False, width=64)
texts = st.text(st.characters(codec="utf-8", exclude_characters="\x00"), max_size=12)


def _vector(n: int):
    return st.lists(values, min_size=n, max_size=n)


def _same(view, msg: JointState) -> None:
    assert (view.header.stamp.sec, view.header.stamp.nanosec) == (msg.header.stamp.sec,
                                                                  msg.header.stamp.nanosec)
    assert view.header.frame_id == msg.header.frame_id
    assert list(view.name) == list(msg.name)
    for field in ("position", "velocity", "effort"):
        assert np.array_equal(getattr(view, field), np.asarray(getattr(msg, field), float))


@settings(max_examples=60, deadline=None)
@given(st.lists(texts.filter(bool), min_size=1, max_size=9, unique=True), st.data(),
       st.integers(0, 2**31 - 1), st.integers(0, 10**9 - 1))
def test_written_joint_states_read_back_by_rclpy(names, data, sec, nanosec):
    q, qd = (data.draw(_vector(len(names))) for _ in range(2))
    msg = deserialize_message(JointStateWriter(names).write(sec * 10**9 + nanosec, q, qd),
                              JointState)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (sec, nanosec)
    assert list(msg.name) == names and msg.header.frame_id == ""
    assert list(msg.position) == q and list(msg.velocity) == qd and len(msg.effort) == 0


@settings(max_examples=80, deadline=None)
@given(texts, st.lists(texts, max_size=9), st.lists(values, max_size=9),
       st.lists(values, max_size=9), st.lists(values, max_size=9),
       st.integers(-2**31, 2**31 - 1), st.integers(0, 2**32 - 1))
def test_rclpy_joint_states_read_here(frame, names, pos, vel, eff, sec, nanosec):
    msg = JointState(name=names, position=pos, velocity=vel, effort=eff)
    msg.header.frame_id = frame
    msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec
    decode = JointStateDecoder()
    _same(decode(serialize_message(msg)), msg)
    msg.position = [v + 1.0 for v in pos]  # the same layout, other values: the cached path
    msg.header.stamp.nanosec = (nanosec + 1) % 2**32
    _same(decode(serialize_message(msg)), msg)


def test_a_changed_layout_is_walked_again():
    decode = JointStateDecoder()
    first = JointState(name=NAMES, position=[0.1] * 7, velocity=[0.2] * 7)
    decode(serialize_message(first))
    # same size, other names: a reordered stream must not be read with the old names
    swapped = JointState(name=NAMES[::-1], position=list(range(7)), velocity=[0.0] * 7)
    _same(decode(serialize_message(swapped)), swapped)
    # same names, one more effort value and one fewer velocity: same size, other counts
    shifted = JointState(name=NAMES, position=[0.1] * 7, velocity=[0.2] * 6, effort=[3.0])
    _same(decode(serialize_message(shifted)), shifted)
    longer = JointState(name=NAMES + ["panda_finger_joint1"], position=[0.5] * 8)
    _same(decode(serialize_message(longer)), longer)


def test_alignment_padding_is_not_part_of_the_layout():
    """Writers leave whatever their memory held in the padding: such bytes must neither
    change the values read nor force a slow read."""
    msg = JointState(name=NAMES, position=[0.1] * 7, velocity=[0.2] * 7)
    raw = bytearray(serialize_message(msg))
    decode = JointStateDecoder()
    decode(bytes(raw))
    layout = decode._layout
    for k in range(len(raw)):  # every byte outside the checked spans and the numbers
        if not (layout.mask >> 8 * k) & 0xFF and k >= 12 and k < layout.arrays[0][0]:
            raw[k] ^= 0x5A
    assert layout.read(bytes(raw)) is not None
    _same(decode(bytes(raw)), msg)


@settings(max_examples=40, deadline=None)
@given(st.integers(1, 9).flatmap(_vector), st.lists(texts, max_size=3))
def test_float64_arrays_both_ways(data, labels):
    written = deserialize_message(Float64ArrayWriter(len(data)).write(data), Float64MultiArray)
    assert list(written.data) == data and len(written.layout.dim) == 0
    msg = Float64MultiArray(data=data)
    msg.layout.dim = [MultiArrayDimension(label=s, size=3, stride=9) for s in labels]
    msg.layout.data_offset = 2
    decode = Float64ArrayDecoder()
    for _ in range(2):  # walked, then cached
        assert np.array_equal(decode(serialize_message(msg)), np.asarray(data))


def test_big_endian_bytes():
    body = struct.pack(">III", 0, 0, 2) + b"\0" * 4 + struct.pack(">dd", 1.5, -2.25)
    assert Float64ArrayDecoder()(b"\x00\x00\x00\x00" + body).tolist() == [1.5, -2.25]


@settings(max_examples=60, deadline=None)
@given(texts, st.lists(texts, max_size=8), st.integers(0, 12), st.data(),
       st.integers(0, 2**31 - 1), st.integers(0, 10**9 - 1))
def test_written_trajectories_read_back_by_rclpy(frame, names, points, data, sec, nanosec):
    """Any joint count (odd ones shift every other point's alignment), point count, frame
    and stamp: rclpy reads the very message it would have built point by point."""
    n = len(names)
    times = np.array(data.draw(st.lists(st.floats(0.0, 1e4), min_size=points,
                                        max_size=points)))
    rows = [np.array(data.draw(st.lists(_vector(n), min_size=points, max_size=points)),
                     float).reshape(points, n) for _ in range(3)]
    raw = JointTrajectoryWriter(names, frame).write((sec, nanosec), times, *rows)
    expected = JointTrajectory(joint_names=names)
    expected.header.frame_id = frame
    expected.header.stamp.sec, expected.header.stamp.nanosec = sec, nanosec
    for i, t in enumerate(times):
        point = JointTrajectoryPoint(positions=rows[0][i].tolist(),
                                     velocities=rows[1][i].tolist(),
                                     accelerations=rows[2][i].tolist())
        ns = int(round(t * 1e9))
        point.time_from_start.sec, point.time_from_start.nanosec = divmod(ns, 10**9)
        expected.points.append(point)
    assert deserialize_message(raw, JointTrajectory) == expected


_coordinate = st.floats(-1.0, 1.0)


@st.composite
def _marker_records(draw):
    """Records of every kind the tracker sends (three primitives, a point set, a DELETE)."""
    kind = draw(st.sampled_from(["sphere", "box", "cylinder", "points", "delete"]))
    ns, frame = draw(texts), draw(texts.filter(bool))
    id = draw(st.integers(-2**31, 2**31 - 1))
    stamp = draw(st.floats(0.0, 1e6))
    if kind == "delete":
        return delete_record(ns, id, frame, stamp)
    position = draw(st.lists(_coordinate, min_size=3, max_size=3))
    size = draw(st.lists(st.floats(0.01, 1.0), min_size=3, max_size=3))
    angle = draw(st.floats(-3.0, 3.0))
    quaternion = [0.0, 0.0, math.sin(0.5 * angle), math.cos(0.5 * angle)]
    if kind == "points":
        n = draw(st.integers(1, 30))
        cloud = np.array(draw(st.lists(_coordinate, min_size=3 * n, max_size=3 * n))) * 0.5
        shape = Shape("points", (), position, points=cloud.reshape(n, 3), name=draw(texts))
    else:
        dims = {"sphere": size[:1], "box": size, "cylinder": size[:2]}[kind]
        shape = Shape(kind, tuple(dims), position, quaternion, name=draw(texts))
    rgba = draw(st.lists(st.floats(0.0, 1.0), min_size=4, max_size=4))
    return shape_record(shape, ns, id, frame, stamp, draw(st.floats(0.0, 10.0)), rgba)


@settings(max_examples=60, deadline=None)
@given(st.lists(_marker_records(), max_size=6))
def test_written_marker_arrays_read_back_by_rclpy(records):
    """Every field the tracker sets, any order of kinds (the points' alignment moves with
    the strings before them): rclpy reads what it reads from its own serialisation of the
    same Marker messages."""
    own = serialize_message(MarkerArray(markers=[to_marker(r) for r in records]))
    assert deserialize_message(marker_array_bytes(records), MarkerArray) == (
        deserialize_message(own, MarkerArray))


@pytest.mark.parametrize("shape, dtype, encoding", [((5, 7, 3), np.uint8, "rgb8"),
                                                    ((480, 640), np.uint16, "16UC1"),
                                                    ((3, 1), np.uint16, "16UC1")])
def test_written_images_read_back_by_rclpy(shape, dtype, encoding):
    """Odd sizes and names shift the pixels' offset: rclpy still reads every pixel."""
    rng = np.random.default_rng(1)
    pixels = rng.integers(0, np.iinfo(dtype).max, shape, dtype=dtype, endpoint=True)
    raw = image_bytes(pixels, encoding, (12, 345), "camera_color_optical_frame_x")
    expected = Image(height=shape[0], width=shape[1], encoding=encoding, is_bigendian=0,
                     step=pixels.strides[0], data=pixels.tobytes())
    expected.header.stamp.sec, expected.header.stamp.nanosec = 12, 345
    expected.header.frame_id = "camera_color_optical_frame_x"
    assert deserialize_message(raw, Image) == expected
    swapped = pixels.astype(pixels.dtype.newbyteorder(">"))  # the same values, big-endian
    assert image_bytes(swapped, encoding, (12, 345), "camera_color_optical_frame_x") == raw
    with pytest.raises(ValueError, match="H x W"):
        image_bytes(np.zeros(4, np.uint8), "mono8", (0, 0), "c")


def test_writers_refuse_the_wrong_length():
    with pytest.raises(ValueError, match="3 x 7"):
        JointTrajectoryWriter(NAMES).write((0, 0), [0.0, 0.1, 0.2], np.zeros((3, 7)),
                                           np.zeros((3, 6)), np.zeros((3, 7)))
    with pytest.raises(ValueError, match="finite times"):
        JointTrajectoryWriter(NAMES).write((0, 0), [0.0, -0.1], *np.zeros((3, 2, 7)))
    with pytest.raises(ValueError, match="7 values"):
        JointStateWriter(NAMES).write(0, [0.0] * 6, [0.0] * 7)
    with pytest.raises(ValueError, match="7 values"):
        Float64ArrayWriter(7).write(1.0)


@pytest.mark.parametrize("decoder", [JointStateDecoder, Float64ArrayDecoder])
def test_unreadable_bytes_raise_value_error(decoder):
    good = serialize_message(JointState(name=NAMES, position=[0.0] * 7)
                             if decoder is JointStateDecoder else Float64MultiArray(data=[1.0]))
    decode = decoder()
    first_length = 12 if decoder is JointStateDecoder else 4  # frame_id's / the dims' count
    for raw in (b"", b"\x00\x01\x00\x00", good[: len(good) // 2],
                good[:first_length] + b"\xff\xff\xff\x7f" + good[first_length + 4:]):
        with pytest.raises(ValueError):
            decode(raw)


def test_a_view_is_checked_like_the_message():
    """The controller hands `JointStateReader` views instead of messages: same answers."""
    msg = JointState(name=NAMES[::-1] + ["panda_finger_joint1"],
                     position=[0.1 * k for k in range(8)], velocity=[0.0] * 8)
    msg.header.stamp.sec = 5
    view = JointStateDecoder()(serialize_message(msg))
    q_msg, q_view = JointStateReader(NAMES).read(msg), JointStateReader(NAMES).read(view)
    assert np.array_equal(q_msg, q_view) and q_view[0] == pytest.approx(0.6)
    msg.position[2] = math.nan
    with pytest.raises(InputError, match="NaN"):
        JointStateReader(NAMES).read(JointStateDecoder()(serialize_message(msg)))


def test_header_stamp_of_a_serialised_message():
    msg = JointState(name=["a"], position=[1.0])
    msg.header.stamp.sec, msg.header.stamp.nanosec = 1234, 500_000_000
    assert header_stamp(serialize_message(msg)) == 1234.5
