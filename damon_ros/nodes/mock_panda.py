"""mock_panda: the hardware stand-in, a thin ROS adapter over
`damon_ros.simulation.mock_arm.ArmSim`.

Velocity commands in (``/damon/joint_commands``, ``std_msgs/Float64MultiArray``, rad/s in the
order of the ``joints`` parameter), joint states out (``/joint_states`` at ``rate_hz``).
The arm model — first-order actuator lag, limit clamps, braking when commands go stale —
is `ArmSim`'s; this module only moves data between it and the ROS graph.

Timing: the simulation step and the joint-state publication run in a `FixedRateLoop` thread
sleeping to absolute deadlines, not in an rclpy timer (a 1 kHz rclpy timer drifts and loses
ticks while message callbacks run; see `FixedRateLoop`). Each step integrates the
real elapsed time, so the mock arm moves in wall-clock time even when a tick is late. The
loop also takes the commands that arrived since its last tick (an `Inbox`: through the
executor the 1 kHz topic cost most of a core), so the executor only serves parameters.

Optional contact report (``contact_check``): with a ``scenario`` loaded, the exact mesh
clearance (`damon_ros.core.robot.Robot("mesh")`) between the arm and the scenario's obstacles at
scenario time is published on ``/damon/sim/contact`` (``diagnostic_msgs/DiagnosticArray``,
level ERROR on contact) at ``contact_rate_hz``, computed in ~0.2 ms slices inside the loop
(see `ContactMonitor` for why not in a timer). Scenario time 0 is ``scenario_start_time_s``
(ROS time, seconds), or this node's start when that is 0; it may be set while the node
runs.

Limit monitor (``limit_check``, on by default): a real Franka stops with a reflex when a
command breaks its velocity, acceleration or jerk limits or a joint reaches a position
limit; the mock arm only clamps. `damon_ros.simulation.mock_arm.LimitMonitor`
counts every accepted command
that would have tripped such a reflex (acceleration and jerk from consecutive commands at
the nominal ``1 / rate_hz`` period; commands sent or received after a gap of more than 1.5
periods are counted as late instead) and every entry of a joint into a position limit. The counts
go out on ``/damon/sim/limits`` (``diagnostic_msgs/DiagnosticArray``) once a second from
the loop (level ERROR on any violation, WARN on late commands only); the first violation of
each kind is logged once with its numbers, and the shutdown log line holds the totals.
"""

from __future__ import annotations

import sys
import threading
from collections.abc import Sequence

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from damon_ros.core.limits import PROFILES, READY, JointLimits, joint_limits
from damon_ros.core.scenario import Scenario, load_scenario
from damon_ros.ros import topics
from damon_ros.ros.cdr import Float64ArrayDecoder, JointStateWriter
from damon_ros.ros.inputs import joint_names
from damon_ros.ros.node_loop import start_loop, stop_loop
from damon_ros.ros.node_main import node_main
from damon_ros.ros.parameters import Param, accept_at_run_time, declare_all
from damon_ros.ros.problems import ProblemLog
from damon_ros.ros.stamps import clock_seconds
from damon_ros.ros.topic_reader import Inbox
from damon_ros.simulation.mock_arm import LATE, LIMIT_KINDS, ArmSim, LimitMonitor

NAME = "mock_panda"
WARN_EVERY_S = 5.0  # a stream of bad commands of one kind: one line per this many seconds

PARAMETERS = (
    Param("joints", (), "joint names in command/state order; empty: <joint_prefix>joint1..7"),
    Param("joint_prefix", "panda_",
          "prefix of the default joint names (panda_, or fr3_ for franka_ros2)"),
    Param("limit_profile", "panda",
          f"joint-limit profile the mock arm clamps to: {' | '.join(PROFILES)}"),
    Param("rate_hz", 1000.0, "simulation step and /joint_states rate (Hz)", 1.0, 10000.0),
    Param("initial_positions", tuple(READY.tolist()),
          "start joint positions (rad); ignored when a scenario is given"),
    Param("scenario", "", "scenario file: start at its start state, obstacles for contact_check"),
    Param("command_timeout_s", 0.1, "a command older than this stops the joints (s)",
          0.001, 10.0),
    Param("actuator_tau_s", 0.02,
          "time constant of the first-order joint velocity response (s)", 0.0001, 1.0),
    Param("contact_check", False, "publish exact mesh clearance/contact on /damon/sim/contact"),
    Param("contact_rate_hz", 50.0,
          "rounds of the contact check over all obstacles per second (Hz)", 0.1, 1000.0),
    Param("scenario_start_time_s", 0.0, "ROS time (s) of scenario time 0; 0: this node's start"),
    Param("realtime_priority", 20,
          "SCHED_FIFO priority of the node's threads, 0: normal scheduling", 0, 99),
    Param("limit_check", True,
          "count commands a real Franka would refuse; 1 Hz on /damon/sim/limits"),
)

def start_positions(initial: Sequence[float], scenario: Scenario | None) -> np.ndarray:
    """The scenario's start state when a scenario is given, else ``initial_positions``."""
    q0 = np.asarray(scenario.start if scenario is not None else list(initial), dtype=float)
    if q0.shape != (7,) or not np.all(np.isfinite(q0)):
        raise ValueError(f"parameter initial_positions must be 7 finite values, got {q0}")
    return q0


class ContactMonitor:
    """Exact (mesh) clearance between the arm and a scenario's obstacles at scenario time.

    One obstacle per call, round robin, and a status after each full round, so that one
    call costs ~0.2 ms (one coal query per link) and fits into a tick of the 1 kHz loop,
    which makes the calls itself. Why not an executor timer: the check holds the GIL (coal
    does not release it) and so does the executor's own Python around each callback;
    measured with the four obstacles of E-001 at 50 Hz, a timer made 0.7-1.5 % of the loop's
    periods exceed 2 ms, as a timer at 10 Hz still did 0.4 %; slices inside the loop keep it
    at the level without any check. Built only when asked for: loading the meshes takes
    about a second.
    """

    def __init__(self, scenario: Scenario):
        from damon_ros.core.robot import Robot  # heavy (pinocchio + coal meshes): only when used

        self.scenario = scenario
        self.robot = Robot("mesh")
        self._next = 0
        self._round: list[tuple[float, str, float]] = []  # (distance, link, time) per obstacle

    @property
    def calls_per_round(self) -> int:
        return max(1, len(self.scenario.obstacles))

    def check_next(self, q: np.ndarray, t: float) -> DiagnosticStatus | None:
        """Check the next obstacle at scenario time ``t``; the round's status when complete.

        The status is OK with the smallest clearance of the round, or ERROR naming the
        obstacle and the link in contact (distance <= 0).
        """
        obstacles = self.scenario.obstacles
        if not obstacles:
            return _contact_status(DiagnosticStatus.OK, "no obstacles", float("inf"), "", "", t)
        c = self.robot.clearance(q, obstacles[self._next].parts_at(t))
        self._round.append((c.distance, c.link, t))
        self._next = (self._next + 1) % len(obstacles)
        if self._next:
            return None
        k = int(np.argmin([r[0] for r in self._round]))
        (distance, link, _), self._round = self._round[k], []
        name = obstacles[k].name
        if distance <= 0.0:
            return _contact_status(DiagnosticStatus.ERROR, f"contact: {link} touches {name}",
                                   distance, name, link, t)
        return _contact_status(DiagnosticStatus.OK, "clear", distance, name, link, t)


def _contact_status(level: bytes, message: str, distance: float, obstacle: str, link: str,
                    t: float) -> DiagnosticStatus:
    values = [KeyValue(key="min_clearance_m", value=f"{distance:.6f}"),
              KeyValue(key="obstacle", value=obstacle), KeyValue(key="link", value=link),
              KeyValue(key="scenario_time_s", value=f"{t:.4f}")]
    return DiagnosticStatus(level=level, name=f"{NAME}: contact", message=message,
                            hardware_id=NAME, values=values)


class MockPanda(Node):
    """Parameters in, `ArmSim` stepped at ``rate_hz``, joint states out."""

    def __init__(self) -> None:
        super().__init__(NAME)
        p = self._params = declare_all(self, PARAMETERS)
        limits: JointLimits = joint_limits(p["limit_profile"])
        self.names = joint_names(p["joints"], p["joint_prefix"])
        scenario = load_scenario(p["scenario"]) if p["scenario"] else None
        q0 = start_positions(p["initial_positions"], scenario)
        self._monitor = (LimitMonitor(limits, 1.0 / p["rate_hz"]) if p["limit_check"]
                         else None)
        self._sim = ArmSim(limits, q0, tau=p["actuator_tau_s"],
                           command_timeout=p["command_timeout_s"], monitor=self._monitor)
        self._lock = threading.Lock()  # the loop thread steps, the executor commands
        self._problems = ProblemLog(self.get_logger().warning, WARN_EVERY_S)
        self._last_command: float | None = None  # monotonic time of the last good command
        self._commanding = False  # inside an episode of fresh commands
        self._last_step: float | None = None
        self._ticks = 0
        self._contact: ContactMonitor | None = None
        self._pub = self.create_publisher(JointState, topics.JOINT_STATES, 10)
        self._joint_state = JointStateWriter(self.names)
        self._commands = Inbox(self, Float64MultiArray, topics.JOINT_COMMANDS, "commands",
                               raw=True)
        self._decode_command = Float64ArrayDecoder()
        self._setup_contact_check(scenario)
        accept_at_run_time(self, {"scenario_start_time_s": self._set_scenario_start})
        self._limits_pub = (self.create_publisher(DiagnosticArray, topics.SIM_LIMITS, 10)
                            if self._monitor is not None else None)
        self._limits_every = max(1, round(p["rate_hz"]))  # once a second
        self._period = 1.0 / p["rate_hz"]  # the loop's, known before its first tick
        self._loop = start_loop(self, NAME, p["rate_hz"], self._tick, "simulation loop",
                                p["realtime_priority"])
        source = f"scenario {scenario.name}" if scenario else "initial_positions"
        self.get_logger().info(
            f"{len(self.names)} joints {self.names[0]}..{self.names[-1]}, profile "
            f"{limits.profile}, {p['rate_hz']:g} Hz, start {np.round(q0, 3).tolist()} "
            f"({source})")

    def _setup_contact_check(self, scenario: Scenario | None) -> None:
        p = self._params
        if not p["contact_check"]:
            return
        if scenario is None:
            raise ValueError("parameter contact_check needs a scenario file (parameter scenario)")
        self._contact = ContactMonitor(scenario)
        start = p["scenario_start_time_s"] or clock_seconds(self)
        self._scenario_start = float(start)
        self._contact_pub = self.create_publisher(DiagnosticArray, topics.SIM_CONTACT, 10)
        calls_per_s = p["contact_rate_hz"] * self._contact.calls_per_round
        self._contact_every = max(1, round(p["rate_hz"] / calls_per_s))

    def _set_scenario_start(self, value: float) -> None:
        """Scenario time 0 moved while running (as mock_camera's: see there)."""
        self._scenario_start = float(value or clock_seconds(self))
        self.get_logger().info(f"scenario t=0 now at {self._scenario_start:.3f} s")

    # -- loop thread

    def _on_command(self, raw: bytes, t: float, sent: float | None) -> None:
        """One serialised command, arrived at monotonic time ``t``; ``sent`` (the
        publisher's send time) is for the limit monitor."""
        try:
            data = self._decode_command(raw)
        except ValueError as exc:
            self._problems.report(f"rejected joint command: {exc}")
            return
        with self._lock:
            reason = self._sim.command(data, t, sent)
            if reason is None:
                self._last_command = t
            reports = self._monitor.take_reports() if self._monitor is not None else ()
        for report in reports:
            self.get_logger().error(report)
        if reason is not None:
            self._problems.report(f"rejected joint command: {reason}")

    def _tick(self, t: float) -> None:
        for item in self._commands.take_all():
            self._on_command(item.msg, min(item.arrived, t), item.sent)
        # Integrate the real elapsed time; a long stall is capped so that the arm never
        # jumps further than one command timeout's worth of motion in one step.
        dt = self._period if self._last_step is None else t - self._last_step
        dt = min(max(dt, 1e-6), self._sim.command_timeout)
        self._last_step = t
        with self._lock:
            q, qd = self._sim.step(dt, t)
            last = self._last_command
            reports = self._monitor.take_reports() if self._monitor is not None else ()
            limits = (self._limits_message()
                      if self._monitor is not None and self._ticks % self._limits_every == 0
                      else None)
        for report in reports:
            self.get_logger().error(report)
        self._watch_commands(t, last)
        self._pub.publish(self._joint_state.write(self.get_clock().now().nanoseconds, q, qd))
        if limits is not None:
            self._limits_pub.publish(limits)
        self._ticks += 1
        if self._contact is not None and self._ticks % self._contact_every == 0:
            self._check_contact(q)

    def _check_contact(self, q: np.ndarray) -> None:
        """One slice of the contact check (see `ContactMonitor`); publish a finished round."""
        status = self._contact.check_next(q, clock_seconds(self) - self._scenario_start)
        if status is None:
            return  # the round goes on
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self._contact_pub.publish(msg)
        if status.level == DiagnosticStatus.ERROR:
            self.get_logger().error(status.message, throttle_duration_sec=1.0)

    def _limits_message(self) -> DiagnosticArray:
        """The limit monitor's counts so far (called under the lock, once a second)."""
        m = self._monitor
        if m.violations:
            level, message = DiagnosticStatus.ERROR, "limit violations: " + ", ".join(
                f"{m.counts[k]} {k}" for k in LIMIT_KINDS if m.counts[k])
        elif m.counts[LATE]:
            level, message = DiagnosticStatus.WARN, f"{m.counts[LATE]} late commands"
        else:
            level, message = DiagnosticStatus.OK, "within limits"
        values = [KeyValue(key="commands", value=str(m.commands))]
        values += [KeyValue(key=k, value=str(v)) for k, v in m.counts.items()]
        values += [KeyValue(key=f"{k}_jitter", value=str(v)) for k, v in m.jitter.items()]
        values += [KeyValue(key=f"peak_{k}_fraction", value=f"{v:.4f}")
                   for k, v in m.peak.items()]
        values.append(KeyValue(key="max_gap_ms", value=f"{1e3 * m.max_gap:.3f}"))
        msg = DiagnosticArray(status=[DiagnosticStatus(
            level=level, name=f"{NAME}: limits", message=message, hardware_id=NAME,
            values=values)])
        msg.header.stamp = self.get_clock().now().to_msg()
        return msg

    def _watch_commands(self, t: float, last: float | None) -> None:
        """Log once per episode when the command stream stops (ArmSim then brakes)."""
        fresh = last is not None and t - last <= self._sim.command_timeout
        if fresh and not self._commanding:
            self._commanding = True
        elif self._commanding and not fresh:
            self._commanding = False
            self.get_logger().warning(
                f"no joint command for {self._sim.command_timeout:g} s: stopping the joints")

    def on_shutdown(self) -> None:
        """Called by `run_single_threaded`: stop the loop and report its timing."""
        log = stop_loop(self._loop, NAME)
        self._commands.close()
        if self._monitor is not None:
            with self._lock:
                log.info(self._monitor.summary())


def main(args: Sequence[str] | None = None) -> int:
    """Console entry point (``--help``, one-line errors): see `node_main`."""
    return node_main(NAME, __doc__.split("\n\n")[0], PARAMETERS, MockPanda, args)


if __name__ == "__main__":
    sys.exit(main())
