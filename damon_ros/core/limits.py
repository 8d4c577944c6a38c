"""Joint-limit profiles of the Franka Panda and FR3, from Franka's published tables, and the
margins kept inside them.

Everything that commands the arm (trajectory generation, the controller, the mock arm)
clamps against one of these profiles, so a real Franka would accept what we send. The
margins live here together so that their order is visible in one place: the controller
brakes to a stop :data:`POSITION_LIMIT_MARGIN` inside a limit, and IK goals and planner
waypoints stay :data:`IK_LIMIT_MARGIN` inside, beyond that braking zone.

Velocity is the one limit that is not a constant on the FR3: libfranka
(``include/franka/rate_limiting.h``) bounds joint velocity toward each position limit by
``min(vmax, -c + sqrt(k (p_up - q)))`` (mirrored toward the lower limit), less a tolerance,
so the arm can always brake before the limit. `JointLimits.velocity_bounds` is that model,
and the only velocity limit the time parameterisation, the controller's command shaping
and mock_panda's monitor use; the Panda's bounds are its constants.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

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

# libfranka's FR3 position-dependent velocity limits (rate_limiting.h, 2023), per joint:
# c (rad/s), k (rad/s^2: twice the URDF's deceleration limit), p_up and p_lo (rad: where
# the bound reaches -c + 0). Toward p_up: v <= min(vmax, max(0, -c + sqrt(k (p_up - q)))).
_VELOCITY_CURVES = {
    "fr3": {
        "c": [0.30, 0.20, 0.20, 0.30, 0.35, 0.35, 0.35],
        "k": [12.0, 5.17, 7.0, 8.0, 34.0, 11.0, 34.0],
        "p_up": [2.7501, 1.7918, 2.9065, -0.1458, 2.8101, 4.5205, 3.0196],
        "p_lo": [-2.7501, -1.7918, -2.9065, -3.0481, -2.8101, 0.54092, -3.0196],
    },
}
VELOCITY_TOLERANCE = 1e-3
"""libfranka's margin under each velocity bound: kLimitEps (1e-3) + kTolNumberPacketsLost (0
on the FR3) x 1e-3 x max_acc. Bounds are this much inside the curve."""


@njit(cache=True)
def curve_bound(q: float, c: float, k: float, p_up: float, p_lo: float,
                vmax: float) -> tuple[float, float]:
    """(lower, upper) unscaled libfranka bound of one joint at ``q`` (NaN for a NaN ``q``).

    Compiled, and called by the controller's shaping inside its own compiled kernel: as
    numpy on one 7-joint state the bound cost ~15 us, twice per 1 kHz tick on the FR3."""
    if q != q:
        return math.nan, math.nan
    up_room = math.sqrt(max(0.0, k * (p_up - q)))
    lo_room = math.sqrt(max(0.0, k * (q - p_lo)))
    upper = min(vmax, max(0.0, up_room - c)) - VELOCITY_TOLERANCE
    lower = max(-vmax, min(0.0, c - lo_room)) + VELOCITY_TOLERANCE
    return lower, upper


@njit(cache=True)
def curve_bounds(q, c, k, p_up, p_lo, vmax, scale: float, lower, upper) -> None:
    """`curve_bound` of every joint of every state in ``q`` (N, n), times ``scale``, into
    ``lower`` and ``upper``."""
    for i in range(q.shape[0]):
        for j in range(q.shape[1]):
            lo, up = curve_bound(q[i, j], c[j], k[j], p_up[j], p_lo[j], vmax[j])
            lower[i, j], upper[i, j] = scale * lo, scale * up


@dataclass(frozen=True)
class VelocityCurve:
    """libfranka's position-dependent velocity bound parameters, one value per joint."""

    c: np.ndarray
    k: np.ndarray
    p_up: np.ndarray
    p_lo: np.ndarray

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
    curve: VelocityCurve | None = None  # None: constant velocity limits (the Panda)
    velocity_scale: float = 1.0  # the fraction of the curve that `velocity_bounds` allows

    def velocity_bounds(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(lower, upper) joint velocity bounds (rad/s) at positions ``q``.

        The Panda's are its constants (scaled with `scaled`). The FR3's follow libfranka:
        ``upper = min(vmax, max(0, -c + sqrt(max(0, k (p_up - q))))) - tol`` and the mirror
        image toward ``p_lo``, tol = `VELOCITY_TOLERANCE`; with a velocity scale s below 1
        both are multiplied by s (the tolerance too: a scaled bound stays inside the
        curve). ``q`` may be one state (7,) or many (N, 7). Close to a position limit
        ``upper`` is slightly negative: libfranka then only lets the joint move away.
        """
        q = np.asarray(q, dtype=float)
        if self.curve is None:  # one state is the 1 kHz loops' case: no broadcast (~20 us)
            upper = (self.velocity.copy() if q.shape == self.velocity.shape
                     else np.broadcast_to(self.velocity, q.shape).copy())
            return -upper, upper
        c, vmax = self.curve, self.velocity / self.velocity_scale  # the unscaled vmax
        states = np.ascontiguousarray(q.reshape(-1, q.shape[-1]))
        lower, upper = np.empty_like(states), np.empty_like(states)
        curve_bounds(states, c.c, c.k, c.p_up, c.p_lo, vmax, self.velocity_scale, lower, upper)
        return lower.reshape(q.shape), upper.reshape(q.shape)

    def velocity_excess(self, q: np.ndarray, qd: np.ndarray) -> np.ndarray:
        """How far each joint velocity ``qd`` at ``q`` lies beyond its bound (0 within)."""
        lower, upper = self.velocity_bounds(q)
        qd = np.asarray(qd, dtype=float)
        return np.maximum(np.maximum(qd - upper, lower - qd), 0.0)

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
            self.curve, self.velocity_scale * velocity,
        )


def joint_limits(profile: str = "panda", prefix: str | None = None) -> JointLimits:
    """The limit profile ``panda`` or ``fr3``; joint names are ``<prefix>joint1..7``."""
    if profile not in _PROFILES:
        raise ValueError(f"unknown limit profile {profile!r}; expected one of {PROFILES}")
    table = _PROFILES[profile]
    prefix = table["prefix"] if prefix is None else prefix
    curve = _VELOCITY_CURVES.get(profile)
    return JointLimits(
        profile=profile,
        names=tuple(f"{prefix}joint{i}" for i in range(1, 8)),
        **{k: np.array(v, dtype=float) for k, v in table.items() if k != "prefix"},
        curve=None if curve is None else VelocityCurve(
            **{k: np.array(v, dtype=float) for k, v in curve.items()}),
    )
