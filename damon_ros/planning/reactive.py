"""DAMON's runtime loop, free of ROS: plan, watch the path, re-route or hold, resume.

The planner node and the closed-loop benchmark both drive this class, so the decisions a
user sees on the robot are exactly the ones the benchmark scores. Every obstacle update
(and a fixed-rate tick) re-certifies the rest of the path: against the static obstacles
swept over a short prediction horizon, as the path checks do, and — the rest of the
*timed* trajectory from where the arm is on it — against where each mover is predicted
then (`GraphPlanner.trajectory_threatened`). When it is no longer certified the loop
re-routes from the current state; when no certified route exists it stops the arm if
braking in place is certified in space and time, else it evades (a certified escape move)
before holding, and a holding arm a mover's prediction will reach evades as well.
"""

from __future__ import annotations

import math
import re
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from damon_ros.core.hull import few_vertices
from damon_ros.core.shapes import Shape, grown
from damon_ros.planning.graph_planner import (
    GraphPlanner,
    PlanResult,
    PoseGoal,
    Scene,
    then_resting,
)
from damon_ros.planning.space_time import movers

TRACKING_RAD = 0.05
"""The arm counts as on its trajectory's schedule when within this of the state due now
(the follower tracks within 0.02 rad); farther (halted, stalled), the rest of the
trajectory is taken from the state nearest the arm instead."""


def swept(shape: Shape, velocity: np.ndarray, horizon: float) -> Shape:
    """A shape of the same kind that contains ``shape`` over the next ``horizon`` seconds of
    straight motion at ``velocity``: centred halfway, a sphere's radius grown by half the
    travel, a box's extents and a cylinder's length by the travel and its radius by half of
    it, a point set joined by its moved copy (the hull is then the exact sweep; its 26-DOP where
    that has more than `hull.MAX_HULL_VERTICES` vertices).

    Why not the bounding sphere of the sweep: a tracked box is never quite still (its
    estimated centre jitters by millimetres, giving ~0.03 m/s of velocity), and the sphere
    around a 0.2 x 0.3 x 0.45 m box has a 0.31 m radius; paths certified against one such
    sphere were refused against the next, and the camera demo stopped and re-routed twice
    a second without reaching its goal. Grown by the travel, the box changes by a
    centimetre or two between updates.
    """
    velocity = np.asarray(velocity, float)
    travel = float(np.linalg.norm(velocity)) * horizon
    if travel < 1e-4:
        return shape
    half = 0.5 * horizon * velocity
    center = shape.position + half
    if shape.kind == "sphere":
        size = (shape.size[0] + 0.5 * travel,)
    elif shape.kind == "box":
        size = tuple(np.asarray(shape.size) + travel)
    elif shape.kind == "cylinder":
        size = (shape.size[0] + 0.5 * travel, shape.size[1] + travel)
    else:  # points, in the shape's frame: the hull of both copies contains every position
        # (no more vertices than `few_vertices` leaves: each one costs every query)
        step = shape.rotation().T @ (2.0 * half)
        points = few_vertices(np.vstack([shape.points, shape.points + step]))
        return Shape("points", (), shape.position, shape.orientation, points, shape.name)
    return Shape(shape.kind, size, center, shape.orientation, name=shape.name)


def resting_buffered(obstacles: Sequence[tuple[Shape, np.ndarray]], buffer_m: float,
                     moving_speed_m_s: float) -> Sequence[tuple[Shape, np.ndarray]]:
    """``obstacles`` with every one at rest (reported slower than ``moving_speed_m_s``, as
    the space-time check's movers are told apart) grown by ``buffer_m`` (`buffered`); the
    list itself when none is at rest, or there is no buffer.

    Why: a thing at rest may start to move at any moment, and one that starts toward an arm
    passing it a few centimetres away reaches it before its motion is even reported. Balls
    diving at 0.3 m/s met routes planned 1-3 cm past them while they rested (seed 1301,
    family G). On the stress bench boxes and compound objects rest too, then cross at up to
    1.5 m/s: with balls alone buffered, 6 contacts in 1,000 scenes (seed 1606), one at
    0.6-1 m/s where RRT-Connect under the same runtime touched as well; with every resting
    thing buffered, 1 and 3 in two runs, none up to 1 m/s. The arm's brake takes ~0.15 s,
    in which a thing at 0.35 m/s covers 5 cm. Only a new goal's route is planned with the
    buffer (and without it when that fails): a re-route is urgent, and the path checks use
    the shapes as they are.
    The price is a longer first route past still things (generated families, seed 1606:
    goal time p50 +0.0-0.5 s)."""
    def resting(velocity: np.ndarray) -> bool:
        return float(np.linalg.norm(velocity)) < moving_speed_m_s

    if buffer_m <= 0.0 or not any(resting(v) for _, v in obstacles):
        return obstacles
    return [(buffered(s, buffer_m), v) if resting(v) else (s, v) for s, v in obstacles]


def buffered(shape: Shape, buffer_m: float) -> Shape:
    """``shape`` grown by ``buffer_m``: a primitive as the same kind (`grown`); a point set
    with each vertex pushed ``buffer_m`` out from their centroid (a preference, as the
    buffer is, not a certified offset)."""
    if shape.kind != "points":
        return grown(shape, buffer_m)
    out = shape.points - shape.points.mean(axis=0)
    reach = np.linalg.norm(out, axis=1, keepdims=True)
    points = shape.points + buffer_m * out / np.maximum(reach, 1e-9)
    return Shape("points", (), shape.position, shape.orientation, points, shape.name)


def _age(perception_age_s: float) -> float:
    """The age of obstacle data for the prediction (an unknown age, inf, counts as none:
    the prediction's own minimum age applies)."""
    return perception_age_s if math.isfinite(perception_age_s) else 0.0


@dataclass
class Event:
    """What the caller must do now. ``kind``: ``trajectory`` (send ``result.trajectory``),
    ``hold`` (stop the arm where it is), ``reached`` or ``refused`` (goal refused)."""

    kind: str
    reason: str = ""
    result: PlanResult | None = None
    latency_ms: float = 0.0


_NUMBER = re.compile(r"-?\d+(\.\d+)?")


@dataclass
class RetryPacer:
    """When a holding arm searches for a route again.

    Every ``period_s`` at most, as before; but a failing search takes its whole budget
    (up to 0.25 s of graph search and 0.8 s of RRT fallback), so retried every 0.1 s it
    pinned a core while the arm held (soak). Now: after a failed retry the next waits
    until the retries have used at most ``cpu_share`` of the time since it began, and the
    period doubles (up to ``max_period_s``) while the same failure repeats (its reason
    with the numbers left out). A changed obstacle picture (an obstacle appeared, went, or
    moved ``moved_m`` since the failed retry) is retried at once, within the share.
    """

    period_s: float = 0.1
    max_period_s: float = 0.8
    cpu_share: float = 0.5
    moved_m: float = 0.03
    _wait: float = 0.0
    _next: float = -math.inf  # the backed-off time of the next retry
    _budget_next: float = -math.inf  # the earliest one within the share
    _reason: str = ""
    _seen: dict = field(default_factory=dict)  # obstacle name -> position at the failure

    def __post_init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        """A new hold (or the end of one): retry at once."""
        self._wait, self._next, self._budget_next = self.period_s, -math.inf, -math.inf
        self._reason, self._seen = "", {}

    def due(self, t: float, shapes: Scene) -> bool:
        """Whether a retry may start at ``t`` with the obstacles ``shapes``."""
        if t >= self._next:
            return True
        return t >= self._budget_next and self._changed(shapes)

    def failed(self, t: float, spent_s: float, reason: str, shapes: Scene) -> None:
        """A retry begun at ``t`` failed after ``spent_s`` s (its cost) with ``reason``."""
        kind = _NUMBER.sub("#", reason)
        self._wait = (min(2.0 * self._wait, self.max_period_s) if kind == self._reason
                      else self.period_s)
        self._reason = kind
        self._budget_next = t + spent_s / self.cpu_share
        self._next = max(t + self._wait, self._budget_next)
        self._seen = _positions(shapes)

    def _changed(self, shapes: Scene) -> bool:
        now = _positions(shapes)
        if now.keys() != self._seen.keys():
            return True
        return any(float(np.linalg.norm(p - self._seen[name])) > self.moved_m
                   for name, p in now.items())


def _positions(shapes: Scene) -> dict:
    """Obstacle name (or index) -> position of the obstacles now."""
    return {s.name or str(k): np.asarray(s.position, float) for k, s in enumerate(shapes.now)}


@dataclass
class RuntimeConfig:
    prediction_horizon_s: float = 0.3
    goal_tolerance_rad: float = 0.01
    settled_speed_rad_s: float = 0.05  # "reached" needs the arm this slow as well as close
    retry_period_s: float = 0.1  # how often a holding arm looks for a route again
    escape_clearance_m: float = 0.05  # a holding arm moves away when an obstacle is closer
    stall_time_s: float = 1.5  # an arm that stopped short of the goal this long is re-planned
    perception_timeout_s: float = 0.0  # 0 = do not require fresh obstacle data
    goal_wait_s: float = 5.0  # a goal waiting for obstacle data is dropped after this long
    obstacle_source: str = "the obstacle topic"  # named in the waiting goal's message
    space_time: bool = True  # timed trajectories checked against the movers' predictions
    resting_buffer_m: float = 0.05  # a new goal's route keeps this much more from things at rest
    # a pose goal whose joint configuration no route has reached for this long while the arm
    # holds is re-chosen among the pose's other IK solutions (`_rechoose_goal`); 0 = never
    goal_rechoose_s: float = 3.0


@dataclass
class RuntimeStats:
    plans: int = 0
    replans: int = 0
    holds: int = 0
    escapes: int = 0
    followed_on: int = 0  # threats met by following the running trajectory (`_update`)
    replan_latency_ms: list[float] = field(default_factory=list)
    # per re-route: a holding arm's retry that found a route, not one on a threat or stall
    replan_resumed: list[bool] = field(default_factory=list)
    retry_failed_ms: list[float] = field(default_factory=list)  # a holding arm's, no route
    plan_latency_ms: list[float] = field(default_factory=list)
    goals_rechosen: int = 0  # goal configurations re-chosen after a long hold


class ReactivePlanner:
    """State machine: ``idle`` → ``executing`` ⇄ ``holding`` → ``reached``."""

    def __init__(self, planner: GraphPlanner, config: RuntimeConfig | None = None,
                 risk=None, on_threat=None) -> None:
        self.planner = planner
        self.config = config or RuntimeConfig()
        self.risk = risk  # optional (q, obstacles) -> p(collision), reported only
        # optional callable(reason) run the moment the path is threatened, before the
        # re-route is computed: the node stops the arm there (halt, re-route, continue)
        self.on_threat = on_threat
        self.state = "idle"
        self.path = np.zeros((0, 7))
        self.segment = 0
        self.trajectory = None  # what runs, and its time 0 on the caller's clock (or None)
        self.trajectory_source = ""  # what found it (`PlanResult.source`)
        self._t_start: float | None = None
        self._update_started: float | None = None  # perf_counter at the running update's start
        self._sample = 0  # the trajectory sample the arm was last found at
        self.retries = RetryPacer(self.config.retry_period_s)
        self._failure = ""  # the reason of the last failed route search (`_reroute`)
        self.last_probability = 0.0
        self.pending_goal = None  # a goal given before obstacle data arrived
        self._pending_since: float | None = None  # first update that saw it waiting
        self._still_q: np.ndarray | None = None  # stall detection
        self._still_since = 0.0
        self.goal = None  # the goal being planned for, as given (a pose or joints)
        self._unreached_since: float | None = None  # first failed retry since a route
        self.stats = RuntimeStats()

    def scene(self, obstacles: Sequence[tuple[Shape, np.ndarray]],
              age_s: float = 0.0) -> Scene:
        """Obstacles now, swept along their velocities over the prediction horizon, and the
        moving ones (``age_s`` old) for the space-time check of timed trajectories."""
        h = self.config.prediction_horizon_s
        moving = movers(obstacles, self.planner.config.prediction) if self.config.space_time \
            else ()
        return Scene(tuple(s for s, _ in obstacles), tuple(swept(s, v, h) for s, v in obstacles),
                     moving, age_s)

    def set_goal(self, q_now: np.ndarray, goal, obstacles: Sequence[tuple[Shape, np.ndarray]],
                 perception_age_s: float = 0.0, qd_now: np.ndarray | None = None,
                 t: float | None = None) -> Event:
        """Plan to a new goal (replacing any current one). Without fresh obstacle data the
        goal waits (the arm holds) and is planned as soon as data arrives: never blind.
        ``qd_now`` (joint velocities, optional): a moving arm's route starts where it stops
        (`GraphPlanner.braking_point`). ``t`` (the clock `update` gets, optional): when the
        trajectory starts, for its re-checks in space and time."""
        event = self._set_goal(q_now, goal, obstacles, perception_age_s, qd_now)
        self._started(event, t)
        return event

    def _set_goal(self, q_now, goal, obstacles, perception_age_s, qd_now) -> Event:
        timeout = self.config.perception_timeout_s
        if timeout > 0 and perception_age_s > timeout:
            self.pending_goal, self._pending_since = goal, None
            self.planner.goal_q = None
            age = (f"none for {perception_age_s:.1f} s" if math.isfinite(perception_age_s)
                   else "none received yet")
            return self._hold(
                f"goal waits for obstacle data on {self.config.obstacle_source} ({age}; "
                f"parameter perception_timeout_s = {timeout:g} s): it is planned when fresh "
                f"data arrives, or dropped after {self.config.goal_wait_s:g} s "
                "(goal_wait_timeout_s)")
        self.pending_goal, self.goal, self._unreached_since = None, goal, None
        result, latency = self._plan(q_now, goal, obstacles, perception_age_s, qd_now)
        if not result.success:
            if self.planner.goal_q is None:  # refused: IK, limits, goal in collision
                self.state = "idle"
                return Event("refused", result.reason, result, latency)
            return self._hold(result.reason, result, latency)
        return self._execute(result, latency)

    def _plan(self, q_now, goal, obstacles, perception_age_s, qd_now
              ) -> tuple[PlanResult, float]:
        """`GraphPlanner.plan` keeping `resting_buffer_m` from things at rest where it can;
        returns the result and its latency (ms)."""
        t0 = time.perf_counter()
        age = _age(perception_age_s)
        buffered = resting_buffered(obstacles, self.config.resting_buffer_m,
                                    self.planner.config.prediction.moving_speed_m_s)
        result = self.planner.plan(q_now, goal, self.scene(buffered, age), qd_start=qd_now)
        if not result.success and buffered is not obstacles:
            result = self.planner.plan(q_now, goal, self.scene(obstacles, age), qd_start=qd_now)
        latency = 1e3 * (time.perf_counter() - t0)
        self.stats.plans += 1
        self.stats.plan_latency_ms.append(latency)
        return result, latency

    def _rechoose_goal(self, t: float, q_now: np.ndarray, obstacles, perception_age_s: float,
                       qd_now: np.ndarray | None) -> Event | None:
        """A pose goal's other IK solution, planned from here, once no route has reached the
        chosen one for `goal_rechoose_s` while the arm held: something came to rest in its
        way (stress bench, S-v1-1.5-s2709-163: two movers stopped beside the base after the
        arm escaped them, and the arm held 27 s while every search toward the elbow-out
        solution failed, RRTConnect's as well). None (hold on) when the pose has no other
        solution with clearance, or no route reaches that one either: the retries then go on
        toward the chosen one (on a stress scene whose mover passed 6 s in, retries toward
        the other solution never ended), and the other is tried again after as long."""
        limit = self.config.goal_rechoose_s
        if limit <= 0 or not isinstance(self.goal, PoseGoal) or \
                self._unreached_since is None or t - self._unreached_since < limit:
            return None
        held = t - self._unreached_since
        self._unreached_since = t
        t0 = time.perf_counter()
        old = self.planner.goal_q
        q_alt, _ = self.planner.resolve_goal(self.goal, q_now, tuple(s for s, _ in obstacles),
                                             avoid=old)
        if q_alt is None:
            return None
        kept = (old, self.planner.goal_exact)
        result, _ = self._plan(q_now, q_alt, obstacles, perception_age_s, qd_now)
        if not result.success:  # the chosen configuration stays the goal
            self.planner.goal_q, self.planner.goal_exact = kept
            return None
        self.stats.goals_rechosen += 1
        event = self._execute(result, 1e3 * (time.perf_counter() - t0))
        event.reason = (f"no route reached the goal's joint configuration for {held:.1f} s; "
                        "planned to another IK solution of the goal pose")
        return event

    def stop(self, reason: str) -> Event:
        self.planner.goal_q = None
        self.pending_goal = None
        self.state = "idle"
        self.path = np.zeros((0, 7))
        return Event("hold", reason)

    def update(self, t: float, q_now: np.ndarray,
               obstacles: Sequence[tuple[Shape, np.ndarray]],
               perception_age_s: float = 0.0, qd_now: np.ndarray | None = None,
               state_age_s: float = 0.0) -> Event | None:
        """Called on every obstacle update and at a fixed rate; returns an event or None.
        ``state_age_s``: how long ago ``q_now`` was measured (a trajectory from a moving arm
        is stamped with that time, so an escape's swerve turns after it: `_escape`)."""
        self._update_started = time.perf_counter() - max(0.0, state_age_s)
        event = self._update(t, q_now, obstacles, perception_age_s, qd_now)
        self._started(event, t)
        return event

    def _started(self, event: Event | None, t: float | None) -> None:
        """When a trajectory decided at ``t`` (the measured state's time) runs from its
        first sample. One from an arm at rest starts when its computation is over; one from
        a moving arm (its first sample moves: a brake, then a route or an escape) is stamped
        with the state's time, as the planner node and the closed loop send it, and the
        arm has coasted on along it meanwhile. Timed from the end of the computation, such
        a trajectory was re-checked as if the arm were a latency behind its true place:
        within `TRACKING_RAD` of that sample it went unnoticed, and on the stress bench
        (S-v0.6-1-s2709-073: a last resort sent 20-45 ms after its state, the arm at
        ~1 rad/s) the re-check saw the arm meet the mover, stopped it and it was hit."""
        if event is None or event.kind != "trajectory":
            return
        tr = event.result.trajectory if event.result is not None else None
        moving = tr is not None and bool(np.any(tr.velocities[0] != 0.0))
        self._t_start = None if t is None else t + (0.0 if moving else event.latency_ms / 1e3)

    def _update(self, t: float, q_now: np.ndarray,
                obstacles: Sequence[tuple[Shape, np.ndarray]],
                perception_age_s: float = 0.0,
                qd_now: np.ndarray | None = None) -> Event | None:
        if self.state == "idle" or (self.state == "reached" and not obstacles):
            return None
        q_now = np.asarray(q_now, float)
        if self.state == "reached":
            return self._evade_at_goal(q_now, self.scene(obstacles, _age(perception_age_s)))
        timeout = self.config.perception_timeout_s
        if timeout > 0 and perception_age_s > timeout and self.state == "executing":
            return self._hold(f"obstacle data is {perception_age_s:.2f} s old "
                              f"(limit {timeout:.2f} s)")
        shapes = self.scene(obstacles, _age(perception_age_s))
        if self.risk is not None and shapes.now:
            self.last_probability = float(self.risk(q_now, shapes.now))
        if self.state == "holding":
            if self.pending_goal is not None:
                if self._pending_since is None:
                    self._pending_since = t
                elif t - self._pending_since > self.config.goal_wait_s:
                    self.stop("")
                    return Event("refused", f"goal dropped: it waited "
                                 f"{t - self._pending_since:.1f} s for obstacle data on "
                                 f"{self.config.obstacle_source}, longer than "
                                 f"goal_wait_timeout_s = {self.config.goal_wait_s:g} s; "
                                 "send it again once obstacles are published")
            if timeout > 0 and perception_age_s > timeout:
                return None
            if self.pending_goal is not None:
                return self.set_goal(q_now, self.pending_goal, obstacles, perception_age_s,
                                     qd_now)
            # escape before the retry: a failing route search takes up to the time budget,
            # and in the soak a falling sphere reached holding arms during those searches
            event = self._escape_if_threatened(q_now, shapes, qd_now)
            if event is None and self.retries.due(t, shapes):
                t0 = time.perf_counter()
                event = self._reroute(q_now, shapes, "route found again; resuming", qd_now)
                if event is None:
                    spent = time.perf_counter() - t0
                    self.stats.retry_failed_ms.append(1e3 * spent)
                    self.retries.failed(t, spent, self._failure, shapes)
                    if self._unreached_since is None:
                        self._unreached_since = t
                    event = self._rechoose_goal(t, q_now, obstacles, perception_age_s,
                                                qd_now)
            return event
        if self._stalled(t, q_now):
            return self._reroute(q_now, shapes, "the arm stopped short of the goal (the "
                                 "controller may have stopped it); re-planning from here",
                                 qd_now)
        if self._settled_at_end(q_now, qd_now):
            if np.max(np.abs(self.path[-1] - self.planner.goal_q)) > 1e-9:
                self.state = "holding"  # an escape move ended
                self.retries.reset()
                return None
            self.state = "reached"
            return Event("reached", "goal reached")
        on_path = self._advance(q_now)
        # re-check the certified path from where the arm is on it: a tracking error alone is
        # no reason to re-route (the short step back onto the path is checked too)
        remaining = np.vstack([on_path[None], self.path[self.segment + 1:]])
        timed = self._remaining(t, q_now) if shapes.moving else None
        if timed is not None and self.trajectory_source == "last resort":
            # an escape taken inside a mover's grown region: the movers re-checked by the
            # rule that chose it (the full one would brake it where holding meets the
            # mover), the static obstacles as always
            if self.planner.nominally_clear(*timed, shapes) and not \
                    self.planner.path_threatened(q_now, remaining, shapes.statics())[0]:
                return None
        if timed is None:
            threatened, why = self.planner.path_threatened(q_now, remaining, shapes)
        else:
            threatened, why = self.planner.trajectory_threatened(
                q_now, remaining, *self._then_resting(*timed), shapes)
        if not threatened:
            return None
        # following on may keep more nominal clearance from the movers than braking here:
        # then no stop is sent before the re-route, and where no route is certified the
        # arm escapes or follows on rather than brake into a mover's way
        follow_on = timed is not None and self.planner.follow_on_safer(
            q_now, qd_now, remaining, *timed, shapes)
        if self.on_threat is not None and not follow_on:
            self.on_threat(why)
        return self._reroute(q_now, shapes, why, qd_now, follow_on)

    def _remaining(self, t: float, q_now: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """The rest of the running trajectory as (times from now, states from ``q_now``):
        from the sample due now when the arm is on schedule (`TRACKING_RAD`), else from the
        sample nearest the arm at or after the last one found; None when the arm is on
        neither (the caller then checks the path against the swept obstacles)."""
        tr = self.trajectory
        if tr is None or len(tr.times) < 2:
            return None
        k = None
        if self._t_start is not None:
            i = int(np.clip(np.searchsorted(tr.times, t - self._t_start), self._sample,
                            len(tr.times) - 1))
            if np.max(np.abs(tr.positions[i] - q_now)) <= TRACKING_RAD:
                k = i
        if k is None:
            gap = np.max(np.abs(tr.positions[self._sample:] - q_now), axis=1)
            if float(gap.min()) > TRACKING_RAD:
                return None
            k = self._sample + int(np.argmin(gap))
        self._sample = k
        rest = slice(k + 1, None) if k + 1 < len(tr.times) else slice(k, None)
        times = np.concatenate([[0.0], tr.times[rest] - tr.times[k]])
        if times[-1] <= 0.0:
            times[-1] = 1e-3
        return times, np.vstack([q_now[None], tr.positions[rest]])

    def _then_resting(self, times: np.ndarray,
                      positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The rest of an escape move, then REST_HORIZON_S at rest at its end (any other
        trajectory as it is): an escape ends in a hold, certified at planning with that
        rest, and a mover that starts toward where it ends is a threat to it now, not once
        the arm holds there. S-v1-1.5-s2710-118: a ball set off toward the end of a last
        resort 0.13 s before it ended; the holding arm found it 0.08 s from contact, too
        late for any escape, and was touched."""
        if self.trajectory_source not in ("escape", "last resort"):
            return times, positions
        return then_resting(times, positions)

    def _escape_if_threatened(self, q_now: np.ndarray, shapes: Scene,
                              qd_now: np.ndarray | None = None) -> Event | None:
        """While holding, move away from an obstacle that comes within the escape distance,
        or from a mover whose predicted region will reach the arm at rest
        (`GraphPlanner.rest_contact`): evade, don't freeze."""
        if not shapes.now:
            return None
        close = self.planner.clearance(q_now, shapes.ahead) <= self.config.escape_clearance_m
        if not close and not (shapes.moving and self.planner.rest_contact(
                q_now, None, shapes) is not None):
            return None
        return self._escape(q_now, shapes, "", qd_now)

    def _escape(self, q_now: np.ndarray, shapes: Scene, why: str,
                qd_now: np.ndarray | None = None) -> Event | None:
        """A certified escape move as a trajectory event, or None when there is none. An
        arm still braking (a hold just sent) escapes from where its brake ends, the brake
        first: planned as if at rest, the move asked a moving arm to start from rest
        where it was."""
        t0 = time.perf_counter()
        result = self.planner.escape(q_now, shapes, qd_now=qd_now,
                                     started=self._update_started)
        if not result.success:
            return None
        self.stats.escapes += 1
        event = self._execute(result, 1e3 * (time.perf_counter() - t0))
        event.reason = why + result.reason
        return event

    def _evade_at_goal(self, q_now: np.ndarray, shapes: Scene) -> Event | None:
        """An arm at rest on its goal still gets out of a mover's way: when a mover's
        predicted region reaches it within the rest horizon (`GraphPlanner.rest_contact`),
        a certified escape move, after which it holds and returns to the goal once a
        route is certified again. Only movers count here: a goal may lie millimetres from
        a static object (a grasp), which is no reason to leave it. In generated G scenes a
        sphere diving onto an arm resting at its goal touched it."""
        if not shapes.moving or self.planner.rest_contact(q_now, None, shapes) is None:
            return None
        return self._escape(q_now, shapes, "a mover is predicted to reach the arm at its "
                            "goal; ")

    def _reroute(self, q_now: np.ndarray, shapes: Scene, why: str,
                 qd_now: np.ndarray | None = None, follow_on: bool = False) -> Event | None:
        """A certified route from here; failing that, with ``follow_on`` (following the
        running trajectory on keeps more nominal clearance from the movers than braking,
        `GraphPlanner.follow_on_safer`; no stop was sent) a certified escape, else on along
        the way; without it, evade or hold. On the stress bench the brake was what met a
        mover that had been at rest."""
        t0 = time.perf_counter()
        # only a holding arm's retries may search longer each time (`GraphPlanner._fallback`)
        holding = self.state == "holding"  # its retries may also leave work to the next
        result = self.planner.replan(q_now, shapes, qd_now=qd_now, escalate=holding,
                                     defer=holding)
        latency = 1e3 * (time.perf_counter() - t0)
        if not result.success:
            self._failure = result.reason
            if self.state == "holding":
                return None
            if follow_on:  # no stop was sent: a certified escape, else on along the way
                escape = self._escape(q_now, shapes, f"{why}; {result.reason}; ", qd_now)
                if escape is None:
                    self.stats.followed_on += 1
                else:
                    escape.latency_ms += latency
                return escape
            evade = self._evade(q_now, shapes, qd_now)
            if evade is not None:
                evade.latency_ms += latency
                evade.reason = f"{why}; {result.reason}; {evade.reason}"
                return evade
            return self._hold(f"{why}; {result.reason}", result, latency)
        self.stats.replans += 1
        self.stats.replan_latency_ms.append(latency)
        self.stats.replan_resumed.append(self.state == "holding")
        self._unreached_since = None
        event = self._execute(result, latency)
        event.reason = why
        return event

    def _evade(self, q_now: np.ndarray, shapes: Scene,
               qd_now: np.ndarray | None) -> Event | None:
        """Where no route is certified: None (stop here) when braking in place and resting
        is certified against the movers' predictions, else a certified escape move from
        where the arm brakes to (None when there is none: stopping is then the best left)."""
        if not shapes.moving or self.planner.rest_contact(q_now, qd_now, shapes) is None:
            return None
        return self._escape(q_now, shapes, "a mover's prediction reaches where the arm would "
                            "stop; ", qd_now)

    def _settled_at_end(self, q_now: np.ndarray, qd_now: np.ndarray | None) -> bool:
        """At the path's end and (where the velocity is known) nearly at rest. Close alone is
        not enough: a controller that brakes the arm after "reached" (stale states under load)
        left it at rest off the goal, and nothing re-plans from "reached"; still moving, it
        stays "executing", where a stall is re-planned."""
        if np.max(np.abs(q_now - self.path[-1])) > self.config.goal_tolerance_rad:
            return False
        return qd_now is None or bool(np.max(np.abs(qd_now)) <= self.config.settled_speed_rad_s)

    def _stalled(self, t: float, q_now: np.ndarray) -> bool:
        """No motion for ``stall_time_s`` while executing and away from the path's end."""
        if self._still_q is None or np.max(np.abs(q_now - self._still_q)) > 0.005:
            self._still_q, self._still_since = q_now.copy(), t
            return False
        away = np.max(np.abs(q_now - self.path[-1])) > self.config.goal_tolerance_rad
        if away and t - self._still_since > self.config.stall_time_s:
            self._still_q = None
            return True
        return False

    def _execute(self, result: PlanResult, latency: float) -> Event:
        self._still_q = None
        self.state = "executing"
        self.path = result.path
        self.segment = 0
        self.trajectory, self._t_start, self._sample = result.trajectory, None, 0
        self.trajectory_source = result.source
        return Event("trajectory", "", result, latency)

    def _hold(self, reason: str, result: PlanResult | None = None, latency: float = 0.0) -> Event:
        self.state = "holding"
        self.stats.holds += 1
        self.retries.reset()
        return Event("hold", reason, result, latency)

    def _advance(self, q_now: np.ndarray) -> np.ndarray:
        """Move to the path segment the arm is on — the nearest at or after the current one
        (the arm only moves forward along a trajectory) — and return the nearest point of
        the path on it."""
        best, best_d, best_p = self.segment, math.inf, self.path[self.segment]
        for i in range(self.segment, len(self.path) - 1):
            a, b = self.path[i], self.path[i + 1]
            ab = b - a
            s = float(np.clip((q_now - a) @ ab / max(ab @ ab, 1e-12), 0.0, 1.0))
            p = a + s * ab
            d = float(np.linalg.norm(p - q_now))
            if d < best_d - 1e-9:
                best, best_d, best_p = i, d, p
        self.segment = best
        return best_p
