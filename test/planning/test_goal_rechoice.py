"""A pose goal whose chosen joint configuration stays unreachable while the arm holds is
re-chosen among the pose's other IK solutions (`ReactivePlanner._rechoose_goal`)."""

from __future__ import annotations

import numpy as np

from damon_ros.core.kinematics import pose_error
from damon_ros.core.scenario import load_public_scenarios
from damon_ros.planning.graph_planner import PlanResult
from damon_ros.planning.reactive import ReactivePlanner, RuntimeConfig
from damon_ros.simulation.closed_loop import pose_goal

SCENE = load_public_scenarios(["A-001"])[0]


def test_ik_can_avoid_a_solution_and_returns_another_of_the_same_pose(fast):
    goal = pose_goal(SCENE)
    first = fast.ik(goal.position, goal.orientation, q_near=SCENE.start)
    other = fast.ik(goal.position, goal.orientation, q_near=SCENE.start, avoid=first.q)
    assert first.success and other.success
    assert np.max(np.abs(other.q - first.q)) >= 0.3
    p_err, o_err = pose_error(*fast.tcp_pose(other.q), goal.position, goal.orientation)
    assert p_err <= 1e-3 and o_err <= 1e-2


def _held(planner, monkeypatch, goal, config: RuntimeConfig):
    """A runtime executing toward ``goal`` whose re-routes all fail from now on, holding."""
    runtime = ReactivePlanner(planner, config)
    assert runtime.set_goal(SCENE.start, goal, [], t=0.0).kind == "trajectory"
    monkeypatch.setattr(planner, "replan", lambda *a, **k: PlanResult(False, "blocked"))
    runtime._hold("a mover came to rest in the way")
    return runtime


def _holding_updates(runtime, seconds: float):
    """Updates every 0.1 s while holding at the start; the first event, and its time."""
    for t in np.arange(0.1, seconds, 0.1):
        event = runtime.update(float(t), SCENE.start, [])
        if event is not None:
            return event, float(t)
    return None, None


def test_a_pose_goal_unreached_for_goal_rechoose_s_is_planned_to_another_ik_solution(
        planner, monkeypatch):
    goal = pose_goal(SCENE)
    runtime = _held(planner, monkeypatch, goal, RuntimeConfig(goal_rechoose_s=1.0))
    old = planner.goal_q.copy()
    event, t = _holding_updates(runtime, 3.0)
    assert event is not None and event.kind == "trajectory"
    assert 1.0 <= t <= 2.0 and "another IK solution" in event.reason
    assert np.max(np.abs(planner.goal_q - old)) >= 0.3
    assert np.array_equal(event.result.path[-1], planner.goal_q)
    p_err, o_err = pose_error(*planner.robot.tcp_pose(planner.goal_q), goal.position,
                              goal.orientation)
    assert p_err <= 1e-3 and o_err <= 1e-2
    assert runtime.state == "executing" and runtime.stats.goals_rechosen == 1


def test_a_joint_goal_or_a_zero_limit_is_never_rechosen(planner, monkeypatch):
    goal_q = planner.resolve_goal(pose_goal(SCENE), SCENE.start, [])[0]
    for goal, limit in ((goal_q, 1.0), (pose_goal(SCENE), 0.0)):
        runtime = _held(planner, monkeypatch, goal, RuntimeConfig(goal_rechoose_s=limit))
        kept = planner.goal_q.copy()
        assert _holding_updates(runtime, 3.0) == (None, None)
        assert np.array_equal(planner.goal_q, kept) and runtime.state == "holding"


def test_another_solution_no_route_reaches_leaves_the_chosen_one_the_goal(planner,
                                                                          monkeypatch):
    """Where no route reaches the other solution either, the retries go on toward the chosen
    one (a mover may yet pass): a stress scene held 6 s and then resumed, and retrying
    toward the other solution it never did."""
    runtime = _held(planner, monkeypatch, pose_goal(SCENE), RuntimeConfig(goal_rechoose_s=1.0))
    old, real_plan, tried = planner.goal_q.copy(), planner.plan, []

    def plan(q, goal, *args, **kwargs):
        tried.append(np.asarray(goal, float))
        real_plan(q, goal, *args, **kwargs)  # takes the goal on, as a plan does
        return PlanResult(False, "blocked")

    monkeypatch.setattr(planner, "plan", plan)
    assert _holding_updates(runtime, 3.5) == (None, None)
    assert tried and np.max(np.abs(tried[0] - old)) >= 0.3
    assert np.array_equal(planner.goal_q, old) and runtime.state == "holding"
