"""Closed-loop simulation of one scenario, without ROS, faster than real time.

The same pieces as on the robot — the runtime loop, the PID trajectory follower, the mock
arm's actuator model — stepped on a simulated clock. Perception is ideal (ground-truth
shapes delivered at the camera rate with a configurable latency and noise) or the real
tracker on rendered frames. Planning time is charged honestly: while a plan is computed
the simulated world (and the obstacles) move on by the measured wall time. As in the planner
node, a threat to the running trajectory stops the arm as soon as it is found (the runtime's
``on_threat``), not only once the re-route that follows it is decided.

Each run is scored as ../shared/scenarios/FORMAT.md says: contact is measured on the exact
meshes at every simulated step (a step the conservative fast model certifies farther than
the running minimum needs no mesh query: mesh distance ≥ fast distance).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from damon_ros.core.kinematics import pose_error
from damon_ros.core.scenario import Scenario
from damon_ros.perception.unseen import Estimate, unseen_blockers, unseen_reason
from damon_ros.planning.follower import TrajectoryFollower
from damon_ros.planning.graph_planner import PoseGoal
from damon_ros.planning.reactive import Event, ReactivePlanner
from damon_ros.planning.trajectory import Trajectory
from damon_ros.simulation.mock_arm import ArmSim


@dataclass
class SimConfig:
    control_dt: float = 0.002
    camera_period: float = 1.0 / 30.0
    perception_latency: float = 0.03  # s from the world to the planner's obstacle update
    perception_noise: float = 0.0  # m std of ideal obstacle positions
    hold_time: float = 0.2  # s the goal must be held (velocities ~0) to count as reached
    settle_speed: float = 0.02  # rad/s below which the arm counts as still
    perception: str = "ideal"  # ideal | camera
    cameras: tuple[str, ...] = ("camera.yaml",)  # camera files of the camera perception
    unseen_goal_wait_s: float = 3.0  # as the planner node's parameter of that name
    unseen_retry_s: float = 0.2
    seed: int = 0


@dataclass
class RunRecord:
    scenario: str
    planner: str
    success: bool = False
    collided: bool = False
    min_clearance_m: float = math.inf
    total_time_s: float = math.nan
    planning_time_s: float = math.nan
    replans: int = 0
    replan_latency_ms: list[float] = field(default_factory=list)
    replan_resumed: list[bool] = field(default_factory=list)  # each: a holding arm's retry
    retry_failed_ms: list[float] = field(default_factory=list)  # holding retries without a route
    path_length_rad: float = 0.0
    max_joint_velocity: float = 0.0
    max_joint_acceleration: float = 0.0
    limits_respected: bool = True
    error: str | None = None
    holds: int = 0
    trajectories_refused: int = 0  # by the follower (JTC semantics), the last one kept running
    planner_settings: dict = field(default_factory=dict)

    def as_json(self) -> dict:
        out = dict(self.__dict__)
        for key in ("min_clearance_m", "total_time_s", "planning_time_s"):
            if not math.isfinite(out[key]):
                out[key] = None
        return out


class _Perception:
    """Obstacles as the planner sees them: (shape, velocity) pairs, delayed and noisy."""

    def __init__(self, scenario: Scenario, config: SimConfig) -> None:
        self.scenario = scenario
        self.config = config
        self.rng = np.random.default_rng(config.seed)
        self.tracker = None
        self.tracks: list = []
        if config.perception == "camera":
            from damon_ros.perception.camera import load_cameras
            from damon_ros.perception.tracking import Tracker
            from damon_ros.simulation.renderer import render, scene_at

            self.cameras = load_cameras(config.cameras)
            self.tracker = Tracker(self.cameras[0])
            self._render, self._scene_at = render, scene_at

    def observe(self, t: float) -> list:
        seen_at = max(0.0, t - self.config.perception_latency)
        if self.tracker is not None:
            scene = self._scene_at(self.scenario, seen_at)  # synchronised cameras
            frames = [self._render(camera, scene, rng=self.rng) for camera in self.cameras]
            self.tracks = self.tracker.update_views(self.cameras, frames, seen_at)
            return [(tr.shape, tr.velocity) for tr in self.tracks]
        out = []
        for obstacle in self.scenario.obstacles:  # a compound: each exact part
            offset = np.zeros(3)
            if self.config.perception_noise > 0:
                offset = self.rng.normal(scale=self.config.perception_noise, size=3)
            velocity = obstacle.velocity_at(seen_at)
            out.extend((shape.moved_to(shape.position + offset), velocity)
                       for shape in obstacle.parts_at(seen_at))
        return out


    def unseen(self, runtime: ReactivePlanner, goal: PoseGoal, q: np.ndarray) -> list[str] | None:
        """The tracks whose unseen part alone blocks a refused goal (`unseen_blockers`)."""
        if not self.tracks:
            return None
        planner = runtime.planner
        estimates = [Estimate(f"{tr.color}#{tr.id}", tr.shape, tr.seen) for tr in self.tracks]
        return unseen_blockers(
            lambda obstacles: planner.resolve_goal(goal, q, obstacles),
            lambda qq, shape: float(planner.robot.distances(qq[None], [shape])[0]),
            planner.config.margin, estimates)


def pose_goal(scenario: Scenario) -> PoseGoal:
    """The scenario's goal as the planner takes it."""
    g = scenario.goal
    return PoseGoal(g.position, g.orientation, g.position_tolerance, g.orientation_tolerance)


def run_scenario(scenario: Scenario, runtime: ReactivePlanner, name: str, mesh, fast,
                 config: SimConfig | None = None) -> RunRecord:
    """Simulate one scenario with one planner; never raises for a planner failure."""
    config = config or SimConfig()
    record = RunRecord(scenario=scenario.name, planner=name)
    limits = runtime.planner.limits
    sim = ArmSim(limits, scenario.start, command_timeout=0.1)
    follower = TrajectoryFollower(limits, rate_hz=1.0 / config.control_dt)
    perception = _Perception(scenario, config)
    goal = pose_goal(scenario)
    t, q, qd_prev = 0.0, scenario.start.copy(), np.zeros(7)
    next_camera, held_since = 0.0, None

    pending: list = []  # (activation, decision time, event): takes effect once computed
    threat: dict = {}  # the running update's start (perf_counter) and when it found a threat
    chained = runtime.on_threat

    def on_threat(why: str) -> None:
        threat["found"] = time.perf_counter() - threat["started"]
        if chained is not None:
            chained(why)

    runtime.on_threat = on_threat

    def decide(event: Event | None, now: float) -> float:
        """Queue a runtime event to act when its computation (measured wall time) is over;
        returns that time. Meanwhile the arm keeps doing what it did and is scored."""
        if event is None:
            return now
        ready = now + event.latency_ms / 1e3
        pending.append((ready, now, event))
        return ready

    def update(now: float) -> float:
        """`ReactivePlanner.update` on the newest frame; returns when its decision acts. A
        threat found on the way stops the arm from then (`_Stop`), as the node does."""
        q_measured, qd_measured = sim.q.copy(), sim.qd.copy()
        threat.clear()
        threat["started"] = time.perf_counter()
        event = runtime.update(now, q_measured, perception.observe(now), qd_now=qd_measured)
        if "found" in threat:
            stop = runtime.planner.stop_trajectory(q_measured, qd_measured)
            pending.append((now + threat["found"], now, _Stop(stop)))
        return decide(event, now)

    def act(now: float) -> None:
        while pending and pending[0][0] <= now:
            _, decided, event = pending.pop(0)
            if isinstance(event, _Stop):
                _stop(follower, event.trajectory, decided, sim.q, record)
            elif event.kind == "trajectory":
                tr = event.result.trajectory
                # one that starts moving (a brake from the measured state, then a route or
                # an escape) is stamped with the time of that state, as the node stamps its
                # brakes: the arm has coasted on along it while it was computed, and is
                # taken from there, not sent back to its first point (a jump refused)
                start = decided if np.any(tr.velocities[0] != 0.0) else now
                _send(follower, tr, start, record)  # refused: what runs goes on
            elif event.kind == "hold":
                follower.hold(sim.q)

    t0 = time.perf_counter()
    event = runtime.set_goal(q, goal, perception.observe(t), t=t)
    record.planning_time_s = time.perf_counter() - t0
    waiting = None  # (since, reason): the goal waits for a better view (`_unseen_refusal`)
    if event.kind == "refused":
        waiting = _unseen_refusal(event, perception, runtime, goal, q, t, None, config)
        if waiting is None:
            record.error = f"goal refused: {event.reason}"
            return _finish(record, runtime, scenario, t)
    busy_until = decide(event, t)
    follower.hold(sim.q)
    while t < scenario.time_limit:
        act(t)
        if t >= next_camera:
            next_camera += config.camera_period
            if waiting is not None and t >= busy_until and t - waiting[2] >= config.unseen_retry_s:
                event = runtime.set_goal(sim.q, goal, perception.observe(t), qd_now=sim.qd)
                if event.kind == "refused":
                    waiting = _unseen_refusal(event, perception, runtime, goal, sim.q, t,
                                              waiting, config)
                    if waiting is None or t - waiting[0] > config.unseen_goal_wait_s:
                        record.error = (f"goal refused: {event.reason}" if waiting is None
                                        else f"goal dropped after waiting {t - waiting[0]:.1f}"
                                        f" s for a better view: {waiting[1]}")
                        break
                else:
                    waiting = None
                busy_until = decide(event, t)
            elif waiting is None and t >= busy_until:  # the newest frame once it is free
                busy_until = update(t)
        u = follower.update(t, sim.q)
        sim.command(u, t)
        t += config.control_dt
        q_prev = q
        q, qd = sim.step(config.control_dt, t)
        record.path_length_rad += float(np.linalg.norm(q - q_prev))
        record.max_joint_velocity = max(record.max_joint_velocity, float(np.max(np.abs(qd))))
        acc = (qd - qd_prev) / config.control_dt
        record.max_joint_acceleration = max(record.max_joint_acceleration,
                                            float(np.max(np.abs(acc))))
        if np.any(limits.velocity_excess(q, qd) > 1e-9) or np.any(
                np.abs(acc) > limits.acceleration + 1e-6) or not limits.within(q, 1e-9):
            record.limits_respected = False
        qd_prev = qd
        _score_contact(record, mesh, fast, q, scenario.obstacles_at(t))
        if record.collided:
            break
        if runtime.state in ("executing", "reached") and np.all(np.abs(qd) < config.settle_speed):
            p_err, o_err = pose_error(*fast.tcp_pose(q), goal.position, goal.orientation)
            if p_err <= goal.position_tolerance and o_err <= goal.orientation_tolerance:
                held_since = t if held_since is None else held_since
                if t - held_since >= config.hold_time:
                    record.success = True
                    break
            else:
                held_since = None
        else:
            held_since = None
    if waiting is not None and record.error is None:
        record.error = f"goal still waiting for a better view at the time limit: {waiting[1]}"
    return _finish(record, runtime, scenario, t)


class _Stop(NamedTuple):
    """The stop the planner node sends when it finds a threat (`GraphPlanner.stop_trajectory`
    from the measured state, stamped with that state's time), before it re-routes."""

    trajectory: Trajectory


def _stop(follower: TrajectoryFollower, stop: Trajectory, measured_at: float,
          q_now: np.ndarray, record: RunRecord) -> None:
    """Send a `_Stop` to the follower as the controller node takes it: a brake from the
    measured state (the arm has coasted on along it since), or a hold of an arm at rest;
    a brake it cannot follow is braked from the arm's own state instead."""
    if stop.times.size <= 2:
        follower.hold(q_now)
    elif not _send(follower, stop, measured_at, record):
        follower.brake()


def _send(follower: TrajectoryFollower, trajectory: Trajectory, start: float,
          record: RunRecord) -> bool:
    """Hand ``trajectory`` (time 0 at ``start``) to the follower; False, counted in
    ``record``, when the follower refuses it (as the controller node does)."""
    try:
        follower.set_trajectory(trajectory.times, trajectory.positions, trajectory.velocities,
                                trajectory.accelerations, start_time=start)
    except ValueError:
        record.trajectories_refused += 1
        return False
    return True


def _unseen_refusal(event: Event, perception: _Perception, runtime: ReactivePlanner,
                    goal: PoseGoal, q: np.ndarray, t: float, waiting: tuple | None,
                    config: SimConfig) -> tuple | None:
    """As the planner node: a goal refused only because of the unseen part of a track waits
    (``(since, reason, last try)``); None when the refusal is final."""
    if config.unseen_goal_wait_s <= 0.0:
        return None
    names = perception.unseen(runtime, goal, q)
    if names is None:
        return None
    since = t if waiting is None else waiting[0]
    return since, unseen_reason(event.reason, names), t


def _score_contact(record: RunRecord, mesh, fast, q: np.ndarray, obstacles) -> None:
    """Exact (mesh) clearance at this step, skipping the mesh query when the conservative
    fast model already proves the clearance is above the running minimum."""
    if not obstacles:
        return
    lower_bound = float(fast.distances(q[None], obstacles)[0])
    if lower_bound >= record.min_clearance_m and record.min_clearance_m > 0.0:
        return
    d = mesh.clearance(q, obstacles).distance
    record.min_clearance_m = min(record.min_clearance_m, d)
    if d <= 0.0:
        record.collided = True


def _finish(record: RunRecord, runtime: ReactivePlanner, scenario: Scenario,
            t: float) -> RunRecord:
    record.replans = runtime.stats.replans
    record.holds = runtime.stats.holds
    record.replan_latency_ms = [round(x, 3) for x in runtime.stats.replan_latency_ms]
    record.replan_resumed = list(runtime.stats.replan_resumed)
    record.retry_failed_ms = [round(x, 3) for x in runtime.stats.retry_failed_ms]
    record.success = record.success and not record.collided
    record.total_time_s = t if record.success else math.nan
    if not record.success and record.error is None:
        record.error = None if record.collided else (
            f"goal not reached within {scenario.time_limit:.1f} s")
    return record
