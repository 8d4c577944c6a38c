"""Node parameters: one declarative table per node, its declaration and its ``--help`` text.

Each node module holds ``PARAMETERS``, a tuple of `Param` giving every parameter's name,
default, description and range in one place. `declare_all` declares them on the node (with a
descriptor, so ``ros2 param describe`` shows the text and rclpy enforces the range) and
returns their values; `print_help` prints the same table before any ROS start-up. The
``config/<node>.yaml`` files repeat the defaults for users to copy and edit;
``test/ros/test_parameters.py`` keeps them equal to the tables.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.node import Node
from rclpy.parameter import Parameter

Value = bool | int | float | str | tuple


@dataclass(frozen=True)
class Param:
    """One ROS parameter of a node.

    ``default`` is a plain value; arrays are tuples (the table is immutable). An empty tuple
    declares an empty *string* array, since rclpy cannot infer a type from an empty list
    (the only such parameter is ``joints``). ``low``/``high`` (both or neither) give an
    inclusive range for a numeric parameter; rclpy refuses values outside it at start-up
    with its own clear message.
    """

    name: str
    default: Value
    description: str
    low: float | None = None
    high: float | None = None
    read_only: bool = False

    def __post_init__(self) -> None:
        if (self.low is None) != (self.high is None):
            raise ValueError(f"parameter {self.name}: give both ends of the range or neither")
        if self.has_range and (isinstance(self.default, bool)
                               or not isinstance(self.default, (int, float))):
            raise TypeError(f"parameter {self.name}: a range needs a numeric default")

    @property
    def has_range(self) -> bool:
        return self.low is not None

    def descriptor(self) -> ParameterDescriptor:
        descriptor = ParameterDescriptor(description=self.description,
                                         read_only=self.read_only)
        if not self.has_range:
            return descriptor
        if isinstance(self.default, int):
            descriptor.integer_range = [IntegerRange(from_value=int(self.low),
                                                     to_value=int(self.high))]
        else:
            descriptor.floating_point_range = [
                FloatingPointRange(from_value=float(self.low), to_value=float(self.high))]
        return descriptor

    def ros_default(self) -> Any:
        """What ``declare_parameter`` takes: a list for an array, a type for an empty one."""
        if self.default == ():
            return Parameter.Type.STRING_ARRAY
        return list(self.default) if isinstance(self.default, tuple) else self.default


def declare_all(node: Node, parameters: Sequence[Param]) -> dict[str, Any]:
    """Declare every parameter of the table on ``node`` and return ``{name: value}``."""
    return {p.name: node.declare_parameter(p.name, p.ros_default(), p.descriptor()).value
            for p in parameters}


def _shown(value: Value) -> str:
    if isinstance(value, tuple):
        return "[" + ", ".join(_shown(v) for v in value) + "]"
    if isinstance(value, str):
        return repr(value)
    return str(value).lower() if isinstance(value, bool) else str(value)


def help_lines(parameters: Sequence[Param]) -> list[str]:
    """Two lines per parameter: ``name = default  [low, high]``, then its description."""
    lines = []
    for p in parameters:
        bounds = f"  [{p.low:g}, {p.high:g}]" if p.has_range else ""
        lines += [f"  {p.name} = {_shown(p.default)}{bounds}", f"      {p.description}"]
    return lines


def print_help(prog: str, description: str, parameters: Sequence[Param],
               config_file: str | None = None) -> None:
    """``--help`` for a node executable: rclpy has none, and ``ros2 run X --help`` is common.

    ``config_file`` is the shipped parameters file of the node (``config/<prog>.yaml``
    unless given).
    """
    print(f"usage: {prog} [--ros-args [-p NAME:=VALUE] [--params-file FILE] [-r FROM:=TO]]")
    print(f"\n{description}\n\nparameters: name = default  [range], description "
          f"(the same in {config_file or f'config/{prog}.yaml'}):")
    print("\n".join(help_lines(parameters)))
