"""controller: PID joint-trajectory controller, a thin ROS adapter over `TrajectoryFollower`.

Trajectories in (``/damon/joint_trajectory``, ``trajectory_msgs/JointTrajectory``), measured
joints in (``/joint_states``), velocity commands out (``/damon/joint_commands``,
``std_msgs/Float64MultiArray``, rad/s in the order of the ``joints`` parameter) at
``rate_hz``, and ``/damon/controller_state`` (``sensor_msgs/JointState``: desired position in
``position``, desired velocity in ``velocity``, position error in ``effort``) at
``state_rate_hz``. Interpolation, PID, tolerances and the limit-respecting command shaping
are `damon_ros.planning.follower`'s; this module decides *when* to call it and what to do on
bad or missing input. Every trajectory is either executed or refused with one log line
saying why (``accepted trajectory …`` / ``rejected trajectory …``); nothing is dropped
silently.

- Trajectories follow ros2_controllers' (Jazzy) joint_trajectory_controller: a zero
  ``header.stamp`` starts on arrival, a future one is approached from the current state so
  as to reach the first point at that time; a new trajectory replaces the old; refused (the
  arm keeps doing what it did): no points (a stop is a one-point hold trajectory), joints
  that don't match (another order is fine; missing ones only with
  ``allow_partial_joints_goal``, they then hold their current position),
  ``time_from_start`` not strictly increasing, NaN/inf, a non-zero velocity at the last
  point (unless ``allow_nonzero_velocity_at_trajectory_end``), a stamped trajectory that
  has already ended, and one that cannot be followed within the limit profile (points or
  the curve between them beyond the position, velocity or acceleration limits) — never
  clipped silently. Unlike the JTC, a well-formed trajectory refused only because it
  cannot be followed from the arm's current state (`TrajectoryFollower.prepare`) brakes
  the arm to a stop and holds it: it may have been a stop, and the motion it was sent to
  end must not go on (a soak arm did). Gains and tolerances take JTC's parameter names
  (``gains.<joint>.p|i|d|i_clamp|ff_velocity_scale``, ``constraints.<joint>.trajectory|goal``,
  ``constraints.goal_time``, ``constraints.stopped_velocity_tolerance``); a tolerance
  violated aborts the trajectory and holds the measured position, with one line.
- On start-up nothing is published until the first joint state (the controller does not
  know where the arm is and has never commanded it); from then on it holds that position.
- Joint states older than ``joint_state_timeout_s`` (default 0.1 s: at 1 kHz on this loaded
  2-core machine the former 50 ms tripped by itself 1-7 times in 75 s): the trajectory is
  aborted and the command brakes to zero within the limit profile's acceleration and jerk
  limits (a step to zero would break them), then holds zero. The stop therefore begins at
  most ``joint_state_timeout_s`` + one period after the last joint state. Logged once; when
  states return the arm holds where it is. A trajectory arriving while the states are
  stale (or before the first one) is refused with a line: where the arm is is unknown, so
  no motion can be planned from it; send it again when they are back. A joint state
  holding NaN/inf, lacking a controller joint or stamped before the last one
  (`damon_ros.ros.inputs.JointStateReader`) is ignored with one warning per kind of problem
  (repeats: one line per 5 s with a count), so that a stream of them ends in this stop.
- ``planner_heartbeat_timeout_s`` > 0 (default 1 s, ten of the planner's 10 Hz status
  messages): while a trajectory is active and no ``/damon/planner_status`` arrived for that
  long, the arm holds (logged once per lapse); a trajectory arriving while the planner is
  silent is refused with a line.

The command loop runs in a `FixedRateLoop` thread (see `FixedRateLoop` for why not an
rclpy timer). It takes the joint states itself at the start of each tick (an `Inbox`: through
the executor the 1 kHz topic cost most of a core); the executor's callbacks (trajectories,
heartbeats) only hand data to it under one lock, and check a trajectory
(`TrajectoryFollower.prepare`) outside it.
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Sequence

import numpy as np
import rclpy.logging
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray
from trajectory_msgs.msg import JointTrajectory

from damon_ros.core.limits import PROFILES, joint_limits
from damon_ros.planning.follower import (
    DEFAULT_VELOCITY_LEAD_S,
    PIDGains,
    Tolerances,
    TrajectoryFollower,
    reorder_points,
    validate_trajectory,
)
from damon_ros.planning.trajectory import METHODS
from damon_ros.ros import topics
from damon_ros.ros.cdr import Float64ArrayWriter, JointStateDecoder
from damon_ros.ros.inputs import JointStateReader, joint_names, read_joint_state
from damon_ros.ros.node_loop import start_loop, stop_loop
from damon_ros.ros.node_main import node_main
from damon_ros.ros.parameters import Param, declare_all
from damon_ros.ros.problems import ProblemLog
from damon_ros.ros.stamps import clock_seconds, is_zero, stamp_seconds
from damon_ros.ros.topic_reader import Inbox

NAME = "controller"
_GAINS = PIDGains()
_TOLERANCES = Tolerances.unchecked()
GAIN_FIELDS = ("p", "i", "d", "i_clamp", "ff_velocity_scale")

BASE_PARAMETERS = (
    Param("joints", (), "joint names in command order; empty: <joint_prefix>joint1..7"),
    Param("joint_prefix", "panda_",
          "prefix of the default joint names (panda_, or fr3_ for franka_ros2)"),
    Param("limit_profile", "panda", f"limits every command respects: {' | '.join(PROFILES)}"),
    Param("warn_every_s", 5.0,
          "a repeated problem of one kind (bad input, refusal) is logged at most this often, "
          "with a count; 0: every time (s)", 0.0, 3600.0),
    Param("rate_hz", 1000.0, "command rate (Hz)", 1.0, 10000.0),
    Param("state_rate_hz", 100.0, "/damon/controller_state rate (Hz)", 0.1, 10000.0),
    Param("interpolation", "quintic", f"between trajectory points: {' | '.join(METHODS)}"),
    Param("allow_partial_joints_goal", False,
          "accept trajectories naming only some joints; the others hold their position"),
    Param("allow_nonzero_velocity_at_trajectory_end", False,
          "accept a trajectory whose last point has a non-zero velocity"),
    Param("ff_velocity_lead_s", DEFAULT_VELOCITY_LEAD_S,
          "feed-forward the desired velocity this far ahead, against the arm's velocity-loop "
          "lag (s); 0: plain feed-forward", 0.0, 1.0),
    Param("constraints.goal_time", _TOLERANCES.goal_time,
          "abort when the goal tolerances are not met this long after the end; 0: wait (s)",
          0.0, 3600.0),
    Param("constraints.stopped_velocity_tolerance", _TOLERANCES.stopped_velocity,
          "the goal is reached only below this joint speed; 0: not checked (rad/s)",
          0.0, 10.0),
    Param("joint_states_topic", topics.JOINT_STATES,
          "joint states in (franka/joint_states for franka_ros2: 1 kHz; joint_states is 30 Hz)"),
    Param("joint_state_timeout_s", 0.1,
          "older joint states abort the trajectory and brake the arm; the stop begins at "
          "most this + one period after the last state (s)", 0.001, 10.0),
    Param("planner_heartbeat_timeout_s", 1.0,
          "hold (and refuse trajectories) when /damon/planner_status is silent this long; "
          "0: off (s)", 0.0, 3600.0),
    Param("realtime_priority", 20,
          "SCHED_FIFO priority of the node's threads, 0: normal scheduling", 0, 99),
)

_GAIN_RANGES = {"p": (0.0, 1000.0), "i": (0.0, 1000.0), "d": (0.0, 10.0),
                "i_clamp": (0.0, 10.0), "ff_velocity_scale": (0.0, 2.0)}
_GAIN_TEXT = {"p": "proportional gain (1/s)", "i": "integral gain (1/s^2)",
              "d": "derivative gain (-)",
              "i_clamp": "largest integral contribution, anti-windup (rad/s)",
              "ff_velocity_scale": "feed-forward velocity scale (-)"}


def joint_parameters(names: Sequence[str]) -> tuple[Param, ...]:
    """The per-joint parameters of the JTC's layout for the controller's joints ``names``.

    Declared after ``joints``/``joint_prefix`` are known, so that the names in a params
    file are the joints' own (``gains.fr3_joint1.p`` for franka_ros2's FR3).
    """
    out = []
    for j, name in enumerate(names):
        out += [Param(f"gains.{name}.{k}", float(getattr(_GAINS, k)[j]),
                      f"{name}: {_GAIN_TEXT[k]}", *_GAIN_RANGES[k]) for k in GAIN_FIELDS]
        out += [Param(f"constraints.{name}.trajectory", float(_TOLERANCES.path[j]),
                      f"{name}: path tolerance, abort and hold beyond it; 0: off (rad)",
                      0.0, 10.0),
                Param(f"constraints.{name}.goal", float(_TOLERANCES.goal[j]),
                      f"{name}: goal tolerance (rad); 0: not checked", 0.0, 10.0)]
    return tuple(out)


PARAMETERS = BASE_PARAMETERS + joint_parameters(joint_names((), "panda_"))
"""Every parameter for the default joints (``--help``, config/controller.yaml); the node
declares `BASE_PARAMETERS`, then `joint_parameters` of its own joints."""


def trajectory_arrays(msg: JointTrajectory):
    """(times, positions, velocities, accelerations) as plain lists, message joint order."""
    points = msg.points
    return ([stamp_seconds(p.time_from_start) for p in points],
            [list(p.positions) for p in points],
            [list(p.velocities) for p in points],
            [list(p.accelerations) for p in points])


class Controller(Node):
    """Parameters in, `TrajectoryFollower.update` at ``rate_hz``, velocity commands out."""

    def __init__(self) -> None:
        super().__init__(NAME)
        p = declare_all(self, BASE_PARAMETERS)
        self.limits = joint_limits(p["limit_profile"])
        self.names = joint_names(p["joints"], p["joint_prefix"])
        p.update(declare_all(self, joint_parameters(self.names)))
        gains = PIDGains(*(np.array([p[f"gains.{n}.{k}"] for n in self.names])
                           for k in GAIN_FIELDS))
        tolerances = Tolerances(
            np.array([p[f"constraints.{n}.trajectory"] for n in self.names]),
            np.array([p[f"constraints.{n}.goal"] for n in self.names]),
            p["constraints.goal_time"], p["constraints.stopped_velocity_tolerance"])
        self._follower = TrajectoryFollower(self.limits, gains, p["rate_hz"],
                                            p["interpolation"], tolerances,
                                            p["ff_velocity_lead_s"])
        self._allow_partial = p["allow_partial_joints_goal"]
        self._allow_end_velocity = p["allow_nonzero_velocity_at_trajectory_end"]
        self._js_timeout = p["joint_state_timeout_s"]
        self._event_loggers: dict[str, object] = {}
        self._hb_timeout = p["planner_heartbeat_timeout_s"]
        self._lock = threading.Lock()  # guards the follower and the latest measurement
        self._q: np.ndarray | None = None
        self._q_time = 0.0  # monotonic arrival time of self._q
        self._reader = JointStateReader(self.names)
        self._problems = ProblemLog(self.get_logger().warning, p["warn_every_s"])
        self._last_heartbeat = time.monotonic()
        self._stale = False
        self._hb_lapsed = False
        self._ticks = 0
        self._state_every = max(1, round(p["rate_hz"] / p["state_rate_hz"]))
        self._cmd_pub = self.create_publisher(Float64MultiArray, topics.JOINT_COMMANDS, 10)
        self._state_pub = self.create_publisher(JointState, topics.CONTROLLER_STATE, 10)
        self._joint_states = Inbox(self, JointState, p["joint_states_topic"], "joint_states",
                                   raw=True)
        self._decode_joint_state = JointStateDecoder()
        self._command = Float64ArrayWriter(len(self.names))
        self.create_subscription(JointTrajectory, topics.JOINT_TRAJECTORY, self._on_trajectory, 10)
        self.create_subscription(DiagnosticArray, topics.PLANNER_STATUS, self._on_heartbeat, 10)
        self._loop = start_loop(self, NAME, p["rate_hz"], self._tick, "control loop",
                                p["realtime_priority"])
        self.get_logger().info(
            f"driving {self.names[0]}..{self.names[-1]} at {p['rate_hz']:g} Hz, profile "
            f"{self.limits.profile}, {p['interpolation']} interpolation, joint-state timeout "
            f"{self._js_timeout:g} s, planner heartbeat "
            f"{f'{self._hb_timeout:g} s' if self._hb_timeout > 0 else 'off'}, partial joints "
            f"{'allowed' if self._allow_partial else 'refused'}, non-zero end velocity "
            f"{'allowed' if self._allow_end_velocity else 'refused'}")

    # -- executor side: hand data to the loop


    def _on_heartbeat(self, _msg: DiagnosticArray) -> None:
        with self._lock:
            self._last_heartbeat = time.monotonic()
            self._hb_lapsed = False

    def _cannot_start(self) -> str | None:
        """Why no trajectory can start now (call under the lock), or None."""
        t = time.monotonic()
        if self._q is None:
            return "no joint state received yet: where the arm is is unknown"
        if self._stale or t - self._q_time > self._js_timeout:
            return (f"joint states are stale ({1e3 * (t - self._q_time):.0f} ms old, timeout "
                    f"{1e3 * self._js_timeout:.0f} ms): the arm is stopped; send it again "
                    "once they are back")
        if self._hb_timeout > 0.0 and (self._hb_lapsed
                                       or t - self._last_heartbeat > self._hb_timeout):
            return (f"no {topics.PLANNER_STATUS} for {t - self._last_heartbeat:.1f} s "
                    f"(planner_heartbeat_timeout_s {self._hb_timeout:g}): the planner may be "
                    "dead, the arm holds")
        return None

    def _event_logger(self, level: str):
        """A logger object for the follower's events of ``level``: rclpy ties a severity to
        a call site per logger object, and every event is logged from one line (with the
        node's own logger, an error after an info line raised ValueError there and stopped
        the control loop)."""
        if level not in self._event_loggers:
            self._event_loggers[level] = rclpy.logging.get_logger(self.get_logger().name)
        return self._event_loggers[level]

    def _on_trajectory(self, msg: JointTrajectory) -> None:
        log = self.get_logger()
        times, pos, vel, acc = trajectory_arrays(msg)
        start = None if is_zero(msg.header.stamp) else stamp_seconds(msg.header.stamp)
        reason = validate_trajectory(msg.joint_names, self.names, times, pos, vel, acc,
                                     self.limits, start_time=start, now=clock_seconds(self),
                                     allow_partial=self._allow_partial,
                                     allow_nonzero_end_velocity=self._allow_end_velocity)
        if reason is None:
            with self._lock:
                reason = self._cannot_start()
                state = self._follower.snapshot()
            if reason is None and state is None:
                reason = "the control loop has not run yet"
        unfollowable = False
        if reason is None:
            try:  # the long checks outside the lock: the 1 kHz loop must not wait for them
                arrays = reorder_points(msg.joint_names, self.names, times, pos, vel, acc,
                                        fill=state[1] if self._allow_partial else None)
                plan = self._follower.prepare(*arrays, start_time=start, state=state)
                with self._lock:
                    reason = self._cannot_start()  # the states may have lapsed meanwhile
                    if reason is None:
                        self._follower.start(plan)
            except ValueError as exc:
                reason, unfollowable = str(exc), True
        if reason is not None and unfollowable:
            # well formed, but not followable from the arm's state: it may have been a stop,
            # so the motion it was sent to replace must not go on (module doc)
            with self._lock:
                self._follower.brake()
            log.error(f"rejected trajectory of {len(msg.points)} points: {reason}; braking "
                      "to a stop and holding there")
            return
        if reason is not None:
            log.error(f"rejected trajectory of {len(msg.points)} points: {reason}; ignored, "
                      "the arm keeps its current motion")
            return
        partial = len(msg.joint_names) < len(self.names)
        log.info(f"accepted trajectory: {len(msg.points)} points over {times[-1]:.3f} s, "
                 f"{'starting now' if start is None else f'starting at t = {start:.3f}'}"
                 f"{f', {len(msg.joint_names)} of {len(self.names)} joints' if partial else ''}"
                 f"{f'; {plan.note}' if plan.note else ''}")

    # -- loop thread

    def _take_joint_states(self, t: float) -> None:
        """The newest good measurement among those arrived since the last tick, with its
        arrival time. A bad one is reported (`read_joint_state`) and not used."""
        for item in self._joint_states.take_all():
            try:
                msg = self._decode_joint_state(item.msg)
            except ValueError as exc:
                self._problems.report(f"ignored joint state: {exc}", "joint_state.unreadable")
                continue
            q = read_joint_state(self._reader, msg, self._problems, self.get_logger().info)
            if q is not None:
                with self._lock:
                    self._q, self._q_time = q, min(item.arrived, t)

    def _tick(self, t: float) -> None:
        self._take_joint_states(t)
        now = clock_seconds(self)
        with self._lock:
            if self._q is None:
                return  # no measurement yet: publish nothing (module doc)
            if t - self._q_time > self._js_timeout:
                u = self._stale_step(now, t)
            else:
                u = self._control_step(now, t, self._q)
            state = self._state_msg() if self._ticks % self._state_every == 0 else None
            events = self._follower.take_events()
        self._ticks += 1
        for level, line in events:  # aborts on a tolerance, goals reached: said once each
            getattr(self._event_logger(level), level)(line)
        self._cmd_pub.publish(self._command.write(u))
        if state is not None:
            state.header.stamp = self.get_clock().now().to_msg()
            self._state_pub.publish(state)

    def _stale_step(self, now: float, t: float) -> np.ndarray:
        """Abort and brake: the follower treats a NaN measurement exactly so."""
        if not self._stale:
            self._stale = True
            self.get_logger().warning(
                f"joint states stale ({1e3 * (t - self._q_time):.0f} ms > "
                f"{1e3 * self._js_timeout:.0f} ms): trajectory aborted, braking to a stop")
        return self._follower.update(now, np.full(len(self.names), np.nan))

    def _control_step(self, now: float, t: float, q: np.ndarray) -> np.ndarray:
        if self._stale:
            self._stale = False
            self._follower.hold(q)
            self.get_logger().info("joint states are back: holding the current position")
        if (self._hb_timeout > 0.0 and self._follower.active and not self._hb_lapsed
                and t - self._last_heartbeat > self._hb_timeout):
            self._hb_lapsed = True
            self._follower.hold(q)
            self.get_logger().warning(
                f"no {topics.PLANNER_STATUS} for {self._hb_timeout:g} s: trajectory stopped, "
                "holding")
        return self._follower.update(now, q)

    def _state_msg(self) -> JointState:
        q_d, qd_d, _ = self._follower.desired
        return JointState(name=self.names, position=q_d.tolist(), velocity=qd_d.tolist(),
                          effort=self._follower.error.tolist())

    def on_shutdown(self) -> None:
        """Called by `run_single_threaded`: stop the loop and report its timing."""
        stop_loop(self._loop, NAME)
        self._joint_states.close()


def main(args: Sequence[str] | None = None) -> int:
    """Console entry point (``--help``, one-line errors): see `node_main`."""
    return node_main(NAME, __doc__.split("\n\n")[0], PARAMETERS, Controller, args)


if __name__ == "__main__":
    sys.exit(main())
