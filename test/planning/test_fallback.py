"""The complete fallback: where the graph has no route, RRT-Connect under the same checker
finds one, it is certified before it is returned, reused the next time the graph has none,
and a failing search escalates instead of repeating itself."""

from __future__ import annotations

import time

import numpy as np
import pytest

from damon_ros.core.limits import joint_limits
from damon_ros.core.robot import Robot
from damon_ros.core.scenario import load_public_scenarios
from damon_ros.learning.bundle import DamonModel
from damon_ros.planning import graph_planner
from damon_ros.planning.graph_planner import GraphPlanner, PlannerConfig
from damon_ros.simulation.closed_loop import pose_goal

SCENE = load_public_scenarios(["A-001"])[0]


class NoGraphRoute(GraphPlanner):
    """The graph search finds nothing, as in a cell the graph was not built for."""

    def _lazy_astar(self, query, active):
        return None


@pytest.fixture(scope="module")
def robots():
    return Robot("fast"), Robot("mesh")


@pytest.fixture()
def planner(robots):
    p = NoGraphRoute(DamonModel.load().graph, robots[0], joint_limits("panda"),
                     PlannerConfig(time_budget_s=5.0, fallback_budget_s=2.0))
    p.warm_up()
    return p


@pytest.fixture()
def calls(planner, monkeypatch):
    """Every sampling search the planner starts: (budget, seed)."""
    seen, real = [], planner._sampling_route

    def spy(query, budget, seed):
        seen.append((budget, seed))
        return real(query, budget, seed)

    monkeypatch.setattr(planner, "_sampling_route", spy)
    return seen


def test_a_route_the_graph_lacks_is_found_certified_and_reused(planner, robots, calls):
    fast, mesh = robots
    obstacles = SCENE.obstacles_at(0.0)
    first = planner.plan(SCENE.start, pose_goal(SCENE), obstacles)
    assert first.success and first.source == "rrtconnect" and len(calls) == 1
    # certified as every route is: fast model with the margin, meshes apart, no self-contact
    for a, b in zip(first.path, first.path[1:], strict=False):
        assert fast.segment_free(a, b, obstacles, margin=planner.config.margin * 0.999,
                                 resolution=planner.config.resolution)
        assert mesh.segment_self_collision_free(a, b)
        states = a + np.linspace(0, 1, 40)[:, None] * (b - a)
        assert mesh.distances(states, obstacles).min() > 0.0
    again = planner.plan(SCENE.start, pose_goal(SCENE), obstacles)
    assert again.success and again.source == "experience" and len(calls) == 1
    np.testing.assert_allclose(again.path[-1], first.path[-1])


def test_a_stored_route_serves_only_where_the_graph_has_none(robots, monkeypatch):
    """Stored routes are detours found around an earlier blockage; tried before the graph,
    they served most soak decisions with motions about three times a graph route's."""
    # the graph's search gets all the time it needs (a loaded machine overran the 5 ms
    # handover, and the fallback answered)
    planner = GraphPlanner(DamonModel.load().graph, robots[0], joint_limits("panda"),
                           PlannerConfig(time_budget_s=5.0, fallback_budget_s=2.0,
                                         handover_s=5.0))
    planner.warm_up()
    obstacles, goal = SCENE.obstacles_at(0.0), pose_goal(SCENE)
    first = planner.plan(SCENE.start, goal, obstacles)
    assert first.success and first.source == "graph"
    planner.experience = [first.path.copy()]  # a stored route that fits this query
    assert planner.plan(SCENE.start, goal, obstacles).source == "graph"
    monkeypatch.setattr(planner, "_lazy_astar", lambda query, active: None)
    assert planner.plan(SCENE.start, goal, obstacles).source == "experience"


def _failing_searches(planner, monkeypatch) -> list[tuple[float, int]]:
    """Make every sampling search fail; the returned list receives each one's (budget,
    seed)."""
    budgets = []

    def nothing(query, budget, seed):
        budgets.append((budget, seed))
        return None

    monkeypatch.setattr(planner, "_sampling_route", nothing)
    return budgets


def test_where_the_graph_missed_a_goal_its_next_search_there_hands_over_sooner(
        planner, monkeypatch):
    """The graph found no route to a goal and the fallback did: the next search toward the
    same goal gives the graph a fifth of ``handover_s`` (its lazy iterations only delayed
    the search that finds one); a new goal gets the full handover again."""
    created, searched = [], []
    real_init, real_search = graph_planner._Query.__init__, planner._lazy_astar

    def init(self, *args, **kwargs):
        real_init(self, *args, **kwargs)
        created.append(self.deadline)

    def search(query, active):
        searched.append(query.deadline)
        return real_search(query, active)

    monkeypatch.setattr(graph_planner._Query, "__init__", init)
    monkeypatch.setattr(planner, "_lazy_astar", search)
    obstacles, goal = SCENE.obstacles_at(0.0), pose_goal(SCENE)

    def plan_and_handover(goal) -> float:
        created.clear()
        searched.clear()
        planner.experience = []  # no stored route: each search runs the sampling fallback
        assert planner.plan(SCENE.start, goal, obstacles).success
        return created[-1] - searched[-1]  # how much the handover was cut

    assert plan_and_handover(goal) == 0.0  # the graph's first search: the full handover
    cut = (1.0 - graph_planner.QUICK_HANDOVER_SHARE) * planner.config.graph_budget()
    assert plan_and_handover(goal) >= cut - 1e-9  # missed before: handed over sooner
    other = planner.plan(SCENE.start, goal, obstacles).goal_q.copy()
    other[0] += 0.05
    assert plan_and_handover(other) == 0.0  # another goal: the full handover again


def test_a_holding_retry_leaves_sampling_after_a_slow_graph_miss_to_the_next_retry(
        planner, monkeypatch):
    """A holding arm's retry (`replan` with ``defer``) whose graph search found nothing after
    more than RETRY_GRAPH_S, where the graph had found the last route, leaves RRT-Connect to
    the next retry and says so; at most RETRY_DEFERRALS retries in a row, then one searches
    in full and finds the route. A retry after a graph miss (whose graph hands over sooner)
    and a re-route without ``defer`` search in full at once."""
    obstacles = SCENE.obstacles_at(0.0)
    assert planner.plan(SCENE.start, pose_goal(SCENE), obstacles).success
    fallbacks, real = [], planner._fallback

    def fallback(query):
        fallbacks.append(query)
        return real(query)

    def slow_miss(query, active):
        time.sleep(2 * graph_planner.RETRY_GRAPH_S)
        return None

    monkeypatch.setattr(planner, "_fallback", fallback)
    monkeypatch.setattr(planner, "_lazy_astar", slow_miss)
    monkeypatch.setattr(planner, "_kept", lambda query: None)  # every retry searches

    def retry(defer: bool = True):
        planner._graph_missed = False  # as after a route the graph found
        return planner.replan(SCENE.start, obstacles, defer=defer)

    for _ in range(graph_planner.RETRY_DEFERRALS):
        result = retry()
        assert not result.success and "left to the next retry" in result.reason
    assert not fallbacks
    assert retry().success and len(fallbacks) == 1  # in full after the deferrals
    assert not retry().success  # a new run of deferrals
    assert planner.replan(SCENE.start, obstacles, defer=True).success  # the graph missed
    assert len(fallbacks) == 2
    assert retry(defer=False).success and len(fallbacks) == 3


def test_a_slow_holding_retry_leaves_the_shortening_of_a_sampled_route_to_the_next_retry(
        planner, monkeypatch):
    """A holding arm's retry that has taken more than RETRY_SHORTEN_S when RRT-Connect
    returns a route leaves its shortening to the next retry, which shortens and certifies
    that route without sampling again. The route is taken up only from where it started; a
    re-route without ``defer`` shortens at once."""
    obstacles = SCENE.obstacles_at(0.0)
    assert planner.plan(SCENE.start, pose_goal(SCENE), obstacles).success
    samplings, shortenings = [], []
    real_sampling, real_shortened = planner._sampling_route, planner._shortened

    def sampling(query, budget, seed):
        samplings.append(seed)
        return real_sampling(query, budget, seed)

    def shortened(path, query):
        shortenings.append(path)
        return real_shortened(path, query)

    monkeypatch.setattr(planner, "_sampling_route", sampling)
    monkeypatch.setattr(planner, "_shortened", shortened)
    monkeypatch.setattr(planner, "_lazy_astar", lambda query, active: None)
    monkeypatch.setattr(planner, "_kept", lambda query: None)
    monkeypatch.setattr(planner, "_from_experience", lambda query: None)
    monkeypatch.setattr(graph_planner, "RETRY_SHORTEN_S", 0.0)

    def retry(defer: bool = True, q=SCENE.start):
        planner._graph_missed = True  # no deferral of the sampling itself
        return planner.replan(q, obstacles, defer=defer)

    first = retry()
    assert not first.success and "shortened by the next retry" in first.reason
    assert len(samplings) == 1 and not shortenings
    second = retry()
    assert second.success and second.source == "rrtconnect"
    assert len(samplings) == 1 and len(shortenings) == 1  # the route of the first retry
    assert np.array_equal(second.path[0], SCENE.start)
    assert not retry().success  # a route left to the next retry again...
    elsewhere = retry(q=SCENE.start + 0.05)  # ...is not taken up from elsewhere
    assert len(samplings) == 3 and "shortened by the next retry" in elsewhere.reason
    shortenings.clear()
    assert retry(defer=False).success and len(shortenings) == 1


def test_a_failing_search_escalates_and_says_so(planner, monkeypatch):
    budgets = _failing_searches(planner, monkeypatch)
    reasons = [planner.plan(SCENE.start, pose_goal(SCENE), SCENE.obstacles_at(0.0)).reason
               for _ in range(5)]
    assert budgets == [(2.0, 0), (4.0, 1), (8.0, 2), (16.0, 3), (16.0, 4)]
    assert "attempt 1" in reasons[0] and "attempt 3" in reasons[2]
    assert all("holding position" in r for r in reasons)


def test_a_moving_arm_gets_the_first_budget_not_the_escalated_one(planner, monkeypatch):
    """The escalation is for a holding arm's retries; an arm in motion coasts on while the
    search runs (an 0.8 s search let a stress-bench arm reach the mover it re-routed
    around), so its searches keep the first budget — and still count as failures."""
    budgets = _failing_searches(planner, monkeypatch)
    obstacles = SCENE.obstacles_at(0.0)
    for _ in range(3):  # a holding arm's retries escalate
        planner.plan(SCENE.start, pose_goal(SCENE), obstacles)
    qd = np.zeros(7)
    qd[0] = 0.5
    result = planner.replan(SCENE.start, obstacles, qd_now=qd)
    assert not result.success
    assert budgets[:3] == [(2.0, 0), (4.0, 1), (8.0, 2)]
    assert budgets[3:] and all(b == 2.0 for b, _ in budgets[3:]), budgets
    assert planner.plan(SCENE.start, pose_goal(SCENE), obstacles).reason  # at rest again:
    assert budgets[-1][0] == 16.0  # the escalation goes on


def test_a_re_route_on_a_threat_gets_the_first_budget_not_the_escalated_one(planner,
                                                                           monkeypatch):
    """An arm whose trajectory a mover threatens may have to escape it next: its search
    keeps the first budget (in a soak a 0.4 s search ran before the escape from a mover
    predicted to reach the arm in 0.27 s), and still counts as a failure."""
    budgets = _failing_searches(planner, monkeypatch)
    obstacles = SCENE.obstacles_at(0.0)
    for _ in range(2):
        planner.plan(SCENE.start, pose_goal(SCENE), obstacles)
    assert not planner.replan(SCENE.start, obstacles, escalate=False).success
    assert budgets == [(2.0, 0), (4.0, 1), (2.0, 2)]
    planner.replan(SCENE.start, obstacles)  # a holding arm's retry escalates on
    assert budgets[-1] == (16.0, 3)


def test_an_uncertified_sampling_route_is_never_returned(planner, monkeypatch):
    # a "route" straight through the box: what the checker must refuse
    goal_q = planner.resolve_goal(pose_goal(SCENE), SCENE.start, SCENE.obstacles_at(0.0))[0]

    def through(query, budget, seed):
        return np.array([query.q_start, 0.5 * (query.q_start + query.q_goal), query.q_goal])

    monkeypatch.setattr(planner, "_sampling_route", through)
    fast = planner.robot
    line = np.linspace(SCENE.start, goal_q, 50)
    assert fast.distances(line, SCENE.obstacles_at(0.0)).min() <= planner.config.margin
    result = planner.plan(SCENE.start, pose_goal(SCENE), SCENE.obstacles_at(0.0))
    assert not result.success and "failed certification" in result.reason


def test_compiled_rrt_connect_routes_through_a_shelf_slot_under_the_fast_model(robots):
    """The compiled search alone, on a problem the graph was never built for: every segment
    it returns keeps the margin on the fast model at the checker's resolution."""
    from damon_ros.core.shapes import Shape
    from damon_ros.planning.rrt_connect import rrt_connect

    fast = robots[0]
    wall = [Shape("box", (0.05, 1.2, 1.2), np.array([0.45, 0.0, 0.6]))]
    q_start = np.array([-1.2, 0.2, 0.0, -1.8, 0.0, 2.0, 0.8])
    q_goal = np.array([1.2, 0.2, 0.0, -1.8, 0.0, 2.0, 0.8])
    assert fast.state_free(q_start, wall, 0.01) and fast.state_free(q_goal, wall, 0.01)
    assert not fast.segment_free(q_start, q_goal, wall, 0.01)
    path = rrt_connect(fast.spheres, q_start, q_goal, fast.limits.lower, fast.limits.upper,
                       wall, 0.01, (0.01, 0.01), 0.02, budget_s=20.0, seed=3)
    assert path is not None
    np.testing.assert_allclose(path[0], q_start)
    np.testing.assert_allclose(path[-1], q_goal)
    assert all(fast.segment_free(a, b, wall, 0.01, resolution=0.02)
               for a, b in zip(path, path[1:], strict=False))


def _mbm_problem(set_dir: str, index: str):
    """One MotionBenchMaker problem read straight from the shared tarball (two members, not
    the 700 problems `load_problems` parses)."""
    import tarfile

    import yaml

    from damon_ros.core.resources import public_scenarios_dir
    from damon_ros.tools.mbm import FINGER_OPENING, problem

    tarball = (public_scenarios_dir().parent / "benchmarks" / "motionbenchmaker" /
               "panda_problems.tar.bz2")
    if not tarball.exists():
        pytest.skip(f"{tarball} is not here")
    with tarfile.open(tarball, "r:*") as tar:
        scene, request = (yaml.safe_load(tar.extractfile(
            f"problems/{set_dir}_panda/{kind}{index}.yaml")) for kind in ("scene", "request"))
    fast = Robot("fast", finger_opening=FINGER_OPENING)
    return fast, problem(set_dir, index, scene, request, fast)


def test_a_goal_between_shelf_boards_grows_its_own_tree():
    """bookshelf_thin 0089: the grasp goal sits between two boards with joint 1 at its limit.
    From there almost every uniform sample's first step hits a board, and the goal tree
    stayed at 14 nodes while the start tree filled its 50,000 (seed 0, 14 s; seeds 1-5 found
    nothing in 3 s each).
    Sampling near the stuck tree's own nodes lets it climb out."""
    from damon_ros.planning.rrt_connect import rrt_connect

    fast, scenario = _mbm_problem("bookshelf_thin", "0089")
    obstacles = scenario.obstacles_at(0.0)
    q_start, q_goal = np.asarray(scenario.start), np.asarray(scenario.goal.joints)
    path = rrt_connect(fast.spheres, q_start, q_goal, fast.limits.lower, fast.limits.upper,
                       obstacles, 0.0, (0.0, 0.0), 0.02, budget_s=20.0, seed=0)
    assert path is not None
    np.testing.assert_allclose(path[[0, -1]], [q_start, q_goal])
    assert all(fast.segment_free(a, b, obstacles, 0.0, resolution=0.02)
               for a, b in zip(path, path[1:], strict=False))
