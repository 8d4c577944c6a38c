"""The soak run's view of the node graph: topic taps, goals, scoring, one row per window.

`Monitor` is an rclpy participant of its own in the soak process (UDP only, see
`damon_ros.ros.environment.observer_environment`). It takes 1 kHz topics raw, without an
executor (`Tap`), follows the planner's and tracker's logs for decision latencies
(`LogTail`), samples every node's memory from ``/proc``, sends the goals and decides when
one is reached; `Monitor.run` returns one row of metrics per window for `soak_report`.
Kept apart from `damon_ros.tools.soak` (arguments, scenario, starting the nodes) because
this is the part that must stay cheap: it shares the machine with the nodes it measures.
"""

from __future__ import annotations

import math
import os
import re
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from damon_ros.ros import topics
from damon_ros.ros.cdr import header_stamp
from damon_ros.ros.stamps import to_stamp
from damon_ros.tools.soak_report import LIMIT_KEYS, VIOLATIONS, print_progress

STILL_RAD_S = 0.02  # a goal is reached when the TCP is within tolerance and this still
SCORE_PERIOD_S = 0.02  # forward kinematics for "reached" at 50 Hz
RSS_PERIOD_S = 2.0
READY_TIMEOUT_S = 90.0  # start-up: a few s on a quiet machine, ~40 s on 2 busy cores
JOINT_PERIOD_S = 1e-3  # mock_panda's rate_hz


OBSERVER = "soak (this monitor)"


@dataclass(frozen=True)
class SoakGoal:
    """One goal pose of the cycle, as `damon_ros.tools.soak.check_goals` checked it."""

    name: str
    position: list[float]
    orientation: list[float]
    position_tolerance: float
    orientation_tolerance: float
    joints: list[float]  # the IK solution checked here (the planner solves again)


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
        stamp = header_stamp(data)
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
                           r"stamp->publish p50 ([\d.]+) ms, p95 ([\d.]+) ms, p99 ([\d.]+) ms")


def rss_mb(pid: int) -> float:
    """Resident set size of a process (MB), NaN once it is gone."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except (OSError, ValueError):
        pass
    return math.nan


_TICKS_PER_S = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


def cpu_seconds(pid: int, tid: int | None = None) -> float:
    """CPU time (user + system, s) a process (or its thread ``tid``) has used so far, NaN
    once it is gone.

    From ``/proc/<pid>/stat`` (``/proc/<pid>/task/<tid>/stat``; fields 14 and 15, clock
    ticks): a difference over a window divided by its length is the process's CPU share in
    cores (1.0 = one core busy), which is what counts on a 2-core machine, whatever the
    wall-clock load of the moment.
    """
    path = f"/proc/{pid}/stat" if tid is None else f"/proc/{pid}/task/{tid}/stat"
    try:
        fields = Path(path).read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / _TICKS_PER_S  # utime, stime
    except (OSError, ValueError, IndexError):
        return math.nan


def cpu_shares(before: dict[str, float], after: dict[str, float], seconds: float,
               observer: str | None = None) -> dict[str, float]:
    """CPU share (cores) of each process between two `cpu_seconds` samples, and the total
    of the nodes: every process but ``observer`` (the soak or demo process watching them,
    which a real cell does not run)."""
    shares = {name: (after.get(name, math.nan) - t0) / max(seconds, 1e-9)
              for name, t0 in before.items()}
    shares["nodes"] = float(np.nansum([v for k, v in shares.items() if k != observer]))
    return shares


def _load_average() -> float:
    """The 1-minute load average (nan where unknown): printed beside every CPU number."""
    try:
        return float(os.getloadavg()[0])
    except OSError:
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


@dataclass
class GoalRecord:
    """One goal sent: when (wall time), when reached (s after the send, None: not), what
    the planner held the arm for meanwhile (its "stopping the arm" lines, by cause) and how
    it ended: ``reached``, ``timed out`` (not reached within ``--goal-timeout-s``: truly
    unreachable, with ``why``, the planner's status then) or ``open`` (the run ended)."""

    name: str
    sent_at: float
    reached_after_s: float | None = None
    holds: dict[str, int] = field(default_factory=dict)
    outcome: str = "open"
    why: str = ""

    def row(self, t0: float) -> dict:
        """The record for the report: times from ``t0`` (the first window's start)."""
        return {"goal": self.name, "sent_s": round(self.sent_at - t0, 2),
                "reached_after_s": None if self.reached_after_s is None
                else round(self.reached_after_s, 2),
                "holds": dict(self.holds), "outcome": self.outcome, "why": self.why}


HOLD = re.compile(r"\[(\d+\.\d+)\] \[planner\]: stopping the arm: (.*)")
_NUMBER = re.compile(r"-?\d+(\.\d+)?")


def hold_cause(reason: str) -> str:
    """A planner hold's reason as a cause to count: its first clause, numbers as #, so
    that the same obstacle in the way reads as one cause at different distances."""
    return _NUMBER.sub("#", reason.split(";")[0].strip())


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
        self.missed: list[str] = []  # why each goal timed out unreached (`_why_missed`)
        self.records: list[GoalRecord] = []  # every goal sent, in order
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
        # best effort: a reliable reader costs mock_panda an acknowledgement exchange per
        # state; what this one misses is counted (js_monitor_lost), the gaps it measures
        # are between consecutive sequence numbers only
        joint_qos = QoSProfile(depth=deep, reliability=ReliabilityPolicy.BEST_EFFORT)
        n = self.node
        self.joints = JointStream()
        self.contacts = Contacts()
        self.trajectories = Trajectories()
        self.limit_status = Latest(DiagnosticArray)
        self.planner_status = Latest(DiagnosticArray)
        frames = (topics.SIM_OBSTACLES, MarkerArray, 200) if self.args.no_camera else (
            topics.CAMERA_INFO, CameraInfo, best_effort)
        self.taps = {
            "joint_states": Tap(n, JointState, topics.JOINT_STATES, joint_qos, self.joints),
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
        if not self._wait_ready(time.time() + READY_TIMEOUT_S):
            return [], self._crashes(), (f"the nodes did not come up within "
                                         f"{READY_TIMEOUT_S:.0f} s (missing: "
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
            rows.append(self._close_window(k + 1, warm_end, time.time(), last=k + 1 == windows))
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
        """Joint states, a planner that has them too, obstacle data, and a matched goal
        subscriber, or False. Obstacles too: a tracker whose compiled kernels were not yet
        cached (a fresh clone) published its first array 25 s after the planner was ready,
        and the first goal was dropped after waiting 5 s for obstacle data."""
        while time.time() < deadline and self._alive():
            self._drain()
            if not self._readiness_missing():
                return True
            time.sleep(0.02)
        return False

    def _readiness_missing(self) -> list[str]:
        obstacles = (topics.SIM_OBSTACLES, "frames") if self.args.no_camera else (
            topics.OBSTACLES, "obstacles")
        return [what for what, ok in (
            (topics.JOINT_STATES, self.joints.raw is not None),
            (f"{topics.PLANNER_STATUS} with a fresh joint state",
             planner_has_state(_status_values(self.planner_status.message))),
            (obstacles[0], self.taps[obstacles[1]].count > 0),
            ("a goal_pose subscriber", self.goal_pub.get_subscription_count() > 0)) if not ok]

    def _not_ready(self) -> str:
        return ", ".join(self._readiness_missing()) or "nothing"

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
            if self._goal_due(now):
                self._score(now)  # scored before it is replaced: reached at the last moment
                self._send_goal(self.goal.index + 1, time.time())
            if now >= next_score:
                next_score = now + SCORE_PERIOD_S
                self._score(now)
            if now >= next_rss:
                next_rss = now + RSS_PERIOD_S
                self._sample_rss()
            time.sleep(0.005)
        self._drain()
        return self._alive()

    def _goal_due(self, now: float) -> bool:
        """The next goal goes out ``--goal-period-s`` after this one was sent once it is
        reached, or ``--goal-timeout-s`` after it unreached. Replaced at a fixed period,
        a goal a passing sphere blocked for a few seconds counted as missed, and the next
        one started late into its own period (the period ran from the schedule, not the
        send)."""
        elapsed = now - self.goal.sent_at
        return elapsed >= self.args.goal_timeout_s or (
            self.goal.reached and elapsed >= self.args.goal_period_s)

    def _send_goal(self, index: int, t: float) -> None:
        from geometry_msgs.msg import PoseStamped

        if self.goal.index >= 0 and not self.goal.reached:
            self.missed.append(self._why_missed())
            self.records[-1].outcome, self.records[-1].why = "timed out", self.missed[-1]
        goal = self.goals[index % len(self.goals)]
        self.records.append(GoalRecord(goal.name, t))
        msg = PoseStamped()
        msg.header.frame_id = "panda_link0"
        msg.header.stamp = to_stamp(time.time())
        msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = goal.position
        o = msg.pose.orientation
        o.x, o.y, o.z, o.w = goal.orientation
        self.goal_pub.publish(msg)
        self.goal = GoalState(index, t, False, self.goal.sent + 1, self.goal.reached_count,
                              self.goal.times)

    def _why_missed(self) -> str:
        """The goal in force when the next one replaced it unreached, and what the planner
        was doing then (its status: state and last decision), so a passing sphere's hold
        reads apart from a refusal."""
        msg = self.planner_status.message
        doing = msg.status[0].message if msg is not None and msg.status else "no planner status"
        return f"{self.goals[self.goal.index % len(self.goals)].name}: {doing}"

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
            self.records[-1].reached_after_s = now - self.goal.sent_at
            self.records[-1].outcome = "reached"

    def _cpu_now(self) -> dict[str, float]:
        cpu = {name: cpu_seconds(proc.pid) for name, proc in self.procs.items()}
        cpu[OBSERVER] = cpu_seconds(os.getpid())
        return cpu

    def _sample_rss(self) -> None:
        for name, proc in self.procs.items():
            self.rss.setdefault(name, []).append(rss_mb(proc.pid))
        self.rss.setdefault(OBSERVER, []).append(rss_mb(os.getpid()))

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
            "reached": self.goal.reached_count, "missed": len(self.missed),
            "records": len(self.records) - 1,  # the goal in force belongs to this window
        }
        self.joints.max_gap, self.joints.gaps = 0.0, 0
        self.contacts.min_clearance, self.contacts.worst = math.inf, ""
        self.goal.times = []
        self.rss = {}
        self._sample_rss()
        self._cpu_mark = self._cpu_now()

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

    def _close_window(self, index: int, warm_end: float, now: float,
                      last: bool = False) -> dict:
        self._drain()
        m, duration = self._mark, max(now - self._window_start, 1e-9)
        row = {"window": index, "t0_s": round(self._window_start - warm_end, 1),
               "t1_s": round(now - warm_end, 1), "duration_s": round(duration, 2)}
        row.update(self._throughput(duration))
        row.update(self._dropped())
        row.update(self._latency())
        row.update(self._safety())
        row["cpu_cores"] = cpu_shares(self._cpu_mark, self._cpu_now(), duration, OBSERVER)
        row["load_avg"] = _load_average()
        row["rss_mb"] = {name: float(np.nanmean(v)) if np.isfinite(v).any() else math.nan
                         for name, v in self.rss.items()}
        row["goals_sent"] = self.goal.sent - m["sent"]
        row["goals_reached"] = self.goal.reached_count - m["reached"]
        row["goal_time_s_p50"] = float(np.median(self.goal.times)) if self.goal.times \
            else math.nan
        row["goals_reached_in_period"] = sum(t <= self.args.goal_period_s
                                             for t in self.goal.times)
        row["goals_missed"] = self.missed[m["missed"]:]
        # the goals that ended in this window (and, in the last, the one still open)
        end = len(self.records) if last else len(self.records) - 1
        row["goal_records"] = [r.row(warm_end) for r in self.records[max(m["records"], 0):end]]
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
            self._count_hold(line)
            match = DECISION.search(line)
            if match and float(match.group(1)) >= self._warm_end:
                decided[match.group(2)].append(float(match.group(3)))
                if match.group(2) == "re-route":
                    after.append(float(match.group(4)))
        stats = np.array([[float(g) for g in m.groups()[1:]] for m in
                          map(TRACKER_STATS.search, self.tracker_log.lines()) if m])
        # each line covers stats_period_s: mean rate, median p50, worst p95 and p99 of the window
        tracker = {} if stats.size == 0 else {
            "tracked_fps": float(stats[:, 0].mean()),
            "latency_p50_ms": float(np.median(stats[:, 1])),
            "latency_p95_ms": float(stats[:, 2].max()),
            "latency_p99_ms": float(stats[:, 3].max())}
        return {"reroute_decided_ms": _percentiles(decided["re-route"]),
                "reroute_after_input_ms": _percentiles(after),
                "plan_decided_ms": _percentiles(decided["plan"]), "tracker": tracker}

    def _count_hold(self, line: str) -> None:
        """A planner hold line counted, by cause, on the goal in force at its stamp."""
        match = HOLD.search(line)
        if match is None:
            return
        stamp = float(match.group(1))
        record = next((r for r in reversed(self.records) if r.sent_at <= stamp), None)
        if record is not None:
            cause = hold_cause(match.group(2))
            record.holds[cause] = record.holds.get(cause, 0) + 1

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


PLANNER_STATE_AGE_S = 0.5
"""s: a goal goes out once the planner's own status shows a joint state this fresh (its
joint_state_timeout_s). A state seen by the sender is not enough: on a busy machine the
planner's /joint_states subscription matched seconds later and it refused the goal (CI, demo
D-001)."""


def planner_has_state(values: dict) -> bool:
    """Whether planner status values (key → text) show a fresh joint state."""
    try:
        return float(values.get("joint_state_age_s", "inf")) < PLANNER_STATE_AGE_S
    except ValueError:
        return False


def _status_values(msg) -> dict:
    if msg is None or not msg.status:
        return {}
    return {kv.key: kv.value for kv in msg.status[0].values}
