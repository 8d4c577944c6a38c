"""Every public scenario loads; broken copies are rejected naming file, field and problem."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import yaml

from damon_ros.core.resources import public_scenarios_dir
from damon_ros.core.scenario import (
    ScenarioError,
    load_public_scenarios,
    load_scenario,
    parse_scenario,
    scenario_files,
)

PUBLIC = scenario_files([public_scenarios_dir()])


def test_public_scenarios_exist():
    assert len(PUBLIC) >= 14


@pytest.mark.parametrize("path", PUBLIC, ids=lambda p: p.stem)
def test_every_public_scenario_loads(path):
    scenario = load_scenario(path)
    assert scenario.name == path.stem
    assert scenario.start.shape == (7,)
    assert scenario.obstacles
    assert scenario.time_limit > 0
    for shape in scenario.obstacles_at(0.0):
        assert np.all(np.isfinite(shape.position))


def test_dynamic_obstacle_moves_piecewise_linearly_and_holds():
    d = next(s for s in load_public_scenarios() if s.name == "D-001")
    ball = next(o for o in d.obstacles if o.is_dynamic)
    wp = ball.waypoints
    assert np.allclose(ball.position_at(-1.0), wp[0, 1:])
    assert np.allclose(ball.position_at(wp[-1, 0] + 5.0), wp[-1, 1:])
    mid_t = 0.5 * (wp[1, 0] + wp[2, 0])
    assert np.allclose(ball.position_at(mid_t), 0.5 * (wp[1, 1:] + wp[2, 1:]))
    expected_v = (wp[2, 1:] - wp[1, 1:]) / (wp[2, 0] - wp[1, 0])
    assert np.allclose(ball.velocity_at(mid_t), expected_v)
    assert d.is_dynamic and d.family == "D"


def _raw(name: str = "D-001.yaml") -> dict:
    return yaml.safe_load((public_scenarios_dir() / name).read_text())


def _break(mutate) -> dict:
    data = copy.deepcopy(_raw())
    mutate(data)
    return data


BROKEN = {
    "missing goal": (lambda d: d.pop("goal"), "goal", "missing"),
    "missing obstacle size": (lambda d: d["obstacles"][0].pop("size"), "obstacles[0].size",
                              "missing"),
    "start wrong length": (lambda d: d["start"].update(joints=[0.0] * 6), "start.joints",
                           "must have 7 values, got 6"),
    "box size wrong length": (lambda d: d["obstacles"][0].update(size=[0.1, 0.2]),
                              "obstacles[0].size", "must have 3 values, got 2"),
    "NaN position": (lambda d: d["goal"]["pose"].update(position=[0.4, math.nan, 0.3]),
                     "goal.pose.position[1]", "must be finite"),
    "unknown shape": (lambda d: d["obstacles"][1].update(shape="torus"), "obstacles[1].shape",
                      "unknown shape 'torus'"),
    "unknown color": (lambda d: d["obstacles"][1].update(color="purple"), "obstacles[1].color",
                      "unknown color"),
    "joint beyond limit": (lambda d: d["start"]["joints"].__setitem__(3, 0.5), "start.joints[3]",
                           "outside joint 4's limits"),
    "non-unit quaternion": (lambda d: d["goal"]["pose"].update(orientation=[0, 0, 0, 2]),
                            "goal.pose.orientation", "unit quaternion"),
    "times not increasing": (
        lambda d: d["obstacles"][1]["motion"]["waypoints"].__setitem__(
            2, [1.0, 0.6, 0.7, 0.4]),
        "obstacles[1].motion.waypoints", "strictly increasing"),
    "wrong format": (lambda d: d.update(format=2), "format", "unsupported format"),
    "negative time limit": (lambda d: d.update(time_limit=-1), "time_limit", "must be positive"),
    "string as number": (lambda d: d["obstacles"][0].update(size=[0.1, "x", 0.2]),
                         "obstacles[0].size[1]", "must be a number"),
}


@pytest.mark.parametrize("case", sorted(BROKEN))
def test_broken_copies_are_rejected_with_file_field_and_problem(case, tmp_path):
    mutate, field, problem = BROKEN[case]
    path = tmp_path / "broken.yaml"
    path.write_text(yaml.safe_dump(_break(mutate)))
    with pytest.raises(ScenarioError) as err:
        load_scenario(path)
    message = str(err.value)
    assert message.startswith(str(path)), message
    assert f": {field}: " in message, message
    assert problem in message, message


def test_unreadable_and_invalid_yaml_files(tmp_path):
    with pytest.raises(ScenarioError, match="cannot be read"):
        load_scenario(tmp_path / "absent.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("format: 1\nname: [unclosed\n")
    with pytest.raises(ScenarioError, match="not valid YAML"):
        load_scenario(bad)


def test_obstacle_names_must_be_unique():
    data = _raw()
    data["obstacles"][1]["name"] = data["obstacles"][0]["name"]
    with pytest.raises(ScenarioError, match="unique"):
        parse_scenario(data, "x.yaml")
