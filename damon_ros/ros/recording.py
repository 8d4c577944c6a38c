"""Record ROS 2 topics to MCAP (``--record FILE.mcap``) readable by standard bag tools.

rosbag2 cannot be installed here, so messages are serialised by rclpy (CDR, exactly as on
the wire) and written with the ``mcap`` library under ``ros2msg`` schemas. The schema
text is generated from each message class's own field table, nested types appended in
the ``MSG: pkg/Type`` blocks that ROS 2 bag readers expect.
"""

from __future__ import annotations

import importlib
import re
import time
from pathlib import Path

from rclpy.qos import qos_profile_sensor_data
from rclpy.serialization import serialize_message

from damon_ros.ros import topics

SEPARATOR = "=" * 80
_PRIMITIVES = {"double": "float64", "float": "float32", "boolean": "bool", "octet": "byte",
               "int8": "int8", "uint8": "uint8", "int16": "int16", "uint16": "uint16",
               "int32": "int32", "uint32": "uint32", "int64": "int64", "uint64": "uint64",
               "string": "string", "char": "char", "wstring": "wstring"}

# topic -> message type (module, class) recorded by the demo
DEMO_TOPICS = {
    topics.JOINT_STATES: ("sensor_msgs.msg", "JointState"),
    topics.JOINT_COMMANDS: ("std_msgs.msg", "Float64MultiArray"),
    topics.JOINT_TRAJECTORY: ("trajectory_msgs.msg", "JointTrajectory"),
    topics.CONTROLLER_STATE: ("sensor_msgs.msg", "JointState"),
    topics.PLANNED_PATH: ("nav_msgs.msg", "Path"),
    topics.PLANNER_STATUS: ("diagnostic_msgs.msg", "DiagnosticArray"),
    topics.OBSTACLES: ("visualization_msgs.msg", "MarkerArray"),
    topics.SIM_OBSTACLES: ("visualization_msgs.msg", "MarkerArray"),
    topics.GRAPH_MARKERS: ("visualization_msgs.msg", "MarkerArray"),
    topics.CAMERA_INFO: ("sensor_msgs.msg", "CameraInfo"),
    topics.GOAL_POSE: ("geometry_msgs.msg", "PoseStamped"),
}


def _type_name(cls) -> str:
    module = cls.__module__.split(".")
    return f"{module[0]}/msg/{cls.__name__}"


def _field_text(idl: str) -> tuple[str, str | None]:
    """(msg-file type text, nested 'pkg/Type' or None) for one IDL field type."""
    suffix = ""
    m = re.fullmatch(r"sequence<(.+?)(?:, (\d+))?>", idl)
    if m:
        idl, bound = m.group(1), m.group(2)
        suffix = f"[<={bound}]" if bound else "[]"
    else:
        m = re.fullmatch(r"(.+)\[(\d+)\]", idl)
        if m:
            idl, suffix = m.group(1), f"[{m.group(2)}]"
    m = re.fullmatch(r"string<(\d+)>", idl)
    if m:
        return f"string<={m.group(1)}{suffix}", None
    if idl in _PRIMITIVES:
        return _PRIMITIVES[idl] + suffix, None
    return idl + suffix, idl


def _load(nested: str):
    pkg, name = nested.split("/")
    return getattr(importlib.import_module(f"{pkg}.msg"), name)


def message_definition(cls) -> str:
    """The ros2msg schema text of a message class, dependencies included."""
    def body(c) -> tuple[str, list[str]]:
        lines, deps = [], []
        for name, idl in c.get_fields_and_field_types().items():
            text, nested = _field_text(idl)
            lines.append(f"{text} {name}")
            if nested:
                deps.append(nested)
        return "\n".join(lines), deps

    text, todo = body(cls)
    seen, blocks = set(), [text]
    while todo:
        nested = todo.pop(0)
        if nested in seen:
            continue
        seen.add(nested)
        nested_text, more = body(_load(nested))
        blocks.append(f"{SEPARATOR}\nMSG: {nested}\n{nested_text}")
        todo.extend(more)
    return "\n".join(blocks)


class BagRecorder:
    """Subscribes to topics on ``node`` and writes every message to an MCAP file."""

    def __init__(self, node, path: str | Path, record: dict | None = None) -> None:
        from mcap.writer import Writer

        self._file = open(path, "wb")  # noqa: SIM115 - closed in close()
        self._writer = Writer(self._file)
        self._writer.start(profile="ros2", library="damon_ros")
        self._channels = {}
        self.count = 0
        for topic, (module, name) in (record or DEMO_TOPICS).items():
            cls = getattr(importlib.import_module(module), name)
            schema = self._writer.register_schema(name=_type_name(cls), encoding="ros2msg",
                                                  data=message_definition(cls).encode())
            self._channels[topic] = self._writer.register_channel(  # the resolved name
                topic=node.resolve_topic_name(topic), message_encoding="cdr",
                schema_id=schema)
            qos = qos_profile_sensor_data if topic.lstrip("/").startswith("camera/") or topic in (
                topics.OBSTACLES,) else 50  # match the publishers' QoS
            node.create_subscription(cls, topic, self._callback(topic), qos)

    def _callback(self, topic: str):
        channel = self._channels[topic]

        def write(msg) -> None:
            now = time.time_ns()
            self._writer.add_message(channel_id=channel, log_time=now, publish_time=now,
                                     data=serialize_message(msg))
            self.count += 1
        return write

    def close(self) -> None:
        self._writer.finish()
        self._file.close()
