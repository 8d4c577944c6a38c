"""controller: PID joint-trajectory controller, a thin ROS adapter over `TrajectoryFollower`.

Trajectories in (``/damon/joint_trajectory``, ``trajectory_msgs/JointTrajectory``), measured
joints in (``/joint_states``), velocity commands out (``/damon/joint_commands``,
``std_msgs/Float64MultiArray``, rad/s in the order of the ``joints`` parameter) at
``rate_hz``, and ``/damon/controller_state`` (``sensor_msgs/JointState``: desired position in
``position``, desired velocity in ``velocity``, position error in ``effort``) at
``state_rate_hz``. Interpolation, PID and the limit-respecting command shaping are
`damon_ros.planning.follower`'s; this module decides *when* to call it and what to do on bad or
missing input:

- Trajectories follow ros2_controllers' JTC: a zero ``header.stamp`` starts on arrival, any
  other starts at that ROS time; a new one replaces the old; one without points holds the
  current position; one whose joints don't match (another order is fine), whose
  ``time_from_start`` is not strictly increasing, that holds NaN/inf or leaves the limits is
  rejected with one log line and ignored, so the arm keeps doing what it did.
- Until the first joint state arrives nothing is published: the controller does not know
  where the arm is, and it has never commanded it, so there is nothing to stop.
- Joint states older than ``joint_state_timeout_s``: the trajectory is aborted and the
  command brakes to zero velocity as fast as the limit profile allows (a step to zero would
  break the acceleration and jerk limits a Franka enforces), then zeros are published while
  the states stay stale. Logged once; when states return the arm holds where it is. A
  joint state holding NaN/inf, lacking a controller joint or stamped before the last one
  (`damon_ros.ros.inputs.JointStateReader`) is ignored with one warning per kind of problem
  (repeats: one line per 5 s with a count), so that a stream of them ends in this stop.
- ``planner_heartbeat_timeout_s`` > 0: while a trajectory is active and no
  ``/damon/planner_status`` arrived for that long, the arm holds (logged once per lapse).

The command loop runs in a `FixedRateLoop` thread (see `FixedRateLoop` for why not an
rclpy timer); callbacks only hand data to it under one lock.
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Sequence

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray
from trajectory_msgs.msg import JointTrajectory

from damon_ros.core.limits import PROFILES, joint_limits
from damon_ros.planning.follower import (
    PIDGains,
    TrajectoryFollower,
    reorder_points,
    validate_trajectory,
)
from damon_ros.planning.trajectory import METHODS
from damon_ros.ros import topics
from damon_ros.ros.inputs import JointStateReader, joint_names, read_joint_state
from damon_ros.ros.node_loop import start_loop, stop_loop
from damon_ros.ros.node_main import node_main
from damon_ros.ros.parameters import Param, declare_all
from damon_ros.ros.problems import ProblemLog
from damon_ros.ros.stamps import clock_seconds, is_zero, stamp_seconds

NAME = "controller"
WARN_EVERY_S = 5.0
_DEFAULT_GAINS = PIDGains()

PARAMETERS = (
    Param("joints", (), "joint names in command order; empty: <joint_prefix>joint1..7"),
    Param("joint_prefix", "panda_",
          "prefix of the default joint names (panda_, or fr3_ for franka_ros2)"),
    Param("limit_profile", "panda", f"limits every command respects: {' | '.join(PROFILES)}"),
    Param("rate_hz", 1000.0, "command rate (Hz)", 1.0, 10000.0),
    Param("state_rate_hz", 100.0, "/damon/controller_state rate (Hz)", 0.1, 10000.0),
    Param("interpolation", "quintic", f"between trajectory points: {' | '.join(METHODS)}"),
    Param("p", tuple(_DEFAULT_GAINS.p.tolist()), "proportional gain per joint (1/s)"),
    Param("i", tuple(_DEFAULT_GAINS.i.tolist()), "integral gain per joint (1/s^2)"),
    Param("d", tuple(_DEFAULT_GAINS.d.tolist()), "derivative gain per joint (-)"),
    Param("i_clamp", tuple(_DEFAULT_GAINS.i_clamp.tolist()),
          "largest integral contribution per joint (rad/s), anti-windup"),
    Param("ff_velocity_scale", tuple(_DEFAULT_GAINS.ff_velocity_scale.tolist()),
          "feed-forward velocity scale per joint"),
    Param("joint_state_timeout_s", 0.05, "older joint states stop the arm (s)", 0.001, 10.0),
    Param("planner_heartbeat_timeout_s", 0.0,
          "hold when the planner is silent this long; 0: off (s)", 0.0, 3600.0),
    Param("realtime_priority", 20,
          "SCHED_FIFO priority of the node's threads, 0: normal scheduling", 0, 99),
)


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
        p = declare_all(self, PARAMETERS)
        self.limits = joint_limits(p["limit_profile"])
        self.names = joint_names(p["joints"], p["joint_prefix"])
        gains = PIDGains(*(np.asarray(p[k], dtype=float) for k in
                           ("p", "i", "d", "i_clamp", "ff_velocity_scale")))
        self._follower = TrajectoryFollower(self.limits, gains, p["rate_hz"],
                                            p["interpolation"])
        self._js_timeout = p["joint_state_timeout_s"]
        self._hb_timeout = p["planner_heartbeat_timeout_s"]
        self._lock = threading.Lock()  # guards the follower and the latest measurement
        self._q: np.ndarray | None = None
        self._q_time = 0.0  # monotonic arrival time of self._q
        self._reader = JointStateReader(self.names)
        self._problems = ProblemLog(self.get_logger().warning, WARN_EVERY_S)
        self._last_heartbeat = time.monotonic()
        self._stale = False
        self._hb_lapsed = False
        self._ticks = 0
        self._state_every = max(1, round(p["rate_hz"] / p["state_rate_hz"]))
        self._cmd_pub = self.create_publisher(Float64MultiArray, topics.JOINT_COMMANDS, 10)
        self._state_pub = self.create_publisher(JointState, topics.CONTROLLER_STATE, 10)
        self.create_subscription(JointState, topics.JOINT_STATES, self._on_joint_state, 10)
        self.create_subscription(JointTrajectory, topics.JOINT_TRAJECTORY, self._on_trajectory, 10)
        self.create_subscription(DiagnosticArray, topics.PLANNER_STATUS, self._on_heartbeat, 10)
        self._loop = start_loop(self, NAME, p["rate_hz"], self._tick, "control loop",
                                p["realtime_priority"])
        self.get_logger().info(
            f"driving {self.names[0]}..{self.names[-1]} at {p['rate_hz']:g} Hz, profile "
            f"{self.limits.profile}, {p['interpolation']} interpolation, joint-state timeout "
            f"{self._js_timeout:g} s, planner heartbeat "
            f"{f'{self._hb_timeout:g} s' if self._hb_timeout > 0 else 'off'}")

    # -- executor side: hand data to the loop

    def _on_joint_state(self, msg: JointState) -> None:
        t = time.monotonic()
        q = read_joint_state(self._reader, msg, self._problems, self.get_logger().info)
        if q is None:
            return  # not a measurement: a stream of them ends in the stale stop
        with self._lock:
            self._q, self._q_time = q, t

    def _on_heartbeat(self, _msg: DiagnosticArray) -> None:
        with self._lock:
            self._last_heartbeat = time.monotonic()
            self._hb_lapsed = False

    def _on_trajectory(self, msg: JointTrajectory) -> None:
        log = self.get_logger()
        if not msg.points:
            with self._lock:
                self._follower.set_trajectory([], [])
            log.info("empty trajectory: stopping and holding the current position")
            return
        times, pos, vel, acc = trajectory_arrays(msg)
        start = None if is_zero(msg.header.stamp) else stamp_seconds(msg.header.stamp)
        reason = validate_trajectory(msg.joint_names, self.names, times, pos, vel, acc,
                                     self.limits, start_time=start, now=clock_seconds(self))
        if reason is None:
            try:
                arrays = reorder_points(msg.joint_names, self.names, times, pos, vel, acc)
                with self._lock:
                    self._follower.set_trajectory(*arrays, start_time=start)
            except ValueError as exc:
                reason = str(exc)
        if reason is not None:
            log.error(f"rejected trajectory of {len(msg.points)} points: {reason}; ignored, "
                      "the arm keeps its current motion")
            return
        log.info(f"accepted trajectory: {len(msg.points)} points over {times[-1]:.3f} s, "
                 f"{'starting now' if start is None else f'starting at t = {start:.3f}'}")

    # -- loop thread

    def _tick(self, t: float) -> None:
        now = clock_seconds(self)
        with self._lock:
            if self._q is None:
                return  # no measurement yet: publish nothing (module doc)
            if t - self._q_time > self._js_timeout:
                u = self._stale_step(now, t)
            else:
                u = self._control_step(now, t, self._q)
            state = self._state_msg() if self._ticks % self._state_every == 0 else None
        self._ticks += 1
        self._cmd_pub.publish(Float64MultiArray(data=u.tolist()))
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
        elif self._hb_lapsed and self._follower.active:
            self._follower.hold(q)  # still no heartbeat: a new trajectory must not run
        return self._follower.update(now, q)

    def _state_msg(self) -> JointState:
        q_d, qd_d, _ = self._follower.desired
        return JointState(name=self.names, position=q_d.tolist(), velocity=qd_d.tolist(),
                          effort=self._follower.error.tolist())

    def on_shutdown(self) -> None:
        """Called by `run_single_threaded`: stop the loop and report its timing."""
        stop_loop(self._loop, NAME)


def main(args: Sequence[str] | None = None) -> int:
    """Console entry point (``--help``, one-line errors): see `node_main`."""
    return node_main(NAME, __doc__.split("\n\n")[0], PARAMETERS, Controller, args)


if __name__ == "__main__":
    sys.exit(main())
