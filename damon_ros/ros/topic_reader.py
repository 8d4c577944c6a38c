"""Taking a fast topic's messages outside the executor: in an owner's loop or a thread of
its own."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import NamedTuple

import rclpy
from rclpy.guard_condition import GuardCondition
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.qos import QoSProfile


class Taken(NamedTuple):
    """One message taken from an `Inbox`."""

    msg: object
    sent: float | None  # the publisher's send time (s, wall clock); None: not known
    arrived: float  # when this process received it (s, time.monotonic())


class Inbox:
    """A subscription that no executor spins: its owner takes what has arrived, when it wants.

    Why: rclpy's executor costs more than the message. Measured on this project's 2-core
    machine, a controller and a mock_panda whose executors ran the other's 1 kHz topic
    used 0.96 and 0.83 of a core, nearly all of it in the executor thread (it rebuilds its
    wait set in Python for every callback); with the same messages taken non-blocking from
    the subscription in the 1 kHz loop's own tick the two used 0.53 and 0.47, and each
    message arrives in the tick that uses it instead of whenever the executor gets round
    to it. The subscription lives on a helper node ``<node>_<suffix>`` in the same context
    (the process's remaps apply to it) that no executor spins. With ``raw`` the messages
    are taken as their serialised bytes, for the owner to read (`damon_ros.ros.cdr`).
    """

    def __init__(self, node: Node, msg_type, topic: str, suffix: str,
                 qos: QoSProfile | int = 50, raw: bool = False):
        self._node = rclpy.create_node(f"{node.get_name()}_{suffix}", context=node.context,
                                       namespace=node.get_namespace(), enable_rosout=False,
                                       start_parameter_services=False)
        self._sub = self._node.create_subscription(msg_type, topic, lambda _msg: None, qos,
                                                   raw=raw)
        self._wake = GuardCondition(None, None, context=node.context)

    def wait(self, timeout_s: float) -> None:
        """Sleep until a message waits (or `interrupt`, or ``timeout_s``), the GIL released.

        Why: a reader that polls a 30 Hz topic every 2 ms wakes 500 times a second; measured
        beside two 1 kHz loops on 2 cores, each Python wake-up costs tens of microseconds
        of CPU and a turn at the GIL. Waiting on the subscription costs nothing until a
        message is there, and hands it over as soon as the middleware has it.
        """
        context = self._node.context
        sub, wake = self._sub.handle, self._wake.handle
        with sub, wake, context.handle:
            wait_set = _rclpy.WaitSet(1, 1, 0, 0, 0, 0, context.handle)
            wait_set.clear_entities()
            wait_set.add_subscription(sub)
            wait_set.add_guard_condition(wake)
            wait_set.wait(max(0, int(timeout_s * 1e9)))

    def interrupt(self) -> None:
        """End a `wait` now (from another thread)."""
        self._wake.trigger()

    def take_all(self) -> list[Taken]:
        """Every message waiting, oldest first; [] when none is.

        ``arrived`` is the middleware's reception time moved onto the monotonic clock, not
        the time of this call: a message that waited for the owner's next tick counts as
        the age it really has.
        """
        handle, out = self._sub.handle, []
        while True:
            with handle:
                taken = handle.take_message(self._sub.msg_type, self._sub.raw)
            if taken is None:
                break
            out.append(taken)
        if not out:
            return []
        mono, wall = time.monotonic(), time.time()
        return [Taken(msg, _seconds(info, "source_timestamp"),
                      mono - max(0.0, wall - (_seconds(info, "received_timestamp") or wall)))
                for msg, info in out]

    def close(self) -> None:
        self._wake.destroy()
        self._node.destroy_node()


def _seconds(info: dict | None, key: str) -> float | None:
    value = info.get(key) if info else None
    return value * 1e-9 if value else None


class TopicReader:
    """Hands every message of a topic to ``on_message`` from a thread of its own, the moment
    it arrives: an `Inbox` the thread waits on, not the executor.

    Why: measured on this project's 2-core machine, the planner's MultiThreadedExecutor
    delivered 12 of mock_panda's 1,000 joint states per second to its callback, with gaps
    up to 1 s (the executor rebuilds its wait set in Python for every callback it runs),
    and left the tracker's 30 Hz obstacle arrays waiting > 1 s about once a second behind
    its planning timer. A planner whose obstacle data is late stops the arm for nothing.
    The thread sleeps in `Inbox.wait` (no polling), then hands each waiting message, in
    order, to ``on_message`` (so a bad one is still seen and logged) and calls
    ``on_drained`` once: slow work belongs there, once per batch, so that other threads
    waiting on the caller's locks get their turn between batches.
    """

    def __init__(self, node: Node, msg_type, topic: str,
                 on_message: Callable[[object], None], suffix: str = "reader",
                 qos: QoSProfile | int = 50, on_drained: Callable[[], None] | None = None):
        self._inbox = Inbox(node, msg_type, topic, suffix, qos)
        self._on_message = on_message
        self._on_drained = on_drained
        self._report = lambda exc: node.get_logger().error(
            f"{topic} reader stopped: {type(exc).__name__}: {exc}")
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"{suffix}_reader", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self._inbox.wait(WAKE_S)
                if not self._stop.is_set():
                    self._drain()
            except Exception as exc:  # reported once; the reader ends (its data goes stale)
                if not self._stop.is_set():
                    self._report(exc)
                return

    def _drain(self) -> None:
        taken = self._inbox.take_all()
        for item in taken:
            self._on_message(item.msg)
        if taken and self._on_drained is not None:
            self._on_drained()

    def close(self, timeout: float = 1.0) -> None:
        """Stop the thread (bounded wait for the batch in hand), then the subscription."""
        self._stop.set()
        self._inbox.interrupt()
        self._thread.join(timeout)
        self._inbox.close()


WAKE_S = 0.5  # a waiting reader looks at its stop flag at least this often
