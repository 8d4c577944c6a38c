"""What every damon_ros node shares: parameter declaration, start-up and clean shutdown.

Nodes stay thin adapters; this module keeps the rclpy boilerplate in one place so that
each node reads as "parameters in, messages in, core call, messages out".
"""

from __future__ import annotations

import math
import os
import re
import sys
import threading
import time
from collections.abc import Callable, Sequence

import numpy as np
import rclpy
from builtin_interfaces.msg import Time
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.executors import (
    Executor,
    ExternalShutdownException,
    SingleThreadedExecutor,
)
from rclpy.node import Node
from rclpy.qos import QoSProfile

from damon_ros.core.resources import config_dir
from damon_ros.ros.inputs import InputError, JointStateReader


def declare(
    node: Node,
    name: str,
    default,
    description: str,
    *,
    read_only: bool = False,
    low: float | None = None,
    high: float | None = None,
):
    """Declare one parameter with a descriptor (type, doc, optional range) and return its value.

    Ranges are enforced by rclpy itself, so an out-of-range value given in a params file or on
    the command line is refused at start-up with rclpy's own clear message.
    """
    descriptor = ParameterDescriptor(description=description, read_only=read_only)
    if low is not None and high is not None:
        if isinstance(default, bool) or not isinstance(default, (int, float)):
            raise TypeError(f"parameter {name}: a range needs a numeric default")
        if isinstance(default, int):
            descriptor.integer_range = [IntegerRange(from_value=int(low), to_value=int(high))]
        else:
            descriptor.floating_point_range = [
                FloatingPointRange(from_value=float(low), to_value=float(high))
            ]
    return node.declare_parameter(name, default, descriptor).value


def stamp_to_sec(stamp: Time) -> float:
    return stamp.sec + 1e-9 * stamp.nanosec


def sec_to_stamp(t: float) -> Time:
    sec = int(t // 1)
    return Time(sec=sec, nanosec=int(round((t - sec) * 1e9)) % 1_000_000_000)


class ProblemLog:
    """One log line per kind of problem, then at most one per ``every_s`` with a count.

    rclpy's ``throttle_duration_sec`` throttles per call site, so two different problems at
    one site would hide each other; here the key is the message with its numbers blanked, so
    "encoding 'bgra8'" and "size 320x240" are separate problems, while the same problem with
    a new stamp in its text is not.
    """

    def __init__(self, log: Callable[[str], None], every_s: float,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self._log = log
        self.every_s = float(every_s)
        self._clock = clock
        self._seen: dict[str, tuple[float, int]] = {}  # key -> (last logged, suppressed)

    @staticmethod
    def key(message: str) -> str:
        return re.sub(r"\d+(\.\d+)?", "#", message)

    def report(self, message: str) -> bool:
        """Log ``message`` unless its kind was logged within ``every_s``; True if logged."""
        key, now = self.key(message), self._clock()
        last = self._seen.get(key)
        if last is not None and now - last[0] < self.every_s:
            self._seen[key] = (last[0], last[1] + 1)
            return False
        suppressed = 0 if last is None else last[1]
        self._log(message if not suppressed else f"{message} ({suppressed} more since)")
        self._seen[key] = (now, 0)
        return True




def joint_names(joints: Sequence[str] | None, prefix: str) -> list[str]:
    """The ``joints`` parameter, or ``<prefix>joint1..7`` when it is unset or empty.

    Every node that talks joint vectors takes the same two parameters, so that one switch
    (``joint_prefix:=fr3_``) moves the whole graph to franka_ros2's names.
    """
    names = [str(n) for n in (joints or [])]
    if not names:
        return [f"{prefix}joint{i}" for i in range(1, 8)]
    if len(names) != 7 or len(set(names)) != 7 or not all(names):
        raise ValueError(f"parameter joints must name 7 distinct joints, got {names}")
    return names


SHM_PROFILE = "fastdds_shm.xml"


def ros_environment(domain_id: int) -> dict[str, str]:
    """Environment variables that put a process on a private, local, shared-memory ROS graph.

    The demo and the tests start several node processes; giving them one ``ROS_DOMAIN_ID``,
    discovery limited to this machine and Fast DDS with the shared-memory profile keeps
    concurrent runs apart and moves 640x480 images in ~3 ms instead of ~13 ms. Merge the
    result into ``os.environ`` (or a copy of it) before starting a process or calling
    ``rclpy.init``: the RMW reads these once per process.
    """
    if isinstance(domain_id, bool) or not isinstance(domain_id, int) or not 0 <= domain_id <= 101:
        raise ValueError(f"domain_id must be an integer in 0..101, got {domain_id!r}")
    profile = config_dir() / SHM_PROFILE
    if not profile.is_file():
        raise ValueError(f"Fast DDS profile {profile} is missing")
    return {
        "ROS_DOMAIN_ID": str(domain_id),
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp",
        "FASTRTPS_DEFAULT_PROFILES_FILE": str(profile),
    }


def print_help(prog: str, description: str, parameters: Sequence[tuple[str, str]]) -> None:
    """``--help`` for a node executable: rclpy has none, and ``ros2 run X --help`` is common."""
    print(f"usage: {prog} [--ros-args [-p NAME:=VALUE] [--params-file FILE] [-r FROM:=TO]]")
    print(f"\n{description}\n\nparameters (defaults in config/{prog}.yaml):")
    for name, doc in parameters:
        print(f"  {name:<28} {doc}")


def set_realtime_priority(priority: int) -> str | None:
    """Run every thread of this process with SCHED_FIFO ``priority``; None, or why not.

    Why the whole process and not only the loop thread: in Python the GIL couples the
    threads, so an RT loop thread still waits whenever a normal-priority thread holding the
    GIL (the executor) or delivering its messages (DDS) is preempted by other work. Measured
    on the loaded 2-core machine (load ~3.5), a closed mock_panda + controller loop with
    normal scheduling saw 50-100 ms stalls, stale-joint-state stops and 5 % of periods over
    2 ms; with the whole processes at FIFO 20 it tracked to 4e-4 rad and < 0.1 % of the
    mock's periods were over 2 ms. Threads started later inherit the policy. 0 restores
    normal scheduling. Refused without CAP_SYS_NICE (or an rtprio limit): the reason is
    returned so the node can log it and run on with normal scheduling.
    """
    if isinstance(priority, bool) or not isinstance(priority, int) or not 0 <= priority <= 99:
        raise ValueError(f"realtime priority must be an integer in 0..99, got {priority!r}")
    policy = os.SCHED_FIFO if priority > 0 else os.SCHED_OTHER
    try:
        for tid in os.listdir("/proc/self/task"):
            os.sched_setscheduler(int(tid), policy, os.sched_param(priority))
    except (AttributeError, FileNotFoundError, OSError) as exc:  # not Linux / not permitted
        return f"SCHED_FIFO priority {priority} refused ({exc}); running with normal scheduling"
    return None


class FixedRateLoop:
    """Calls ``step(t)`` every ``1 / rate_hz`` s from its own thread, at absolute deadlines.

    Why not an rclpy timer: measured on this project's 2-core machine, a 1 kHz rclpy timer
    drifts (mean period 1.02-1.18 ms, ticks lost while message callbacks run) because each
    period is re-armed from the executor. A thread sleeping to absolute deadlines keeps the
    mean period exact; it only inherits the OS wake-up jitter and the GIL. ``t`` is
    ``time.monotonic()`` at the tick. A tick more than one period late is not repeated
    (a control loop gains nothing from a burst of catch-up ticks): deadlines skip ahead in
    phase and `missed` counts them. An exception in ``step`` is handed to ``on_error`` and
    ends the loop: its outputs then stop, which downstream command/state timeouts turn into
    a stop of the arm (fail-safe) rather than a loop repeating a broken step 1000 times/s.
    Periods are kept (last ``history`` of them) for `period_stats`. For real-time
    scheduling see `set_realtime_priority`.
    """

    def __init__(self, rate_hz: float, step: Callable[[float], None], name: str,
                 on_error: Callable[[BaseException], None] | None = None,
                 history: int = 120_000):
        if not (math.isfinite(rate_hz) and rate_hz > 0.0):
            raise ValueError(f"loop rate must be a positive number of Hz, got {rate_hz}")
        self.period = 1.0 / rate_hz
        self._step = step
        self._on_error = on_error
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._periods = np.zeros(max(int(history), 1))
        self._count = 0
        self.missed = 0

    def start(self) -> None:
        self._thread.start()

    def stop(self, timeout: float = 1.0) -> None:
        """Ask the loop to end and wait (bounded) for its current tick to finish."""
        self._stop.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout)

    @property
    def running(self) -> bool:
        return self._thread.is_alive()

    def _run(self) -> None:
        period = self.period
        deadline = time.monotonic()
        last = None
        while not self._stop.is_set():
            deadline += period
            delay = deadline - time.monotonic()
            if delay > 0.0:
                time.sleep(delay)
            now = time.monotonic()
            late = int((now - deadline) // period)
            if late > 0:
                deadline += late * period
                self.missed += late
            if last is not None:
                self._periods[self._count % self._periods.size] = now - last
                self._count += 1
            last = now
            try:
                self._step(now)
            except Exception as exc:  # reported, then the loop ends (see the class doc)
                if self._on_error is not None:
                    self._on_error(exc)
                return

    def summary(self) -> str:
        """One log line on the loop's timing (`period_stats`), for a node's shutdown log."""
        s = self.period_stats()
        if not s["count"]:
            return "loop timing: no periods"
        return (f"loop timing: {s['count']} periods, mean {s['mean_ms']:.3f} ms, p99 "
                f"{s['p99_ms']:.3f} ms, p99.9 {s['p999_ms']:.3f} ms, max {s['max_ms']:.2f} ms, "
                f"{100.0 * s['late_fraction']:.3f} % over {2e3 * self.period:.1f} ms, "
                f"{s['missed']} ticks skipped")

    def period_stats(self, late_s: float | None = None) -> dict[str, float]:
        """Count, mean/p99/p99.9/max period (ms) and the fraction of periods over ``late_s``.

        ``late_s`` defaults to two periods (2 ms at 1 kHz), the bound the nodes are held to.
        """
        periods = self._periods[: min(self._count, self._periods.size)]
        late_s = 2.0 * self.period if late_s is None else late_s
        if periods.size == 0:
            return {"count": 0, "mean_ms": math.nan, "p99_ms": math.nan, "p999_ms": math.nan,
                    "max_ms": math.nan, "late_fraction": math.nan, "missed": self.missed}
        ms = periods * 1e3
        return {
            "count": int(periods.size),
            "mean_ms": float(ms.mean()),
            "p99_ms": float(np.percentile(ms, 99.0)),
            "p999_ms": float(np.percentile(ms, 99.9)),
            "max_ms": float(ms.max()),
            "late_fraction": float(np.mean(periods > late_s)),
            "missed": self.missed,
        }


def read_joint_state(reader: JointStateReader, msg, problems: ProblemLog,
                     log: Callable[[str], None]) -> np.ndarray | None:
    """`JointStateReader.read` for a node: the positions, or None for a refused message,
    which is reported (one line per kind); an accepted clock reset is logged."""
    resets = reader.clock_resets
    try:
        q = reader.read(msg)
    except InputError as exc:
        problems.report(f"ignored joint state: {exc}")
        return None
    if reader.clock_resets != resets:
        log("joint-state stamps jumped back (clock reset): accepted")
    return q


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


def run_single_threaded(
    node_factory: Callable[[], Node],
    args: Sequence[str] | None = None,
) -> int:
    """Spin a node on a single-threaded executor until SIGINT/SIGTERM, then shut down cleanly.

    Every damon_ros node runs so; their real work is in threads of their own (`FixedRateLoop`,
    `TopicReader`). Measured on a 2-core machine, the loop thread of a 1 kHz node misses its
    2 ms bound 5-10x more often beside a multi-threaded executor, whose Python dispatch
    competes for the GIL, and the planner's multi-threaded executor once ran no goal callback
    for minutes while its main thread spun.
    """
    return _spin(node_factory, args, SingleThreadedExecutor)


def _spin(
    node_factory: Callable[[], Node],
    args: Sequence[str] | None,
    make_executor: Callable[[], Executor],
) -> int:
    # SIGINT and SIGTERM are left to rclpy's own handlers (SignalHandlerOptions.ALL): they
    # wake the executor's wait and end spin() with ExternalShutdownException. A Python
    # handler (signal.signal) would only run once the main thread leaves that wait, which
    # an idle node never does: measured, such a node ignored SIGTERM.
    args = list(sys.argv if args is None else args)
    rclpy.init(args=args)
    node = None
    executor = make_executor()
    try:
        node = node_factory()
        executor.add_node(node)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception:
        # A signal that lands between two waits lets spin() build its next wait set on the
        # already shut-down context and raise RCLError instead: still a normal shutdown.
        if rclpy.ok():
            raise
    finally:
        if node is not None:
            shutdown_hook = getattr(node, "on_shutdown", None)
            if shutdown_hook is not None:
                shutdown_hook()
            node.destroy_node()
        if rclpy.ok():
            rclpy.try_shutdown()
    return 0


def node_main(name: str, description: str, parameters: Sequence[tuple[str, str]],
              node_factory: Callable[[], Node], args: Sequence[str] | None = None,
              extra_help: str = "", errors: tuple[type[BaseException], ...] = ()) -> int:
    """A node's console entry point: ``--help`` before any ROS start-up, a one-line error
    (exit 2) on bad parameters or files, otherwise `run_single_threaded`."""
    from rclpy.exceptions import ParameterException

    argv = list(sys.argv if args is None else args)
    own = argv[1:argv.index("--ros-args")] if "--ros-args" in argv else argv[1:]
    if "--help" in own or "-h" in own:
        print_help(name, description, parameters)
        if extra_help:
            print(f"\n{extra_help}")
        return 0
    try:
        return run_single_threaded(node_factory, argv)
    except (ValueError, OSError, ParameterException, *errors) as exc:
        print(f"{name}: {exc}", file=sys.stderr)
        return 2

