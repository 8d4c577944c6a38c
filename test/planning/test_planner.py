"""The certified planner on the shipped default model (issue: DAMON core, "Done when")."""

from __future__ import annotations

import numpy as np
import pytest

from damon_ros.core.limits import joint_limits
from damon_ros.core.robot import Robot
from damon_ros.core.scenario import load_public_scenarios
from damon_ros.core.shapes import Shape
from damon_ros.learning.bundle import DamonModel
from damon_ros.planning.graph_planner import GraphPlanner, PlannerConfig, PoseGoal, Scene, _Query
from damon_ros.planning.reactive import (
    ReactivePlanner,
    RuntimeConfig,
    resting_buffered,
    swept,
)
from damon_ros.simulation.closed_loop import pose_goal

SCENARIOS = load_public_scenarios()
TEST_CONFIG = PlannerConfig(time_budget_s=5.0, handover_s=5.0)
"""The node's 0.25 s wall-clock budget is a latency target of the node (benchmarks and the
soak measure it); on a loaded 2-core machine it ran out on A-002 and D-002 ("no certified
route ... within the time budget"; ~0.5 s of search on a quiet one). 5 s leaves the search
bounded in practice by what does not depend on the machine's speed, ``max_lazy_iterations``
and the ``widen`` steps, so a test asserts what the planner finds, not how fast this
machine is today (a scene with no route costs the whole 5 s)."""


@pytest.fixture(scope="module")
def model() -> DamonModel:
    return DamonModel.load()


@pytest.fixture(scope="module")
def robots() -> tuple[Robot, Robot]:
    return Robot("fast"), Robot("mesh")


@pytest.fixture()
def planner(model, robots) -> GraphPlanner:
    p = GraphPlanner(model.graph, robots[0], joint_limits("panda"), TEST_CONFIG)
    p.warm_up()
    return p


def _mesh_clearance_along(mesh: Robot, path: np.ndarray, obstacles, step: float = 0.02):
    worst = np.inf
    for a, b in zip(path, path[1:], strict=False):
        n = max(1, int(np.ceil(np.max(np.abs(b - a)) / step)))
        states = a + np.linspace(0.0, 1.0, n + 1)[:, None] * (b - a)
        worst = min(worst, float(mesh.distances(states, obstacles).min()))
        assert not any(mesh.self_collision(q) for q in states[::5])
    return worst


@pytest.mark.parametrize("scenario", SCENARIOS, ids=lambda s: s.name)
def test_every_public_scenario_gets_a_plan_certified_by_the_exact_meshes(scenario, planner,
                                                                          robots):
    _, mesh = robots
    obstacles = scenario.obstacles_at(0.0)
    result = planner.plan(scenario.start, pose_goal(scenario), obstacles)
    assert result.success, result.reason
    assert np.allclose(result.path[0], scenario.start)
    position, _ = mesh.tcp_pose(result.path[-1])
    assert np.linalg.norm(position - scenario.goal.position) <= scenario.goal.position_tolerance
    assert _mesh_clearance_along(mesh, result.path, obstacles) > 0.0


def test_trajectories_respect_the_limit_profile(planner):
    limits = joint_limits("panda")
    for scenario in SCENARIOS[:6]:
        result = planner.plan(scenario.start, pose_goal(scenario), scenario.obstacles_at(0.0))
        tr = result.trajectory
        assert np.all(np.abs(tr.velocities) <= limits.velocity + 1e-9)
        assert np.all(np.abs(tr.accelerations) <= limits.acceleration + 1e-6)
        jerk = np.diff(tr.accelerations, axis=0) / np.diff(tr.times)[:, None]
        assert np.all(np.abs(jerk) <= limits.jerk * 1.01)
        assert np.all(tr.positions >= limits.lower - 1e-9)
        assert np.all(tr.positions <= limits.upper + 1e-9)
        assert np.allclose(tr.positions[-1], result.path[-1], atol=1e-9)


def test_an_obstacle_moved_onto_the_path_triggers_a_reroute_that_avoids_it(planner, robots):
    _, mesh = robots
    scenario = next(s for s in SCENARIOS if s.name == "B-001")
    result = planner.plan(scenario.start, pose_goal(scenario), [])
    assert result.success
    # put a ball on the middle of the first segment's swept TCP path
    mid = 0.5 * (result.path[0] + result.path[1])
    ball = Shape("sphere", (0.06,), mesh.fk(mid)[:3, 3])
    runtime = ReactivePlanner(planner)
    runtime._execute(result, 0.0)
    event = runtime.update(0.0, scenario.start, [(ball, np.zeros(3))])
    assert event is not None and event.kind == "trajectory", event
    assert "blocks" in event.reason
    assert _mesh_clearance_along(mesh, event.result.path, [ball]) > 0.0


def test_a_re_route_from_where_the_last_route_started_takes_it_while_it_is_certified(
        planner, robots, monkeypatch):
    """An arm still at rest where its last route started (waiting out a mover, holding) is
    re-routed onto that route without a search while the route is certified (`_certified`,
    the rule every route meets, not the fast screen); an obstacle
    on it, another start or a new goal are searched as before."""
    fast, _ = robots
    scenario, first, searches = _planned_then_counting_searches(planner, monkeypatch)
    far = Shape("sphere", (0.05,), np.array([-0.6, -0.6, 0.2]))
    again = planner.replan(scenario.start, [far])
    assert again.success and not searches
    np.testing.assert_array_equal(again.path, first.path)
    # the fast model's screen is no condition: a route only the meshes' contact band accepts
    # (as RRT-Connect's often are) is taken again too
    with monkeypatch.context() as patched:
        patched.setattr(planner, "_screened", lambda path, query: False)
        assert planner.replan(scenario.start, [far]).success and not searches
    # an obstacle on the route's middle: refused there, searched, and the new route avoids it
    mid = 0.5 * (first.path[0] + first.path[1])
    ball = Shape("sphere", (0.06,), fast.fk(mid)[:3, 3])
    around = planner.replan(scenario.start, [ball])
    assert around.success and searches
    assert _fast_clearance_along(fast, around.path, [ball]) > 0.0
    # another start: searched
    searches.clear()
    moved = scenario.start + 0.01
    assert planner.replan(moved, [far]).success and searches
    # a new goal (plan) from the start of the last route: searched afresh
    searches.clear()
    assert planner.plan(moved, pose_goal(scenario), [far]).success and searches


def test_an_arm_at_rest_keeps_its_route_where_a_mover_only_sweeps_now(planner, robots,
                                                                        monkeypatch):
    """For an arm at rest on its last route's start, a mover's swept shape lying on that
    route is no reason to search again: the movers are certified where they will be (the
    space-time check), so the route is checked against what stands still. A mover leaving
    the route keeps it; one that stays on it is searched around."""
    fast, _ = robots
    scenario, first, searches = _planned_then_counting_searches(planner, monkeypatch)
    mid = 0.5 * (first.path[0] + first.path[1])
    ball = Shape("sphere", (0.05,), fast.fk(mid)[:3, 3])
    leaving = np.array([0.0, 0.0, 1.5])
    scene = Scene((ball,), (swept(ball, leaving, 0.3),), ((ball, leaving),))
    assert fast.distances(mid[None], scene.ahead)[0] < 0.0  # the sweep lies on the route
    kept = planner.replan(scenario.start, scene)
    assert kept.success and not searches
    np.testing.assert_array_equal(kept.path, first.path)
    # a mover crawling along the route stays on it: refused in space and time, searched
    crawling = np.array([0.0, 0.0, 0.01])
    scene = Scene((ball,), (swept(ball, crawling, 0.3),), ((ball, crawling),))
    around = planner.replan(scenario.start, scene)
    assert searches
    assert not around.success or _fast_clearance_along(fast, around.path, [ball]) > 0.0


def _planned_then_counting_searches(planner, monkeypatch):
    """B-001 planned from its start; then each graph search appends to the returned list."""
    scenario = next(s for s in SCENARIOS if s.name == "B-001")
    first = planner.plan(scenario.start, pose_goal(scenario), [])
    assert first.success
    searches = []
    real = planner._lazy_astar
    monkeypatch.setattr(planner, "_lazy_astar",
                        lambda query, active: searches.append(1) or real(query, active))
    return scenario, first, searches


def _fast_clearance_along(fast: Robot, path: np.ndarray, obstacles, step: float = 0.02):
    states = [a + f * (b - a) for a, b in zip(path, path[1:], strict=False)
              for f in np.linspace(0.0, 1.0, max(2, int(np.ceil(np.max(np.abs(b - a)) / step))))]
    return float(fast.distances(np.array(states), obstacles).min())


def _ball_beside(fast: Robot, q: np.ndarray, low: float, high: float) -> Shape:
    """A small ball low..high m from the arm at ``q`` (first of a few directions)."""
    tcp = fast.fk(q)[:3, 3]
    for direction in ([0, 1, 0], [0, -1, 0], [1, 0, 0], [-1, 0, 0], [0, 0, -1]):
        for reach in np.arange(0.05, 0.3, 0.005):
            ball = Shape("sphere", (0.03,), tcp + reach * np.asarray(direction, float))
            if low <= fast.clearance(q, [ball]).distance <= high:
                return ball
    raise AssertionError("no place for the ball")


def test_a_new_goals_route_keeps_the_buffer_from_things_at_rest_unless_none_does(planner,
                                                                                  robots):
    """A thing at rest may start to move: a new goal's route keeps `resting_buffer_m` more
    from it than the margin (B-001's ball lies by the direct route), and a goal the buffer
    would refuse (a ball beside the goal pose) is still planned, without it. Whatever is
    slower than the movers' threshold counts as at rest, balls, boxes and point sets alike
    (on the stress bench resting boxes and compound objects started toward passing arms)."""
    fast, _ = robots
    scenario = next(s for s in SCENARIOS if s.name == "B-001")
    (ball,) = scenario.obstacles_at(0.0)
    margin, buffer = planner.config.margin, 0.05
    box = Shape("box", (0.1, 0.1, 0.1), np.array([0.5, 0.3, 0.3]))
    cube = np.array([[x, y, z] for x in (-0.05, 0.05) for y in (-0.05, 0.05)
                     for z in (-0.05, 0.05)])
    points = Shape("points", (), np.array([0.5, -0.3, 0.3]), points=cube)
    slow, fast_v = np.array([0.01, 0.0, 0.0]), np.array([0.2, 0.0, 0.0])
    grown = resting_buffered([(ball, slow), (ball, fast_v), (box, np.zeros(3)),
                              (box, fast_v), (points, slow)], buffer, 0.05)
    assert [s.size for s, _ in grown[:4]] == [(ball.size[0] + buffer,), ball.size,
                                              (0.2, 0.2, 0.2), box.size]
    corners = grown[4][0].points
    assert np.allclose(np.linalg.norm(corners, axis=1),
                       np.linalg.norm(cube, axis=1) + buffer)  # each pushed out by the buffer
    assert resting_buffered([(box, fast_v)], buffer, 0.05)[0][0] is box
    plain = planner.plan(scenario.start, pose_goal(scenario), [ball])
    assert plain.success
    assert _fast_clearance_along(fast, plain.path, [ball]) < margin + buffer  # nearer
    runtime = ReactivePlanner(planner, RuntimeConfig(resting_buffer_m=buffer))
    event = runtime.set_goal(scenario.start, pose_goal(scenario), [(ball, np.zeros(3))])
    assert event.kind == "trajectory", event.reason
    assert _fast_clearance_along(fast, event.result.path, [ball]) >= margin + buffer - 1e-6
    beside = _ball_beside(fast, plain.path[-1], 0.02, 0.035)
    event = runtime.set_goal(scenario.start, pose_goal(scenario), [(beside, np.zeros(3))])
    assert event.kind == "trajectory", event.reason
    assert _fast_clearance_along(fast, event.result.path, [beside]) < margin + buffer


def test_a_goal_inside_an_obstacle_is_refused_with_a_reason(planner):
    scenario = SCENARIOS[0]
    engulf = Shape("sphere", (0.15,), scenario.goal.position)
    result = planner.plan(scenario.start, pose_goal(scenario), [engulf])
    assert not result.success
    assert "goal pose refused" in result.reason and "collide" in result.reason


def test_a_goal_out_of_reach_is_refused_with_a_reason(planner):
    goal = PoseGoal(np.array([1.6, 0.0, 0.4]), np.array([1.0, 0.0, 0.0, 0.0]))
    result = planner.plan(SCENARIOS[0].start, goal, [])
    assert not result.success and "reach" in result.reason


def test_no_route_means_no_path_and_a_reason(planner, monkeypatch):
    """When no edge can be certified nothing is returned: the planner never falls back on an
    unchecked path (here every segment that comes near the goal is refused)."""
    scenario = SCENARIOS[0]
    goal = pose_goal(scenario)
    q_goal, _ = planner.resolve_goal(goal, scenario.start, scenario.obstacles_at(0.0))
    original = planner.segment_free

    def refuse_near_goal(q0, q1, obstacles, margin, exact=True):
        if min(np.linalg.norm(q0 - q_goal), np.linalg.norm(q1 - q_goal)) < 1e-9:
            return False
        return original(q0, q1, obstacles, margin, exact)

    monkeypatch.setattr(planner, "segment_free", refuse_near_goal)
    result = planner.plan(scenario.start, goal, scenario.obstacles_at(0.0))
    assert not result.success
    assert len(result.path) == 0 and result.trajectory is None
    assert "no certified route" in result.reason and "holding" in result.reason


def _local(shape: Shape, p: np.ndarray) -> np.ndarray:
    return shape.rotation().T @ (p - shape.position)


@pytest.mark.parametrize("kind", ["box", "cylinder", "points"])
def test_swept_shapes_keep_their_kind_and_contain_their_motion(kind):
    q = np.array([0.2, -0.1, 0.4, 0.9]) / np.linalg.norm([0.2, -0.1, 0.4, 0.9])
    size = {"box": (0.2, 0.3, 0.45), "cylinder": (0.05, 0.3), "points": ()}[kind]
    corners = np.array([[x, y, z] for x in (-0.1, 0.1) for y in (-0.15, 0.15)
                        for z in (-0.2, 0.2)])
    shape = Shape(kind, size, [0.5, 0.0, 0.4], q,
                  points=corners if kind == "points" else None)
    v = np.array([0.03, -0.02, 0.3])
    s = swept(shape, v, 1.0)
    assert s.kind == kind
    if kind == "points":  # the hull of both copies: the moved corners are among its points
        moved = [s.position + s.rotation() @ p for p in s.points]
        for c in corners:
            p0 = shape.position + shape.rotation() @ c
            assert min(np.linalg.norm(p0 - m) for m in moved) < 1e-12
            assert min(np.linalg.norm(p0 + v - m) for m in moved) < 1e-12
        return
    half = 0.5 * np.asarray(shape.size)
    if kind == "box":
        extremes = [shape.position + shape.rotation() @ (c / np.array([0.1, 0.15, 0.2]) * half)
                    for c in corners]
    else:  # rim points of both end caps
        r, h = shape.size[0], 0.5 * shape.size[1]
        extremes = [shape.position + shape.rotation() @ np.array([r * np.cos(a), r * np.sin(a), z])
                    for a in np.linspace(0, 2 * np.pi, 12) for z in (-h, h)]
    for t in np.linspace(0.0, 1.0, 5):
        for p in extremes:
            x = _local(s, p + t * v)
            if kind == "box":
                assert np.all(np.abs(x) <= 0.5 * np.asarray(s.size) + 1e-12)
            else:
                assert np.hypot(x[0], x[1]) <= s.size[0] + 1e-12
                assert abs(x[2]) <= 0.5 * s.size[1] + 1e-12


def test_swept_sphere_contains_its_motion():
    ball = Shape("sphere", (0.05,), [0.5, 0.0, 0.5])
    s = swept(ball, np.array([0.4, 0.0, 0.0]), 0.5)
    for t in np.linspace(0.0, 0.5, 6):
        centre = ball.position + t * np.array([0.4, 0.0, 0.0])
        assert np.linalg.norm(centre - s.position) + 0.05 <= s.size[0] + 1e-12


def test_a_moving_arm_is_planned_from_where_it_stops(planner, robots):
    scenario = next(s for s in load_public_scenarios() if s.name == "B-001")
    q0, qd = scenario.start, np.array([1.5, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0])
    q_stop = planner.braking_point(q0, qd)
    lim = planner.limits
    # phase-synchronised: the stop lies on the line along qd, and the joint that needs the
    # longest brake (per-joint, deceleration ramp included) brakes exactly that far
    per_joint = qd**2 / (2 * lim.acceleration) + np.abs(qd) * lim.acceleration / (2 * lim.jerk)
    along = (q_stop - q0)[0] / qd[0]
    np.testing.assert_allclose(q_stop - q0, along * qd, atol=1e-9)
    limiting = int(np.argmax(per_joint / np.abs(np.where(qd == 0, np.inf, qd))))
    assert abs(q_stop - q0)[limiting] == pytest.approx(per_joint[limiting]
                                                       + abs(qd[limiting]) * 0.03, rel=1e-6)
    assert np.all(np.abs(q_stop - q0) >= per_joint + np.abs(qd) * 0.03 - 1e-9)
    goal = scenario.goal.joints
    moving = planner.plan(q0, goal, scenario.obstacles_at(0.0), qd_start=qd)
    assert moving.success, moving.reason
    np.testing.assert_allclose(moving.path[:2], [q0, q_stop])  # brake, then the route
    assert moving.trajectory.positions[0] == pytest.approx(q0)
    # it starts from the measured velocity too (no step for the controller to absorb)
    np.testing.assert_allclose(moving.trajectory.velocities[0], qd)
    # an obstacle on the braking segment: no route may start there
    fast, _ = robots
    ball = Shape("sphere", (0.04,), fast.tcp_pose(0.5 * (q0 + q_stop))[0])
    refused = planner.plan(q0, goal, [*scenario.obstacles_at(0.0), ball], qd_start=qd)
    assert not refused.success and "braking" in refused.reason


def test_braking_points_and_escape_candidates_stay_off_the_joint_limits(planner):
    lim = planner.limits
    q = np.clip(np.zeros(7), lim.lower, lim.upper)
    q[0] = lim.upper[0] - 0.03
    stop = planner.braking_point(q, np.array([2.0, 0, 0, 0, 0, 0, 0]))
    assert stop[0] < lim.upper[0] and stop[0] == pytest.approx(lim.upper[0] - 0.02)
    far = planner.inside_limits(np.full(7, 100.0))
    assert np.all(far < lim.upper) and np.all(planner.inside_limits(-far) > lim.lower)


def test_a_graph_route_is_shortened_only_into_a_certified_path(planner, monkeypatch):
    """The compiled shortcut's result is kept only when certified as a whole (self-collision
    and the start's margins included); refused, the route is shortened segment by segment
    (`_shortcut`, each segment certified as it goes)."""
    scenario = next(s for s in SCENARIOS if s.family == "A")
    obstacles = tuple(scenario.obstacles_at(0.0))
    q_goal, _ = planner.resolve_goal(pose_goal(scenario), scenario.start, obstacles)
    query = _Query(planner, scenario.start, q_goal, Scene.of(obstacles))
    ids = planner._lazy_astar(query, planner.graph.safe.copy())
    raw = np.array([query.config(v) for v in ids])
    assert len(raw) > 2
    short = planner._graph_shortened(raw, query)
    assert planner._certified(short, query) and len(short) <= len(raw)
    assert np.array_equal(short[[0, -1]], raw[[0, -1]])
    monkeypatch.setattr(planner, "_certified", lambda path, query: False)
    assert np.array_equal(planner._graph_shortened(raw, query), planner._shortcut(raw, query))
