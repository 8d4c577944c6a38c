"""Generated scenarios: valid files, clear starts and goals at every instant, reproducible."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from damon_ros.cli import main as cli
from damon_ros.core.robot import Robot
from damon_ros.core.scenario import load_scenario, parse_scenario
from damon_ros.simulation.scenario_generation import (
    FAMILIES,
    GenerationConfig,
    ScenarioGenerator,
    generate_family,
)


@pytest.fixture(scope="module")
def mesh():
    return Robot("mesh")


@pytest.mark.parametrize("family", sorted(FAMILIES))
def test_each_family_parses_and_keeps_start_and_goal_clear_at_all_times(mesh, family):
    config = GenerationConfig(speed=(0.6, 1.0))
    for item in generate_family(ScenarioGenerator(mesh, config), family, 2, seed=5):
        scenario = parse_scenario(yaml.safe_load(item.yaml()), "<round trip>")
        assert scenario.family == family and scenario.goal.joints is not None
        assert scenario.is_dynamic == (family in "DEG")
        end = max((o.waypoints[-1, 0] for o in scenario.obstacles if o.is_dynamic), default=0)
        for t in np.arange(0.0, end + 0.1, 0.1):
            for q in (scenario.start, scenario.goal.joints):
                assert mesh.clearance(q, scenario.obstacles_at(t)).distance > 0.045
        position, _ = mesh.tcp_pose(scenario.goal.joints)
        assert np.linalg.norm(position - scenario.goal.position) < 2e-3
        for o in scenario.obstacles:
            if o.is_dynamic:
                w = o.waypoints
                speed = np.linalg.norm(w[-1, 1:] - w[-2, 1:]) / (w[-1, 0] - w[-2, 0])
                assert 0.6 - 1e-3 <= speed <= 1.0 + 1e-3


def test_the_same_seed_writes_the_same_files_and_nothing_is_overwritten(tmp_path, capsys):
    args = ["scenarios", "generate", "--families", "D", "--count", "2", "--seed", "3"]
    assert cli([*args, "--out", str(tmp_path / "a"), "--quiet"]) == 0
    assert cli([*args, "--out", str(tmp_path / "b"), "--quiet"]) == 0
    names = sorted(p.name for p in (tmp_path / "a").iterdir())
    assert names == ["D-s3-000.yaml", "D-s3-001.yaml"]
    for name in names:
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes()
        load_scenario(tmp_path / "a" / name)
    assert cli([*args, "--out", str(tmp_path / "a"), "--quiet"]) == 0
    assert "kept 2 existing" in capsys.readouterr().out


def test_bad_arguments_are_refused_with_a_reason(tmp_path, capsys):
    assert cli(["scenarios", "generate", "--families", "AZ", "--out", str(tmp_path)]) == 2
    assert cli(["scenarios", "generate", "--speed", "1:0.5", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "unknown families ['Z']" in err and "--speed" in err
