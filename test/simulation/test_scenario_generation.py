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
    STRESS,
    STRESS_BANDS,
    GenerationConfig,
    ScenarioGenerator,
    band_tag,
    generate_family,
    mover_speed,
    speed_band,
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
    assert cli(["scenarios", "generate", "--bands", "0.1:0.3,fast", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "unknown families ['Z']" in err and "--speed" in err and "--bands 'fast'" in err


def _movers(scenario):
    return [o for o in scenario.obstacles if o.is_dynamic]


@pytest.mark.parametrize("band", STRESS_BANDS)
def test_stress_scenarios_cross_the_hands_way_in_their_band_with_start_and_goal_clear(mesh,
                                                                                      band):
    items = generate_family(ScenarioGenerator(mesh, GenerationConfig(speed=band)), STRESS, 2,
                            seed=11)
    for item in items:
        scenario = parse_scenario(yaml.safe_load(item.yaml()), "<round trip>")
        assert scenario.family == "S" and f"-{band_tag(band)}-" in scenario.name
        movers = _movers(scenario)
        static = [o for o in scenario.obstacles if not o.is_dynamic]
        assert 1 <= len(movers) <= 3 and 1 <= len(static) <= 2
        assert all(o.shape.kind == "box" for o in static)
        assert len({o.color for o in scenario.obstacles}) == len(scenario.obstacles)
        assert speed_band(mover_speed(scenario)) == band
        a, _ = mesh.tcp_pose(scenario.start)
        b = scenario.goal.position
        for o in movers:
            w = o.waypoints
            speed = np.linalg.norm(w[-1, 1:] - w[-2, 1:]) / (w[-1, 0] - w[-2, 0])
            assert band[0] - 1e-3 <= speed <= band[1] + 1e-3
            # its straight line passes within 0.2 m of the hand's straight way
            s = np.linspace(0, 1, 200)[:, None]
            way = a + s * (b - a)
            line = w[0, 1:] + s * (w[-1, 1:] - w[0, 1:])
            assert np.min(np.linalg.norm(way[:, None] - line[None], axis=2)) < 0.2
        end = max(o.waypoints[-1, 0] for o in movers)
        for t in np.arange(0.0, end + 0.05, 0.05):
            for q in (scenario.start, scenario.goal.joints):
                assert mesh.clearance(q, scenario.obstacles_at(t)).distance > 0.045


def test_stress_movers_are_spheres_boxes_and_compounds_one_to_three_at_a_time(mesh):
    items = generate_family(ScenarioGenerator(mesh, GenerationConfig(speed=(0.3, 0.6))),
                            STRESS, 8, seed=2)
    movers = [o for item in items for o in _movers(item.scenario)]
    kinds = {"compound" if o.is_compound else o.shape.kind for o in movers}
    assert kinds == {"sphere", "box", "compound"}
    assert len({len(_movers(item.scenario)) for item in items}) >= 2


def test_stress_bands_write_reproducible_files_named_by_band(tmp_path):
    args = ["scenarios", "generate", "--families", "S", "--bands", "0.6:1.0,1.0:1.5",
            "--count", "1", "--seed", "4", "--quiet"]
    assert cli([*args, "--out", str(tmp_path / "a")]) == 0
    assert cli([*args, "--out", str(tmp_path / "b")]) == 0
    names = sorted(p.name for p in (tmp_path / "a").iterdir())
    assert names == ["S-v0.6-1-s4-000.yaml", "S-v1-1.5-s4-000.yaml"]
    for name in names:
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes()
        scenario = load_scenario(tmp_path / "a" / name)
        assert speed_band(mover_speed(scenario)) in STRESS_BANDS[2:]
