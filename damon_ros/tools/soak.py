"""``damon-ros soak``: every node for N minutes, goals and crossing obstacles without end.

A long run finds what a demo does not: slow leaks, latency that creeps up, a 1 kHz loop
that drops samples once a minute, a rare contact. mock_panda (1 kHz, exact contact check,
limit monitor), controller, planner, mock_camera (``--fps``) and tracker run on a private
ROS domain, each its own process, on a soak scenario built here (a public start state, the
box of D-001 and two spheres that sweep across the paths between the goals for the whole
run). A new goal, cycling through poses of public scenarios, goes out every
``--goal-period-s``. This process watches the graph (see `Monitor`) and closes one row per
``--window-s``: throughput, latency percentiles, RSS of every node, dropped messages,
contacts and limit violations. It prints a progress line per window, then the tables and
a verdict, and writes ``soak.json`` (parameters, rows, verdict) beside the node logs and
the scenario file in ``--out``.

Exit 0 only when: no node crashed, no contact, no limit violation, at least one goal was
reached, and (with 3 or more windows) the last window's p99 re-route latency (obstacle
update -> trajectory published, from the planner's log) and every node's mean RSS are each
at most DRIFT_BOUND (1.10) times the first window's (the latency only when both windows
hold DRIFT_MIN_SAMPLES re-routes: the p99 of a handful is their maximum). Start-up (node
start, discovery, the first goal) is excluded: the first window starts one goal period
after the first goal.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import struct
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import yaml

from damon_ros.ros import topics
from damon_ros.ros.environment import ros_environment
from damon_ros.ros.stamps import to_stamp

DRIFT_BOUND = 1.10  # last window / first window, p99 re-route latency and each node's RSS
DRIFT_MIN_WINDOWS = 3  # fewer windows: too short to tell drift from warm-up
DRIFT_MIN_SAMPLES = 30  # re-routes per window below which its p99 is not compared
NODES = ("mock_panda", "controller", "planner", "mock_camera", "tracker")
START_SCENARIO = "D-001"  # its start state and its static box
# Goals right, left, right, left of the box, so that every move crosses in front of it. Each
# goal configuration keeps >= 6 cm from the box (B-002, 5 cm from it and 3 cm from a sweep,
# was tried and left out) and GOAL_CLEARANCE_M from the sweeps (checked in `check_goals`),
# so an arm waiting at a goal is never hit: the crossings happen on the way.
GOAL_SCENARIOS = ("D-001", "C-002", "A-001", "F-001")
GOAL_CLEARANCE_M = 0.08
STILL_RAD_S = 0.02  # a goal is reached when the TCP is within tolerance and this still
SCORE_PERIOD_S = 0.02  # forward kinematics for "reached" at 50 Hz
RSS_PERIOD_S = 2.0
JOINT_PERIOD_S = 1e-3  # mock_panda's rate_hz
VIOLATIONS = ("velocity", "acceleration", "jerk", "position", "q_outside")
# /damon/sim/limits counters (damon_ros.simulation.mock_arm.LimitMonitor);
# *_jitter are a subset, late apart
LIMIT_KEYS = ("velocity", "acceleration", "jerk", "position", "late", "acceleration_jitter",
              "jerk_jitter")


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


@dataclass(frozen=True)
class SoakGoal:
    name: str
    position: list[float]
    orientation: list[float]
    position_tolerance: float
    orientation_tolerance: float
    joints: list[float]  # the IK solution checked here (the planner solves again)


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
                   help="a new goal every this many seconds (default 6)")
    p.add_argument("--fps", type=float, default=90.0, help="mock camera frame rate (default 90)")
    p.add_argument("--no-camera", action="store_true",
                   help="planner on ground-truth obstacles; no images, no tracker")
    p.add_argument("--out", default="soak_output", help="folder for logs, scenario, soak.json")
    p.add_argument("--domain-id", type=int, default=None, help="ROS_DOMAIN_ID (1..100)")
    p.add_argument("--startup-s", type=float, default=12.0,
                   help="seconds the nodes get to start before the scenario clock runs")
    p.add_argument("--model", default=None, help="model directory (default: shipped)")
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
    specs = {
        "mock_panda": ("mock_panda", {**common, "contact_check": True, "limit_check": True},
                       None),
        "controller": ("controller", {"planner_heartbeat_timeout_s": 1.0,
                                      "joint_state_timeout_s": 0.1}, None),
        "planner": ("planner", {"model_dir": args.model or ""},
                    {topics.OBSTACLES: topics.SIM_OBSTACLES} if args.no_camera else None),
        "mock_camera": ("mock_camera", {**common, "fps": args.fps,
                                        "truth_lifetime_frames": args.fps,  # 1 s
                                        "publish_images": not args.no_camera}, None),
    }
    if not args.no_camera:
        specs["tracker"] = ("tracker", {"stats_period_s": min(10.0, args.window_s)}, None)
    return specs


MONITOR_PROFILE = """<?xml version="1.0" encoding="UTF-8" ?>
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <transport_descriptors>
    <transport_descriptor><transport_id>soak_udpv4</transport_id><type>UDPv4</type>
    </transport_descriptor>
  </transport_descriptors>
  <participant profile_name="soak_monitor_udp_only" is_default_profile="true">
    <rtps>
      <userTransports><transport_id>soak_udpv4</transport_id></userTransports>
      <useBuiltinTransports>false</useBuiltinTransports>
    </rtps>
  </participant>
</profiles>
"""


def monitor_environment(domain: int, out: Path) -> dict[str, str]:
    """This process's ROS environment: the nodes' graph, but UDP only (no shared memory).

    config/fastdds_shm.xml explains why: a normal-priority reader of the real-time nodes'
    1 kHz topics over shared memory can hold a cross-process mutex and stall them. An
    observer must not disturb what it observes.
    """

    profile = out / "monitor_fastdds_udp.xml"
    profile.write_text(MONITOR_PROFILE)
    env = ros_environment(domain)
    env["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(profile.resolve())
    return env


def run_soak(args, domain: int, out: Path, scenario: Path, goals: list[SoakGoal]) -> dict:
    """Start the graph, monitor it, stop it (always); the result for the report."""
    from damon_ros.ros.launch import start_node, stop_node

    env = dict(os.environ, PYTHONUNBUFFERED="1", RCUTILS_COLORIZED_OUTPUT="0",
               ROS_LOG_DIR=str(Path(tempfile.gettempdir()) / "damon_soak_ros_logs"))
    env.update(ros_environment(domain))
    os.environ.update(monitor_environment(domain, out))
    start_time = time.time() + args.startup_s
    print(f"damon-ros soak: {args.minutes:g} min on ROS_DOMAIN_ID={domain}, "
          f"{'ground-truth obstacles' if args.no_camera else f'camera {args.fps:g} fps + tracker'}"
          f", a goal every {args.goal_period_s:g} s over {len(goals)} poses, "
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


# ----------------------------------------------------------------------------- monitor

def _cdr_stamp(data: bytes) -> float:
    """header.stamp of a serialised message that starts with a std_msgs/Header (CDR)."""
    sec, nanosec = struct.unpack_from("<iI" if data[1] == 1 else ">iI", data, 4)
    return sec + 1e-9 * nanosec


class Tap:
    """One subscription taken directly, serialised, on a node no executor waits on.

    Why: an executor callback costs ~0.4 ms of Python per message on this machine, far too
    much for 1 kHz topics; a direct take of the raw bytes is a fraction of that, and a deep
    history keeps every message while this process is busy. Counts what arrived, and the
    publisher's sequence numbers, so what was *published* is known even if this process
    missed some.
    """

    def __init__(self, node, msg_type, topic: str, qos, handler=None):
        self.sub = node.create_subscription(msg_type, topic, lambda _m: None, qos, raw=True)
        self.handler = handler
        self.count = 0
        self.first_seq: int | None = None
        self.last_seq: int | None = None

    def drain(self) -> None:
        sub = self.sub
        with sub.handle:
            while (taken := sub.handle.take_message(sub.msg_type, True)) is not None:
                data, info = taken
                seq = info.get("publication_sequence_number") or 0
                self.count += 1
                self.first_seq = seq if self.first_seq is None else self.first_seq
                self.last_seq = seq
                if self.handler is not None:
                    self.handler(data, seq)

    @property
    def published(self) -> int:
        """Messages published since the first one seen (from sequence numbers)."""
        return 0 if self.first_seq is None else self.last_seq - self.first_seq + 1


@dataclass
class JointStream:
    """Stamps and sequence numbers of /joint_states: ticks mock_panda did not publish."""

    last_stamp: float | None = None
    last_seq: int | None = None
    max_gap: float = 0.0
    gaps: int = 0
    raw: bytes | None = None

    def __call__(self, data: bytes, seq: int) -> None:
        stamp = _cdr_stamp(data)
        if self.last_seq is not None and seq == self.last_seq + 1:
            gap = stamp - self.last_stamp
            self.max_gap = max(self.max_gap, gap)
            self.gaps += gap > 1.5 * JOINT_PERIOD_S
        self.last_stamp, self.last_seq, self.raw = stamp, seq, data


@dataclass
class Latest:
    """The newest message of a low-rate topic, deserialised (its `Tap` counts them)."""

    msg_type: type
    message: object = None

    def __call__(self, data: bytes, _seq: int) -> None:
        from rclpy.serialization import deserialize_message

        self.message = deserialize_message(data, self.msg_type)


@dataclass
class Contacts:
    """/damon/sim/contact rounds: how many said contact, and the smallest clearance."""

    errors: int = 0
    min_clearance: float = math.inf
    worst: str = ""

    def __call__(self, data: bytes, _seq: int) -> None:
        from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
        from rclpy.serialization import deserialize_message

        for status in deserialize_message(data, DiagnosticArray).status:
            values = {kv.key: kv.value for kv in status.values}
            d = float(values.get("min_clearance_m", "inf"))
            if d < self.min_clearance:
                self.min_clearance, self.worst = d, f"{values.get('link')}/{values.get('obstacle')}"
            if status.level == DiagnosticStatus.ERROR:
                self.errors += 1


@dataclass
class Trajectories:
    published: int = 0
    holds: int = 0  # empty trajectories: stop and hold

    def __call__(self, data: bytes, _seq: int) -> None:
        from rclpy.serialization import deserialize_message
        from trajectory_msgs.msg import JointTrajectory

        msg = deserialize_message(data, JointTrajectory)
        if msg.points:
            self.published += 1
        else:
            self.holds += 1


class LogTail:
    """New complete lines of a node's log file, read incrementally."""

    def __init__(self, path: Path):
        self.path = path
        self.offset = 0
        self.partial = ""

    def lines(self) -> list[str]:
        try:
            with open(self.path, errors="replace") as f:
                f.seek(self.offset)
                text = f.read()
                self.offset = f.tell()
        except OSError:
            return []
        text = self.partial + text
        *lines, self.partial = text.split("\n")
        return lines


DECISION = re.compile(r"\[(\d+\.\d+)\] \[planner\]: (plan|re-route): .*decided in ([\d.]+) ms "
                      r"\(([\d.]+) ms after the input\)")
TRACKER_STATS = re.compile(r"\[(\d+\.\d+)\] \[tracker\]: ([\d.]+) frames/s tracked; latency "
                           r"stamp->publish p50 ([\d.]+) ms, p95 ([\d.]+) ms")


def rss_mb(pid: int) -> float:
    """Resident set size of a process (MB), NaN once it is gone."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except (OSError, ValueError):
        pass
    return math.nan


def _percentiles(values: list[float]) -> dict[str, float]:
    if not values:
        return {"n": 0, "p50": math.nan, "p90": math.nan, "p99": math.nan, "max": math.nan}
    v = np.asarray(values)
    return {"n": int(v.size), "p50": float(np.percentile(v, 50)),
            "p90": float(np.percentile(v, 90)), "p99": float(np.percentile(v, 99)),
            "max": float(v.max())}


@dataclass
class GoalState:
    """The goal in force and whether (and when) the arm reached it."""

    index: int = -1
    sent_at: float = math.nan
    reached: bool = False
    sent: int = 0
    reached_count: int = 0
    times: list[float] = field(default_factory=list)  # goal -> reached (s), this window


class Monitor:
    """This process's view of the graph: own rclpy context, direct takes, no executor.

    Everything it needs arrives on topics (taken raw, see `Tap`) or in the node logs
    (decision latencies, tracker statistics), plus ``/proc`` for memory. The goal publisher
    is the only thing it sends.
    """

    def __init__(self, args, domain: int, procs: dict, goals: list[SoakGoal], out: Path):
        import rclpy
        from rclpy.signals import SignalHandlerOptions

        from damon_ros.core.limits import joint_limits
        from damon_ros.core.robot import Robot

        self.args, self.procs, self.goals, self.out = args, procs, goals, out
        self.robot = Robot("fast")
        self.limits = joint_limits("panda")
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain,
                   signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node("damon_soak", context=self.context)
        self._subscribe()
        self.planner_log = LogTail(out / "planner.log")
        self.tracker_log = LogTail(out / "tracker.log")
        self.goal = GoalState()
        self.rss: dict[str, list[float]] = {}
        self.q_outside = 0
        self._window_start = 0.0
        self._warm_end = math.inf  # decisions logged before it belong to the start-up

    def _subscribe(self) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseStamped
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import CameraInfo, JointState
        from trajectory_msgs.msg import JointTrajectory
        from visualization_msgs.msg import MarkerArray

        deep = 2000  # 2 s of a 1 kHz topic: nothing lost while this process is busy
        best_effort = QoSProfile(depth=200, reliability=ReliabilityPolicy.BEST_EFFORT)
        n = self.node
        self.joints = JointStream()
        self.contacts = Contacts()
        self.trajectories = Trajectories()
        self.limit_status = Latest(DiagnosticArray)
        self.planner_status = Latest(DiagnosticArray)
        frames = (topics.SIM_OBSTACLES, MarkerArray, 200) if self.args.no_camera else (
            topics.CAMERA_INFO, CameraInfo, best_effort)
        self.taps = {
            "joint_states": Tap(n, JointState, topics.JOINT_STATES, deep, self.joints),
            "frames": Tap(n, frames[1], frames[0], frames[2]),
            "obstacles": Tap(n, MarkerArray, topics.OBSTACLES, 200),
            "trajectories": Tap(n, JointTrajectory, topics.JOINT_TRAJECTORY, 100,
                                self.trajectories),
            "contact": Tap(n, DiagnosticArray, topics.SIM_CONTACT, 500, self.contacts),
            "limits": Tap(n, DiagnosticArray, topics.SIM_LIMITS, 10, self.limit_status),
            "status": Tap(n, DiagnosticArray, topics.PLANNER_STATUS, 100,
                          self.planner_status),
        }
        self.goal_pub = n.create_publisher(PoseStamped, topics.GOAL_POSE, 10)

    def close(self) -> None:
        import rclpy

        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)

    # -- the run

    def run(self, start_time: float) -> tuple[list[dict], list[str], str]:
        """Wait for the graph, send goals, close a row per window; (rows, crashes, note)."""
        if not self._wait_ready(start_time + 30.0):
            return [], self._crashes(), (f"the nodes did not come up within "
                                         f"{self.args.startup_s + 30.0:.0f} s (missing: "
                                         f"{self._not_ready()}; see their logs)")
        self._sleep_until(start_time)
        t_first = time.time()
        self._send_goal(0, t_first)
        warm_end = self._warm_end = t_first + self.args.goal_period_s
        self._pump_until(warm_end)
        self._open_window(warm_end)
        windows = max(1, math.ceil(60.0 * self.args.minutes / self.args.window_s - 1e-9))
        end = warm_end + 60.0 * self.args.minutes
        rows: list[dict] = []
        for k in range(windows):
            w_end = min(warm_end + (k + 1) * self.args.window_s, end)
            crashed = not self._pump_until(w_end)
            rows.append(self._close_window(k + 1, warm_end, time.time()))
            print_progress(rows[-1], windows)
            if crashed:
                return rows, self._crashes(), "stopped early: a node exited"
            self._open_window(time.time())
        return rows, [], ""

    def _crashes(self) -> list[str]:
        return [f"{name} exited with {p.returncode}" for name, p in self.procs.items()
                if p.poll() is not None]

    def _alive(self) -> bool:
        return all(p.poll() is None for p in self.procs.values())

    def _drain(self) -> None:
        for tap in self.taps.values():
            tap.drain()

    def _wait_ready(self, deadline: float) -> bool:
        """Joint states, planner status and a matched goal subscriber, or False."""
        while time.time() < deadline and self._alive():
            self._drain()
            if (self.joints.raw is not None and self.planner_status.message is not None
                    and self.goal_pub.get_subscription_count() > 0):
                return True
            time.sleep(0.02)
        return False

    def _not_ready(self) -> str:
        missing = [what for what, ok in (
            (topics.JOINT_STATES, self.joints.raw is not None),
            (topics.PLANNER_STATUS, self.planner_status.message is not None),
            ("a goal_pose subscriber", self.goal_pub.get_subscription_count() > 0)) if not ok]
        return ", ".join(missing) or "nothing"

    def _sleep_until(self, t: float) -> None:
        while time.time() < t:
            self._drain()
            time.sleep(min(0.01, max(0.0, t - time.time())))

    def _pump_until(self, t_end: float) -> bool:
        """Take messages, send goals, score and sample until ``t_end``; False on a crash."""
        next_score = next_rss = 0.0
        while (now := time.time()) < t_end:
            self._drain()
            if not self._alive():
                return False
            k = int((now - self.goal.sent_at) // self.args.goal_period_s)
            if k >= 1:
                self._send_goal(self.goal.index + 1, self.goal.sent_at +
                                k * self.args.goal_period_s)
            if now >= next_score:
                next_score = now + SCORE_PERIOD_S
                self._score(now)
            if now >= next_rss:
                next_rss = now + RSS_PERIOD_S
                self._sample_rss()
            time.sleep(0.005)
        self._drain()
        return self._alive()

    def _send_goal(self, index: int, t: float) -> None:
        from geometry_msgs.msg import PoseStamped

        goal = self.goals[index % len(self.goals)]
        msg = PoseStamped()
        msg.header.frame_id = "panda_link0"
        msg.header.stamp = to_stamp(time.time())
        msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = goal.position
        o = msg.pose.orientation
        o.x, o.y, o.z, o.w = goal.orientation
        self.goal_pub.publish(msg)
        self.goal = GoalState(index, t, False, self.goal.sent + 1, self.goal.reached_count,
                              self.goal.times)

    def _score(self, now: float) -> None:
        """Reached (TCP within tolerance, arm still) and joint positions inside the limits."""
        from rclpy.serialization import deserialize_message
        from sensor_msgs.msg import JointState

        from damon_ros.core.kinematics import pose_error

        if self.joints.raw is None:
            return
        msg = deserialize_message(self.joints.raw, JointState)
        q, qd = np.asarray(msg.position[:7]), np.asarray(msg.velocity[:7])
        self.q_outside += int(np.any(q < self.limits.lower) or np.any(q > self.limits.upper))
        if self.goal.reached or self.goal.index < 0 or float(np.max(np.abs(qd))) >= STILL_RAD_S:
            return
        goal = self.goals[self.goal.index % len(self.goals)]
        p_err, o_err = pose_error(*self.robot.tcp_pose(q), goal.position, goal.orientation)
        if p_err <= goal.position_tolerance and o_err <= goal.orientation_tolerance:
            self.goal.reached = True
            self.goal.reached_count += 1
            self.goal.times.append(now - self.goal.sent_at)

    def _sample_rss(self) -> None:
        for name, proc in self.procs.items():
            self.rss.setdefault(name, []).append(rss_mb(proc.pid))
        self.rss.setdefault("soak (this monitor)", []).append(rss_mb(os.getpid()))

    # -- windows

    def _open_window(self, t: float) -> None:
        """Remember every counter's value at the window's start."""
        self._drain()
        self._window_start = t
        self._mark = {
            "taps": {k: (tap.count, tap.last_seq) for k, tap in self.taps.items()},
            "js": (self.joints.last_stamp, self.joints.last_seq),
            "contacts": self.contacts.errors, "trajectories": self.trajectories.published,
            "holds": self.trajectories.holds, "q_outside": self.q_outside,
            "limits": self._limit_counts(), "sent": self.goal.sent,
            "reached": self.goal.reached_count,
        }
        self.joints.max_gap, self.joints.gaps = 0.0, 0
        self.contacts.min_clearance, self.contacts.worst = math.inf, ""
        self.goal.times = []
        self.rss = {}
        self._sample_rss()

    def _limit_counts(self) -> dict[str, float]:
        msg = self.limit_status.message
        if msg is None or not msg.status:
            return {}
        return {kv.key: float(kv.value) for kv in msg.status[0].values}

    def _published(self, key: str) -> int:
        """Messages published on a tap's topic during the window (sequence numbers)."""
        tap, (_, seq0) = self.taps[key], self._mark["taps"][key]
        if tap.last_seq is None:
            return 0
        return tap.last_seq - (seq0 if seq0 is not None else tap.first_seq - 1)

    def _close_window(self, index: int, warm_end: float, now: float) -> dict:
        self._drain()
        m, duration = self._mark, max(now - self._window_start, 1e-9)
        row = {"window": index, "t0_s": round(self._window_start - warm_end, 1),
               "t1_s": round(now - warm_end, 1), "duration_s": round(duration, 2)}
        row.update(self._throughput(duration))
        row.update(self._dropped())
        row.update(self._latency())
        row.update(self._safety())
        row["rss_mb"] = {name: float(np.nanmean(v)) if np.isfinite(v).any() else math.nan
                         for name, v in self.rss.items()}
        row["goals_sent"] = self.goal.sent - m["sent"]
        row["goals_reached"] = self.goal.reached_count - m["reached"]
        row["goal_time_s_p50"] = float(np.median(self.goal.times)) if self.goal.times \
            else math.nan
        row["planner_status"] = _status_values(self.planner_status.message)
        return row

    def _throughput(self, duration: float) -> dict:
        limits, before = self._limit_counts(), self._mark["limits"]
        commands = limits.get("commands", 0.0) - before.get("commands", 0.0)
        return {"joint_states_hz": self._published("joint_states") / duration,
                "commands_hz": commands / duration,  # accepted by mock_panda
                "frames_hz": self._published("frames") / duration,
                "obstacles_hz": self._published("obstacles") / duration,
                "trajectories": self.trajectories.published - self._mark["trajectories"],
                "holds": self.trajectories.holds - self._mark["holds"]}

    def _dropped(self) -> dict:
        """Ticks mock_panda skipped (stamps vs. sequence numbers), frames not tracked."""
        stamp0, seq0 = self._mark["js"]
        j = self.joints
        skipped = 0
        if stamp0 is not None and j.last_seq is not None and j.last_seq > seq0:
            ticks = round((j.last_stamp - stamp0) / JOINT_PERIOD_S)
            skipped = max(0, ticks - (j.last_seq - seq0))
        received = self.taps["joint_states"].count - self._mark["taps"]["joint_states"][0]
        untracked = (None if self.args.no_camera
                     else self._published("frames") - self._published("obstacles"))
        return {"js_skipped": skipped, "js_gaps": j.gaps, "js_max_gap_ms": 1e3 * j.max_gap,
                "js_monitor_lost": self._published("joint_states") - received,
                "frames_untracked": untracked}

    def _latency(self) -> dict:
        """Planner decisions logged since the last window (after the warm-up) and the
        tracker's statistics lines; a line counts in the window in which it is read."""
        decided: dict[str, list[float]] = {"plan": [], "re-route": []}
        after: list[float] = []
        for line in self.planner_log.lines():
            match = DECISION.search(line)
            if match and float(match.group(1)) >= self._warm_end:
                decided[match.group(2)].append(float(match.group(3)))
                if match.group(2) == "re-route":
                    after.append(float(match.group(4)))
        stats = np.array([[float(g) for g in m.groups()[1:]] for m in
                          map(TRACKER_STATS.search, self.tracker_log.lines()) if m])
        # each line covers stats_period_s: mean rate, median p50, worst p95 of the window
        tracker = {} if stats.size == 0 else {
            "tracked_fps": float(stats[:, 0].mean()),
            "latency_p50_ms": float(np.median(stats[:, 1])),
            "latency_p95_ms": float(stats[:, 2].max())}
        return {"reroute_decided_ms": _percentiles(decided["re-route"]),
                "reroute_after_input_ms": _percentiles(after),
                "plan_decided_ms": _percentiles(decided["plan"]), "tracker": tracker}

    def _safety(self) -> dict:
        limits, before = self._limit_counts(), self._mark["limits"]
        counts = {k: int(limits.get(k, 0.0) - before.get(k, 0.0)) for k in LIMIT_KEYS}
        counts["q_outside"] = self.q_outside - self._mark["q_outside"]
        peaks = {k: limits.get(f"peak_{k}_fraction", math.nan)
                 for k in ("velocity", "acceleration", "jerk")}
        return {"contacts": self.contacts.errors - self._mark["contacts"],
                "min_clearance_m": self.contacts.min_clearance,
                "closest": self.contacts.worst, "limits": counts,
                "violations": sum(counts[k] for k in VIOLATIONS),
                "limit_peaks_so_far": peaks,
                "limit_max_gap_ms": limits.get("max_gap_ms", math.nan)}


def _status_values(msg) -> dict:
    if msg is None or not msg.status:
        return {}
    return {kv.key: kv.value for kv in msg.status[0].values}


# ----------------------------------------------------------------------------- verdict

def _drift(first: float, last: float) -> tuple[bool | None, str]:
    if not (math.isfinite(first) and math.isfinite(last)) or first <= 0.0:
        return None, "no data"
    return last <= DRIFT_BOUND * first, f"{last / first:.3f} x"


def verdict(rows: list[dict], crashes: list[str], note: str) -> dict:
    """Every check with its numbers; passed only if none failed (see the module doc)."""
    checks = []

    def check(name: str, ok: bool | None, detail: str) -> None:
        checks.append({"check": name, "ok": ok, "detail": detail})

    check("no crash", not crashes and not note, "; ".join(crashes) or note or "all nodes ran")
    contacts = sum(r["contacts"] for r in rows)
    clearance = min((r["min_clearance_m"] for r in rows), default=math.nan)
    check("0 contacts", contacts == 0 and bool(rows),
          f"{contacts} contact rounds, min clearance {clearance:.3f} m (exact meshes)")
    total = {k: sum(r["limits"][k] for r in rows) for k in (*VIOLATIONS, *LIMIT_KEYS[4:])}
    check("0 limit violations", sum(total[k] for k in VIOLATIONS) == 0 and bool(rows),
          ", ".join(f"{total[k]} {k}" for k in VIOLATIONS) + f" (of the acceleration and "
          f"jerk ones {total['acceleration_jitter']} and {total['jerk_jitter']} are within "
          f"the limits at the controller's own tick spacing); {total['late']} late commands")
    reached = sum(r["goals_reached"] for r in rows)
    check("goals reached", reached > 0,
          f"{reached} of {sum(r['goals_sent'] for r in rows)} goals reached")
    _drift_checks(rows, check)
    failed = [c["check"] for c in checks if c["ok"] is False]
    return {"passed": not failed, "failed": failed, "checks": checks,
            "bound": DRIFT_BOUND, "min_windows_for_drift": DRIFT_MIN_WINDOWS}


def _drift_checks(rows: list[dict], check) -> None:
    if len(rows) < DRIFT_MIN_WINDOWS:
        check("latency/RSS drift", None, f"not checked: {len(rows)} windows < "
              f"{DRIFT_MIN_WINDOWS}")
        return
    first, last = rows[0], rows[-1]
    a, b = first["reroute_after_input_ms"], last["reroute_after_input_ms"]
    name = f"p99 re-route latency last <= {DRIFT_BOUND:.2f} x first"
    counts = (a.get("n", 0), b.get("n", 0))
    if min(counts) < DRIFT_MIN_SAMPLES:  # a p99 of a few values is their maximum: noise
        check(name, None, f"not checked: {counts[0]} and {counts[1]} re-routes, fewer than "
              f"{DRIFT_MIN_SAMPLES} in a window")
    else:
        ok, detail = _drift(a["p99"], b["p99"])
        check(name, ok, f"{a['p99']:.1f} -> {b['p99']:.1f} ms over {counts[0]} and "
              f"{counts[1]} re-routes ({detail})")
    for name in NODES:
        if name not in first["rss_mb"]:
            continue
        mb = (first["rss_mb"][name], last["rss_mb"].get(name, math.nan))
        ok, detail = _drift(*mb)
        check(f"RSS {name} last <= {DRIFT_BOUND:.2f} x first", ok,
              f"{mb[0]:.1f} -> {mb[1]:.1f} MB ({detail})")


# ----------------------------------------------------------------------------- report

def print_progress(row: dict, windows: int) -> None:
    rr = row["reroute_after_input_ms"]
    rss = ", ".join(f"{k.split(' ')[0]} {v:.0f}" for k, v in row["rss_mb"].items())
    print(f"[soak] window {row['window']}/{windows} ({row['t0_s']:.0f}-{row['t1_s']:.0f} s): "
          f"js {row['joint_states_hz']:.0f} Hz, cmd {row['commands_hz']:.0f} Hz, frames "
          f"{row['frames_hz']:.1f} Hz, goals {row['goals_reached']}/{row['goals_sent']}, "
          f"re-routes {rr['n']} p99 {rr['p99']:.0f} ms, contacts {row['contacts']}, "
          f"violations {row['violations']}, RSS MB {rss}", flush=True)


def _fmt(value, spec: str = ".1f") -> str:
    if value is None:
        return "-"
    if isinstance(value, float) and not math.isfinite(value):
        return "nan"
    return format(value, spec)


def _table(header: list[str], lines: list[list[str]]) -> str:
    widths = [max(len(h), *(len(r[i]) for r in lines)) for i, h in enumerate(header)]
    out = ["| " + " | ".join(h.ljust(w) for h, w in zip(header, widths, strict=True)) + " |",
           "|" + "|".join("-" * (w + 2) for w in widths) + "|"]
    out += ["| " + " | ".join(c.rjust(w) for c, w in zip(r, widths, strict=True)) + " |"
            for r in lines]
    return "\n".join(out)


def report_tables(rows: list[dict]) -> list[str]:
    """Three tables per window: throughput and drops, latency, safety and memory."""
    if not rows:
        return ["(no window completed)"]
    throughput = _table(
        ["win", "t (s)", "js Hz", "cmd Hz", "frames Hz", "obst Hz", "goals sent/reached",
         "goal T p50 s", "traj", "holds", "js skipped", "js gaps", "js max gap ms",
         "untracked frames"],
        [[str(r["window"]), f"{r['t0_s']:.0f}-{r['t1_s']:.0f}", _fmt(r["joint_states_hz"]),
          _fmt(r["commands_hz"]), _fmt(r["frames_hz"]), _fmt(r["obstacles_hz"]),
          f"{r['goals_sent']}/{r['goals_reached']}", _fmt(r["goal_time_s_p50"], ".2f"),
          str(r["trajectories"]), str(r["holds"]), str(r["js_skipped"]), str(r["js_gaps"]),
          _fmt(r["js_max_gap_ms"]), _fmt(r["frames_untracked"], "d")] for r in rows])
    latency = _table(
        ["win", "re-routes", "decided p50/p90/p99/max ms", "after input p50/p90/p99/max ms",
         "plans", "plan p50 ms", "tracker fps", "tracker lat p50/p95 ms"],
        [[str(r["window"]), str(r["reroute_decided_ms"]["n"]),
          _pcts(r["reroute_decided_ms"]), _pcts(r["reroute_after_input_ms"]),
          str(r["plan_decided_ms"]["n"]), _fmt(r["plan_decided_ms"]["p50"]),
          _fmt(r["tracker"].get("tracked_fps")),
          f"{_fmt(r['tracker'].get('latency_p50_ms'))}/"
          f"{_fmt(r['tracker'].get('latency_p95_ms'))}"] for r in rows])
    names = list(rows[0]["rss_mb"])
    safety = _table(
        ["win", "contacts", "min clr m", "violations v/a/j/pos/q", "a/j jitter", "late cmds",
         *[f"RSS {n.split(' ')[0]} MB" for n in names]],
        [[str(r["window"]), str(r["contacts"]), _fmt(r["min_clearance_m"], ".3f"),
          "/".join(str(r["limits"][k]) for k in VIOLATIONS),
          f"{r['limits']['acceleration_jitter']}/{r['limits']['jerk_jitter']}",
          str(r["limits"]["late"]), *[_fmt(r["rss_mb"].get(n)) for n in names]]
         for r in rows])
    return [throughput, latency, safety]


def _pcts(p: dict) -> str:
    return "/".join(_fmt(p[k], ".0f") for k in ("p50", "p90", "p99", "max"))


def print_report(result: dict) -> None:
    for table in report_tables(result["rows"]):
        print("\n" + table)
    v = result["verdict"]
    print(f"\nverdict: {'PASS' if v['passed'] else 'FAIL'} (bounds: 0 crashes, 0 contacts, "
          f"0 limit violations, >= 1 goal reached; with >= {DRIFT_MIN_WINDOWS} windows the "
          f"last window's p99 re-route latency and each node's mean RSS <= "
          f"{DRIFT_BOUND:.2f} x the first window's)")
    for c in v["checks"]:
        mark = {True: "ok  ", False: "FAIL", None: "n/a "}[c["ok"]]
        print(f"  {mark} {c['check']}: {c['detail']}")
    if v["failed"]:
        print("failed: " + "; ".join(v["failed"]))
