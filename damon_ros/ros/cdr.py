"""The two 1 kHz messages as CDR bytes: ``sensor_msgs/JointState`` and
``std_msgs/Float64MultiArray`` written and read without rclpy's message conversion; and
written from their values, the planner's ``trajectory_msgs/JointTrajectory``, the
tracker's ``visualization_msgs/MarkerArray`` and the mock camera's ``sensor_msgs/Image``.

Why: rclpy turns a Python message into a C struct and then into CDR on every publish, and
back on every take, one Python attribute at a time. At 1 kHz that was a large part of the
two loops' CPU: measured on this project's 2-core machine (cold caches, as between ticks),
serialising a JointState took ~35 us and taking one ~43 us, a Float64MultiArray ~21 and
~28 us, beside ticks of ~290 us. Here a writer keeps one serialised message and patches
the stamp and the numbers in place (the names never change), and a reader walks the bytes
once into numpy arrays. rclpy publishes and takes such bytes itself (``publish(bytes)``, a
``raw`` subscription).

The format is plain CDR (XCDR1), what rmw_fastrtps_cpp puts on the wire: a 4-byte
encapsulation header (``00 01``: little endian, ``00 00``: big endian, then two option
bytes), then the fields in order, each aligned to its own size counted from the end of
that header; a string is a uint32 length that counts the trailing NUL, then its bytes; a
sequence is a uint32 count, then its elements. Bytes in any other encoding (XCDR2, another
middleware's) go to rclpy's own deserialisation. Plain-CDR bytes that do not hold a whole
message raise ValueError naming what is wrong (rclpy's would hand back an empty message).
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

HEADER = 4  # encapsulation bytes before the first field
_ENDIAN = {b"\x00\x01": "<", b"\x00\x00": ">"}  # CDR_LE, CDR_BE


class Stamp(NamedTuple):
    sec: int
    nanosec: int


class Header(NamedTuple):
    stamp: Stamp
    frame_id: str


class JointStateView(NamedTuple):
    """A JointState read from CDR: the fields a `JointStateReader` uses, with the message's
    names, and numpy arrays for the numbers."""

    header: Header
    name: tuple[str, ...]
    position: np.ndarray
    velocity: np.ndarray
    effort: np.ndarray


class _OtherEncoding(ValueError):
    """Bytes that are not plain CDR: for rclpy's deserialisation to read."""


class _Cursor:
    """Walks plain-CDR bytes field by field; a short or inconsistent buffer raises
    ValueError. Records where each float64 sequence's count and values lie (`arrays`)."""

    def __init__(self, raw: bytes):
        endian = _ENDIAN.get(bytes(raw[:2]))
        if endian is None or len(raw) < HEADER:
            raise _OtherEncoding(f"not plain CDR (encapsulation {bytes(raw[:4]).hex() or 'none'})")
        self.raw, self.endian, self.pos = raw, endian, HEADER
        self._u32 = struct.Struct(endian + "I")
        self.arrays: list[tuple[int, int, int]] = []  # (count offset, values offset, count)
        self.spans: list[tuple[int, int]] = []  # the bytes read, without alignment padding

    def align(self, size: int) -> None:
        self.pos += -(self.pos - HEADER) % size

    def _take(self, size: int, fixed: bool = True) -> int:
        """``size`` bytes; ``fixed``: part of the layout (a length, a count, a name), not
        a value that changes from message to message."""
        start, self.pos = self.pos, self.pos + size
        if self.pos > len(self.raw):
            raise ValueError(f"truncated: {size} bytes wanted at {start}, {len(self.raw)} in all")
        if fixed and self.spans and self.spans[-1][1] == start:
            self.spans[-1] = (self.spans[-1][0], self.pos)
        elif fixed:
            self.spans.append((start, self.pos))
        return start

    def uint32(self) -> int:
        self.align(4)
        return self._u32.unpack_from(self.raw, self._take(4))[0]

    def int32(self) -> int:
        value = self.uint32()
        return value - (1 << 32) if value >= 1 << 31 else value

    def string(self) -> str:
        size = self.uint32()
        start = self._take(size)
        if size == 0 or self.raw[start + size - 1] != 0:
            raise ValueError(f"string at {start} is not NUL-terminated")
        return bytes(self.raw[start:start + size - 1]).decode("utf-8")

    def count(self, element_size: int) -> int:
        """A sequence's element count, refused when the bytes cannot hold that many."""
        n = self.uint32()
        if n * element_size > len(self.raw) - self.pos:
            raise ValueError(f"sequence of {n} elements overruns the {len(self.raw)} bytes")
        return n

    def float64s(self) -> np.ndarray:
        """A float64 sequence, copied (native byte order)."""
        n = self.count(8)
        count_at = self.pos - 4
        if n:  # no alignment before no elements (as Fast CDR writes an empty sequence)
            self.align(8)
        start = self._take(8 * n, fixed=False)
        self.arrays.append((count_at, start, n))
        return _float64s(self.raw, self.endian, start, n)


def _float64s(raw: bytes, endian: str, start: int, n: int) -> np.ndarray:
    return np.frombuffer(raw, dtype=endian + "f8", count=n, offset=start).astype(float)


class _Layout:
    """Where the float64 sequences of one message lie, to read the next like it directly.

    A 1 kHz stream repeats the same names and lengths in every message, so once one was
    walked the next is known to share its layout when it has the same size and the same
    encapsulation, lengths, counts and strings (its names, for a JointState) at the same
    places. Those bytes are compared in one masked integer comparison; alignment padding is
    left out (it holds whatever the writer's memory held), and so is ``volatile``, the
    bytes that change but do not move anything (a stamp).
    """

    def __init__(self, cursor: _Cursor, volatile: tuple[int, int] = (0, 0)):
        raw = cursor.raw
        spans = [(0, 2)] + [(a, b) for a, b in cursor.spans
                            if b <= volatile[0] or a >= volatile[1]]
        self.size, self.endian = len(raw), cursor.endian
        self.end = max(b for _, b in spans)
        self.mask = sum(((1 << 8 * (b - a)) - 1) << 8 * a for a, b in spans)
        self.key = int.from_bytes(raw[:self.end], "little") & self.mask
        self.arrays = [(start, n) for _, start, n in cursor.arrays]

    def read(self, raw: bytes) -> list[np.ndarray] | None:
        """The float64 sequences of ``raw``, or None when its layout is not this one."""
        if (len(raw) != self.size
                or int.from_bytes(raw[:self.end], "little") & self.mask != self.key):
            return None
        return [_float64s(raw, self.endian, start, n) for start, n in self.arrays]


def _joint_state(cursor: _Cursor) -> JointStateView:
    stamp = Stamp(cursor.int32(), cursor.uint32())
    frame_id = cursor.string()
    names = tuple(cursor.string() for _ in range(cursor.count(5)))
    position, velocity, effort = (cursor.float64s() for _ in range(3))
    return JointStateView(Header(stamp, frame_id), names, position, velocity, effort)


def _float64_array(cursor: _Cursor) -> np.ndarray:
    """``data`` of a Float64MultiArray (its layout is walked over)."""
    for _ in range(cursor.count(13)):  # MultiArrayDimension: label, size, stride
        cursor.string()
        cursor.uint32()
        cursor.uint32()
    cursor.uint32()  # data_offset
    return cursor.float64s()


_STAMP = (HEADER, HEADER + 8)  # JointState: the stamp's sec and nanosec


def header_stamp(raw: bytes) -> float:
    """``header.stamp`` (s) of a serialised message that starts with a std_msgs/Header."""
    sec, nanosec = struct.unpack_from((">" if raw[1] == 0 else "<") + "iI", raw, HEADER)
    return sec + 1e-9 * nanosec


class JointStateDecoder:
    """Serialised JointStates to `JointStateView` (or, in another encoding, as rclpy reads
    them); ValueError for bytes that do not hold one. One decoder per stream: it keeps the last
    message's layout (`_Layout`)."""

    def __init__(self) -> None:
        self._layout: _Layout | None = None
        self._last: JointStateView | None = None
        self._stamp: struct.Struct | None = None  # sec and nanosec in the layout's byte order

    def __call__(self, raw: bytes) -> JointStateView | JointState:
        last = self._last
        arrays = self._layout.read(raw) if self._layout is not None else None
        if arrays is None:
            return self._walk(raw)
        stamp = Stamp(*self._stamp.unpack_from(raw, HEADER))
        return JointStateView(Header(stamp, last.header.frame_id), last.name, *arrays)

    def _walk(self, raw: bytes) -> JointStateView | JointState:
        try:
            cursor = _Cursor(raw)
        except _OtherEncoding:
            return _standard(raw, JointState)
        view = _joint_state(cursor)
        self._layout, self._last = _Layout(cursor, _STAMP), view
        self._stamp = struct.Struct(cursor.endian + "iI")
        return view


class Float64ArrayDecoder:
    """``data`` of serialised Float64MultiArrays, as a numpy array (see
    `JointStateDecoder`)."""

    def __init__(self) -> None:
        self._layout: _Layout | None = None

    def __call__(self, raw: bytes) -> np.ndarray:
        arrays = self._layout.read(raw) if self._layout is not None else None
        if arrays is not None:
            return arrays[0]
        try:
            cursor = _Cursor(raw)
        except _OtherEncoding:
            return np.asarray(_standard(raw, Float64MultiArray).data, dtype=float)
        data = _float64_array(cursor)
        self._layout = _Layout(cursor)
        return data


def _standard(raw: bytes, msg_type):
    try:
        return deserialize_message(bytes(raw), msg_type)
    except Exception as exc:  # rclpy raises RuntimeError/RMWError for bytes it cannot read
        raise ValueError(f"unreadable {msg_type.__name__} ({len(raw)} bytes): {exc}") from exc


def _array(values, n: int, what: str) -> np.ndarray:
    a = np.asarray(values, dtype=float)
    if a.shape != (n,):
        raise ValueError(f"{what} must hold {n} values, got shape {a.shape}")
    return a


class JointStateWriter:
    """Serialised JointStates of fixed ``names`` with a stamp, positions and velocities
    (no efforts, empty ``frame_id``), for ``Publisher.publish``."""

    def __init__(self, names: Sequence[str]):
        self.n = len(names)
        zeros = [0.0] * self.n
        self._buf = bytearray(serialize_message(
            JointState(name=list(names), position=zeros, velocity=zeros)))
        cursor = _Cursor(self._buf)
        _joint_state(cursor)
        (_, pos_at, _), (_, vel_at, _) = cursor.arrays[:2]
        f8 = cursor.endian + "f8"
        self._pos = np.frombuffer(self._buf, dtype=f8, count=self.n, offset=pos_at)
        self._vel = np.frombuffer(self._buf, dtype=f8, count=self.n, offset=vel_at)
        self._stamp = struct.Struct(cursor.endian + "iI")

    def write(self, stamp_ns: int, position, velocity) -> bytes:
        """The message stamped ``stamp_ns`` (ns since the epoch of the node's clock)."""
        self._pos[:] = _array(position, self.n, "position")
        self._vel[:] = _array(velocity, self.n, "velocity")
        self._stamp.pack_into(self._buf, HEADER, *divmod(int(stamp_ns), 1_000_000_000))
        return bytes(self._buf)


class Float64ArrayWriter:
    """Serialised Float64MultiArrays of ``n`` values and an empty layout."""

    def __init__(self, n: int):
        self.n = int(n)
        self._buf = bytearray(serialize_message(Float64MultiArray(data=[0.0] * self.n)))
        cursor = _Cursor(self._buf)
        _float64_array(cursor)
        at = cursor.arrays[0][1]
        self._data = np.frombuffer(self._buf, dtype=cursor.endian + "f8", count=self.n,
                                   offset=at)

    def write(self, data) -> bytes:
        self._data[:] = _array(data, self.n, "data")
        return bytes(self._buf)


_U32 = struct.Struct("<I")
_TIME = struct.Struct("<iI")
_IDS = struct.Struct("<iii")
_POSE_SCALE = struct.Struct("<10d")
_RGBA = struct.Struct("<4f")
_POINT_END = struct.Struct("<IiI")  # a trajectory point's (empty) efforts, time_from_start


class _Out:
    """A plain-CDR little-endian message being written, field by field (the writers below
    build whole messages; the 1 kHz writers above patch one that rclpy serialised)."""

    def __init__(self, start: bytes = b"\x00\x01\x00\x00") -> None:
        self.buf = bytearray(start)  # the encapsulation header, or a message begun before

    def align(self, size: int) -> None:
        self.buf += bytes(-(len(self.buf) - HEADER) % size)

    def put(self, fmt: struct.Struct, align: int, *values) -> None:
        self.align(align)
        self.buf += fmt.pack(*values)

    def string(self, text: str) -> None:
        data = text.encode("utf-8") + b"\x00"
        self.put(_U32, 4, len(data))
        self.buf += data


class JointTrajectoryWriter:
    """Serialised JointTrajectories of fixed joint ``names`` and ``frame_id``, written from
    the sample arrays (no efforts), for ``Publisher.publish``.

    Why: a re-route is published the moment it is decided, and rclpy built one
    JointTrajectoryPoint object per sample and then converted each field by field: ~3.4 ms
    for the 56 samples of a 1.1 s move, several times the search behind it on a quiet
    machine. Here each sample is a few small packs into one buffer (~0.2 ms for 56)."""

    def __init__(self, names: Sequence[str], frame_id: str = ""):
        self.n = len(names)
        head = _Out()  # the header (its stamp patched per message) and the names
        head.put(_TIME, 4, 0, 0)
        head.string(frame_id)
        head.put(_U32, 4, self.n)
        for name in names:
            head.string(name)
        self._head = bytes(head.buf)

    def write(self, stamp: tuple[int, int], times, positions, velocities,
              accelerations) -> bytes:
        """The message stamped ``stamp`` (sec, nanosec; (0, 0): start on arrival), one
        point per row of the (N, n) arrays, ``times`` (N,) from the start in seconds,
        non-negative and finite."""
        times = np.asarray(times, dtype=float)
        arrays = [np.ascontiguousarray(a, dtype="<f8")
                  for a in (positions, velocities, accelerations)]
        for a, what in zip(arrays, ("positions", "velocities", "accelerations"), strict=True):
            if a.shape != (len(times), self.n):
                raise ValueError(f"{what} must be {len(times)} x {self.n}, got {a.shape}")
        if not (np.all(np.isfinite(times)) and np.all(times >= 0.0)):
            raise ValueError("time_from_start must be finite times >= 0")
        ns = np.rint(times * 1e9).astype(np.int64)
        out = _Out(self._head)
        _TIME.pack_into(out.buf, HEADER, *stamp)
        out.put(_U32, 4, len(times))
        for i in range(len(times)):
            for a in arrays:  # a sequence<float64>: its count, then 8-aligned values
                out.put(_U32, 4, self.n)
                if self.n:  # (Fast CDR aligns no empty sequence)
                    out.align(8)
                out.buf += a[i].tobytes()
            out.put(_POINT_END, 4, 0, *divmod(int(ns[i]), 1_000_000_000))
        return bytes(out.buf)


def marker_array_bytes(markers: Sequence) -> bytes:
    """A serialised ``MarkerArray`` of ``markers`` (`markers.MarkerRecord`: the fields a
    shape's marker sets; colours per point, textures, UV coordinates and meshes empty).

    Why: the tracker publishes one array per frame, two markers an obstacle (its bound and
    its visible surface as points); building the Marker and Point objects and rclpy's
    conversion of them cost ~1 ms a frame of three obstacles, a fifth of tracking them."""
    out = _Out()
    out.put(_U32, 4, len(markers))
    for r in markers:
        out.put(_TIME, 4, *r.stamp)
        out.string(r.frame_id)
        out.string(r.ns)
        out.put(_IDS, 4, r.id, r.type, r.action)
        out.put(_POSE_SCALE, 8, *r.position, *r.orientation, *r.scale)
        out.put(_RGBA, 4, *r.rgba)
        out.put(_TIME, 4, *r.lifetime)
        out.buf += b"\x00"  # frame_locked
        points = np.zeros((0, 3)) if r.points is None else np.asarray(r.points, dtype="<f8")
        out.put(_U32, 4, len(points))
        if len(points):
            out.align(8)
            out.buf += np.ascontiguousarray(points).tobytes()
        out.put(_U32, 4, 0)  # colors
        out.string("")  # texture_resource
        out.put(_TIME, 4, 0, 0)  # texture: header stamp, frame_id, format, data
        out.string("")
        out.string("")
        out.put(_U32, 4, 0)
        out.put(_U32, 4, 0)  # uv_coordinates
        out.string(r.text)
        out.string("")  # mesh_resource
        out.string("")  # mesh_file: filename, data
        out.put(_U32, 4, 0)
        out.buf += b"\x00"  # mesh_use_embedded_materials
    return bytes(out.buf)


_SIZE = struct.Struct("<II")


def image_bytes(array: np.ndarray, encoding: str, stamp: tuple[int, int],
                frame_id: str) -> bytes:
    """A serialised ``sensor_msgs/Image`` of an H x W (x C) array: the header, the size
    fields and the pixels (little-endian, ``is_bigendian`` 0), copied once.

    Why: the mock camera sends 1.5 MB a frame at 30 fps; rclpy turned the message's pixel
    bytes into its C message and Fast DDS then serialised that, and publishing a frame took
    ~2.2 ms (p50 in a 10-minute soak, over the 2 ms a frame may take)."""
    pixels = np.asarray(array)
    pixels = np.ascontiguousarray(pixels, dtype=pixels.dtype.newbyteorder("<"))
    if pixels.ndim not in (2, 3):
        raise ValueError(f"an image is an H x W (x C) array, got shape {pixels.shape}")
    out = _Out()
    out.put(_TIME, 4, *stamp)
    out.string(frame_id)
    out.put(_SIZE, 4, pixels.shape[0], pixels.shape[1])
    out.string(encoding)
    out.buf += b"\x00"  # is_bigendian
    out.put(_SIZE, 4, pixels.strides[0], pixels.nbytes)  # step, then the data's count
    return b"".join((out.buf, memoryview(pixels).cast("B")))
