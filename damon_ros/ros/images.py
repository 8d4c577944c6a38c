"""sensor_msgs/Image fields -> numpy frames, and colour/depth frames paired by stamp.

The tracker node receives colour and depth as separate ``sensor_msgs/Image`` messages.
Decoding their fields (encoding, step, endianness) into the arrays the perception layer
works on, and pairing the two streams by stamp, are transport concerns, so they live with
the other ROS adapters; the functions take plain fields, not messages, so they are tested
without a ROS graph. ``FrameSynchronizer`` pairs colour and depth frames by stamp
(message_filters' approximate policy, which is not installable here).
"""

from __future__ import annotations

import bisect
import math
from typing import Any, NamedTuple

import cv2
import numpy as np

COLOR_ENCODINGS = ("rgb8", "bgr8")
DEPTH_ENCODINGS = ("16UC1", "mono16", "32FC1")


def _buffer(data: Any, height: int, step: int, what: str) -> np.ndarray:
    if height <= 0 or step <= 0:
        raise ValueError(f"{what} image has height {height} and step {step}; both must be > 0")
    buf = np.frombuffer(data, dtype=np.uint8)
    if buf.size < height * step:
        raise ValueError(
            f"{what} image holds {buf.size} bytes, less than height*step = {height * step}"
        )
    return buf[: height * step].reshape(height, step)


def decode_color(encoding: str, height: int, width: int, step: int, data: Any) -> np.ndarray:
    """A sensor_msgs/Image's fields as an ``rgb8`` array (H, W, 3); ``bgr8`` is converted."""
    if encoding not in COLOR_ENCODINGS:
        raise ValueError(f"colour image encoding {encoding!r} is not supported; "
                         f"expected one of {COLOR_ENCODINGS}")
    if step < 3 * width:
        raise ValueError(f"colour image step {step} is less than 3 * width = {3 * width}")
    rows = _buffer(data, height, step, "colour")
    image = rows[:, : 3 * width].reshape(height, width, 3)
    if encoding == "bgr8":
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    return np.ascontiguousarray(image)


def decode_depth(
    encoding: str, height: int, width: int, step: int, data: Any, is_bigendian: bool = False
) -> np.ndarray:
    """A depth sensor_msgs/Image as uint16 millimetres (0 = no return).

    ``16UC1``/``mono16`` are RealSense's millimetres; ``32FC1`` (metres, NaN = no return) is
    converted so that one code path serves both drivers.
    """
    if encoding not in DEPTH_ENCODINGS:
        raise ValueError(f"depth image encoding {encoding!r} is not supported; "
                         f"expected one of {DEPTH_ENCODINGS}")
    size = 4 if encoding == "32FC1" else 2
    if step < size * width:
        raise ValueError(f"depth image step {step} is less than {size} * width = {size * width}")
    rows = _buffer(data, height, step, "depth")[:, : size * width]
    order = ">" if is_bigendian else "<"
    if size == 2:
        return np.ascontiguousarray(rows).view(f"{order}u2").astype(np.uint16)
    metres = np.ascontiguousarray(rows).view(f"{order}f4").astype(np.float64)
    metres[~np.isfinite(metres) | (metres < 0.0)] = 0.0
    return np.clip(metres * 1000.0 + 0.5, 0, 65535).astype(np.uint16)


# --- colour/depth synchronisation -----------------------------------------------------------


class FramePair(NamedTuple):
    """A colour frame and the depth frame taken with it."""

    stamp: float
    color: Any
    depth: Any


class FrameSynchronizer:
    """Pairs colour and depth frames whose stamps differ by at most ``tolerance_s``.

    A frame is matched with the closest-stamped frame of the other stream inside the
    tolerance. Pairs come out with increasing stamps: once a pair is out, frames older than it
    can no longer be used by a tracker and are dropped, as are late arrivals older than it.
    Each queue holds at most ``queue_size`` unmatched frames (oldest dropped first).
    """

    def __init__(self, tolerance_s: float = 0.005, queue_size: int = 10) -> None:
        if not tolerance_s >= 0.0 or not math.isfinite(tolerance_s):
            raise ValueError(f"tolerance_s {tolerance_s} must be a finite number >= 0")
        if int(queue_size) < 1:
            raise ValueError(f"queue_size {queue_size} must be >= 1")
        self.tolerance_s = float(tolerance_s)
        self.queue_size = int(queue_size)
        self._queues: dict[str, list[tuple[float, Any]]] = {"color": [], "depth": []}
        self._last = {"color": -math.inf, "depth": -math.inf}
        self.dropped = 0

    def add_color(self, stamp: float, msg: Any) -> list[FramePair]:
        return self._add("color", "depth", float(stamp), msg)

    def add_depth(self, stamp: float, msg: Any) -> list[FramePair]:
        return self._add("depth", "color", float(stamp), msg)

    def pending(self) -> tuple[int, int]:
        """Unmatched frames held: ``(colour, depth)``."""
        return len(self._queues["color"]), len(self._queues["depth"])

    def _add(self, mine: str, other: str, stamp: float, msg: Any) -> list[FramePair]:
        if not math.isfinite(stamp):
            raise ValueError(f"{mine} frame stamp {stamp} is not finite")
        if stamp <= self._last[mine]:
            self.dropped += 1  # older than a pair already emitted
            return []
        candidates = self._queues[other]
        best = min(range(len(candidates)), key=lambda i: abs(candidates[i][0] - stamp),
                   default=None)
        if best is None or abs(candidates[best][0] - stamp) > self.tolerance_s:
            self._insert(mine, stamp, msg)
            return []
        other_stamp, other_msg = candidates.pop(best)
        self._last[mine], self._last[other] = stamp, other_stamp
        self._prune(mine)
        self._prune(other)
        color, depth = (msg, other_msg) if mine == "color" else (other_msg, msg)
        return [FramePair(stamp if mine == "color" else other_stamp, color, depth)]

    def _insert(self, side: str, stamp: float, msg: Any) -> None:
        queue = self._queues[side]
        keys = [s for s, _ in queue]
        queue.insert(bisect.bisect_right(keys, stamp), (stamp, msg))
        while len(queue) > self.queue_size:
            queue.pop(0)
            self.dropped += 1

    def _prune(self, side: str) -> None:
        """Drop frames at or before the last pair's stamp on this stream."""
        queue = self._queues[side]
        keep = [item for item in queue if item[0] > self._last[side]]
        self.dropped += len(queue) - len(keep)
        self._queues[side] = keep
