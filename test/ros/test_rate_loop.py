"""The 1 kHz loops' scheduling: `node_loop.start_loop` on `rate_loop.FixedRateLoop`."""

from __future__ import annotations

import os
import sys
import time

import pytest

from damon_ros.ros.node_loop import start_loop
from damon_ros.ros.rate_loop import set_realtime_priority


class _Logger:
    def __init__(self) -> None:
        self.lines: list[str] = []

    def warning(self, line: str) -> None:
        self.lines.append(line)

    error = warning


class _Node:
    """What `start_loop` uses of a node: its logger and whether its context is ok."""

    class context:  # noqa: N801 - an attribute of rclpy's Node
        @staticmethod
        def ok() -> bool:
            return True

    def __init__(self) -> None:
        self.logger = _Logger()

    def get_logger(self) -> _Logger:
        return self.logger


def test_the_loop_thread_runs_one_priority_above_its_process():
    node, ticks = _Node(), []
    switch = sys.getswitchinterval()
    loop = start_loop(node, "probe", 1000.0, ticks.append, "probe loop", 20)
    try:
        if node.logger.lines:
            pytest.skip(f"no SCHED_FIFO here: {node.logger.lines[0]}")
        assert os.sched_getscheduler(loop.native_id) == os.SCHED_FIFO
        assert os.sched_getparam(loop.native_id).sched_priority == 21
        assert os.sched_getparam(0).sched_priority == 20  # this (the executor's) thread
        deadline = time.monotonic() + 5.0
        while len(ticks) < 10 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert len(ticks) >= 10
    finally:
        loop.stop()
        set_realtime_priority(0)
        sys.setswitchinterval(switch)
    assert os.sched_getscheduler(0) == os.SCHED_OTHER
