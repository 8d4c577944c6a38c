"""A certified stop at every instant, the running trajectory re-checked in space and time,
and a holding arm that evades a mover instead of freezing in its way."""

from __future__ import annotations

import time
from types import SimpleNamespace

import numpy as np
import pytest
from test_space_time import AGE, _long_move  # the space-time tests' move and data age

from damon_ros.core.limits import READY, joint_limits
from damon_ros.core.robot import Robot
from damon_ros.core.shapes import Shape
from damon_ros.planning import graph_planner
from damon_ros.planning.graph_planner import (
    BRAKE_LATENCY_S,
    REST_HORIZON_S,
    STOP_MARGIN_M,
    SWERVE_BRANCH_S,
    GraphPlanner,
    PlanResult,
    Scene,
    _stop_states,
)
from damon_ros.planning.reactive import ReactivePlanner, RuntimeConfig, swept
from damon_ros.planning.space_time import Prediction, first_contact, stops_screen
from damon_ros.planning.trajectory import braking_states, stop_trajectory, time_parameterize


def test_braking_states_are_the_stop_the_runtime_sends():
    limits = joint_limits("panda")
    q0, q1 = _long_move()
    tr = time_parameterize(np.array([q0, q1]), limits, 0.9, 0.8, 0.8, dt=0.01)
    for i in (3, len(tr.times) // 4, len(tr.times) // 2):
        stop = stop_trajectory(tr.positions[i], tr.velocities[i], limits,
                               coast_s=BRAKE_LATENCY_S)
        times, states = braking_states(tr.positions[i], tr.velocities[i], limits,
                                       BRAKE_LATENCY_S)
        assert times[-1] == pytest.approx(stop.duration, abs=1e-6)
        for t, q in zip(times, states, strict=True):
            assert np.max(np.abs(stop.sample(t)[0] - q)) < 1e-5
    times, states = braking_states(q0, np.zeros(7), limits)  # at rest: the hold
    assert np.allclose(states, q0)


def test_the_compiled_stop_screen_flags_the_stops_the_python_check_refuses(fast):
    """`stops_screen` (one compiled call for all stops) against the check it screens for,
    stop by stop in Python: the braking states, `first_contact` at the stop's age with the
    stop margin, then the braking line against the statics on the fast model."""
    limits, p = joint_limits("panda"), Prediction()
    q0, q1 = _long_move()
    tr = time_parameterize(np.array([q0, q1]), limits, 0.9, 0.8, 0.8, dt=0.01)
    stops = _stop_states(tr)
    hand, _ = fast.tcp_pose(tr.sample(0.7 * tr.duration)[0])
    statics = (Shape("box", (0.08, 0.08, 0.08), hand),)  # some braking lines run into it
    tau0, margin = max(AGE, p.min_age_s), 0.01 + STOP_MARGIN_M
    seen = set()
    for ball, v in _rising_scenes(fast, tr, np.random.default_rng(11), 12):
        moving = ((ball, v),)
        expected = []
        for j, i in enumerate(stops):
            times, states = braking_states(tr.positions[i], tr.velocities[i], limits,
                                           BRAKE_LATENCY_S)
            if first_contact(fast, times, states, moving, margin, 0.02, p,
                             tau0 + tr.times[i]) is not None:
                expected.append((j, 1))
            elif not fast.segment_free(tr.positions[i], states[-1], statics, 0.0, 0.02,
                                       exact_band=False):
                expected.append((j, 2))
        flagged, j = [], 0
        while True:
            j, what = stops_screen(fast, tr, stops, j, moving, margin, 0.02, p, tau0, limits,
                                   BRAKE_LATENCY_S, statics)
            if j < 0:
                break
            flagged.append((j, what))
            j += 1
        assert flagged == expected
        seen.update("mover" if w == 1 else "static" for _, w in expected)
        if len(expected) < len(stops):
            seen.add("clear")
    assert seen == {"mover", "static", "clear"}  # each kind of answer came up


def _rising_scenes(fast: Robot, trajectory, rng: np.random.Generator, n: int):
    """Balls at 0.3-1.2 m/s rising through where the hand will be at random times of the
    trajectory, 0.05-0.4 s after it passed there, and on away from the robot (upward and
    outward: a ball that flies on into the robot leaves no goal to rest at), reported AGE
    s ago."""
    for _ in range(n):
        at = rng.uniform(0.3, 0.9) * trajectory.duration
        target, _ = fast.tcp_pose(trajectory.sample(at)[0])
        radial = np.array([target[0], target[1], 0.0]) / np.linalg.norm(target[:2])
        d = (np.cross([0.0, 0.0, 1.0], radial) * rng.uniform(-1, 1)
             + radial * rng.uniform(0, 1) + np.array([0.0, 0.0, 1.0]))
        v = rng.uniform(0.3, 1.2) * d / np.linalg.norm(d)
        delay = rng.uniform(0.05, 0.4)
        yield Shape("sphere", (0.05,), target - v * (at + delay + AGE), name="ball"), v


def test_every_published_trajectory_keeps_a_certified_stop_from_each_state(planner, fast):
    """Property, from every sample (10 ms apart, denser than the planner's checks): the
    stop from there — coast, then the full-limit brake; at the end, resting there — stays
    out of each mover's predicted region by the margin the planner certifies (λ, or the
    start margin from the movers, less the half time step its checks add). The balls
    cross the hand's way just after it passed: some trajectories are then clear while a
    stop on them, or the goal right after the arrival, is not (without the stop check
    such a trajectory is published)."""
    q0, q1 = _long_move()
    free = planner.plan(q0, q1, ())
    limits, prediction = planner.limits, planner.config.prediction
    rng = np.random.default_rng(7)
    published = 0
    for ball, v in _rising_scenes(fast, free.trajectory, rng, 80):
        scene = Scene((ball,), (swept(ball, v, 0.3),), ((ball, v),), AGE)
        result = planner.plan(q0, q1, scene)
        if not result.success:
            continue
        published += 1
        margin = planner._mover_margin(q0, scene) - 0.5 * prediction.step_m
        tr = result.trajectory
        for i in range(len(tr.times)):
            times, states = braking_states(tr.positions[i], tr.velocities[i], limits,
                                           BRAKE_LATENCY_S)
            if i == len(tr.times) - 1:  # arrived: it stays there
                times, states = np.array([0.0, REST_HORIZON_S]), states[[0, -1]]
            assert first_contact(fast, times, states, [(ball, v)], margin,
                                 planner.config.resolution, prediction,
                                 AGE + float(tr.times[i])) is None, (i, tr.times[i])
    assert published >= 2


def test_a_refusal_asked_near_a_hint_is_the_certified_stops_answer(planner, fast):
    """`_refusal` (the stops near a hint first, then the instants near it, then the rest)
    refuses exactly the trajectories that `_contact` (every instant, then every stop in
    time order, then the rest at the end) refuses, whatever the hint."""
    q0, q1 = _long_move()
    tr = planner.plan(q0, q1, ()).trajectory
    rng = np.random.default_rng(13)
    answers = set()
    for k, (ball, v) in enumerate(_rising_scenes(fast, tr, rng, 16)):
        if k % 4 == 0:  # one in four passes high above the arm
            ball = ball.moved_to(ball.position + [0.0, 0.0, 1.5])
        scene = Scene((ball,), (swept(ball, v, 0.3),), ((ball, v),), AGE)
        refused = planner._contact(tr, scene, 0.01) is not None
        for hint in (None, rng.uniform(0.0, tr.duration), tr.duration + 1.0):
            assert (planner._refusal(tr, scene, 0.01, hint) is not None) == refused
        answers.add(refused)
    assert answers == {True, False}


def _executing(planner: GraphPlanner, space_time: bool) -> ReactivePlanner:
    runtime = ReactivePlanner(planner, RuntimeConfig(space_time=space_time))
    q0, q1 = _long_move()
    event = runtime.set_goal(q0, q1, [], t=0.0)
    assert event.kind == "trajectory"
    return runtime


def test_the_running_trajectory_is_rechecked_where_each_mover_will_be(planner, fast):
    q0, _ = _long_move()
    zero = np.zeros(7)
    runtime = _executing(planner, True)
    tr = runtime.trajectory
    # one moving away beside the path: its 0.3 s sweep reaches the path, the ball never does
    mid, _ = fast.tcp_pose(tr.sample(0.5 * tr.duration)[0])
    outward = np.array([mid[0], mid[1], 0.0]) / np.linalg.norm(mid[:2])
    away = [(Shape("sphere", (0.05,), mid + np.array([0.0, 0.0, 0.12])), 1.0 * outward)]
    assert runtime.update(0.0, q0, away, qd_now=zero) is None
    assert _executing(planner, False).update(0.0, q0, away, qd_now=zero) is not None
    # one that will hit the hand late in the trajectory, far beyond the sweep now
    at = 0.8 * tr.duration
    target, _ = fast.tcp_pose(tr.sample(at)[0])
    radial = np.array([target[0], target[1], 0.0]) / np.linalg.norm(target[:2])
    diver = [(Shape("sphere", (0.05,), target + 0.3 * radial * (at + AGE)), -0.3 * radial)]
    assert _executing(planner, False).update(0.0, q0, diver, qd_now=zero) is None
    assert _executing(planner, True).update(0.0, q0, diver, qd_now=zero) is not None


def test_a_holding_arm_in_a_movers_path_evades(planner, fast):
    """A ball 0.45 m away comes at the hand at 0.8 m/s: farther than the escape distance
    (the old rule waits until it is within 5 cm, 0.5 s later), but its predicted region
    reaches the arm at rest within the rest horizon. The arm moves, and where it goes it
    stays clear of the ball's true motion."""
    q = READY.copy()
    hand, _ = fast.tcp_pose(q)
    v = np.array([0.0, -0.8, 0.0])
    ball = Shape("sphere", (0.05,), hand - v / 0.8 * 0.45, name="ball")
    for space_time, evades in ((False, False), (True, True)):
        runtime = ReactivePlanner(planner, RuntimeConfig(space_time=space_time))
        runtime.state = "holding"
        planner.goal_q = None  # nothing to resume toward: only the escape can move it
        event = runtime.update(0.0, q, [(ball, v)], qd_now=np.zeros(7))
        assert (event is not None and event.kind == "trajectory") == evades
    tr = event.result.trajectory
    assert "escaping" in event.reason
    assert _keeps_clear(fast, tr, ball, v)
    times = np.concatenate([tr.times, tr.duration + np.linspace(0.01, 1.0, 50)])
    states = np.vstack([tr.positions, np.repeat(tr.positions[-1:], 50, axis=0)])
    assert first_contact(fast, times, states, [(ball, v)], 0.0, 0.02, Prediction(), AGE) is None


def test_the_goal_is_reached_only_by_an_arm_at_rest_on_it(planner):
    """Passing through the goal tolerance at speed is not "reached": a controller that then
    brakes (stale joint states under load did) leaves the arm at rest off the goal, and the
    stall rule re-plans from there; at rest on the goal, it is reached."""
    q0, q1 = _long_move()
    runtime = ReactivePlanner(planner, RuntimeConfig())
    assert runtime.set_goal(q0, q1, [], t=0.0).kind == "trajectory"
    moving = np.full(7, 0.2)
    assert runtime.update(9.0, q1 - 0.005, [], qd_now=moving) is None
    assert runtime.state == "executing"
    braked = q1 - 0.04  # where the brake left it
    stall = runtime.config.stall_time_s
    events = [runtime.update(9.1 + k * stall / 4, braked, [], qd_now=np.zeros(7))
              for k in range(6)]
    replans = [e for e in events if e is not None]
    assert len(replans) == 1 and replans[0].kind == "trajectory", events
    assert "stopped short of the goal" in replans[0].reason
    assert runtime.update(20.0, q1, [], qd_now=np.zeros(7)).kind == "reached"


def test_an_arm_resting_on_its_goal_gets_out_of_a_movers_way_and_returns(planner, fast):
    """The goal reached, a ball comes at the hand: the arm at its goal evades like a
    holding one (a sphere diving onto an arm at rest on its goal touched it in generated
    G scenes), then holds and plans back to the goal. A ball going elsewhere, or a static
    object beside the goal, does not move it."""
    q0, q1 = _long_move()
    runtime = ReactivePlanner(planner, RuntimeConfig())
    assert runtime.set_goal(q0, q1, [], t=0.0).kind == "trajectory"
    assert runtime.update(9.0, q1, [], qd_now=np.zeros(7)).kind == "reached"
    hand, _ = fast.tcp_pose(q1)
    radial = np.array([hand[0], hand[1], 0.0]) / np.linalg.norm(hand[:2])
    across = np.array([-radial[1], radial[0], 0.0])  # it crosses the hand's place
    v = -0.8 * across
    ball = Shape("sphere", (0.05,), hand + 0.45 * across, name="ball")
    elsewhere = (ball.moved_to(hand + 0.45 * across + np.array([0.0, 0.0, 0.5])), v)
    beside = (Shape("box", (0.05, 0.05, 0.05), hand + np.array([0.0, 0.0, -0.12])), np.zeros(3))
    assert runtime.update(9.1, q1, [elsewhere, beside], qd_now=np.zeros(7)) is None
    assert runtime.state == "reached"
    event = runtime.update(9.2, q1, [(ball, v), beside], qd_now=np.zeros(7))
    assert event is not None and event.kind == "trajectory", event
    assert "reach the arm at its goal" in event.reason and "escaping" in event.reason
    tr = event.result.trajectory
    times = np.concatenate([tr.times, tr.duration + np.linspace(0.01, 1.0, 50)])
    states = np.vstack([tr.positions, np.repeat(tr.positions[-1:], 50, axis=0)])
    assert first_contact(fast, times, states, [(ball, v)], 0.0, 0.02, Prediction(), AGE) is None
    # at the escape's end it holds, and plans back to the goal once the ball is gone
    assert runtime.update(9.2 + tr.duration, tr.positions[-1], [beside],
                          qd_now=np.zeros(7)) is None
    assert runtime.state == "holding"
    back = runtime.update(20.0, tr.positions[-1], [beside], qd_now=np.zeros(7))
    assert back is not None and back.kind == "trajectory"
    assert np.allclose(back.result.path[-1], q1)


class _NoRoute(GraphPlanner):
    """The shipped planner with no route and no escape to be found: what is left is to
    stop or to follow on."""

    def replan(self, q_now, obstacles=(), qd_now=None, escalate=True, defer=False):
        return PlanResult(False, "no route (test)")

    def escape(self, q_now, obstacles, candidates=96, rng=None, qd_now=None, started=None):
        return PlanResult(False, "no escape (test)")


def test_without_a_route_the_arm_follows_on_when_braking_would_meet_the_mover(planner, fast):
    """The arm at speed, a ball coming up behind the hand along its way: nothing is
    certified any more, and braking here would let the ball catch the hand, while the
    hand, followed on, keeps ahead of it. No stop is sent; the arm follows on. A ball
    waiting where the hand is going makes braking the better choice: the stop goes out."""
    blocked = _NoRoute(planner.graph, fast, planner.limits, planner.config)
    blocked.warm_up()
    q0, q1 = _long_move()
    stops: list[str] = []
    runtime = ReactivePlanner(blocked, RuntimeConfig(), on_threat=stops.append)
    assert runtime.set_goal(q0, q1, [], t=0.0).kind == "trajectory"
    tr = runtime.trajectory
    t_k = 0.4 * tr.duration  # cruising
    q_k, qd_k = tr.sample(t_k)[:2]
    hand, _ = fast.tcp_pose(q_k)
    ahead, _ = fast.tcp_pose(tr.sample(t_k + 0.01)[0])
    along = (ahead - hand) / np.linalg.norm(ahead - hand)
    behind = 0.6 * along  # from behind, slower than the hand: it reaches the hand's place
    chaser = [(Shape("sphere", (0.05,), hand - behind * (AGE + 0.35), name="ball"), behind)]
    now = runtime._t_start + t_k
    assert runtime.update(now, q_k, chaser, perception_age_s=AGE, qd_now=qd_k) is None
    assert stops == [] and runtime.stats.followed_on == 1 and runtime.state == "executing"
    # the same ball waiting where the hand will be in 0.35 s
    runtime = ReactivePlanner(blocked, RuntimeConfig(), on_threat=stops.append)
    assert runtime.set_goal(q0, q1, [], t=0.0).kind == "trajectory"
    later, _ = fast.tcp_pose(tr.sample(t_k + 0.35)[0])
    waiting = [(Shape("sphere", (0.05,), later + 0.06 * along, name="ball"), -0.1 * along)]
    now = runtime._t_start + t_k
    event = runtime.update(now, q_k, waiting, perception_age_s=AGE, qd_now=qd_k)
    assert stops and event is not None and event.kind == "hold"
    assert runtime.stats.followed_on == 0


def test_an_escape_is_timed_from_when_the_arm_state_was_measured(planner, fast):
    """The escape of a moving arm is stamped with the measured state's time; the runtime
    hands the planner that time (`escape(started=...)`: the update's start less the
    state's age, which the planner node knows) so that a swerve turns after it."""
    started_at = []

    class _Recording(_NoRoute):
        def escape(self, q_now, obstacles, candidates=96, rng=None, qd_now=None,
                   started=None):
            started_at.append(started)
            return super().escape(q_now, obstacles, candidates, rng, qd_now)

    blocked = _Recording(planner.graph, fast, planner.limits, planner.config)
    q0, q1 = _long_move()
    runtime = ReactivePlanner(blocked, RuntimeConfig())
    assert runtime.set_goal(q0, q1, [], t=0.0).kind == "trajectory"
    tr = runtime.trajectory
    t_k = 0.4 * tr.duration
    q_k, qd_k = tr.sample(t_k)[:2]
    hand, _ = fast.tcp_pose(q_k)
    ahead, _ = fast.tcp_pose(tr.sample(t_k + 0.01)[0])
    behind = 0.6 * (ahead - hand) / np.linalg.norm(ahead - hand)
    chaser = [(Shape("sphere", (0.05,), hand - behind * (AGE + 0.35), name="ball"), behind)]
    before = time.perf_counter()
    runtime.update(runtime._t_start + t_k, q_k, chaser, perception_age_s=AGE, qd_now=qd_k,
                   state_age_s=0.2)
    after = time.perf_counter()
    assert started_at and before - 0.2 <= started_at[0] <= after - 0.2


def _ball_below(fast: Robot, q: np.ndarray, gap: float) -> Shape:
    """A 5 cm ball straight below the hand, ``gap`` m from the arm (fast model)."""
    hand, _ = fast.tcp_pose(q)
    lo, hi = 0.0, 0.5  # depth below the hand: bisect on the clearance
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        ball = Shape("sphere", (0.05,), hand - np.array([0.0, 0.0, mid]), name="ball")
        lo, hi = (lo, mid) if float(fast.distances(q[None], [ball])[0]) > gap else (mid, hi)
    return Shape("sphere", (0.05,), hand - np.array([0.0, 0.0, hi]), name="ball")


@pytest.mark.parametrize("gap", [0.04, 0.015])
def test_a_holding_arm_above_a_ball_that_starts_rising_gets_out(planner, fast, gap):
    """The 10-minute soak's contacts: a ball at rest under a held hand rises at 0.13 m/s.
    Holding meets it; so does the first stop of every escape (it rests where the arm is),
    which the full stop rule refused: no escape, the ball rose through the hand. An
    escape's stops need only be no worse than holding; 1.5 cm away, inside the ball's grown
    region, only the last resort (clear of its nominal path) is left. Either way the arm
    moves and keeps clear of the ball's true motion over the move and a second after."""
    q = READY.copy()
    v = np.array([0.0, 0.0, 0.133])
    ball = _ball_below(fast, q, gap)
    scene = Scene((ball,), (swept(ball, v, 0.3),), ((ball, v),), AGE)
    assert planner.rest_contact(q, None, scene) is not None  # holding is not safe
    result = planner.escape(q, scene)
    assert result.success, result.reason
    assert ("last resort" in result.reason) == (gap < 0.02)
    assert _keeps_clear(fast, result.trajectory, ball, v)


def _keeps_clear(fast, tr, ball: Shape, v: np.ndarray) -> bool:
    """Whether the trajectory, then a second at rest at its end, keeps clear of the ball's
    true motion (velocity ``v``, reported ``AGE`` late)."""
    times = np.concatenate([tr.times, tr.duration + np.linspace(0.01, 1.0, 50)])
    states = np.vstack([tr.positions, np.repeat(tr.positions[-1:], 50, axis=0)])
    gaps = [float(fast.distances(s[None], [ball.moved_to(ball.position + v * (t + AGE))])[0])
            for t, s in zip(times, states, strict=True)]
    return min(gaps) > 0.0


def test_a_running_last_resort_escape_is_not_braked_where_holding_meets_the_mover(planner, fast):
    """The held arm 1.5 cm above the rising ball takes the last-resort escape; the next
    update, on schedule along it, lets it run: re-checked by the full rule it is inside the
    ball's grown region, and braking there is what holding would have been."""
    q = READY.copy()
    v = np.array([0.0, 0.0, 0.133])
    ball = _ball_below(fast, q, 0.015)
    runtime = ReactivePlanner(planner, RuntimeConfig())
    runtime.state = "holding"
    planner.goal_q = None  # nothing to resume toward: only the escape can move it
    event = runtime.update(0.0, q, [(ball, v)], qd_now=np.zeros(7))
    assert event is not None and event.kind == "trajectory", event
    assert event.result.source == "last resort" and "last resort" in event.reason
    tr = event.result.trajectory
    runtime._t_start = 0.0  # as if decided at once: the check, not this machine's latency
    t = 0.005  # (from 0.01 on the arm is out of the grown region: nothing to flag)
    at, qd = tr.sample(t)[:2]
    later = ball.moved_to(ball.position + v * t)
    assert runtime.update(t, at, [(later, v)], qd_now=qd) is None
    assert runtime.state == "executing"
    # a static object that appears where the escape goes is still a threat to it
    end, _ = fast.tcp_pose(tr.positions[-1])
    box = Shape("box", (0.05, 0.05, 0.05), end, name="box")
    event = runtime.update(t + 0.01, at, [(later, v), (box, np.zeros(3))], qd_now=qd)
    assert event is not None, "the last resort ran on into a static box"


def _brake_refused(fast, monkeypatch, refuse: dict, certified: list):
    """An arm at READY moving at 0.3 rad/s on joint 1, a ball 0.3 m ahead of the hand
    coming at 1.2 m/s, and `_Query.segment_certified` refusing the brake (from the measured
    state) where ``refuse`` says: "with movers" (the movers' grown regions) or "statics".
    Each other segment certified is appended to ``certified``: (start, end)."""
    q = READY.copy()
    p, _ = fast.tcp_pose(q)
    v = np.array([-1.2, 0.0, 0.0])
    ball = Shape("sphere", (0.05,), p + np.array([0.3, 0.0, 0.0]), name="ball")
    scene = Scene((ball,), (swept(ball, v, 0.3),), ((ball, v),), AGE)
    qd = np.zeros(7)
    qd[0] = 0.3
    real = graph_planner._Query.segment_certified

    def brake_refused(self, a, b, first=False):
        if np.array_equal(a, q) and first:  # the brake: from the measured state
            if self.scene.moving and refuse["with movers"] or refuse["statics"]:
                return False
        ok = real(self, a, b, first=first)
        if ok:
            certified.append((a, b))
        return ok

    monkeypatch.setattr(graph_planner._Query, "segment_certified", brake_refused)
    return q, qd, scene, ball, v


def test_a_brake_refused_only_for_a_movers_grown_region_still_leaves_the_last_resort(
        planner, fast, monkeypatch):
    """A moving arm whose brake is refused escaped nowhere: every escape starts with that
    brake. Refused only for a mover's grown region (the arm is already inside it), the
    brake still leaves the last resort, judged by the movers' nominal paths (it keeps clear
    of the ball's true motion here); refused for a static obstacle, it leaves nothing. (A
    two-camera stress run and S-v1-1.5-s1205-000: the arm, on a last-resort escape, was
    refused every move for its brake, held, and was hit.)"""
    refuse = {"with movers": True, "statics": False}
    q, qd, scene, ball, v = _brake_refused(fast, monkeypatch, refuse, [])
    result = planner.escape(q, scene, qd_now=qd)
    assert result.success and result.source == "last resort", result.reason
    assert _keeps_clear(fast, result.trajectory, ball, v)
    refuse["statics"] = True
    result = planner.escape(q, scene, qd_now=qd)
    assert not result.success and "braking" in result.reason


def test_after_a_refused_brake_the_first_last_resort_is_taken_at_once(planner, fast,
                                                                       monkeypatch):
    """With the brake refused no escape can be certified, so the clearest candidate that
    the last resort accepts is taken as soon as it is found: no candidate is certified
    after it. (The arm is moving toward a mover that has just started; in one stress scene,
    S-v0.6-1-s1606-044, whether it touched turned on this reaction's milliseconds.)"""
    certified = []
    q, qd, scene, _, _ = _brake_refused(fast, monkeypatch,
                                        {"with movers": True, "statics": False}, certified)
    result = planner.escape(q, scene, qd_now=qd)
    assert result.success and result.source == "last resort", result.reason
    moves = [(a, b) for a, b in certified if not np.array_equal(a, q)]
    assert moves and np.array_equal(moves[-1][1], result.path[-1])


def _diving_ball_state():
    """G-s2607-030 (generated, seed 2607) 45 ms after its ball (5.8 cm, 0.31 m/s) started
    to dive: (q, qd, scene, ball, v) with the arm at 2.2 rad/s beside a pole."""
    q = np.array([0.23532, 0.14172, -0.07497, -1.87085, -0.12317, 2.12094, 1.05975])
    qd = np.array([0.24322, 0.34264, 0.82347, 0.0198, 0.07364, -0.08075, 2.20228])
    pole = Shape("cylinder", (0.0539, 0.2118), np.array([0.5746, 0.0357, 0.2014]),
                 np.array([0.53521, 0.0, 0.0, 0.84472]), name="pole")
    ball = Shape("sphere", (0.0578,), np.array([0.60378, 0.23424, 0.72329]), name="ball")
    v = np.array([-0.07442, -0.18962, -0.2322])
    return q, qd, Scene((pole, ball), (pole, swept(ball, v, 0.3)), ((ball, v),), 0.0), ball, v


def test_a_fast_arm_whose_every_stop_meets_a_diving_ball_turns_away_while_braking(
        planner, fast, monkeypatch):
    """G-s2607-030: the arm brakes into the ball's way, and every brake-then-move escape
    passes through it. The last resort is then a swerve: the stop already sent, followed
    for `SWERVE_BRANCH_S`, then a turn to a clearer state without stopping first, clear of
    the ball's true motion. (Before, the arm found no escape, held where it stopped, and
    was hit 0.23 s later.) The turn as on a machine that computes it within the stop's
    coast: how much later a slower computation turns is the next test's."""
    monkeypatch.setattr(graph_planner, "SWERVE_LATE_FACTOR", 0.0)
    q, qd, scene, ball, v = _diving_ball_state()
    result = planner.escape(q, scene, qd_now=qd)
    assert result.success and result.source == "last resort", result.reason
    tr, stop = result.trajectory, planner.stop_trajectory(q, qd)
    branch = int(np.searchsorted(stop.times, SWERVE_BRANCH_S - 1e-9))
    assert np.allclose(tr.positions[:branch + 1], stop.positions[:branch + 1])
    assert np.allclose(tr.velocities[:branch + 1], stop.velocities[:branch + 1])
    # it turns: it leaves the line along qd that every brake stays on
    off_line = tr.positions - q - np.outer((tr.positions - q) @ qd / (qd @ qd), qd)
    assert np.max(np.abs(off_line)) > 0.05
    assert np.all(np.abs(tr.velocities) <= planner.limits.velocity + 1e-9)
    assert np.all(np.abs(tr.accelerations) <= planner.limits.acceleration + 1e-6)
    assert np.array_equal(tr.velocities[-1], np.zeros(7))
    assert np.allclose(result.path[-1], tr.positions[-1])
    assert _keeps_clear(fast, tr, ball, v)


def test_a_swerve_turns_only_after_its_computation_has_reached_the_controller(
        planner, fast, monkeypatch):
    """A swerve is stamped with the measured state's time and joins the stop already sent:
    one computed for longer than the stop's coast must turn later, where the arm is by
    then (S-v0.6-1-s2709-073: an escape of 35-82 ms on a loaded machine turned 0.03 s
    after the state, the arm lagged it, its re-check failed, it stopped and was hit). A
    swerve found after its own turn is searched once more, turning later. The planner's
    clock is the test's, so that the machine's load does not set the times."""
    clock = SimpleNamespace(now=100.0)
    clock.perf_counter = lambda: clock.now
    monkeypatch.setattr(graph_planner, "time", clock)
    assert GraphPlanner._swerve_branch(clock.now) == SWERVE_BRANCH_S
    assert GraphPlanner._swerve_branch(clock.now - 0.1) == pytest.approx(
        graph_planner.SWERVE_LATE_FACTOR * 0.1)
    q, qd, scene, ball, v = _diving_ball_state()
    branches = []
    search = GraphPlanner._swerve_from

    def slow_search(self, brake, branch_s, *args):
        branches.append(branch_s)
        clock.now += 0.05  # each search ends 50 ms later: the first after its own turn
        return search(self, brake, branch_s, *args)

    monkeypatch.setattr(GraphPlanner, "_swerve_from", slow_search)
    result = planner.escape(q, scene, qd_now=qd)
    assert result.success and result.source == "last resort", result.reason
    assert branches == [SWERVE_BRANCH_S, pytest.approx(graph_planner.SWERVE_LATE_FACTOR
                                                       * 0.05)]
    stop, tr = planner.stop_trajectory(q, qd), result.trajectory
    kept = int(np.searchsorted(stop.times, branches[1] - 1e-9))
    assert np.allclose(tr.positions[:kept + 1], stop.positions[:kept + 1])
    assert not np.allclose(tr.positions[kept + 1], stop.positions[kept + 1])
    assert _keeps_clear(fast, tr, ball, v)


def test_a_trajectory_from_a_moving_arm_is_rechecked_on_the_schedule_it_was_stamped_with(
        planner):
    """One whose first sample moves (a brake, then a route or an escape) goes out stamped
    with the measured state's time and the arm coasts on along it while it is computed:
    its re-check takes the rest of it from where it is due at that stamp. Timed from the
    end of the computation (40 ms here), an arm at 0.6 rad/s was ~20 mrad ahead of the
    sample taken for it, within `TRACKING_RAD`, and the rest was checked 40 ms late. A
    trajectory from an arm at rest starts when its computation is over."""
    runtime = ReactivePlanner(planner, RuntimeConfig())
    q, qd = READY.copy(), np.zeros(7)
    qd[0] = 0.6
    brake = planner.stop_trajectory(q, qd)
    route = time_parameterize(np.array([READY, READY + 0.3]), joint_limits("panda"))
    for trajectory, moving in ((brake, True), (route, False)):
        result = PlanResult(True, "", trajectory.positions[[0, -1]], trajectory)
        runtime.path = result.path
        event = runtime._execute(result, 40.0)
        runtime._started(event, 1.0)
        due = 0.045 if moving else 0.005  # trajectory time at t = 1.045 (between samples)
        q_now = trajectory.sample(due)[0]
        times, states = runtime._remaining(1.045, q_now)
        k = int(np.searchsorted(trajectory.times, due))  # the sample due next
        assert np.allclose(states[1], trajectory.positions[k + 1])
        assert times[1] == pytest.approx(trajectory.times[k + 1] - trajectory.times[k])


def test_a_mover_heading_for_where_an_escape_ends_is_a_threat_to_the_escape(planner, fast):
    """An escape ends in a hold, certified at planning with REST_HORIZON_S at rest at its
    end. A ball that sets off toward that end while the escape runs, and gets there only
    after it, is a threat now: the re-check of the running escape takes the rest at its end
    too, instead of leaving the ball to the hold (found 0.08 s before contact on the stress
    bench, too late for any escape)."""
    q = READY.copy()
    hand, _ = fast.tcp_pose(q)
    v = np.array([0.0, -0.8, 0.0])
    ball = Shape("sphere", (0.05,), hand - v / 0.8 * 0.45, name="ball")
    runtime = ReactivePlanner(planner, RuntimeConfig())
    runtime.state = "holding"
    planner.goal_q = None  # nothing to resume toward: only the escape can move it
    event = runtime.update(0.0, q, [(ball, v)], qd_now=np.zeros(7))
    assert event is not None and event.kind == "trajectory" and "escaping" in event.reason
    tr = event.result.trajectory
    runtime._t_start = 0.0  # as if decided at once: the check, not this machine's latency
    t = 0.005
    at, qd = tr.sample(t)[:2]
    end, _ = fast.tcp_pose(tr.positions[-1])
    up = np.array([0.0, 0.0, 1.0])  # a second ball falls onto where the hand will rest
    other = Shape("sphere", (0.04,), end + up * (tr.duration + 0.4 - t), name="other")
    obstacles = [(ball.moved_to(ball.position + v * t), v), (other, -up)]
    timed = runtime._remaining(t, at)
    remaining = np.vstack([at[None], runtime.path[runtime.segment + 1:]])
    assert not planner.trajectory_threatened(at, remaining, *timed,
                                             runtime.scene(obstacles, 0.0))[0]
    event = runtime.update(t, at, obstacles, qd_now=qd)
    assert event is not None and "other is predicted" in event.reason, event


def test_an_arm_inside_a_fast_movers_sweep_still_finds_an_escape(planner, fast):
    """A ball 0.3 m from the hand comes at it at 1-1.3 m/s: its region swept over the
    prediction horizon covers every escape candidate within reach. Ranked by that sweep,
    none was tried (the stress bench: a holding arm found no escape, last resort included,
    in ten tries, and was hit); ranked by where the ball is predicted, one is found, and
    it keeps clear of the ball's true motion."""
    q = READY.copy()
    hand, _ = fast.tcp_pose(q)
    runtime = ReactivePlanner(planner, RuntimeConfig())
    for speed in (1.0, 1.3):
        v = np.array([speed, 0.0, 0.0])
        ball = Shape("sphere", (0.04,), hand - np.array([0.3, 0.0, 0.0]), name="ball")
        scene = runtime.scene([(ball, v)], AGE)
        pool, _, _ = planner._escape_pool(q, scene, 96, np.random.default_rng(0))
        assert float(np.max(fast.distances(pool, scene.ahead))) < planner.config.margin + 0.01
        planner.goal_q = None
        result = planner.escape(q, scene)
        assert result.success, result.reason
        assert _keeps_clear(fast, result.trajectory, ball, v)
