"""The shipped franka_ros2 parameter set, end to end under a namespace: planner and
controller with ``config/franka_ros2/*.yaml``, mock_panda standing in for franka_hardware
(fr3_ joints, the FR3 limit profile, its joint states on ``franka/joint_states``), our
controller standing in for JTC on ``fr3_arm_controller/joint_trajectory``. Every name is
relative, so all of it lives under ``/fr3test``: nothing may appear in the root namespace.
mock_panda's limit monitor checks every command against libfranka's position-dependent
FR3 velocity bounds."""

from __future__ import annotations

import subprocess
import time

import numpy as np
import pytest
import rosutil
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory
from visualization_msgs.msg import MarkerArray

from damon_ros.core.limits import READY
from damon_ros.core.robot import Robot
from damon_ros.core.shapes import Shape
from damon_ros.ros import launch
from damon_ros.ros.environment import node_environment
from damon_ros.ros.markers import shape_to_marker

CONFIG = rosutil.ROOT / "config"
FRANKA = CONFIG / "franka_ros2"
NS = "/fr3test"
FRAME = "fr3_link0"
NS_ARGS = ["-r", f"__ns:={NS}"]
FAR = Shape("sphere", (0.05,), [-0.6, 0.0, 0.3], name="far")


def _goal(q) -> PoseStamped:
    return rosutil.pose_msg(*Robot("fast", "fr3").tcp_pose(np.asarray(q, dtype=float)), FRAME)


def test_planner_and_controller_under_a_namespace_with_the_franka_parameter_set(tmp_path):
    domain = rosutil.next_domain_id(__file__)
    env = node_environment(domain, tmp_path)
    procs: dict[str, subprocess.Popen] = {}
    nodes = {
        "mock_panda": ({"joint_prefix": "fr3_", "limit_profile": "fr3", "rate_hz": 500.0},
                       None, ["-r", "joint_states:=franka/joint_states"]),
        "controller": ({"realtime_priority": 0}, FRANKA / "controller.yaml",
                       ["-r", "damon/joint_trajectory:=fr3_arm_controller/joint_trajectory"]),
        "planner": ({"realtime_priority": 0, "velocity_scale": 0.6},
                    FRANKA / "planner.yaml", []),
    }
    try:
        with rosutil.RosClient(domain) as ros:
            states = ros.record(JointState, f"{NS}/franka/joint_states")
            trajectories = ros.record(JointTrajectory, f"{NS}/fr3_arm_controller/joint_trajectory")
            limits = ros.record(DiagnosticArray, f"{NS}/damon/sim/limits")
            goal_pub = ros.publisher(PoseStamped, f"{NS}/goal_pose")
            markers = ros.publisher(MarkerArray, f"{NS}/damon/obstacles")
            ros.node.create_timer(0.05, lambda: markers.publish(MarkerArray(markers=[
                shape_to_marker(FAR, "test", 0, FRAME, time.time(), 0.3, (1, 0, 0, 1))])))
            for name, (params, extra, args) in nodes.items():
                ros_args = NS_ARGS + args + ([] if extra is None else
                                             ["--params-file", str(extra)])
                procs[name] = launch.start_node(name, params, env, tmp_path / f"{name}.log",
                                                params_file=CONFIG / f"{name}.yaml",
                                                ros_args=ros_args, cwd=rosutil.ROOT)

            def logs() -> str:
                return "".join(f"\n--- {n} ---\n{rosutil.read_log(p)[-2500:]}"
                               for n, p in procs.items())

            assert ros.spin_until(lambda: bool(rosutil.log_lines(procs["planner"],
                                                                 "planner ready")), 180.0), logs()
            assert ros.spin_until(lambda: len(states) > 20, 60.0), logs()
            assert list(states.last.name) == [f"fr3_joint{i}" for i in range(1, 8)]
            assert ros.wait_for_subscribers(goal_pub, 1, 20.0), logs()
            # nothing in the root namespace: the names were relative
            for topic in ("/joint_states", "/franka/joint_states", "/damon/joint_trajectory",
                          "/fr3_arm_controller/joint_trajectory", "/damon/joint_commands"):
                assert ros.node.count_publishers(topic) == 0, topic
            ros.spin_for(1.0)  # the planner's state reader and the obstacle feed settle

            target = READY + np.array([0.5, 0.2, 0.0, 0.3, 0.0, 0.0, 0.0])
            want = Robot("fast", "fr3").tcp_pose(target)[0]

            def reached() -> bool:
                q = np.asarray(states.last.position)
                still = np.max(np.abs(states.last.velocity)) < 0.01
                return still and np.linalg.norm(Robot("fast", "fr3").tcp_pose(q)[0]
                                                - want) < 0.01

            deadline = time.monotonic() + 60.0
            while not trajectories.messages and time.monotonic() < deadline:
                goal_pub.publish(_goal(target))  # refused until the state is fresh
                ros.spin_for(1.0)
            assert trajectories.messages, logs()
            assert ros.spin_until(reached, 40.0), logs()
            assert ros.spin_until(lambda: len(limits) > 0, 5.0), logs()
            values = {kv.key: kv.value for kv in limits.last.status[0].values}
            print(f"\nfranka set under {NS}: reached; mock_panda monitor {values}")
            for kind in ("velocity", "acceleration", "jerk", "position"):
                assert int(values[kind]) == 0, (kind, values, logs())
    finally:
        results = {n: rosutil.stop_node(p) for n, p in procs.items()}
    for name, (code, log) in results.items():
        assert code == 0, f"{name} exited with {code}:\n{log[-3000:]}"
        assert "Traceback" not in log, f"{name}:\n{log[-3000:]}"


@pytest.mark.parametrize("node", ["planner", "controller"])
def test_the_franka_files_name_only_declared_parameters(node):
    import importlib

    import yaml

    data = yaml.safe_load((FRANKA / f"{node}.yaml").read_text(encoding="utf-8"))
    (key,) = data
    assert key == f"/**/{node}"
    declared = {p.name for p in importlib.import_module(f"damon_ros.nodes.{node}").PARAMETERS}
    assert set(data[key]["ros__parameters"]) <= declared
