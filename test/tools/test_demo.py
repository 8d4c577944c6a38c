"""The README's main command end to end: every node its own process over real DDS.

Each run gets its own ROS_DOMAIN_ID; the demo itself bounds every wait (node start-up, the
scenario's time limit) and stops its nodes in a ``finally``, and the subprocess timeout
here is the last resort.
"""

from __future__ import annotations

import math
import re
import subprocess
import sys

import numpy as np
import pytest
import yaml
from rosutil import next_domain_id

from damon_ros.core.resources import public_scenarios_dir
from damon_ros.core.robot import Robot
from damon_ros.core.shapes import Shape

TIMEOUT_S = 240  # start-up may take 90 s on a busy machine (the demo's --startup-s)


def _demo(tmp_path, *args: str) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "damon_ros.cli", "demo", "--out", str(tmp_path / "out"),
           "--domain-id", str(next_domain_id(__file__)), *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=TIMEOUT_S)


def _reroutes(stdout: str) -> int:
    match = re.search(r"\((\d+) re-routes", stdout)
    return int(match.group(1)) if match else -1


def test_static_scenario_goal_reached_and_held_with_plots(tmp_path):
    run = _demo(tmp_path, "--scenario", str(public_scenarios_dir() / "B-001.yaml"),
                "--no-camera")
    assert run.returncode == 0, run.stdout + run.stderr[-3000:]
    assert "success             True" in run.stdout
    for name in ("joints.png", "clearance.png", "demo.gif"):
        assert (tmp_path / "out" / name).stat().st_size > 1000


def test_public_dynamic_scenario_recorded_to_mcap(tmp_path):
    # Ground-truth obstacles: the camera + tracker path is covered over DDS by
    # test_node_tracker.py; with it, this 2-core machine runs seven processes and two 1 kHz
    # loops at once, and the run's timing depends on whatever else the machine is doing.
    run = _demo(tmp_path, "--scenario", str(public_scenarios_dir() / "D-001.yaml"),
                "--no-camera", "--no-plots", "--record", str(tmp_path / "run.mcap"))
    assert run.returncode == 0, run.stdout + run.stderr[-3000:]
    assert "success             True" in run.stdout
    assert (tmp_path / "run.mcap").stat().st_size > 10_000


@pytest.fixture()
def crossing_scenario(tmp_path):
    """D-001's start and goal without its obstacles, and a ball that drops onto the route the
    planner takes in the empty scene (where the wrist will be part-way through the motion, clear of
    the start and goal poses) shortly
    after the goal is given: the plan made at t = 0 is then blocked and must be re-routed."""
    from damon_ros.learning.bundle import DamonModel
    from damon_ros.planning.graph_planner import GraphPlanner, PlannerConfig, PoseGoal

    data = yaml.safe_load((public_scenarios_dir() / "D-001.yaml").read_text())
    robot = Robot("fast")
    # a budget that does not depend on this machine's load (see test_planner.TEST_CONFIG)
    planner = GraphPlanner(DamonModel.load().graph, robot, robot.limits,
                           PlannerConfig(time_budget_s=60.0, handover_s=60.0))
    pose = data["goal"]["pose"]
    plan = planner.plan(np.array(data["start"]["joints"]),
                        PoseGoal(np.array(pose["position"]), np.array(pose["orientation"])), [])
    assert plan.success, plan.reason
    start, end = plan.path[0], plan.path[-1]

    def clear_of_start_and_goal(centre) -> bool:
        ball = [Shape("sphere", (0.05,), centre)]
        return robot.clearance(start, ball).distance > 0.12 and \
            robot.clearance(end, ball).distance > 0.1

    for fraction in (0.8, 0.7, 0.6, 0.5):
        on_route = plan.trajectory.sample(fraction * plan.trajectory.duration)[0]
        target = robot.fk(on_route, "panda_hand")[:3, 3]
        parked = target + np.array([0.0, 0.0, 0.35])  # it drops in at 0.35 m/s
        if clear_of_start_and_goal(target) and clear_of_start_and_goal(parked):
            break
    else:
        pytest.fail("no point of the route is clear of the start and goal poses")
    parked = parked.tolist()
    data["name"] = "crossing"
    data["description"] = "a ball moves onto the empty-scene route"
    data["obstacles"] = [{
        "name": "ball", "shape": "sphere", "size": [0.05], "color": "green",
        "pose": {"position": parked, "orientation": [0, 0, 0, 1]},
        "motion": {"type": "waypoints", "waypoints": [[0.0, *parked],
                                                       [1.0, *target.tolist()]]},
    }]
    path = tmp_path / "crossing.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def test_an_obstacle_moved_into_the_path_is_avoided(tmp_path, crossing_scenario):
    # a slow arm (0.3 of the velocity limits) so that the test measures the re-route, not a
    # race between a falling ball and this loaded 2-core machine
    run = _demo(tmp_path, "--scenario", str(crossing_scenario), "--no-camera", "--no-plots",
                "--velocity-scale", "0.3")
    assert run.returncode == 0, run.stdout + run.stderr[-3000:]
    assert "success             True" in run.stdout
    assert _reroutes(run.stdout) >= 1, run.stdout


def test_default_demo_puts_the_ball_on_the_first_route():
    """`make demo`'s settings make its dodge necessary, not a matter of the tracker's noise:
    the route planned when the goal is sent (D-001's ball still parked: no mover to plan
    around) is the graph's, and the arm that followed it as planned would meet the ball on
    the exact meshes — also with the goal up to 0.2 s late (the node's latency)."""
    from damon_ros.core.scenario import load_scenario
    from damon_ros.learning.bundle import DamonModel
    from damon_ros.nodes.planner import PARAMETERS
    from damon_ros.planning.graph_planner import GraphPlanner, PlannerConfig
    from damon_ros.simulation.closed_loop import pose_goal
    from damon_ros.tools.demo import DEFAULT_GOAL_AT_S, DEFAULT_PLANNER, DEFAULT_SCENARIO

    scenario = load_scenario(public_scenarios_dir() / DEFAULT_SCENARIO)
    ball = next(o for o in scenario.obstacles if o.is_dynamic)
    assert not np.any(ball.velocity_at(DEFAULT_GOAL_AT_S))  # parked when the goal comes
    node = {p.name: p.default for p in PARAMETERS} | DEFAULT_PLANNER
    fields = ("margin", "resolution", "velocity_scale", "acceleration_scale", "jerk_scale",
              "time_budget_s", "fallback_budget_s", "handover_s")
    robot = Robot("fast")
    planner = GraphPlanner(DamonModel.load().graph, robot, robot.limits,
                           PlannerConfig(**{f: node[f] for f in fields}))
    plan = planner.plan(scenario.start, pose_goal(scenario), scenario.obstacles_at(0.0))
    assert plan.success and plan.source == "graph", plan.reason
    traj = plan.trajectory
    times = np.append(traj.times[::5], traj.times[-1] + np.arange(0.1, 10.0, 0.1))
    states = np.vstack([traj.positions[::5]] + [traj.positions[-1:]] * (len(times) - len(
        traj.times[::5])))
    mesh = Robot("mesh")
    for late in (0.0, 0.1, 0.2):
        t0 = DEFAULT_GOAL_AT_S + late
        closest = min(mesh.clearance(q, ball.parts_at(t0 + t)).distance
                      for t, q in zip(times, states, strict=True))
        assert closest <= 0.0, (late, closest)


def test_as_planned_clearance_follows_the_plan_then_rests_at_its_end():
    """The summary's "first route" line: the arm on its plan's schedule, then resting at its
    end while the movers still move, against where each mover is at that scenario time."""
    from damon_ros.core.scenario import load_scenario
    from damon_ros.tools.demo import as_planned_clearance

    scenario = load_scenario(public_scenarios_dir() / "D-001.yaml")
    mesh = Robot("mesh")
    ball = next(o for o in scenario.obstacles if o.is_dynamic)
    # a state whose hand is where the ball passes at t = 5 s (found by its own IK)
    centre = ball.position_at(5.0)
    q = mesh.ik(centre, [0.7071068, 0.0, 0.7071068, 0.0], q_near=scenario.start).q  # forward
    still = (0.0, np.array([0.0, 1.0]), np.array([scenario.start, scenario.start]))
    assert math.isnan(as_planned_clearance(scenario, mesh, None))
    far = as_planned_clearance(scenario, mesh, still)
    assert far > 0.05
    # there from t = 4.5 s to 5.5 s: met; there only while the ball is parked, then back
    # at the start before it moves (1.94 s): not met
    met = as_planned_clearance(scenario, mesh, (4.5, np.array([0.0, 1.0]), np.array([q, q])))
    assert met <= 0.0
    gone = as_planned_clearance(scenario, mesh, (0.0, np.array([0.0, 1.0]),
                                                 np.array([q, scenario.start])))
    assert gone > 0.05
    # resting at the end counts: a plan that ends in the ball's way before it comes
    rests = as_planned_clearance(scenario, mesh, (0.0, np.array([0.0, 1.0]),
                                                  np.array([scenario.start, q])))
    assert rests <= 0.0


def test_animation_draws_true_shapes_and_the_estimate():
    """A box is drawn as a box (its 12 hull triangles), a sphere as a surface, an estimate as
    a wireframe, and the estimate shown is the last one received before the frame."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from damon_ros.core.shapes import contains, point
    from damon_ros.tools.demo_plots import _estimate_at, draw_shape, shape_faces

    box = Shape("box", (0.1, 0.2, 0.3), [0.5, 0.0, 0.4], [0.0, 0.0, 0.38, 0.92])
    ball = Shape("sphere", (0.05,), [0.3, 0.3, 0.5])
    fig = plt.figure()
    ax = fig.add_subplot(projection="3d")
    faces = shape_faces(box)
    assert faces.shape == (12, 3, 3)  # 6 faces, 2 triangles each
    assert contains(box, faces.reshape(-1, 3), 1e-9).all()  # its corners, nothing outside
    assert shape_faces(point(np.zeros(3))) is None
    draw_shape(ax, box, "tab:red", estimate=False)
    draw_shape(ax, ball, "tab:blue", estimate=False)
    draw_shape(ax, ball, "0.2", estimate=True)
    assert len(ax.collections) == 3
    plt.close(fig)
    estimates = [(0.0, [ball]), (1.0, [box]), (2.0, [])]
    assert _estimate_at(estimates, -0.5) == []
    assert _estimate_at(estimates, 0.5) == [ball]
    assert _estimate_at(estimates, 1.0) == [box]
    assert _estimate_at(estimates, 5.0) == []
