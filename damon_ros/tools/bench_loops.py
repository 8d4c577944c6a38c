"""``damon-ros bench-loops``: the CPU of the two 1 kHz nodes, mock_panda and the controller,
closed loop and alone.

Why: the soak measures the whole cell, and this project's 2-core machine drifts by about
±0.3 cores between hours for the same code, so a change to the 1 kHz path cannot be judged
from one soak. Here only the pair runs (the controller holding the arm from its defaults) on
a private domain with the shared-memory profile, beside ``--readers`` passive subscribers of
``/joint_states`` (in the cell: the planner and the soak's monitor). After a warm-up, each
process's CPU over ``--seconds`` is read from ``/proc`` and split into its threads (the
loop, Fast DDS's receive and event threads); the loops' own timing comes from their
shutdown lines. Compare versions by alternating runs in one sitting.
"""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

READER = """
import time, rclpy
from sensor_msgs.msg import JointState
from damon_ros.ros.launch import exit_with_parent
exit_with_parent()
rclpy.init()
node = rclpy.create_node("bench_loops_reader_{k}")
node.create_subscription(JointState, "joint_states", lambda _msg: None, 10)
while True:
    time.sleep(3600)
"""


def thread_cpu(pid: int) -> dict[str, float]:
    """CPU seconds (user + system) per thread name of a process (`cpu_seconds` of each of
    its threads); threads of one name summed, Fast DDS's ``dds.*`` threads as one."""
    from damon_ros.tools.soak_monitor import cpu_seconds

    out: dict[str, float] = {}
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            name = Path(f"/proc/{pid}/task/{tid}/comm").read_text().strip()
        except OSError:
            continue  # the thread ended meanwhile
        seconds = cpu_seconds(pid, int(tid))
        if not math.isnan(seconds):
            name = "dds.*" if name.startswith("dds.") else name
            out[name] = out.get(name, 0.0) + seconds
    return out


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="damon-ros bench-loops", description=__doc__.split("\n\n")[0])
    p.add_argument("--seconds", type=float, default=20.0, help="measured window (s)")
    p.add_argument("--warmup", type=float, default=8.0, help="start-up before it (s)")
    p.add_argument("--readers", type=int, default=1,
                   help="passive /joint_states subscribers beside the pair")
    p.add_argument("--realtime-priority", type=int, default=None,
                   help="the nodes' realtime_priority (default: theirs)")
    p.add_argument("--domain-id", type=int, default=None,
                   help="ROS_DOMAIN_ID (1..100; default: from this process's id)")
    return p


def run(seconds: float, warmup: float, readers: int, priority: int | None, domain: int,
        log_dir: Path) -> tuple[dict[str, dict[str, float]], float, list[str]]:
    """CPU seconds per process and thread over the window, its length, the loop lines."""
    from damon_ros.ros.environment import node_environment
    from damon_ros.ros.launch import read_log, start_node, start_process, stop_node

    env = node_environment(domain, log_dir)
    params = None if priority is None else {"realtime_priority": priority}
    procs = {name: start_node(name, params, env, log_dir / f"{name}.log")
             for name in ("mock_panda", "controller")}
    for k in range(readers):
        procs[f"reader {k}"] = start_process([sys.executable, "-c", READER.format(k=k)], env,
                                             log_dir / f"reader{k}.log")
    try:
        time.sleep(warmup)
        for name, proc in procs.items():
            if proc.poll() is not None:
                raise RuntimeError(f"{name} exited ({proc.returncode}): {read_log(proc)[-2000:]}")
        before = {name: thread_cpu(p.pid) for name, p in procs.items()}
        t0 = time.monotonic()
        time.sleep(seconds)
        after = {name: thread_cpu(p.pid) for name, p in procs.items()}
        window = time.monotonic() - t0
    finally:
        for proc in procs.values():
            stop_node(proc)
        logs = {name: read_log(p) for name, p in procs.items()}
    used = {name: {t: after[name][t] - before[name].get(t, 0.0) for t in after[name]}
            for name in procs}
    lines = [f"{name}: {line.split('loop timing: ', 1)[1]}" for name, log in logs.items()
             for line in log.splitlines() if "loop timing: " in line]
    return used, window, lines


def table(used: dict[str, dict[str, float]], window: float) -> str:
    rows = ["| process | CPU cores | threads (cores) |", "|---|---|---|"]
    total = 0.0
    for name, threads in used.items():
        cores = sum(threads.values()) / window
        total += cores
        top = sorted(threads.items(), key=lambda kv: -kv[1])
        parts = ", ".join(f"{t} {v / window:.3f}" for t, v in top if v / window >= 0.005)
        rows.append(f"| {name} | {cores:.3f} | {parts} |")
    rows.append(f"| all | {total:.3f} | |")
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    domain = args.domain_id if args.domain_id is not None else 1 + os.getpid() % 100
    if not (args.seconds > 0 and args.warmup >= 0 and args.readers >= 0 and 1 <= domain <= 100):
        print("bench-loops: --seconds must be > 0, --warmup and --readers >= 0, --domain-id "
              "in 1..100", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory(prefix="bench_loops_") as tmp:
        print(f"bench-loops: mock_panda + controller, {args.readers} extra /joint_states "
              f"reader(s), {args.warmup:g} s warm-up, {args.seconds:g} s measured", flush=True)
        try:
            used, window, lines = run(args.seconds, args.warmup, args.readers,
                                      args.realtime_priority, domain, Path(tmp))
        except (RuntimeError, subprocess.SubprocessError) as exc:
            print(f"bench-loops: {exc}", file=sys.stderr)
            return 1
    print(table(used, window))
    print("\n".join(lines))
    return 0
