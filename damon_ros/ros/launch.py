"""Start and stop damon_ros node processes (launch_ros cannot be installed here).

The demo, the soak run and the tests all start nodes the same way, through this module:
``python -m damon_ros.nodes.<name> --ros-args --params-file f -p k:=v -r from:=to`` in its
own process group, with stdout and stderr in a log file (`read_log`), and stop them with
SIGINT, then SIGTERM, then SIGKILL, each wait bounded (`stop_node`).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Mapping, Sequence
from pathlib import Path


def format_param(value) -> str:
    """``-p name:=value`` text that rcl parses back to the same type.

    JSON is YAML; quoting stops "1.0" or "true" strings from turning into numbers or
    booleans, and numbers in a list are written as floats because every array parameter of
    the nodes is a double array (``[1, 2]`` would arrive as an integer array and be refused).
    """
    if isinstance(value, (bool, int, float, str)):
        return json.dumps(value)
    if isinstance(value, (list, tuple)):
        return json.dumps([float(v) if isinstance(v, (int, float)) and not isinstance(
            v, bool) else v for v in value])
    raise ValueError(f"parameter value {value!r} is not a bool, number, string or list")


def node_command(module: str, params: Mapping[str, object] | None = None,
                 remaps: Mapping[str, str] | None = None,
                 params_file: str | Path | None = None,
                 ros_args: Sequence[str] = ()) -> list[str]:
    """The command line of ``damon_ros.nodes.<module>``; ``params`` come after
    ``params_file``, so they override it."""
    cmd = [sys.executable, "-m", f"damon_ros.nodes.{module}", "--ros-args"]
    if params_file is not None:
        cmd += ["--params-file", str(params_file)]
    for name, value in (params or {}).items():
        cmd += ["-p", f"{name}:={format_param(value)}"]
    for src, dst in (remaps or {}).items():
        cmd += ["-r", f"{src}:={dst}"]
    return cmd + list(ros_args)


def start_node(module: str, params: Mapping[str, object] | None, env: Mapping[str, str],
               log_path: str | Path, remaps: Mapping[str, str] | None = None,
               params_file: str | Path | None = None, ros_args: Sequence[str] = (),
               cwd: str | Path | None = None) -> subprocess.Popen:
    """Run one node (`node_command`) with `start_process`."""
    return start_process(node_command(module, params, remaps, params_file, ros_args), env,
                         log_path, cwd)


ORPHAN_GRACE_S = 10.0
"""How long an orphaned node may take to shut down on SIGINT before it exits outright."""
PARENT_VARIABLE = "DAMON_EXIT_WITH_PARENT"
"""Set by `start_process` to the starter's pid; a process that runs `exit_with_parent` ends
when that pid is no longer its parent."""


def start_process(cmd: Sequence[str], env: Mapping[str, str], log_path: str | Path,
                  cwd: str | Path | None = None) -> subprocess.Popen:
    """Run ``cmd`` in its own process and process group, logging to ``log_path``.

    The process group lets `stop_node` reach whatever the process starts; the log file's
    folder is created, and this process closes its copy of the file at once (the child
    holds its own), so nothing is left open here. The returned Popen carries ``log_path``
    for `read_log`. The child is told this process's pid (`PARENT_VARIABLE`), so a node
    whose starter dies without stopping it (a test killed at its timeout, a demo killed
    with SIGKILL) ends by itself instead of running on at real-time priority.
    """
    log_path = Path(log_path)
    log_path.parent.mkdir(parents=True, exist_ok=True)
    env = dict(env, **{PARENT_VARIABLE: str(os.getpid())})
    with open(log_path, "wb") as log:
        proc = subprocess.Popen(list(cmd), cwd=cwd, env=env, stdout=log,
                                stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                start_new_session=True)
    proc.log_path = log_path  # type: ignore[attr-defined]
    return proc


def stop_node(proc: subprocess.Popen, timeout: float = 5.0,
              first_signal: int = signal.SIGINT) -> int:
    """``first_signal``, then SIGTERM, then SIGKILL to the node's process group, each
    waiting ``timeout``; returns the exit code. A process that ended by itself is reaped."""
    for sig in (first_signal, signal.SIGTERM, signal.SIGKILL):
        if proc.poll() is not None:
            break
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            break
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            continue
    proc.wait(timeout=timeout)
    return proc.returncode


def read_log(proc: subprocess.Popen) -> str:
    """Everything the node has written to its log so far ("" when it has none)."""
    path = getattr(proc, "log_path", None)
    if path is None or not Path(path).exists():
        return ""
    return Path(path).read_text(errors="replace")


def exit_with_parent(period_s: float = 0.5) -> None:
    """End this process with SIGINT once the process that started it is gone.

    Only for processes started by `start_process` (others have no `PARENT_VARIABLE` and
    this does nothing). A daemon thread compares ``os.getppid()`` with the recorded pid
    every ``period_s``: an orphan is re-parented, so the two differ within one period, and
    SIGINT takes the process through its normal shutdown (nodes stop their loops and exit).
    """
    expected = os.environ.get(PARENT_VARIABLE)
    if not expected or not expected.isdigit():
        return

    def watch() -> None:
        while os.getppid() == int(expected):
            time.sleep(period_s)
        # SIGINT again each period: one that lands during start-up, before the node's
        # handler is installed, can be lost (a loaded test run saw an orphan run on for a
        # minute); after ORPHAN_GRACE_S the process ends without its shutdown
        deadline = time.monotonic() + ORPHAN_GRACE_S
        while time.monotonic() < deadline:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(period_s)
        print(f"{PARENT_VARIABLE}: the starting process is gone and SIGINT did not end this "
              f"one within {ORPHAN_GRACE_S:.0f} s; exiting", file=sys.stderr, flush=True)
        os._exit(1)

    threading.Thread(target=watch, name="exit_with_parent", daemon=True).start()
