"""Start and stop damon_ros node processes (launch_ros cannot be installed here).

The demo, the soak run and the tests all start nodes the same way: ``python -m
damon_ros.nodes.<name> --ros-args -p k:=v -r from:=to`` with stdout and stderr in a log
file, and stop them with SIGINT, then SIGTERM, then SIGKILL, each wait bounded.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from collections.abc import Mapping
from pathlib import Path


def format_param(value) -> str:
    """``-p name:=value`` text that rcl parses back to the same type (JSON is YAML; quoting
    stops "1.0" or "true" strings from turning into numbers or booleans)."""
    if isinstance(value, (list, tuple)):
        return json.dumps([float(v) if isinstance(v, (int, float)) and not isinstance(
            v, bool) else v for v in value])
    return json.dumps(value)


def node_command(module: str, params: Mapping[str, object] | None = None,
                 remaps: Mapping[str, str] | None = None,
                 params_file: str | Path | None = None) -> list[str]:
    cmd = [sys.executable, "-m", f"damon_ros.nodes.{module}", "--ros-args"]
    if params_file is not None:
        cmd += ["--params-file", str(params_file)]
    for name, value in (params or {}).items():
        cmd += ["-p", f"{name}:={format_param(value)}"]
    for src, dst in (remaps or {}).items():
        cmd += ["-r", f"{src}:={dst}"]
    return cmd


def start_node(module: str, params: Mapping[str, object] | None, env: Mapping[str, str],
               log_path: str | Path, remaps: Mapping[str, str] | None = None,
               params_file: str | Path | None = None) -> subprocess.Popen:
    """Run one node in its own process (and process group), logging to ``log_path``."""
    log = open(log_path, "w")  # noqa: SIM115 - the process owns it until stop_node
    proc = subprocess.Popen(node_command(module, params, remaps, params_file), env=dict(env),
                            stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                            start_new_session=True)
    proc.log_path = Path(log_path)  # type: ignore[attr-defined]
    proc.log_file = log  # type: ignore[attr-defined]
    return proc


def stop_node(proc: subprocess.Popen, timeout: float = 5.0) -> int:
    """SIGINT, then SIGTERM, then SIGKILL, each wait bounded; returns the exit code."""
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGKILL):
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
    log = getattr(proc, "log_file", None)
    if log is not None:
        log.close()
    return proc.returncode


def read_log(proc: subprocess.Popen) -> str:
    path = getattr(proc, "log_path", None)
    return Path(path).read_text(errors="replace") if path and Path(path).exists() else ""
