"""Seconds <-> ``builtin_interfaces`` Time and Duration, and the node clock in seconds.

Every node, the recorder and the tools convert stamps; one pair of functions keeps the
rounding (to the nearest nanosecond) and the refusal of negative or non-finite times the
same everywhere.
"""

from __future__ import annotations

import math

from builtin_interfaces.msg import Duration, Time


def _split_ns(seconds: float, what: str) -> tuple[int, int]:
    if not (math.isfinite(seconds) and seconds >= 0.0):
        raise ValueError(f"{what} {seconds} s must be a finite time >= 0")
    ns = int(round(seconds * 1e9))
    return ns // 1_000_000_000, ns % 1_000_000_000


def to_stamp(seconds: float) -> Time:
    """A ``Time`` for a non-negative time in seconds."""
    sec, nanosec = _split_ns(seconds, "stamp")
    return Time(sec=sec, nanosec=nanosec)


def to_duration(seconds: float, what: str = "duration") -> Duration:
    """A ``Duration`` for a non-negative span in seconds (``what`` names it in the error)."""
    sec, nanosec = _split_ns(seconds, what)
    return Duration(sec=sec, nanosec=nanosec)


def stamp_seconds(stamp: Time | Duration) -> float:
    """Seconds of a ``Time`` or ``Duration`` message."""
    return stamp.sec + 1e-9 * stamp.nanosec


def is_zero(stamp: Time | Duration) -> bool:
    """A zero stamp: ROS's "now" / "unset"."""
    return stamp.sec == 0 and stamp.nanosec == 0


def clock_seconds(node) -> float:
    """The node's clock (ROS time, or sim time where enabled) in seconds."""
    return node.get_clock().now().nanoseconds * 1e-9
