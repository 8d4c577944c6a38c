"""Checks on the messages that enter the planner and the controller: goals and joint states.

A user's stack will send NaN poses, goals in another frame, joint states without our joints
or out of order in time. Each check here turns such a message into a one-line reason (the
node logs it and keeps running) instead of a motion; a good message turns into plain numpy
values. Message classes only, no rclpy, so the checks are tested without a ROS graph.
(Trajectories are checked by `damon_ros.planning.follower.validate_trajectory`, obstacle markers by
`damon_ros.ros.markers`, images by the tracker.)
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import JointState

from damon_ros.ros.problems import Problem, ProblemError, ProblemLog
from damon_ros.ros.stamps import stamp_seconds

QUATERNION_TOLERANCE = 1e-3
"""A goal quaternion must have a norm within this of 1. A driver that sends (0, 0, 0, 0) or an
unnormalised rotation has a bug; guessing the rotation it meant could move the arm anywhere."""

CLOCK_RESET_S = 1.0
"""Joint-state stamps that go back by more than this are a clock reset (simulator restart,
bag loop), not a late message: the reader starts over from the new stamp."""


class InputError(ProblemError):
    """A message that must not be acted on; the text says why, in one line, and ``kind``
    names the check (`ProblemLog` throttles per kind)."""


def goal_problem(msg: PoseStamped, base_frame: str) -> Problem | str:
    """'' for a usable goal pose, else why not. An empty ``frame_id`` means the base frame.

    Reachability and collisions are the planner's to judge; this is only what makes a pose
    meaningless: another frame (no tf2 here to transform it), NaN/inf, a quaternion that is
    not a rotation.
    """
    frame = msg.header.frame_id
    if frame not in ("", base_frame):
        return Problem(f"frame_id '{frame}' is not the base frame '{base_frame}'",
                       "goal.frame_other")
    p, o = msg.pose.position, msg.pose.orientation
    values = (p.x, p.y, p.z, o.x, o.y, o.z, o.w)
    if not all(math.isfinite(v) for v in values):
        return Problem("pose holds NaN or inf", "goal.not_finite")
    norm = math.hypot(o.x, o.y, o.z, o.w)  # no overflow for huge components
    if abs(norm - 1.0) > QUATERNION_TOLERANCE:
        return Problem(f"orientation is not a unit quaternion (norm {norm:.4f})",
                       "goal.orientation_not_unit")
    return ""


class JointStateReader:
    """The positions of ``names`` from ``sensor_msgs/JointState`` messages, checked.

    Accepted: the joints in any order, among other joints (fingers). Refused with an
    `InputError`: a joint missing, ``position`` not as long as ``name``, NaN/inf, and a stamp
    older than the last accepted one (a message delivered out of order describes the past;
    acting on it would command the arm from where it was). A jump back by more than
    ``CLOCK_RESET_S`` is taken as a clock reset and accepted; a zero stamp (unstamped
    publisher) is accepted without the order check. The name -> index lookup is cached,
    since it is the same for every message of a 1 kHz stream.
    """

    def __init__(self, names: Sequence[str]) -> None:
        self.names = tuple(names)
        self._key: tuple[str, ...] = ()
        self._index: np.ndarray | None = None
        self._missing: list[str] = list(self.names)
        self.last_stamp = -math.inf
        self.clock_resets = 0

    def read(self, msg: JointState) -> np.ndarray:
        """The positions in ``names`` order; raises `InputError` when the message is refused."""
        index = self._lookup(tuple(msg.name))
        if index is None:
            raise InputError(f"joint state lacks {self._missing} (has {list(msg.name)})",
                             "joint_state.joints_missing")
        if len(msg.position) != len(msg.name):
            raise InputError(f"joint state has {len(msg.name)} names but "
                             f"{len(msg.position)} positions", "joint_state.lengths")
        q = np.asarray(msg.position, dtype=float)[index]
        if not np.all(np.isfinite(q)):
            raise InputError("joint state holds NaN or inf positions",
                             "joint_state.not_finite")
        self._check_stamp(stamp_seconds(msg.header.stamp))
        return q

    def velocities(self, msg: JointState) -> np.ndarray | None:
        """The velocities of ``names`` of a message `read` accepted, or None when it carries
        none usable (the field is optional in JointState)."""
        if self._index is None or len(msg.velocity) != len(msg.name):
            return None
        qd = np.asarray(msg.velocity, dtype=float)[self._index]
        return qd if np.all(np.isfinite(qd)) else None

    def _lookup(self, key: tuple[str, ...]) -> np.ndarray | None:
        if key != self._key:
            where = {n: k for k, n in enumerate(key)}
            self._missing = [n for n in self.names if n not in where]
            self._index = None if self._missing else np.array([where[n] for n in self.names])
            self._key = key
        return self._index

    def _check_stamp(self, stamp: float) -> None:
        if stamp == 0.0:
            return
        back = self.last_stamp - stamp
        if 0.0 < back <= CLOCK_RESET_S:
            raise InputError(f"joint state stamp goes backwards ({1e3 * back:.1f} ms older "
                             "than the last one)", "joint_state.stamp_backwards")
        if back > CLOCK_RESET_S:
            self.clock_resets += 1
        self.last_stamp = stamp


def joint_names(joints: Sequence[str] | None, prefix: str) -> list[str]:
    """The ``joints`` parameter, or ``<prefix>joint1..7`` when it is unset or empty.

    Every node that talks joint vectors takes the same two parameters, so that one switch
    (``joint_prefix:=fr3_``) moves the whole graph to franka_ros2's names.
    """
    names = [str(n) for n in (joints or [])]
    if not names:
        return [f"{prefix}joint{i}" for i in range(1, 8)]
    if len(names) != 7 or len(set(names)) != 7 or not all(names):
        raise ValueError(f"parameter joints must name 7 distinct joints, got {names}")
    return names


def read_joint_state(reader: JointStateReader, msg, problems: ProblemLog,
                     log: Callable[[str], None]) -> np.ndarray | None:
    """`JointStateReader.read` for a node: the positions, or None for a refused message,
    which is reported (one line per kind); an accepted clock reset is logged."""
    resets = reader.clock_resets
    try:
        q = reader.read(msg)
    except InputError as exc:
        problems.report(f"ignored joint state: {exc}", exc.kind)
        return None
    if reader.clock_resets != resets:
        log("joint-state stamps jumped back (clock reset): accepted")
    return q
