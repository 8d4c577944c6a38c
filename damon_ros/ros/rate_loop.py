"""Fixed-rate loops on threads of their own, and real-time scheduling for them."""

from __future__ import annotations

import math
import os
import threading
import time
from collections.abc import Callable

import numpy as np


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
