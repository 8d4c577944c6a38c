"""A node's own loop thread and its real-time scheduling, the way every damon_ros node uses them.

controller and mock_panda both build a `FixedRateLoop`, switch the process to SCHED_FIFO
before the loop thread starts (threads started later inherit the policy), log an exception
that ends the loop unless ROS is shutting down, and at shutdown stop the loop and log its
timing. One copy here keeps the order and the log lines alike. `use_realtime_priority`
serves the nodes without a loop of their own too.
"""

from __future__ import annotations

import sys
from collections.abc import Callable

import rclpy.logging
from rclpy.impl.rcutils_logger import RcutilsLogger
from rclpy.node import Node

from damon_ros.ros.rate_loop import FixedRateLoop, set_realtime_priority


def use_realtime_priority(node: Node, priority: int) -> None:
    """`set_realtime_priority`; a refusal is logged as a warning and the node runs on."""
    refused = set_realtime_priority(priority)
    if refused:
        node.get_logger().warning(refused)


def hand_over_gil_within(seconds: float) -> None:
    """Make a thread that holds the GIL give it up to a waiting one after ``seconds``.

    Why: CPython lets a running thread keep the GIL for the switch interval (5 ms by
    default) before a waiting thread may take it. The controller checks and prepares a new
    trajectory on its executor thread (5-20 ms of Python for a few hundred points); its
    1 kHz loop thread, woken meanwhile, waited up to 5 ms for the GIL, and 0.2 % of its
    periods were over 2 ms in a soak. A quarter of the loop's period bounds that wait; with
    no other Python thread running it changes nothing.
    """
    sys.setswitchinterval(min(sys.getswitchinterval(), max(seconds, 1e-5)))


def start_loop(node: Node, name: str, rate_hz: float, step: Callable[[float], None],
               what: str, priority: int) -> FixedRateLoop:
    """Start ``step`` at ``rate_hz`` on a thread ``<name>_loop``, at SCHED_FIFO ``priority``.

    ``what`` names the loop in the one error line logged when ``step`` raises (the loop then
    ends: see `FixedRateLoop`).
    """
    def on_error(exc: BaseException) -> None:
        if not node.context.ok():
            return  # publishing failed because ROS is shutting down: nothing to report
        node.get_logger().error(f"{what} stopped: {type(exc).__name__}: {exc}")

    loop = FixedRateLoop(rate_hz, step, f"{name}_loop", on_error=on_error)
    use_realtime_priority(node, priority)
    hand_over_gil_within(0.25 / rate_hz)
    loop.start()
    return loop


def stop_loop(loop: FixedRateLoop, name: str) -> RcutilsLogger:
    """Stop the loop, log its timing and return the logger for more shutdown lines.

    ROS may already be shut down (rosout gone): a logger outside the node prints only.
    """
    loop.stop()
    log = rclpy.logging.get_logger(f"{name}.shutdown")
    log.info(loop.summary())
    return log
