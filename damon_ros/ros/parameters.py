"""Node parameters: declaration with descriptors and ranges, and the ``--help`` text."""

from __future__ import annotations

from collections.abc import Sequence

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.node import Node


def declare(
    node: Node,
    name: str,
    default,
    description: str,
    *,
    read_only: bool = False,
    low: float | None = None,
    high: float | None = None,
):
    """Declare one parameter with a descriptor (type, doc, optional range) and return its value.

    Ranges are enforced by rclpy itself, so an out-of-range value given in a params file or on
    the command line is refused at start-up with rclpy's own clear message.
    """
    descriptor = ParameterDescriptor(description=description, read_only=read_only)
    if low is not None and high is not None:
        if isinstance(default, bool) or not isinstance(default, (int, float)):
            raise TypeError(f"parameter {name}: a range needs a numeric default")
        if isinstance(default, int):
            descriptor.integer_range = [IntegerRange(from_value=int(low), to_value=int(high))]
        else:
            descriptor.floating_point_range = [
                FloatingPointRange(from_value=float(low), to_value=float(high))
            ]
    return node.declare_parameter(name, default, descriptor).value


def print_help(prog: str, description: str, parameters: Sequence[tuple[str, str]]) -> None:
    """``--help`` for a node executable: rclpy has none, and ``ros2 run X --help`` is common."""
    print(f"usage: {prog} [--ros-args [-p NAME:=VALUE] [--params-file FILE] [-r FROM:=TO]]")
    print(f"\n{description}\n\nparameters (defaults in config/{prog}.yaml):")
    for name, doc in parameters:
        print(f"  {name:<28} {doc}")
