"""``planner`` node: goals in, certified joint trajectories out, re-routed on every threat.

Thin adapter over :class:`damon_ros.planning.reactive.ReactivePlanner`: it parses parameters and
messages, keeps the latest joint state and obstacle table, and publishes what the runtime
decides. Obstacle arrays are taken by a reader thread of its own (`TopicReader`: the
executor let them go stale) that sleeps until one arrives, so they keep arriving while a
route is computed; each batch is decided on at once in that thread, goals, services and
the fixed-rate path check in the (single-threaded) executor, one at a time (``deciding``).
Joint states are not read as they come (1 kHz from franka or mock_panda): a decision takes
the newest one from its subscription (an `Inbox` keeping one message) when it needs it, so
the planner pays for the states it uses, not for 1,000 a second.
"""

from __future__ import annotations

import math
import sys
import threading
import time
from collections.abc import Sequence

import numpy as np
import rclpy.logging
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point, Pose, PoseStamped
from nav_msgs.msg import Path
from nav_msgs.srv import GetPlan
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import JointState
from std_msgs.msg import ColorRGBA
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory
from visualization_msgs.msg import Marker, MarkerArray

from damon_ros.core.limits import PROFILES
from damon_ros.planning.trajectory import held_until
from damon_ros.ros import topics
from damon_ros.ros.cdr import JointTrajectoryWriter
from damon_ros.ros.inputs import JointStateReader, goal_problem, read_joint_state
from damon_ros.ros.node_loop import use_realtime_priority
from damon_ros.ros.node_main import node_main
from damon_ros.ros.parameters import Param, declare_all
from damon_ros.ros.problems import ProblemLog
from damon_ros.ros.stamps import (
    clock_seconds,
    is_zero,
    stamp_seconds,
    to_stamp,
)
from damon_ros.ros.topic_reader import Inbox, TopicReader

NAME = "planner"

STOP_HOLD_S = 1.0
"""s: a stop's end is held at least this long after it is sent (see `_publish_stop`)."""

PARAMETERS = (
    Param("model_dir", "", "model directory ('' = the shipped models/default)"),
    Param("joint_prefix", "panda_", "joint names are <prefix>joint1..7 (panda_ or fr3_)"),
    Param("limit_profile", "panda", f"joint-limit profile: {' | '.join(PROFILES)}"),
    Param("base_frame", "panda_link0", "frame of goals, obstacles and paths"),
    Param("warn_every_s", 5.0,
          "a repeated problem of one kind (bad input, refusal) is logged at most this often, "
          "with a count; 0: every time (s)", 0.0, 3600.0),
    Param("trajectory_topic", topics.JOINT_TRAJECTORY, "where trajectories go "
          "(/fr3_arm_controller/joint_trajectory for franka_ros2's JTC)"),
    Param("joint_states_topic", topics.JOINT_STATES, "joint states in (franka/joint_states "
          "for franka_ros2: 1 kHz; its joint_states is the broadcaster's 30 Hz)"),
    Param("margin", 0.01,
          "λ: clearance (m) required on top of the conservative collision model", 0.0, 0.5),
    Param("resolution", 0.02, "rad between checked states along a path segment", 0.001, 0.1),
    Param("velocity_scale", 0.9, "fraction of the profile's velocity limits", 0.01, 1.0),
    Param("acceleration_scale", 0.5, "fraction of the profile's acceleration limits",
          0.01, 1.0),
    Param("jerk_scale", 0.5, "fraction of the profile's jerk limits", 0.01, 1.0),
    Param("prediction_horizon_s", 1.0, "obstacles are swept along their velocity this far "
          "ahead (s): at least the time a decision takes to reach the arm", 0.0, 5.0),
    # the movers' prediction model of space-time certification (planning/space_time.py):
    # a report at p, v, age a is inside its shape moved by v*tau, grown by
    # sigma_p + (sigma_v + kappa*|v|)*tau + a_max*tau^2/2 at tau = a + t
    Param("prediction_position_sigma_m", 0.005, "sigma_p: error of a reported obstacle "
          "position (m; the tracker's noise)", 0.0, 0.5),
    Param("prediction_velocity_sigma_m_s", 0.05, "sigma_v: absolute error of a reported "
          "velocity (m/s)", 0.0, 5.0),
    Param("prediction_velocity_sigma_rel", 0.1, "kappa: relative error of a reported "
          "velocity", 0.0, 2.0),
    Param("prediction_acceleration_m_s2", 0.0, "a_max: unmodelled obstacle acceleration "
          "(m/s^2; 0 = constant velocity)", 0.0, 50.0),
    Param("prediction_min_age_s", 0.033, "obstacle data is taken as at least this old (s; "
          "one camera frame) when its stamp says less", 0.0, 1.0),
    Param("prediction_step_m", 0.01, "most a mover's predicted region may move or grow "
          "between two checked instants (m)", 0.001, 0.1),
    Param("prediction_moving_speed_m_s", 0.05, "obstacles reported slower are static "
          "(m/s; above a still box's velocity jitter)", 0.0, 1.0),
    Param("resting_buffer_m", 0.05, "a new goal's route keeps this much more from anything "
          "at rest (m; it may start to move; dropped when no route keeps it)", 0.0, 0.5),
    Param("goal_rechoose_s", 3.0, "a pose goal whose joint configuration no route reached "
          "for this long while the arm held is planned to another IK solution of the pose "
          "(s; 0 = never)", 0.0, 60.0),
    Param("monitor_rate_hz", 20.0, "fixed-rate re-check of the remaining path (Hz)",
          0.5, 1000.0),
    Param("perception_timeout_s", 1.0, "obstacle data older than this stops a moving arm "
          "(s; 0 = off, for a setup without perception)", 0.0, 60.0),
    Param("goal_wait_timeout_s", 5.0, "a goal waiting for obstacle data is dropped after "
          "this long (s), never started by surprise later", 0.1, 3600.0),
    Param("unseen_goal_wait_s", 3.0, "a goal refused only because of the unseen (hidden-"
          "extent) part of a tracked obstacle waits this long for a better view, tried "
          "again every 0.2 s, then is dropped (s; 0 = dropped at once)", 0.0, 60.0),
    Param("joint_state_timeout_s", 0.5, "refuse to plan from joint states older than this (s)",
          0.001, 60.0),
    Param("time_budget_s", 0.25, "a route search gives up after this long (s)", 0.001, 10.0),
    Param("fallback_budget_s", 0.1, "RRT-Connect (same checker) where the graph has no route; "
          "doubled per further failure toward a goal, up to 8x (0 = off)", 0.0, 10.0),
    Param("handover_s", 0.005, "with a fallback, the graph's lazy search hands over to it "
          "after this long (s; at most time_budget_s)", 0.001, 10.0),
    Param("realtime_priority", 15, "SCHED_FIFO priority of the node's threads (0 = normal "
          "scheduling): above the camera and tracker, below the 1 kHz control loops", 0, 99),
)


LATEST_ONLY = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)
"""QoS of a reader that needs only the newest message of a 1 kHz topic."""
MOVING_START_RAD_S = 1e-6
"""rad/s: a trajectory whose first sample moves faster than this starts from a moving arm
and goes out stamped (`_publish_trajectory`); the planner's from a state at rest start at
exactly zero."""

UNSEEN_RETRY_S = 0.2
"""s between tries of a goal that waits for a better view (`unseen_goal_wait_s`)."""

REST_RESIDUE = 1e-9
"""rad/s, rad/s²: a trajectory's end is at rest, but a plan from a moving state leaves
residues of ~1e-15 there after time parameterisation; they go out as exact zeros, so that
any controller's check of the end (JTC's is float epsilon) sees a trajectory at rest."""


def _exactly_at_rest(rates: np.ndarray) -> np.ndarray:
    """The (N, 7) velocities or accelerations with the last row's residues made zeros."""
    if rates.size and float(np.max(np.abs(rates[-1]))) <= REST_RESIDUE:
        rates = rates.copy()
        rates[-1] = 0.0
    return rates


class PlannerNode(Node):
    def __init__(self) -> None:
        super().__init__(NAME)
        from damon_ros.core.limits import joint_limits
        from damon_ros.core.robot import Robot
        from damon_ros.learning.bundle import DamonModel, ModelError
        from damon_ros.planning.graph_planner import GraphPlanner, PlannerConfig
        from damon_ros.planning.reactive import ReactivePlanner, RuntimeConfig
        from damon_ros.planning.space_time import Prediction
        from damon_ros.ros.markers import ObstacleTable

        p = declare_all(self, PARAMETERS)
        # Start-up (model, graph, warm-up: ~5 CPU-s) at the node's priority too: at normal
        # priority, on 2 busy cores, it took 40 s while the 1 kHz loops held the arm.
        use_realtime_priority(self, p["realtime_priority"])
        self.limits = joint_limits(p["limit_profile"], p["joint_prefix"])
        try:
            self.model = DamonModel.load(p["model_dir"] or None)
        except ModelError as exc:  # a ValueError: `node_main` prints it in one line
            raise ModelError(f"cannot load the model: {exc}") from exc
        self.robot = Robot("fast", p["limit_profile"])
        config = PlannerConfig(margin=p["margin"], resolution=p["resolution"],
                               velocity_scale=p["velocity_scale"],
                               acceleration_scale=p["acceleration_scale"],
                               jerk_scale=p["jerk_scale"], time_budget_s=p["time_budget_s"],
                               fallback_budget_s=p["fallback_budget_s"],
                               handover_s=p["handover_s"], prediction=Prediction(
                                   position_sigma_m=p["prediction_position_sigma_m"],
                                   velocity_sigma_m_s=p["prediction_velocity_sigma_m_s"],
                                   velocity_sigma_rel=p["prediction_velocity_sigma_rel"],
                                   acceleration_m_s2=p["prediction_acceleration_m_s2"],
                                   min_age_s=p["prediction_min_age_s"],
                                   step_m=p["prediction_step_m"],
                                   moving_speed_m_s=p["prediction_moving_speed_m_s"]))
        planner = GraphPlanner(self.model.graph, self.robot, self.limits, config)
        planner.warm_up()
        # TCP positions of every vertex, for the graph markers (not on the first goal's path)
        self._vertex_tcp = self.robot.tcp_positions(self.model.graph.q)
        self.runtime = ReactivePlanner(planner, RuntimeConfig(
            prediction_horizon_s=p["prediction_horizon_s"],
            perception_timeout_s=p["perception_timeout_s"],
            goal_wait_s=p["goal_wait_timeout_s"],
            resting_buffer_m=p["resting_buffer_m"],
            goal_rechoose_s=p["goal_rechoose_s"],
            obstacle_source=self.resolve_topic_name(topics.OBSTACLES)),
            risk=lambda q, shapes: self.model.collision_probability(self.robot, q, shapes),
            on_threat=lambda why: self._publish_stop())
        self.base_frame = p["base_frame"]
        self.joint_state_timeout = p["joint_state_timeout_s"]
        self.table = ObstacleTable(self.base_frame)
        self.joint_reader = JointStateReader(self.limits.names)
        # one line per kind of bad input at once, repeats of a kind once per 5 s with a count
        self.problems = ProblemLog(self.get_logger().warning, p["warn_every_s"])
        # goal refusals: the same, per kind of refusal (a client retrying at 10 Hz logged
        # 24 identical lines in 2.4 s). Through a logger object of their own: rclpy fixes
        # the severity per call site and logger, and both logs call from ProblemLog.report —
        # sharing the node's logger, a joint-state warning after a refusal raised ValueError
        # and stopped the joint-state reader.
        self.refusals = ProblemLog(rclpy.logging.get_logger(self.get_logger().name).error,
                                   p["warn_every_s"])
        self.joint_states_topic = p["joint_states_topic"]
        self.lock = threading.Lock()  # the latest joint state
        # the runtime and the obstacle table: obstacle arrays arrive on a reader thread,
        # goals, services and the monitor tick on the executor's
        self.deciding = threading.RLock()
        self.q: np.ndarray | None = None
        self.qd: np.ndarray | None = None
        self.q_stamp = -math.inf
        self.q_measured_at = -math.inf  # the state's header stamp (reception if unset)
        self._decided_from = -math.inf  # q_measured_at of the state the last decision took
        self.last_event = "idle"
        self.unseen_wait_s = p["unseen_goal_wait_s"]
        self._unseen_goal: tuple | None = None  # (goal, since, last try): see `_unseen`
        self._to_show = None  # a published route not yet visualised

        self.pub_traj = self.create_publisher(JointTrajectory, p["trajectory_topic"], 10)
        self._trajectory_writer = JointTrajectoryWriter(self.limits.names, self.base_frame)
        self.pub_path = self.create_publisher(Path, topics.PLANNED_PATH, 10)
        self.pub_graph = self.create_publisher(MarkerArray, topics.GRAPH_MARKERS, 1)
        self.pub_status = self.create_publisher(DiagnosticArray, topics.PLANNER_STATUS, 10)
        # the newest joint state only: `_take_joint_state` reads it when a decision needs it;
        # best effort: a reliable reader costs the 1 kHz publisher an acknowledgement
        # exchange for states this one overwrites unread
        self.joint_states = Inbox(self, JointState, p["joint_states_topic"], "joint_states",
                                  qos=LATEST_ONLY)
        self._obstacles_received: float | None = None  # first array of the pending batch
        self.obstacle_reader = TopicReader(self, MarkerArray, topics.OBSTACLES,
                                           self._on_obstacles, suffix="obstacles",
                                           qos=qos_profile_sensor_data,
                                           on_drained=self._on_obstacles_drained)
        # goals, services and both timers on one executor thread (`run_single_threaded`):
        # a MultiThreadedExecutor here busy-spun its main thread and ran no goal callback
        # for minutes while the obstacle reader held `deciding` for a route search (soak)
        self.create_subscription(PoseStamped, topics.GOAL_POSE, self._on_goal, 10)
        self.create_service(GetPlan, topics.PLAN_SERVICE, self._on_plan_service)
        self.create_service(Trigger, topics.STOP_SERVICE, self._on_stop_service)
        self._monitor_period = 1.0 / p["monitor_rate_hz"]
        self._last_step = -math.inf  # monotonic time of the last path check (`_step`)
        self.create_timer(self._monitor_period, self._monitor)
        self.create_timer(0.1, self._publish_status)
        self.get_logger().info(
            f"planner ready: model {self.model.directory} ({self.model.graph.n_vertices} "
            f"vertices, {len(self.model.graph.nodes)} obstacle nodes), margin {config.margin} m")

    # ---- inputs -----------------------------------------------------------------------
    def _take_joint_state(self) -> None:
        """Keep the newest joint state waiting in the subscription, if a good one is.

        Its age counts from its reception by the middleware, not from this call."""
        with self.lock:
            for item in self.joint_states.take_all():
                msg = item.msg
                q = read_joint_state(self.joint_reader, msg, self.problems,
                                     self.get_logger().info)
                if q is None:
                    continue
                now = clock_seconds(self)
                received = now - max(0.0, time.monotonic() - item.arrived)
                measured = (received if is_zero(msg.header.stamp)
                            else min(stamp_seconds(msg.header.stamp), now))
                self.q, self.qd = q, self.joint_reader.velocities(msg)
                self.q_stamp, self.q_measured_at = received, measured

    def _current_state(self) -> tuple[np.ndarray | None, np.ndarray | None]:
        """(positions, velocities or None) of a fresh joint state; (None, None) if stale."""
        self._take_joint_state()
        with self.lock:
            if self.q is None or clock_seconds(self) - self.q_stamp > self.joint_state_timeout:
                return None, None
            self._decided_from = self.q_measured_at  # a trajectory from it: `_publish_trajectory`
            return self.q.copy(), None if self.qd is None else self.qd.copy()

    def _perception(self) -> tuple[list, float]:
        """(obstacle shape, velocity) pairs now, and the age of the obstacle data (inf
        before any valid data): what every decision of the runtime takes."""
        now = clock_seconds(self)
        obstacles = [(o.shape, o.velocity) for o in self.table.obstacles(now)]
        return obstacles, now - self.table.last_update

    def _on_obstacles(self, msg: MarkerArray) -> None:
        if self._obstacles_received is None:
            self._obstacles_received = time.perf_counter()
        with self.deciding:
            for error in self.table.apply(msg.markers, clock_seconds(self)):
                self.problems.report(f"obstacle marker refused: {error}",
                                     getattr(error, "kind", None))

    def _on_obstacles_drained(self) -> None:
        """One decision per batch of obstacle arrays (a decision in a holding arm may search
        for the whole time budget; one per array starved goals of the lock: soak, 0/10)."""
        received, self._obstacles_received = self._obstacles_received, None
        self._step(received)

    def _on_goal(self, msg: PoseStamped) -> None:
        self._set_goal(msg, time.perf_counter())

    def _set_goal(self, msg: PoseStamped, received: float):
        problem = goal_problem(msg, self.base_frame)
        if problem:
            self.refusals.report(f"goal refused: {problem}", problem.kind)
            return None
        with self.deciding:  # the state and the decision from it under one hold
            return self._plan_goal(msg, received)

    def _plan_goal(self, msg: PoseStamped, received: float):
        from damon_ros.planning.graph_planner import PoseGoal

        q, qd = self._current_state()
        if q is None:
            age = clock_seconds(self) - self.q_stamp
            topic = self.resolve_topic_name(self.joint_states_topic)
            self.refusals.report(
                "goal refused: no fresh joint state (" + (
                    f"the last one is {age:.2f} s old, limit joint_state_timeout_s = "
                    f"{self.joint_state_timeout:g} s)" if math.isfinite(age) else
                    f"none yet on {topic}: is it published? parameter joint_states_topic)"),
                "goal.no_joint_state")
            return None
        o = msg.pose.orientation
        goal = PoseGoal(np.array([msg.pose.position.x, msg.pose.position.y,
                                  msg.pose.position.z]), np.array([o.x, o.y, o.z, o.w]))
        return self._decide_goal(goal, q, qd, received, None)

    def _decide_goal(self, goal, q: np.ndarray, qd, received: float, waiting: tuple | None):
        """Plan ``goal`` with the obstacles now and act on the outcome (`_unseen` first);
        ``waiting`` is the goal's wait for a better view in force (None: a new goal)."""
        with self.deciding:
            self._unseen_goal = waiting
            obstacles, age = self._perception()
            event = self.runtime.set_goal(q, goal, obstacles, perception_age_s=age, qd_now=qd)
            event = self._unseen(event, goal, q)
            self._act(event, received, "goal")
        return event

    def _unseen(self, event, goal, q: np.ndarray):
        """A refusal caused only by the unseen part of an estimate (`unseen_blockers`) says
        so, and the goal waits ``unseen_goal_wait_s`` for a better view (`_retry_unseen`);
        while it waits, a repeated refusal is not logged again (None)."""
        from damon_ros.perception.unseen import Estimate, unseen_blockers, unseen_reason
        from damon_ros.planning.reactive import Event

        if event is None or event.kind != "refused" or self.unseen_wait_s <= 0.0:
            self._unseen_goal = None
            return event
        now = clock_seconds(self)
        seen = self.table.seen_parts(now)
        estimates = [Estimate(f"{o.ns}#{o.id}", o.shape, seen.get((o.ns, o.id)))
                     for o in self.table.obstacles(now)]
        planner = self.runtime.planner
        names = unseen_blockers(
            lambda obstacles: planner.resolve_goal(goal, q, obstacles),
            lambda qq, shape: float(self.robot.distances(qq[None], [shape])[0]),
            planner.config.margin, estimates)
        if names is None:
            self._unseen_goal = None
            return event
        reason = unseen_reason(event.reason, names)
        if self._unseen_goal is None:
            self._unseen_goal = (goal, now, now)
            return Event("refused", f"{reason}: waiting up to {self.unseen_wait_s:g} s "
                         "(unseen_goal_wait_s) for a better view", event.result)
        _, since, _ = self._unseen_goal
        if now - since > self.unseen_wait_s:
            self._unseen_goal = None
            return Event("refused", f"goal dropped after waiting {now - since:.1f} s for a "
                         f"better view: {reason}", event.result)
        return None

    def _retry_unseen(self) -> None:
        """Plan a goal waiting for a better view again, every 0.2 s, with fresh obstacles."""
        goal, since, tried = self._unseen_goal
        now = clock_seconds(self)
        if now - tried < UNSEEN_RETRY_S or self.runtime.state not in ("idle", "reached"):
            return
        with self.deciding:
            q, qd = self._current_state()
            if q is not None:
                self._decide_goal(goal, q, qd, time.perf_counter(), (goal, since, now))

    # ---- the loop ---------------------------------------------------------------------
    def _monitor(self) -> None:
        """The fixed-rate path check: skipped when a decision on an obstacle batch checked
        the path within the last period (at 30 fps the tracker's arrays come faster than
        this timer, which then only repeated the check on the same data)."""
        if self._unseen_goal is not None:
            self._retry_unseen()
        if time.monotonic() - self._last_step < self._monitor_period:
            return
        self._step(time.perf_counter())

    def _step(self, received: float) -> None:
        with self.deciding:  # the state and the decision from it under one hold
            self._last_step = time.monotonic()
            q, qd = self._current_state()
            if q is None or self.runtime.state == "idle":  # "reached": movers may come
                return
            obstacles, age = self._perception()
            now = clock_seconds(self)
            # a moving arm's trajectory carries the state's stamp: an escape counts from it
            state_age = min(now - self._decided_from, self.joint_state_timeout)
            event = self.runtime.update(now, q, obstacles, perception_age_s=age, qd_now=qd,
                                        state_age_s=state_age)
            self._act(event, received, "update")

    def _act(self, event, received: float, cause: str) -> None:
        if event is None:
            return
        log = self.get_logger()
        if event.kind == "trajectory":
            self._publish_trajectory(event.result)
            latency = 1e3 * (time.perf_counter() - received)
            what = "plan" if cause == "goal" else "re-route"
            log.info(f"{what}: {len(event.result.path)} waypoints ({event.result.source} "
                     "route), "
                     f"{event.result.trajectory.duration:.2f} s of motion, decided in "
                     f"{event.latency_ms:.1f} ms ({latency:.1f} ms after the input)"
                     + (f" — {event.reason}" if event.reason else ""))
        elif event.kind == "hold":
            self._publish_stop()
            log.warn(f"stopping the arm: {event.reason}")
        elif event.kind == "reached":
            log.info("goal reached")
        elif event.kind == "refused":
            self.refusals.report(f"goal refused: {event.reason}",
                                 "goal.refused:" + ProblemLog.key(event.reason))
        self.last_event = f"{event.kind}: {event.reason}" if event.reason else event.kind

    # ---- outputs ----------------------------------------------------------------------
    def _trajectory_bytes(self, traj, first: int = 0, stamp: float | None = None) -> bytes:
        """``traj``'s samples from index ``first`` on, serialised (`cdr.JointTrajectoryWriter`);
        header.stamp zero (start on arrival) unless ``stamp`` (s) is given (`_publish_stop`;
        JTC refuses a stamped trajectory whose end has passed)."""
        at = to_stamp(0.0 if stamp is None else stamp)
        return self._trajectory_writer.write(
            (at.sec, at.nanosec), traj.times[first:],
            traj.positions[first:], _exactly_at_rest(traj.velocities[first:]),
            _exactly_at_rest(traj.accelerations[first:]))

    def _publish_stop(self) -> bytes | None:
        """Stop the arm with a trajectory every controller executes (never an empty one:
        Jazzy JTC rejects it and goes on with the motion just judged unsafe): from the last
        measured position and velocity, `GraphPlanner.stop_trajectory` — a jerk-limited
        brake, or a one-point hold at rest. Its first sample (time 0, the measured state)
        is left out: JTC and our controller start from their current state and interpolate
        to the first point, whose time_from_start is then > 0.

        A brake is stamped with the time its state was measured: the arm has moved on since
        (the state's age plus transport, 0.1-0.5 s on a saturated machine), and a zero stamp
        would ask it to be back at the brake's first point 10 ms after arrival — a jump that
        our JTC-semantics controller refused as infeasible (the arm went on into the threat)
        and JTC would follow as a step. Stamped, both controllers take the brake from where
        the coasting arm is by now. Its end is held until at least `STOP_HOLD_S` after now,
        so that a brake from an old state has not ended on arrival (JTC refuses a stamped
        trajectory whose end has passed); the arm then settles at the brake's end. A hold at
        rest goes out unstamped: it starts on arrival."""
        self._take_joint_state()
        with self.lock:
            q, qd, measured_at = self.q, self.qd, self.q_measured_at
        if q is None:
            self.problems.report("no stop sent: no joint state received yet, so the arm has "
                                 "not been moved by this planner", kind="stop.no_state")
            return None
        stop = self.runtime.planner.stop_trajectory(q, qd)
        if stop.times.size <= 2:  # at rest: a hold
            data = self._trajectory_bytes(stop, first=1)
        else:
            age = max(0.0, clock_seconds(self) - measured_at)
            data = self._trajectory_bytes(held_until(stop, age + STOP_HOLD_S), first=1,
                                          stamp=measured_at)
        self.pub_traj.publish(data)
        return data

    def _publish_trajectory(self, result) -> None:
        """A route from an arm at rest starts on arrival (zero stamp). One from a moving
        arm (`GraphPlanner._route_moving`: a brake along the line, then the route) starts
        at the measured state's position *and velocity*, where the arm was when the state
        was measured: it goes out stamped with that time, like a stop (`_publish_stop`), so
        the controller takes it from where the coasting arm is by now; unstamped, it would
        ask the arm to be back there on arrival."""
        traj = result.trajectory.resample(0.02)
        if float(np.max(np.abs(traj.velocities[0]))) < MOVING_START_RAD_S:
            self.pub_traj.publish(self._trajectory_bytes(traj))
        else:
            self.pub_traj.publish(self._trajectory_bytes(traj, first=1,
                                                         stamp=self._decided_from))
        self._to_show = result  # its path and graph markers: `_publish_visualisation`

    def _publish_visualisation(self) -> None:
        """The last route's TCP path and searched subgraph, for RViz, from the status timer.

        Why not with the trajectory: the markers hold up to 5,000 points built one Python
        object at a time, and the path a forward kinematics per pose, 5-15 ms that the next
        decision waited for (they ran under ``deciding``) and that the arm gains nothing
        from. Nothing is built for a topic nobody subscribes to."""
        result, self._to_show = self._to_show, None
        if result is None:
            return
        if self.pub_path.get_subscription_count():
            self.pub_path.publish(self._tcp_path(result.path))
        if self.pub_graph.get_subscription_count():
            self.pub_graph.publish(self._graph_markers(result))

    def _tcp_path(self, path: np.ndarray) -> Path:
        msg = Path()
        msg.header.frame_id = self.base_frame
        msg.header.stamp = self.get_clock().now().to_msg()
        for a, b in zip(path, path[1:], strict=False):
            for s in np.linspace(0.0, 1.0, 10, endpoint=False):
                msg.poses.append(self._pose_stamped(a + s * (b - a)))
        msg.poses.append(self._pose_stamped(path[-1]))
        return msg

    def _pose_stamped(self, q: np.ndarray) -> PoseStamped:
        position, quat = self.robot.tcp_pose(q)
        pose = PoseStamped()
        pose.header.frame_id = self.base_frame
        pose.pose = Pose()
        pose.pose.position.x, pose.pose.position.y, pose.pose.position.z = map(float, position)
        (pose.pose.orientation.x, pose.pose.orientation.y, pose.pose.orientation.z,
         pose.pose.orientation.w) = map(float, quat)
        return pose

    def _graph_markers(self, result) -> MarkerArray:
        """The searched subgraph's vertices (as TCP positions) and the certified route."""
        graph = self.model.graph
        nodes = graph.nearest_nodes(graph.nodes[max(result.subgraph, 0)],
                                    k=max(1, result.searched_nodes))
        members = np.concatenate([graph.members[m] for m in nodes])[:5000]
        stamp = self.get_clock().now().to_msg()
        vertices = Marker(ns="subgraph", id=0, type=Marker.POINTS, action=Marker.ADD)
        vertices.header.frame_id, vertices.header.stamp = self.base_frame, stamp
        vertices.scale.x = vertices.scale.y = 0.01
        vertices.pose.orientation.w = 1.0
        vertices.color = ColorRGBA(r=0.6, g=0.6, b=0.6, a=0.5)
        vertices.points = [Point(x=float(a), y=float(b), z=float(c))
                           for a, b, c in self._vertex_tcp[members]]
        route = Marker(ns="route", id=0, type=Marker.LINE_STRIP, action=Marker.ADD)
        route.header.frame_id, route.header.stamp = self.base_frame, stamp
        route.scale.x = 0.01
        route.pose.orientation.w = 1.0
        route.color = ColorRGBA(r=0.1, g=0.8, b=0.2, a=1.0)
        route.points = [p.pose.position for p in self._tcp_path(result.path).poses]
        for m in (vertices, route):
            m.lifetime = Duration(seconds=0).to_msg()
        return MarkerArray(markers=[vertices, route])

    def _publish_status(self) -> None:
        self._publish_visualisation()
        self._take_joint_state()  # the age it reports is that of the newest state
        rt = self.runtime
        stats = rt.stats
        latencies = stats.replan_latency_ms
        level = {"holding": DiagnosticStatus.WARN}.get(rt.state, DiagnosticStatus.OK)
        status = DiagnosticStatus(level=level, name="damon_ros/planner", hardware_id="damon",
                                  message=f"{rt.state}: {self.last_event}")
        values = {
            "state": rt.state, "plans": stats.plans, "replans": stats.replans,
            "holds": stats.holds, "escapes": stats.escapes, "obstacles": len(self.table),
            # certified routes the RRT-Connect fallback found, reused for the same blockage
            "experience_routes": len(rt.planner.experience),
            "collision_probability": f"{rt.last_probability:.3f}",
            "replan_latency_p50_ms": f"{np.median(latencies):.2f}" if latencies else "nan",
            # inf until the first one: a goal sent before then is refused
            "joint_state_age_s": f"{clock_seconds(self) - self.q_stamp:.3f}",
            "obstacle_data_age_s": f"{clock_seconds(self) - self.table.last_update:.3f}",
        }
        status.values = [KeyValue(key=k, value=str(v)) for k, v in values.items()]
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = to_stamp(clock_seconds(self))
        self.pub_status.publish(msg)

    def on_shutdown(self) -> None:
        """Called by `run_single_threaded`: stop the reader threads."""
        self.joint_states.close()
        self.obstacle_reader.close()

    # ---- services ---------------------------------------------------------------------
    def _on_plan_service(self, request: GetPlan.Request, response: GetPlan.Response):
        event = self._set_goal(request.goal, time.perf_counter())
        if event is not None and event.kind == "trajectory":
            response.plan = self._tcp_path(event.result.path)
        else:
            response.plan = Path()
            response.plan.header.frame_id = self.base_frame
        return response

    def _on_stop_service(self, request: Trigger.Request, response: Trigger.Response):
        with self.deciding:
            self._unseen_goal = None
            self._act(self.runtime.stop("stop requested on ~/stop"), time.perf_counter(),
                      "stop")
        response.success, response.message = True, "arm stopped; goal cleared"
        return response


def main(args: Sequence[str] | None = None) -> int:
    """Console entry point (``--help``, one-line errors): see `node_main`."""
    return node_main(NAME, "DAMON latent-graph planner: goal_pose in, certified "
                     "JointTrajectory out, re-routed on every obstacle threat.", PARAMETERS,
                     PlannerNode, args)


if __name__ == "__main__":
    sys.exit(main())
