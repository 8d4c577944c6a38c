"""Draining a fast topic from a thread of its own instead of through the executor."""

from __future__ import annotations

from collections.abc import Callable

import rclpy
from rclpy.node import Node
from rclpy.qos import QoSProfile

from damon_ros.ros.rate_loop import FixedRateLoop


class TopicReader:
    """Takes every message of a fast topic from a thread of its own, not via the executor.

    Why: measured on this project's 2-core machine, the planner's MultiThreadedExecutor
    delivered 12 of mock_panda's 1,000 joint states per second to its callback, with gaps
    up to 1 s (the executor rebuilds its wait set in Python for every callback it runs; a
    plain 4-thread executor with one subscription managed ~80/s), and left the tracker's
    30 Hz obstacle arrays waiting > 1 s about once a second behind its planning timer. A
    planner that plans from a joint state 0.5 s old starts its certified path where the
    arm no longer is; one whose obstacle data is late stops the arm for nothing.
    This reader's subscription lives on a helper node that no executor spins
    (``<node>_<suffix>``); a `FixedRateLoop` drains it every ``period_s`` and hands each
    message, in order, to ``on_message`` (so a bad one is still seen and logged), then calls
    ``on_drained`` once: slow work belongs there, once per batch, so that the loop sleeps
    between batches and other threads waiting on the caller's locks get their turn.
    """

    def __init__(self, node: Node, msg_type, topic: str, period_s: float,
                 on_message: Callable[[object], None], suffix: str = "reader",
                 qos: QoSProfile | int = 50, on_drained: Callable[[], None] | None = None):
        self._node = rclpy.create_node(f"{node.get_name()}_{suffix}", context=node.context,
                                       namespace=node.get_namespace(), enable_rosout=False,
                                       start_parameter_services=False)
        self._sub = self._node.create_subscription(msg_type, topic, lambda _msg: None, qos)
        self._on_message = on_message
        self._on_drained = on_drained
        self._loop = FixedRateLoop(1.0 / period_s, self._drain, f"{suffix}_loop",
                                   on_error=lambda exc: node.get_logger().error(
                                       f"{topic} reader stopped: {type(exc).__name__}: {exc}"))
        self._loop.start()

    def _drain(self, _t: float) -> None:
        handle, taken_any = self._sub.handle, False
        while True:
            with handle:
                taken = handle.take_message(self._sub.msg_type, False)
            if taken is None:
                break
            taken_any = True
            self._on_message(taken[0])
        if taken_any and self._on_drained is not None:
            self._on_drained()

    def close(self) -> None:
        self._loop.stop()
        self._node.destroy_node()
