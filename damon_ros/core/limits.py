"""Joint-limit profiles of the Franka Panda and FR3, from Franka's published tables, and the
margins kept inside them.

Everything that commands the arm (trajectory generation, the controller, the mock arm)
clamps against one of these profiles, so a real Franka would accept what we send. The
margins live here together so that their order is visible in one place: the controller
brakes to a stop :data:`POSITION_LIMIT_MARGIN` inside a limit, and IK goals and planner
waypoints stay :data:`IK_LIMIT_MARGIN` inside, beyond that braking zone.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

READY = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])
"""Franka's "ready" posture: mock_panda's start, IK's default seed, every test's home.
Within the limits of both profiles."""

IK_LIMIT_MARGIN = 0.02
"""rad: IK solutions, planner waypoints and braking points keep this far inside the joint
limits (and outside :data:`POSITION_LIMIT_MARGIN`, where the controller brakes to a stop): a
goal on a limit is a motion that ends on it, and a Franka stops with a reflex there
(mock_panda's monitor counted one; the soak hit joint 1's limit through a braking point and
through an escape candidate)."""
POSITION_LIMIT_MARGIN = 0.01
"""rad: the command brakes to a stop this far inside each position limit. Braking to the
limit itself let the actuator's lag carry the mock arm onto it (the soak's limit monitor
counted joint 1 reaching 2.8973 rad); a Franka stops with a reflex there."""
START_LIMIT_TOLERANCE = 1e-3
"""rad: a start state may lie this far outside the joint limits and still be planned from
(the planner checks measured joint states; a hair beyond a limit is rounding, not a fault)."""

# Franka Control Interface documentation, "Limits for Panda" and "Limits for Franka Research 3".
_PROFILES = {
    "panda": {
        "prefix": "panda_",
        "lower": [-2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973],
        "upper": [2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973],
        "velocity": [2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61],
        "acceleration": [15.0, 7.5, 10.0, 12.5, 15.0, 20.0, 20.0],
        "jerk": [7500.0, 3750.0, 5000.0, 6250.0, 7500.0, 10000.0, 10000.0],
    },
    "fr3": {
        "prefix": "fr3_",
        "lower": [-2.7437, -1.7837, -2.9007, -3.0421, -2.8065, 0.5445, -3.0159],
        "upper": [2.7437, 1.7837, 2.9007, -0.1518, 2.8065, 4.5169, 3.0159],
        "velocity": [2.62, 2.62, 2.62, 2.62, 5.26, 4.18, 5.26],
        "acceleration": [10.0] * 7,
        "jerk": [5000.0] * 7,
    },
}

PROFILES = tuple(_PROFILES)


@dataclass(frozen=True)
class JointLimits:
    """Per-joint position, velocity, acceleration and jerk limits, and the joint names."""

    profile: str
    names: tuple[str, ...]
    lower: np.ndarray
    upper: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray
    jerk: np.ndarray

    def within(self, q: np.ndarray, tolerance: float = 0.0) -> bool:
        """True when every joint position lies inside its range (widened by ``tolerance``)."""
        q = np.asarray(q, dtype=float)
        return bool(np.all(q >= self.lower - tolerance) and np.all(q <= self.upper + tolerance))

    def clip(self, q: np.ndarray) -> np.ndarray:
        return np.clip(np.asarray(q, dtype=float), self.lower, self.upper)

    def scaled(self, velocity: float = 1.0, acceleration: float = 1.0, jerk: float = 1.0):
        """A copy with the derivative limits scaled, e.g. to keep a safety reserve."""
        for name, s in (("velocity", velocity), ("acceleration", acceleration), ("jerk", jerk)):
            if not 0.0 < s <= 1.0:
                raise ValueError(f"{name} scale must be in (0, 1], got {s}")
        return JointLimits(
            self.profile, self.names, self.lower, self.upper,
            self.velocity * velocity, self.acceleration * acceleration, self.jerk * jerk,
        )


def joint_limits(profile: str = "panda", prefix: str | None = None) -> JointLimits:
    """The limit profile ``panda`` or ``fr3``; joint names are ``<prefix>joint1..7``."""
    if profile not in _PROFILES:
        raise ValueError(f"unknown limit profile {profile!r}; expected one of {PROFILES}")
    table = _PROFILES[profile]
    prefix = table["prefix"] if prefix is None else prefix
    return JointLimits(
        profile=profile,
        names=tuple(f"{prefix}joint{i}" for i in range(1, 8)),
        **{k: np.array(v, dtype=float) for k, v in table.items() if k != "prefix"},
    )
