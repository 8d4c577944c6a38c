"""The README's main command end to end: every node its own process over real DDS.

Each run gets its own ROS_DOMAIN_ID; the demo itself bounds every wait (node start-up, the
scenario's time limit) and stops its nodes in a ``finally``, and the subprocess timeout
here is the last resort.
"""

from __future__ import annotations

import re
import subprocess
import sys

import numpy as np
import pytest
import yaml
from rosutil import next_domain_id

from damon_ros.robot import Robot
from damon_ros.scenario import public_scenarios_dir

TIMEOUT_S = 150


def _demo(tmp_path, *args: str) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "damon_ros.cli", "demo", "--out", str(tmp_path / "out"),
           "--domain-id", str(next_domain_id(__file__)), "--startup-s", "10", *args]
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


def test_dynamic_scenario_through_the_camera_and_tracker(tmp_path):
    run = _demo(tmp_path, "--scenario", str(public_scenarios_dir() / "D-001.yaml"),
                "--no-plots", "--record", str(tmp_path / "run.mcap"))
    assert run.returncode == 0, run.stdout + run.stderr[-3000:]
    assert "success             True" in run.stdout
    assert (tmp_path / "run.mcap").stat().st_size > 10_000


@pytest.fixture()
def crossing_scenario(tmp_path):
    """B-001's start and goal, and a ball that moves onto the middle of the straight TCP line
    shortly after the goal is given — the plan made at t = 0 is then blocked."""
    data = yaml.safe_load((public_scenarios_dir() / "B-001.yaml").read_text())
    robot = Robot("fast")
    start_tcp = robot.fk(np.array(data["start"]["joints"]))[:3, 3]
    mid = 0.5 * (start_tcp + np.array(data["goal"]["pose"]["position"]))
    parked = [0.9, 0.0, 1.3]
    data["name"] = "crossing"
    data["obstacles"] = [{
        "name": "ball", "shape": "sphere", "size": [0.05], "color": "green",
        "pose": {"position": parked, "orientation": [0, 0, 0, 1]},
        "motion": {"type": "waypoints", "waypoints": [[0.0, *parked], [0.4, *parked],
                                                       [0.9, *mid.tolist()]]},
    }]
    path = tmp_path / "crossing.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def test_an_obstacle_moved_into_the_path_is_avoided(tmp_path, crossing_scenario):
    run = _demo(tmp_path, "--scenario", str(crossing_scenario), "--no-camera", "--no-plots")
    assert run.returncode == 0, run.stdout + run.stderr[-3000:]
    assert "success             True" in run.stdout
    assert _reroutes(run.stdout) >= 1, run.stdout
