"""Space-time certification: a timed trajectory against where each mover will be."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from damon_ros.core.limits import READY, joint_limits
from damon_ros.core.robot import Robot
from damon_ros.core.shapes import Shape
from damon_ros.planning import graph_planner
from damon_ros.planning.graph_planner import Scene
from damon_ros.planning.reactive import ReactivePlanner, RuntimeConfig, swept
from damon_ros.planning.space_time import (
    Contact,
    Prediction,
    check_instants,
    first_contact,
    least_distance,
    refused_at,
)
from damon_ros.planning.trajectory import time_parameterize

AGE = 0.033
HORIZON = RuntimeConfig().prediction_horizon_s  # the bench's fixed sweep, 0.3 s


def _long_move():
    """READY to READY with joint 1 turned by 2.2 rad: one long straight segment (> 1 s)."""
    goal = READY.copy()
    goal[0] += 2.2
    return READY.copy(), goal


def _diver(fast: Robot, trajectory, at: float, speed: float = 0.3) -> tuple[Shape, np.ndarray]:
    """A ball coming horizontally toward the base onto where the hand will be ``at`` s into
    the trajectory, reported ``AGE`` s ago: until then it is farther out than any part of
    the turning arm reaches."""
    target, _ = fast.tcp_pose(trajectory.sample(at)[0])
    radial = np.array([target[0], target[1], 0.0]) / np.linalg.norm(target[:2])
    v = -speed * radial
    return Shape("sphere", (0.05,), target - v * (at + AGE), name="diver"), v


def _true_clearance(robot: Robot, trajectory, ball: Shape, v: np.ndarray) -> float:
    """Least distance of the executed trajectory to the ball where it really is."""
    return min(float(robot.distances(q[None], [ball.moved_to(ball.position + v * (t + AGE))])[0])
               for t, q in zip(trajectory.times, trajectory.positions, strict=True))


def test_a_mover_reaching_a_long_segment_after_the_horizon_is_caught_in_time(fast):
    q0, q1 = _long_move()
    tr = time_parameterize(np.array([q0, q1]), joint_limits("panda"), 0.9, 0.8, 0.8, dt=0.01)
    assert tr.duration > 1.0
    at = 0.8 * tr.duration
    ball, v = _diver(fast, tr, at)
    # today's rule: the segment is free of the ball now and swept over the horizon
    for shape in (ball, swept(ball, v, HORIZON)):
        assert fast.segment_free(q0, q1, [shape], margin=0.01, resolution=0.02)
    assert _true_clearance(fast, tr, ball, v) < 0.0  # ... yet the arm would be hit
    contact = first_contact(fast, tr.times, tr.positions, [(ball, v)], 0.01, 0.02,
                            Prediction(), AGE)
    assert contact is not None and HORIZON < contact.time_s <= at + 0.05
    assert "diver" in contact.describe()
    # the same ball arriving after the arm has passed is no reason to refuse
    late, _ = _diver(fast, tr, tr.duration + 1.5)
    assert first_contact(fast, tr.times, tr.positions, [(late, v)], 0.01, 0.02, Prediction(),
                         AGE) is None
    # the exact meshes give the same verdicts
    mesh = Robot("mesh")
    assert first_contact(mesh, tr.times, tr.positions, [(ball, v)], 0.01, 0.02, Prediction(),
                         AGE) is not None


def test_the_planner_refuses_or_reroutes_a_trajectory_a_mover_will_cross(planner, fast):
    q0, q1 = _long_move()
    today = planner.plan(q0, q1, Scene((), ()))
    assert today.success, today.reason
    ball, v = _diver(fast, today.trajectory, 0.8 * today.trajectory.duration)
    h = HORIZON
    static_picture = Scene((ball,), (swept(ball, v, h),))
    blind = planner.plan(q0, q1, static_picture)
    assert blind.success and _true_clearance(fast, blind.trajectory, ball, v) < 0.0
    in_time = planner.plan(q0, q1, Scene((ball,), (swept(ball, v, h),), ((ball, v),), AGE))
    if in_time.success:  # re-routed: it keeps clear of where the ball really goes
        assert _true_clearance(fast, in_time.trajectory, ball, v) > 0.0
    else:
        assert "space and time" in in_time.reason


def test_a_scene_without_movers_is_not_checked_in_time(planner, monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("space-time check ran for a static scene")

    monkeypatch.setattr(graph_planner, "first_contact", refuse)
    q0, q1 = _long_move()
    box = Shape("box", (0.1, 0.1, 0.1), np.array([-0.5, -0.5, 0.3]))
    assert planner.plan(q0, q1, Scene((box,), (box,))).success


def test_only_moving_obstacles_reach_the_space_time_check(planner):
    runtime = ReactivePlanner(planner)
    box = Shape("box", (0.1, 0.1, 0.1), np.array([0.5, 0.0, 0.3]))
    ball = Shape("sphere", (0.05,), np.array([0.5, 0.3, 0.3]))
    scene = runtime.scene([(box, np.array([0.02, 0.0, 0.0])), (ball, np.array([0.0, 0.4, 0]))],
                          age_s=0.05)
    assert [s.name for s, _ in scene.moving] == [ball.name] and len(scene.moving) == 1
    assert scene.moving[0][0] is ball and scene.age_s == 0.05


def test_check_instants_keep_both_resolutions(fast):
    q0, q1 = _long_move()
    tr = time_parameterize(np.array([q0, q1]), joint_limits("panda"), 1.0, 1.0, 1.0, dt=0.05)
    for rate in (0.1, 2.0):
        t, q = check_instants(tr.times, tr.positions, 0.02, rate, 0.01)
        assert t[0] == 0.0 and t[-1] == tr.duration
        assert np.max(np.abs(np.diff(q, axis=0))) <= 0.02 + 1e-12
        assert np.max(np.diff(t)) * rate <= 0.01 + 1e-12
        # states are on the trajectory's own samples or between them
        assert np.allclose(q, [np.array([np.interp(ti, tr.times, tr.positions[:, j])
                                         for j in range(7)]) for ti in t])


def _sphere_at_distance(fast: Robot, states: np.ndarray, centre: np.ndarray,
                        distance: float, name: str) -> Shape:
    """A sphere at ``centre`` sized so the closest of ``states`` is ``distance`` from it."""
    probe = Shape("sphere", (0.01,), centre)
    d = float(fast.distances(states, [probe]).min())
    return Shape("sphere", (0.01 + d - distance,), centre, name=name)


def test_the_relaxed_start_margin_is_only_for_what_is_already_close(planner, fast):
    """Something within λ of the start relaxes the first segment's margin for itself only:
    a box the segment passes later keeps the full λ (it did not, and a direct route grazed
    a static box 2 mm deep on the meshes beside a mover's swept shape)."""
    q0, q1 = _long_move()
    states = q0 + np.linspace(0, 1, 111)[:, None] * (q1 - q0)
    tcp0, _ = fast.tcp_pose(q0)
    mid, _ = fast.tcp_pose(states[55])
    ahead = fast.tcp_pose(states[1])[0] - tcp0
    behind = tcp0 - 0.15 * ahead / np.linalg.norm(ahead)  # the hand moves away from it
    near = _sphere_at_distance(fast, q0[None], behind, 0.004, "near")
    relaxed, full = planner._start_margin(q0, (near,)), planner.config.margin
    assert relaxed < full
    far = _sphere_at_distance(fast, states, mid + 0.25 * np.array([mid[0], mid[1], 0.0])
                              / np.linalg.norm(mid[:2]), 0.5 * (relaxed + full), "far")
    assert fast.distances(q0[None], [far])[0] > 0.1  # far from the start, close later
    scene = Scene((near, far), (near, far))
    query = graph_planner._Query(planner, q0, q1, scene)
    assert query.start_margin == relaxed and query.start_near == (near,)
    # one relaxed margin for both would certify the segment closer than λ to the far one
    # (on the fast model alone: its refusals in the contact band go to the meshes)
    assert planner.segment_free(q0, q1, (near, far), relaxed, exact=False)
    assert not planner.segment_free(q0, q1, (far,), full, exact=False)
    assert not query.segment_certified(q0, q1, first=True, band=False)
    # the exact meshes still have their say, with λ for the far one too
    assert query.segment_certified(q0, q1, first=True) == (
        planner.segment_free(q0, q1, (near,), relaxed)
        and planner.segment_free(q0, q1, (far,), full))


def test_an_arm_at_rest_waits_for_a_falling_ball_to_pass(planner, fast, monkeypatch):
    """Re-timed rather than refused: the ball falls through the hand's way three quarters
    along it; starting later, the arm passes above it (the wait is checked as well). A
    well-measured ball (small velocity error): with the default growth its region, falling
    on past the table top, grazes the robot's own base however long the arm waits."""
    monkeypatch.setattr(planner, "config", replace(planner.config, prediction=Prediction(
        velocity_sigma_m_s=0.01, velocity_sigma_rel=0.02)))
    q0, q1 = _long_move()
    today = planner.plan(q0, q1, Scene((), ()))
    tr = today.trajectory
    target, _ = fast.tcp_pose(tr.sample(0.75 * tr.duration)[0])
    v = np.array([0.0, 0.0, -1.0])
    ball = Shape("sphere", (0.04,), target - v * (0.75 * tr.duration + AGE), name="falling")
    assert _true_clearance(fast, tr, ball, v) < 0.0  # on time, the arm meets it
    result = planner.plan(q0, q1, Scene((ball,), (swept(ball, v, HORIZON),), ((ball, v),),
                                        AGE))
    assert result.success, result.reason
    waited = result.trajectory
    assert waited.duration > tr.duration + 0.1
    still = waited.times <= 0.19
    assert np.allclose(waited.positions[still], q0) and np.allclose(waited.positions[-1], q1)
    assert _true_clearance(fast, waited, ball, v) > 0.0


def test_a_refusal_asked_near_a_hint_answers_as_the_first_contact(fast):
    """`refused_at` (instants near the hint first, no contact described) says whether
    `first_contact` finds one, for any hint; the time it gives is never before the first."""
    q0, q1 = _long_move()
    tr = time_parameterize(np.array([q0, q1]), joint_limits("panda"), 1.0, 1.0, 1.0)
    rng = np.random.default_rng(2)
    answers = set()
    for k in range(10):
        ball, v = _diver(fast, tr, rng.uniform(0.2, 0.9) * tr.duration, rng.uniform(0.2, 1.0))
        ball = ball.moved_to(ball.position + [0.0, 0.0, 0.8 * (k % 2)])  # every other misses
        first = first_contact(fast, tr.times, tr.positions, [(ball, v)], 0.01, 0.02,
                              Prediction(), AGE)
        for hint in (None, 0.0, rng.uniform(0.0, tr.duration), 5.0):
            t = refused_at(fast, tr.times, tr.positions, ((ball, v),), 0.01, 0.02, Prediction(),
                           AGE, hint)
            assert (t is None) == (first is None)
            assert t is None or t >= first.time_s
        answers.add(first is None)
    assert answers == {True, False}


def test_a_search_around_a_region_decides_every_edge_as_a_fresh_one(planner, fast):
    """The search around a mover's predicted region takes over the first search's edge
    decisions (`_Query._inherit`): for graph edges and the start's and goal's links alike,
    with a region far from the start and one closer than anything was (the start margin
    drops: links the first search refused may pass now), every answer is the one a fresh
    query with all the obstacles gives."""
    q0, q1 = _long_move()
    states = q0 + np.linspace(0, 1, 111)[:, None] * (q1 - q0)
    tcp0, _ = fast.tcp_pose(q0)
    ahead = fast.tcp_pose(states[1])[0] - tcp0
    ahead /= np.linalg.norm(ahead)
    side = np.cross(ahead, [0.0, 0.0, 1.0])
    near = _sphere_at_distance(fast, q0[None], tcp0 + 0.15 * side / np.linalg.norm(side),
                               0.012, "near")
    box = Shape("box", (0.2, 0.2, 0.2), np.array([0.45, -0.35, 0.35]), name="box")
    scene = Scene((box, near), (box, near))
    start, goal = graph_planner._Query.START, graph_planner._Query.GOAL
    closest = np.argsort(np.linalg.norm(planner.graph.q - q0, axis=1))[:200]
    edges = [(start, int(v)) for v in closest] + [(start, goal)] + [
        (v, goal) for v, _ in planner._attach(q1, np.arange(planner.graph.n_vertices))]
    for u in np.random.default_rng(3).choice(planner.graph.n_vertices, 40, replace=False):
        lo, hi = planner.graph.indptr[u], planner.graph.indptr[u + 1]
        edges += [(int(u), int(v)) for v in planner.graph.indices[lo:hi][:3]]
    mid, _ = fast.tcp_pose(states[55])
    regions = (Shape("sphere", (0.12,), mid, name="far region"),
               _sphere_at_distance(fast, q0[None], tcp0 - 0.15 * ahead, 0.004, "closer"))
    for region in regions:
        prior = graph_planner._Query(planner, q0, q1, scene)
        decided = [prior.edge_free(u, v) for u, v in edges]
        around = replace(scene, ahead=(*scene.ahead, region))
        reused = graph_planner._Query(planner, q0, q1, around, prior)
        fresh = graph_planner._Query(planner, q0, q1, around)
        assert reused.added == (region,) and reused.free_before
        answers = [reused.edge_free(u, v) for u, v in edges]
        assert answers == [fresh.edge_free(u, v) for u, v in edges]
        assert answers != decided  # the region mattered
        assert np.array_equal(reused.search.blocked, fresh.search.blocked)
    assert any(not d and a for d, a in zip(decided, answers, strict=True))  # a lower margin


def _every_route_refused(planner, monkeypatch):
    """A planned long move, a mover's scene, and every route refused in space and time (at
    half its duration, by a region beside the path): (start, scene)."""
    q0, q1 = _long_move()
    assert planner.plan(q0, q1, Scene((), ())).success
    ball = Shape("sphere", (0.05,), np.array([-0.8, 0.8, 1.5]), name="mover")
    v = np.array([0.0, 0.0, -0.3])
    scene = Scene((ball,), (swept(ball, v, HORIZON),), ((ball, v),), AGE)
    region = Shape("sphere", (0.05,), np.array([0.0, 0.7, 1.3]), name="mover")
    monkeypatch.setattr(planner, "_deferrals", 0)
    monkeypatch.setattr(planner, "_contact", lambda trajectory, scene, margin: Contact(
        0.5 * trajectory.duration, 0, q0, region, 0.0))
    return q0, scene


def test_a_slow_holding_retry_leaves_the_search_around_a_region_to_the_next_one(
        planner, fast, monkeypatch):
    """A holding arm's retry (`replan` with ``defer``) whose route a mover's prediction
    refused searches around the predicted region only when it is quick (RETRY_AROUND_S;
    here it never is): it holds and says why; after RETRY_DEFERRALS such retries in a row
    the next one searches around the region, as a re-route without ``defer`` does at once."""
    q0, scene = _every_route_refused(planner, monkeypatch)
    searches = []
    real = planner._route_moving

    def route_moving(*args):
        searches.append(args)
        return real(*args)

    monkeypatch.setattr(graph_planner, "RETRY_AROUND_S", 0.0)
    monkeypatch.setattr(planner, "_route_moving", route_moving)
    monkeypatch.setattr(planner, "_delayed", lambda *args: None)

    def searches_of(defer: bool) -> int:
        searches.clear()
        result = planner.replan(q0, scene, defer=defer)
        assert not result.success
        assert ("only when quick" in result.reason) == (len(searches) == 1)
        return len(searches)

    assert [searches_of(True) for _ in range(graph_planner.RETRY_DEFERRALS + 1)] == [
        *[1] * graph_planner.RETRY_DEFERRALS, 2]
    assert searches_of(False) == 2


def test_a_slow_holding_retry_leaves_re_timing_the_route_around_a_region_to_the_next_one(
        planner, fast, monkeypatch):
    """The route found around a predicted region, refused in turn, is re-timed (delayed
    starts) in a holding retry only while the retry is quick (RETRY_AROUND_S, here spent
    during the second search): the retry holds and says why. Without ``defer`` both routes
    get their delayed starts."""
    q0, scene = _every_route_refused(planner, monkeypatch)
    delays = []
    real = planner._route_moving

    def route_moving(*args):
        result = real(*args)
        if len(args[3].ahead) > len(scene.ahead):  # the search around the region took long
            monkeypatch.setattr(graph_planner, "RETRY_AROUND_S", 0.0)
        return result

    monkeypatch.setattr(planner, "_route_moving", route_moving)
    monkeypatch.setattr(planner, "_delayed", lambda *args: delays.append(args) and None)

    def delays_of(defer: bool) -> int:
        delays.clear()
        monkeypatch.setattr(graph_planner, "RETRY_AROUND_S", 1e9)
        result = planner.replan(q0, scene, defer=defer)
        assert not result.success
        assert ("only when quick" in result.reason) == defer
        return len(delays)

    assert delays_of(True) == 1
    assert delays_of(False) == 2


def test_least_distance_is_the_least_distance_to_the_movers_where_they_are(fast):
    """The compiled loop against one query per instant, movers of every packed kind (a
    ball, a yawed box, a point set's hull) translated by v * (age + t); with a floor it
    stops at an instant at or below it."""
    q0, q1 = _long_move()
    tr = time_parameterize(np.array([q0, q1]), joint_limits("panda"), 0.9, 0.8, 0.8, dt=0.01)
    ball, v = _diver(fast, tr, 0.6 * tr.duration)
    box = Shape("box", (0.1, 0.2, 0.05), np.array([0.5, -0.3, 0.4]),
                np.array([0.0, 0.0, np.sin(0.3), np.cos(0.3)]))
    points = Shape("points", (), np.array([0.3, 0.4, 0.5]),
                   points=np.random.default_rng(3).uniform(-0.05, 0.05, (12, 3)))
    moving = ((ball, v), (box, np.array([0.0, 0.4, 0.0])), (points, np.array([0.2, -0.3, 0.1])))
    p = Prediction()

    def reference(robot, times, states):
        tau0 = max(AGE, p.min_age_s)
        return min(float(robot.distances(q[None], [s.moved_to(s.position + w * (tau0 + t))
                                                   for s, w in moving])[0])
                   for t, q in zip(times, states, strict=True))

    least = least_distance(fast, tr.times, tr.positions, moving, p, AGE)
    assert least < 0.0  # the diver meets the arm
    assert least == pytest.approx(reference(fast, tr.times, tr.positions), abs=1e-9)
    early = tr.times <= 0.2 * tr.duration  # before the diver comes near
    clear = least_distance(fast, tr.times[early], tr.positions[early], moving, p, AGE)
    assert clear > 0.0
    assert clear == pytest.approx(reference(fast, tr.times[early], tr.positions[early]),
                                  abs=1e-9)
    floor = 0.5 * clear + 0.5 * least
    assert least_distance(fast, tr.times, tr.positions, moving, p, AGE, floor) <= floor
    assert least_distance(fast, tr.times, tr.positions, (), p, AGE) == np.inf
    mesh = Robot("mesh")  # the exact meshes: one query per instant and mover
    few = slice(None, None, 10)
    assert least_distance(mesh, tr.times[few], tr.positions[few], moving, p, AGE) == (
        pytest.approx(reference(mesh, tr.times[few], tr.positions[few]), abs=1e-9))


def test_a_contact_names_the_mover_whose_grown_region_is_nearest(fast):
    """The compiled choice of the contact's mover against one query per mover: at the
    contact instant, the least distance less that mover's growth (a fast mover's region
    grows faster, so it may be named though its shape is farther)."""
    q0, q1 = _long_move()
    tr = time_parameterize(np.array([q0, q1]), joint_limits("panda"), 0.9, 0.8, 0.8, dt=0.01)
    ball, v = _diver(fast, tr, 0.6 * tr.duration)
    box = Shape("box", (0.1, 0.2, 0.05), np.array([0.5, -0.3, 0.4]),
                np.array([0.0, 0.0, np.sin(0.3), np.cos(0.3)]), name="box")
    points = Shape("points", (), np.array([0.3, 0.4, 0.5]),
                   points=np.random.default_rng(3).uniform(-0.05, 0.05, (12, 3)), name="hull")
    p = Prediction()
    for moving in (((box, np.array([0.0, 0.4, 0.0])), (points, np.array([0.2, -0.3, 0.1])),
                    (ball, v)),
                   ((ball, v), (box, 2.5 * v))):
        contact = first_contact(fast, tr.times, tr.positions, moving, 0.01, 0.02, p, AGE)
        assert contact is not None
        tau = max(AGE, p.min_age_s) + contact.time_s
        gaps = [float(fast.distances(contact.q[None], [s.moved_to(s.position + w * tau)])[0])
                - p.growth(float(np.linalg.norm(w)), tau) for s, w in moving]
        assert contact.obstacle == int(np.argmin(gaps))
        shape, w = moving[contact.obstacle]
        assert contact.region.name == shape.name
        np.testing.assert_allclose(contact.region.position, shape.position + w * tau)
        assert contact.growth_m == pytest.approx(p.growth(float(np.linalg.norm(w)), tau))
