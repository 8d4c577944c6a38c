"""Process launching: a node whose starter dies without stopping it ends by itself.

A test killed at its timeout, or a demo killed with SIGKILL, never reaches `stop_node`;
before `exit_with_parent` its 1 kHz real-time nodes ran on for minutes and starved the
machine. The starter here is a short-lived Python process that starts mock_panda and exits.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time

from rosutil import ROOT, next_domain_id

from damon_ros.ros.environment import node_environment
from damon_ros.ros.launch import PARENT_VARIABLE, format_param, node_command

STARTER = """
import sys
from damon_ros.ros.launch import start_node
proc = start_node("mock_panda", None, dict(__import__("os").environ), sys.argv[1])
print(proc.pid, flush=True)
"""


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(") ", 1)[1][0] != "Z"
    except (FileNotFoundError, IndexError):
        return False


def test_a_node_ends_when_its_starter_dies(tmp_path):
    env = node_environment(next_domain_id(__file__), tmp_path)
    starter = subprocess.run([sys.executable, "-c", STARTER, str(tmp_path / "node.log")],
                             env=env, cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert starter.returncode == 0, starter.stderr
    pid = int(starter.stdout.split()[0])
    deadline = time.monotonic() + 60.0  # start-up (imports) plus one watch period, loaded
    while _alive(pid) and time.monotonic() < deadline:
        time.sleep(0.2)
    alive = _alive(pid)
    if alive:
        os.kill(pid, 9)
    assert not alive, (tmp_path / "node.log").read_text()[-2000:]


def test_the_starter_pid_is_passed_and_parameters_keep_their_types():
    assert PARENT_VARIABLE == "DAMON_EXIT_WITH_PARENT"
    cmd = node_command("planner", {"margin": 0.01, "joints": ["a", "b"], "rate": [1, 2]})
    assert cmd[-6:] == ["-p", "margin:=0.01", "-p", 'joints:=["a", "b"]', "-p",
                        "rate:=[1.0, 2.0]"]
    assert format_param(True) == "true" and format_param("1.0") == '"1.0"'
