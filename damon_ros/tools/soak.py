"""``damon-ros soak``: every node for N minutes, goals and crossing obstacles without end.

A long run finds what a demo does not: slow leaks, latency that creeps up, a 1 kHz loop
that drops samples once a minute, a rare contact. mock_panda (1 kHz, exact contact check,
limit monitor), controller, planner, mock_camera (``--fps``) and tracker run on a private
ROS domain, each its own process, on a soak scenario built here (a public start state, the
box of D-001 and two spheres that sweep across the paths between the goals for the whole
run). A new goal, cycling through poses of public scenarios, goes out ``--goal-period-s``
after the last was sent once that one is reached (scored before it is replaced), or after
``--goal-timeout-s`` unreached: a goal a passing sphere blocks is reached once it passes,
and one still unreached then is reported as truly unreachable, with the planner's status
and the causes of its holds (every goal's record is in the report). This process watches
the graph (`soak_monitor.Monitor`) and closes one row per ``--window-s``: throughput,
latency percentiles, RSS of every node, dropped messages, contacts and limit violations.
It prints a progress line per window, then the tables, the goals and a verdict, and
writes ``soak.json`` (parameters, rows, verdict) beside the node logs and the scenario file
in ``--out``.

Exit 0 only when: no node crashed, no contact, no limit violation, at least one goal was
reached, and (with 3 or more windows) the last window's p99 re-route latency (obstacle
update -> trajectory published, from the planner's log) and every node's mean RSS are each
at most DRIFT_BOUND (1.10) times the first window's (the latency only when both windows
hold DRIFT_MIN_SAMPLES re-routes: the p99 of a handful is their maximum). Start-up (node
start, discovery, the first goal) is excluded: the first window starts one goal period
after the first goal.

This module holds the command line, the soak scenario and goal schedule, and starting and
stopping the nodes; `damon_ros.tools.soak_monitor` watches the running graph and
`damon_ros.tools.soak_report` judges and prints the rows.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import yaml

from damon_ros.core.limits import PROFILES
from damon_ros.ros import topics
from damon_ros.ros.environment import node_environment, observer_environment
from damon_ros.ros.launch import start_node, stop_node
from damon_ros.tools.soak_monitor import Monitor, SoakGoal
from damon_ros.tools.soak_report import (
    DRIFT_BOUND,
    DRIFT_MIN_WINDOWS,
    print_report,
    verdict,
)

START_SCENARIO = "D-001"  # its start state and its static box
# Goals right, left, right, left of the box, so that every move crosses in front of it. Each
# goal configuration keeps >= 6 cm from the box (B-002, 5 cm from it and 3 cm from a sweep,
# was tried and left out) and GOAL_CLEARANCE_M from the sweeps (checked in `check_goals`),
# so an arm waiting at a goal is never hit: the crossings happen on the way.
GOAL_SCENARIOS = ("D-001", "C-002", "A-001", "F-001")
GOAL_CLEARANCE_M = 0.08


@dataclass(frozen=True)
class Sweep:
    """A sphere moving back and forth between ``a`` and ``b`` for the whole run."""

    name: str
    color: str
    radius: float
    a: tuple[float, float, float]
    b: tuple[float, float, float]
    travel_s: float
    dwell_s: float
    offset_s: float

    def waypoints(self, duration_s: float) -> list[list[float]]:
        """[t, x, y, z] rows: hold at ``a`` until ``offset_s``, then a, b, a, ... to the end."""
        rows, t, ends = [[0.0, *self.a]], self.offset_s, (self.b, self.a)
        if t > 0.0:
            rows.append([t, *self.a])
        k = 0
        while t < duration_s:
            t += self.travel_s
            rows.append([round(t, 3), *ends[k % 2]])
            t += self.dwell_s
            rows.append([round(t, 3), *ends[k % 2]])
            k += 1
        return rows


# One sphere crosses behind the goals along y (D-001's sweep, made periodic), one drops
# through the region the arm passes between the right and the left goals (checked in
# `check_goals`: neither comes within GOAL_CLEARANCE_M of a goal configuration).
SWEEPS = (
    Sweep("ball", "green", 0.056, (0.70, -0.60, 0.50), (0.70, 0.60, 0.50), 7.0, 1.5, 0.0),
    Sweep("drop", "blue", 0.05, (0.50, 0.10, 0.85), (0.50, 0.10, 0.45), 3.0, 2.0, 1.0),
)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="damon-ros soak", description=__doc__.split("\n\n")[0],
        epilog=f"Pass/fail: exit 0 only with no crash, no contact, no limit violation "
               f"(velocity, acceleration, jerk, position; late commands are reported, not "
               f"failed), at least one goal reached, and with >= {DRIFT_MIN_WINDOWS} windows: "
               f"last-window p99 re-route latency <= {DRIFT_BOUND:.2f} x the first window's "
               f"and each node's last-window mean RSS <= {DRIFT_BOUND:.2f} x its first "
               "window's. Exit 1 otherwise (the verdict names the failed check), 2 on bad "
               "arguments.")
    p.add_argument("--minutes", type=float, default=10.0, help="measured time (default 10)")
    p.add_argument("--window-s", type=float, default=60.0, help="seconds per row (default 60)")
    p.add_argument("--goal-period-s", type=float, default=6.0,
                   help="a reached goal is replaced this many seconds after it was sent "
                        "(default 6)")
    p.add_argument("--goal-timeout-s", type=float, default=20.0,
                   help="an unreached goal stays in force this long, then counts as "
                        "unreachable and is replaced (default 20)")
    p.add_argument("--fps", type=float, default=90.0, help="mock camera frame rate (default 90)")
    p.add_argument("--no-camera", action="store_true",
                   help="planner on ground-truth obstacles; no images, no tracker")
    p.add_argument("--out", default="soak_output", help="folder for logs, scenario, soak.json")
    p.add_argument("--domain-id", type=int, default=None, help="ROS_DOMAIN_ID (1..100)")
    p.add_argument("--startup-s", type=float, default=12.0,
                   help="seconds the nodes get to start before the scenario clock runs "
                        "(slower ones get up to 90 s; the goals start once they are up)")
    p.add_argument("--model", default=None, help="model directory (default: shipped)")
    p.add_argument("--profile", choices=PROFILES, default="panda",
                   help="joint-limit profile of planner, controller and mock_panda's monitor "
                        "(fr3: libfranka's position-dependent velocity bound)")
    return p


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    problem = _argument_problem(args)
    if problem:
        print(f"damon-ros soak: {problem}", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    domain = args.domain_id if args.domain_id is not None else 1 + os.getpid() % 100
    total_s = args.startup_s + args.goal_period_s + 60.0 * args.minutes
    scenario_path, goals = write_soak_scenario(out, total_s + 60.0)
    result = run_soak(args, domain, out, scenario_path, goals)
    print_report(result)
    (out / "soak.json").write_text(json.dumps(_plain(result), indent=1))
    print(f"wrote {out / 'soak.json'} (node logs and {scenario_path.name} beside it)")
    return 0 if result["verdict"]["passed"] else 1


def _argument_problem(args) -> str:
    checks = [(args.minutes > 0, "--minutes must be > 0"),
              (args.window_s >= 5.0, "--window-s must be >= 5"),
              (args.goal_period_s >= 1.0, "--goal-period-s must be >= 1"),
              (args.goal_timeout_s >= args.goal_period_s,
               "--goal-timeout-s must be >= --goal-period-s"),
              (0.1 <= args.fps <= 240.0, "--fps must be in 0.1..240"),
              (args.startup_s >= 0.0, "--startup-s must be >= 0"),
              (args.domain_id is None or 1 <= args.domain_id <= 100,
               "--domain-id must be in 1..100")]
    return next((why for ok, why in checks if not ok), "")


def _plain(value):
    """JSON-ready copy: numpy scalars as numbers, NaN and inf as null (strict JSON)."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    return str(value)


# ----------------------------------------------------------------------------- scenario

def check_goals(robot, scenario) -> list[SoakGoal]:
    """Goal poses of public scenarios, each solved with the planner's IK (chained, as the
    arm moves from one to the next) and kept clear of every sweep; ValueError otherwise."""
    from damon_ros.core.scenario import load_public_scenarios

    static = [o.shape for o in scenario.obstacles if not o.is_dynamic]
    moving = [o for o in scenario.obstacles if o.is_dynamic]
    goals, q_near = [], scenario.start
    by_name = {s.name: s for s in load_public_scenarios(GOAL_SCENARIOS)}
    for source in (by_name[name] for name in GOAL_SCENARIOS):
        g = source.goal
        ik = robot.ik(g.position, g.orientation, q_near=q_near, obstacles=static,
                      min_clearance=0.01)
        if not ik.success:
            raise ValueError(f"soak goal {source.name} is unreachable: {ik.reason}")
        clearance = min(robot.clearance(ik.q, [o.shape_at(t)]).distance for o in moving
                        for t in np.linspace(0.0, float(o.waypoints[-1, 0]), 200))
        if clearance < GOAL_CLEARANCE_M:
            raise ValueError(f"a sweep comes {clearance:.3f} m close to soak goal "
                             f"{source.name} (needs {GOAL_CLEARANCE_M} m)")
        goals.append(SoakGoal(source.name, g.position.tolist(), g.orientation.tolist(),
                              g.position_tolerance, g.orientation_tolerance, ik.q.tolist()))
        q_near = ik.q
    return goals


def soak_mapping(duration_s: float) -> dict:
    """The soak scenario (format 1) as YAML data: start and box of START_SCENARIO + SWEEPS."""
    from damon_ros.core.resources import public_scenarios_dir

    base = yaml.safe_load((public_scenarios_dir() / f"{START_SCENARIO}.yaml").read_text())
    static = [o for o in base["obstacles"] if "motion" not in o]
    spheres = [{"name": s.name, "shape": "sphere", "size": [s.radius], "color": s.color,
                "pose": {"position": list(s.a), "orientation": [0.0, 0.0, 0.0, 1.0]},
                "motion": {"type": "waypoints", "waypoints": s.waypoints(duration_s)}}
               for s in SWEEPS]
    return {"format": 1, "name": "soak",
            "description": f"{START_SCENARIO}'s start and box, spheres sweeping for "
                           f"{duration_s:.0f} s; goals cycle (damon-ros soak)",
            "robot": "panda", "start": base["start"], "goal": base["goal"],
            "obstacles": static + spheres, "time_limit": float(duration_s)}


def write_soak_scenario(out: Path, duration_s: float) -> tuple[Path, list[SoakGoal]]:
    """Write ``soak_scenario.yaml`` (loadable by the nodes) and check the goals against it."""
    from damon_ros.core.robot import Robot
    from damon_ros.core.scenario import load_scenario

    path = out / "soak_scenario.yaml"
    path.write_text(yaml.safe_dump(soak_mapping(duration_s), sort_keys=False,
                                   default_flow_style=None))
    goals = check_goals(Robot("fast"), load_scenario(path))
    return path.resolve(), goals


# ----------------------------------------------------------------------------- nodes

def node_specs(args, scenario: Path, start_time: float) -> dict:
    """name -> (module, parameters, remaps) of the graph, as `damon_ros.tools.demo` starts it."""
    common = {"scenario": str(scenario), "scenario_start_time_s": start_time}
    profile = {"limit_profile": args.profile}
    specs = {
        "mock_panda": ("mock_panda", {**common, **profile, "contact_check": True,
                                      "limit_check": True}, None),
        "controller": ("controller", profile, None),
        "planner": ("planner", {**profile, "model_dir": args.model or ""},
                    {topics.OBSTACLES: topics.SIM_OBSTACLES} if args.no_camera else None),
        "mock_camera": ("mock_camera", {**common, "fps": args.fps,
                                        "truth_lifetime_frames": args.fps,  # 1 s
                                        "publish_images": not args.no_camera}, None),
    }
    if not args.no_camera:
        specs["tracker"] = ("tracker", {"stats_period_s": min(10.0, args.window_s)}, None)
    return specs


def run_soak(args, domain: int, out: Path, scenario: Path, goals: list[SoakGoal]) -> dict:
    """Start the graph, monitor it, stop it (always); the result for the report."""
    env = node_environment(domain, Path(tempfile.gettempdir()) / "damon_soak_ros_logs")
    # this process watches the same graph, over UDP only (see observer_environment)
    os.environ.update(observer_environment(domain, out / "monitor_fastdds_udp.xml"))
    start_time = time.time() + args.startup_s
    print(f"damon-ros soak: {args.minutes:g} min on ROS_DOMAIN_ID={domain}, "
          f"{'ground-truth obstacles' if args.no_camera else f'camera {args.fps:g} fps + tracker'}"
          f", a goal every {args.goal_period_s:g} s once reached (unreached: "
          f"{args.goal_timeout_s:g} s) over {len(goals)} poses, "
          f"{args.window_s:g} s windows; logs in {out}", flush=True)
    procs: dict = {}
    exit_codes: dict[str, int] = {}
    try:
        for name, (module, params, remaps) in node_specs(args, scenario, start_time).items():
            procs[name] = start_node(module, params, env, out / f"{name}.log", remaps)
        monitor = Monitor(args, domain, procs, goals, out)
        try:
            rows, crashes, note = monitor.run(start_time)
        finally:
            monitor.close()
    finally:
        for name, proc in procs.items():
            exit_codes[name] = stop_node(proc)
    result = {"parameters": {**vars(args), "domain_id": domain, "scenario": str(scenario),
                             "goals": [asdict(g) for g in goals]},
              "rows": rows, "crashes": crashes, "note": note, "exit_codes": exit_codes}
    result["verdict"] = verdict(rows, crashes, note)
    return result
