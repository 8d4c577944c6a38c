"""The Panda's kinematic model: loading it from ``example-robot-data``, batched forward
kinematics, and the error between a TCP pose and a goal pose.

It lives below :mod:`damon_ros.core.collision` and :mod:`damon_ros.core.robot` because both
need it: the collision models place their spheres and meshes with :class:`Chain`, the data
collector aims its samples with it, and every "has the TCP reached the goal" test (IK's
callers, the closed-loop simulation, the demo, the soak) measures with :func:`pose_error`.
Fingers are locked at :data:`FINGER_OPENING` m each (fully open: the largest, hence most
conservative, hand). No rclpy here.
"""

from __future__ import annotations

import importlib.metadata
import math
from collections.abc import Sequence
from functools import cache
from pathlib import Path

import numpy as np
import pinocchio as pin

FINGER_OPENING = 0.04
TCP_FRAME = "panda_hand_tcp"


@cache
def description_dir() -> tuple[Path, Path]:
    """(share directory for ``package://``, ``panda_description`` directory) of the installed
    ``example-robot-data`` distribution — found through the package, never hard-coded."""
    dist = importlib.metadata.distribution("example-robot-data")
    share = Path(str(dist.locate_file("cmeel.prefix/share")))
    panda = share / "example-robot-data" / "robots" / "panda_description"
    if not (panda / "urdf" / "panda.urdf").is_file():
        raise FileNotFoundError(f"example-robot-data has no Panda description under {panda}")
    return share, panda


def load_arm(urdf_name: str, finger_opening: float = FINGER_OPENING
             ) -> tuple[pin.Model, pin.GeometryModel]:
    """The 7-joint arm (each finger locked ``finger_opening`` m from the hand's centre) with
    its collision geometry. A benchmark may define a wider opening than the Panda's joint
    limit (MotionBenchMaker: 0.065 m); its problems are scored with it."""
    share, panda = description_dir()
    urdf = str(panda / "urdf" / urdf_name)
    full = pin.buildModelFromUrdf(urdf)
    geom = pin.buildGeomFromUrdf(full, urdf, pin.GeometryType.COLLISION, package_dirs=[str(share)])
    q_ref = pin.neutral(full)
    fingers = [full.getJointId(f"panda_finger_joint{i}") for i in (1, 2)]
    for j in fingers:
        q_ref[full.joints[j].idx_q] = finger_opening
    return pin.buildReducedModel(full, geom, fingers, q_ref)


# ---- batched forward kinematics ---------------------------------------------------------
class Chain:
    """Forward kinematics of many configurations at once.

    Every Panda joint turns about its local z axis, so the placement of joint k relative to
    its parent is ``P_k Rz(q_k) = A_k + cos q_k B_k + sin q_k C_k`` with constant A, B, C:
    one small matrix product per joint for the whole batch. :meth:`transforms` returns the
    3×4 poses of the base and the 7 joints side by side, laid out (3, N, 32) (rows x, y, z
    first), so that points fixed to joints are placed by one matrix product with a (32, K)
    block of their homogeneous local coordinates (:meth:`block`, :meth:`points`,
    :meth:`positions`). The collision model's spheres, the mesh bounds and the collector's
    arm skeleton (:meth:`frame_block`) all go through it."""

    def __init__(self, model: pin.Model) -> None:
        if model.njoints != 8:
            raise ValueError(f"expected a 7-joint arm, got {model.njoints - 1} joints")
        for j in range(1, model.njoints):
            if model.joints[j].shortname() != "JointModelRZ" or model.parents[j] != j - 1:
                raise ValueError("Chain needs a serial chain of z-revolute joints")
        z = np.zeros((4, 4))
        z[0, 1], z[1, 0] = -1.0, 1.0
        self.abc = []
        for j in range(1, 8):
            p = model.jointPlacements[j].homogeneous
            self.abc.append(np.hstack([p @ np.diag([0.0, 0.0, 1.0, 1.0]),
                                       p @ np.diag([1.0, 1.0, 0.0, 0.0]), p @ z]))
        self.first = [m[:3, None, :] for m in np.split(self.abc[0], 3, axis=1)]
        self.model, self.data = model, model.createData()

    def transforms(self, Q: np.ndarray) -> np.ndarray:
        """Poses (3, N, 32) of the base and the 7 joints for configurations Q (N, 7)."""
        n = len(Q)
        out = np.empty((3, n, 8, 4))
        out[:, :, 0] = np.eye(3, 4)[:, None]
        if n == 1:  # one configuration: pinocchio's C++ is cheaper than the numpy calls
            pin.forwardKinematics(self.model, self.data, Q[0])
            for j in range(1, 8):
                out[:, 0, j] = self.data.oMi[j].homogeneous[:3]
            return out.reshape(3, 1, 32)
        c, s = np.cos(Q).T[:, None, :, None], np.sin(Q).T[:, None, :, None]
        a, b, cc = self.first
        t = a + c[0] * b + s[0] * cc
        out[:, :, 1] = t
        for k in range(1, 7):
            x = (t.reshape(3 * n, 4) @ self.abc[k]).reshape(3, n, 12)
            t = x[:, :, 0:4] + c[k] * x[:, :, 4:8] + s[k] * x[:, :, 8:12]
            out[:, :, k + 1] = t
        return out.reshape(3, n, 32)

    def positions(self, Q: np.ndarray, block: np.ndarray) -> np.ndarray:
        """World positions (N, K, 3) of the K points of ``block`` for configurations Q (N, 7)."""
        return self.points(self.transforms(Q), block).reshape(3, len(Q), -1).transpose(1, 2, 0)

    def frame_block(self, frames: Sequence[str]) -> np.ndarray:
        """(32, K) block placing the origins of the named model frames."""
        ids = [self.model.getFrameId(f) for f in frames]
        if any(i >= self.model.nframes for i in ids):
            raise ValueError(f"the robot model lacks one of the frames {tuple(frames)}")
        return self.block(np.array([self.model.frames[i].parentJoint for i in ids]),
                          np.array([self.model.frames[i].placement.translation for i in ids]))

    @staticmethod
    def points(T: np.ndarray, block: np.ndarray) -> np.ndarray:
        """World positions (3, N·K) of the K points of ``block`` in each of the N states."""
        return (T.reshape(-1, 32) @ block).reshape(3, -1)

    @staticmethod
    def block(joints: np.ndarray, local: np.ndarray) -> np.ndarray:
        """(32, K) matrix placing point k, fixed at ``local[k]`` in joint ``joints[k]``."""
        b = np.zeros((32, len(joints)))
        for k, (j, p) in enumerate(zip(joints, local, strict=True)):
            b[4 * j:4 * j + 3, k] = p
            b[4 * j + 3, k] = 1.0
        return b


# ---- pose error -------------------------------------------------------------------------
def quaternion_angle(qa: np.ndarray, qb: np.ndarray) -> float:
    """Rotation angle (rad) between two unit quaternions (either sign of each)."""
    return 2.0 * math.acos(min(1.0, abs(float(np.asarray(qa) @ np.asarray(qb)))))


def pose_error(position: np.ndarray, quat: np.ndarray, goal_position: np.ndarray,
               goal_orientation: np.ndarray) -> tuple[float, float]:
    """(position error in m, orientation error in rad) of a TCP pose from a goal pose;
    quaternions are ``[x, y, z, w]``."""
    p_err = float(np.linalg.norm(np.asarray(position) - np.asarray(goal_position)))
    return p_err, quaternion_angle(quat, goal_orientation)
