"""Each node's parameter table (``PARAMETERS``) against its shipped ``config/*.yaml``.

The table in the node module is the one source of names, defaults, ranges and help texts;
the YAML files repeat the defaults for users to copy. These tests keep the two equal (same
keys, same values of the same types), every default inside its range, and ``--help``
listing every parameter. No ROS process is started.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from damon_ros.nodes import controller, mock_camera, mock_panda, planner, tracker
from damon_ros.ros.parameters import Param

CONFIG = Path(__file__).resolve().parents[2] / "config"

NODES = {  # node module -> its shipped parameters file, as the tests and the docs start it
    controller: "controller.yaml",
    mock_camera: "mock_camera.yaml",
    mock_panda: "mock_panda.yaml",
    planner: "planner.yaml",
    tracker: "tracker_node.yaml",  # config/tracker.yaml holds the tracking settings instead
}

YAML_OVERRIDES: dict[tuple[str, str], str] = {
    # (node, parameter) -> why the shipped YAML deliberately differs from the code default.
    # Empty: every shipped file holds the code defaults (the demo and the soak override
    # values on their command lines, not in these files).
}

IDS = [module.NAME for module in NODES]


def _flat(tree: dict, prefix: str = "") -> dict:
    """Nested YAML maps as ROS reads a params file: ``gains: {j1: {p: 1}}`` is ``gains.j1.p``."""
    out = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            out.update(_flat(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def _yaml_parameters(module) -> dict:
    data = yaml.safe_load((CONFIG / NODES[module]).read_text(encoding="utf-8"))
    assert list(data) == [module.NAME], f"{NODES[module]}: one top-level key, the node name"
    return _flat(data[module.NAME]["ros__parameters"])


def _plain(value):
    """YAML's view of a default: lists for arrays."""
    return list(value) if isinstance(value, tuple) else value


def _same_type(a, b) -> bool:
    """A params file must give a parameter its declared type (rclpy refuses 1000 for 1000.0)."""
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(type(x) is type(y) for x, y in zip(a, b, strict=True))
    return type(a) is type(b)


def _in_range(p: Param, value) -> bool:
    return not p.has_range or p.low <= value <= p.high


@pytest.mark.parametrize("module", NODES, ids=IDS)
def test_yaml_names_every_parameter_and_no_other(module):
    names = [p.name for p in module.PARAMETERS]
    assert len(names) == len(set(names)), "a parameter is declared twice"
    assert set(_yaml_parameters(module)) == set(names)


@pytest.mark.parametrize("module", NODES, ids=IDS)
def test_yaml_holds_the_code_defaults(module):
    shipped = _yaml_parameters(module)
    for p in module.PARAMETERS:
        value, default = shipped[p.name], _plain(p.default)
        assert _same_type(value, default), f"{p.name}: {value!r} vs the code's {default!r}"
        assert _in_range(p, value), f"{p.name}: {value} outside [{p.low}, {p.high}]"
        if (module.NAME, p.name) not in YAML_OVERRIDES:
            assert value == default, f"{NODES[module]} {p.name}: {value!r} != {default!r}"


def test_overrides_name_real_parameters():
    names = {(m.NAME, p.name) for m in NODES for p in m.PARAMETERS}
    assert set(YAML_OVERRIDES) <= names


@pytest.mark.parametrize("module", NODES, ids=IDS)
def test_every_default_is_within_its_range(module):
    for p in module.PARAMETERS:
        assert _in_range(p, p.default), f"{p.name}: {p.default} outside [{p.low}, {p.high}]"
        assert p.description, f"{p.name} has no description"


@pytest.mark.parametrize("module", NODES, ids=IDS)
def test_help_lists_every_parameter_and_the_file(module, capsys):
    assert module.main([module.NAME, "--help"]) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"usage: {module.NAME}")
    assert f"config/{NODES[module]}" in out
    for p in module.PARAMETERS:
        assert f"\n  {p.name} = " in out, f"--help does not list {p.name}"


def test_a_range_needs_both_ends_and_a_number():
    with pytest.raises(ValueError, match="both ends"):
        Param("x", 1.0, "x", low=0.0)
    with pytest.raises(TypeError, match="numeric default"):
        Param("x", "a", "x", 0.0, 1.0)
    with pytest.raises(TypeError, match="numeric default"):
        Param("x", True, "x", 0, 1)


@pytest.fixture
def ros_context():
    """An rclpy context of this process only: nodes in it are made, never spun."""
    import rclpy
    from rclpy.context import Context

    context = Context()
    rclpy.init(args=["test", "--ros-args", "-p", "rate_hz:=20000.0"], context=context,
               domain_id=230)  # nothing is published: the domain only has to be valid
    yield context
    rclpy.shutdown(context=context)


@pytest.mark.parametrize("module", NODES, ids=IDS)
def test_declare_all_returns_the_defaults(module, ros_context):
    from rclpy.node import Node

    from damon_ros.ros.parameters import declare_all

    node = Node(f"declared_{module.NAME}", context=ros_context, use_global_arguments=False,
                enable_rosout=False, start_parameter_services=False)
    try:
        values = declare_all(node, module.PARAMETERS)
        descriptors = node.describe_parameters([p.name for p in module.PARAMETERS])
    finally:
        node.destroy_node()
    for p, descriptor in zip(module.PARAMETERS, descriptors, strict=True):
        expected = None if p.default == () else _plain(p.default)  # an unset string array
        assert values[p.name] == expected, p.name
        assert descriptor.description == p.description
        ranges = descriptor.integer_range or descriptor.floating_point_range
        assert bool(ranges) == p.has_range, p.name


def test_declare_all_refuses_a_value_out_of_range(ros_context):
    from rclpy.exceptions import ParameterException
    from rclpy.node import Node

    from damon_ros.ros.parameters import declare_all

    node = Node("declared_out_of_range", context=ros_context, enable_rosout=False,
                start_parameter_services=False)  # takes -p rate_hz:=20000.0
    try:
        with pytest.raises(ParameterException, match="rate_hz out of range"):
            declare_all(node, controller.PARAMETERS)
    finally:
        node.destroy_node()


def test_only_the_named_parameters_change_at_run_time(ros_context):
    from rclpy.node import Node
    from rclpy.parameter import Parameter

    from damon_ros.ros.parameters import accept_at_run_time, declare_all

    node = Node("run_time_changes", context=ros_context, use_global_arguments=False,
                enable_rosout=False, start_parameter_services=False)
    seen = []
    try:
        declare_all(node, mock_camera.PARAMETERS)
        accept_at_run_time(node, {"scenario_start_time_s": seen.append})
        ok = node.set_parameters([Parameter("scenario_start_time_s", value=123.5)])[0]
        refused = node.set_parameters([Parameter("fps", value=10.0)])[0]
        fps = node.get_parameter("fps").value
    finally:
        node.destroy_node()
    assert ok.successful and seen == [123.5]
    assert not refused.successful and "read at start only" in refused.reason
    assert fps == 30.0  # unchanged


def test_controller_declares_per_joint_parameters_for_its_own_joints():
    """gains.<joint>.* and constraints.<joint>.* follow the joints (JTC's layout): the
    table for fr3_ joints names fr3_joint1..7, with the same defaults."""
    fr3 = controller.joint_parameters([f"fr3_joint{i}" for i in range(1, 8)])
    panda = [p for p in controller.PARAMETERS if p.name.startswith(("gains.", "constraints.p"))]
    assert [p.name.replace("fr3_", "panda_") for p in fr3] == [p.name for p in panda]
    assert [p.default for p in fr3] == [p.default for p in panda]
    assert {"gains.fr3_joint7.ff_velocity_scale", "constraints.fr3_joint1.trajectory",
            "constraints.fr3_joint1.goal"} <= {p.name for p in fr3}


def test_planner_prediction_parameters_default_to_the_model():
    """The node's ``prediction_*`` table starts where the library's `Prediction` does, term
    for term, so a node run with its defaults certifies as the bench and the tests do."""
    from dataclasses import fields

    from damon_ros.planning.space_time import Prediction

    table = {p.name: p.default for p in planner.PARAMETERS}
    for field in fields(Prediction):
        assert table[f"prediction_{field.name}"] == getattr(Prediction(), field.name), field.name
