"""PID joint-trajectory follower for a velocity-controlled arm, with JTC semantics.

Reading downward: `validate_trajectory` / `reorder_points` decide whether an incoming
JointTrajectory is acceptable and put it in the controller's joint order (the rejection rules
of ros2_controllers' joint_trajectory_controller); `TrajectoryFollower` interpolates it like
the JTC and turns the tracking error into a velocity command; `CommandShaper` is the last
stage, which makes every command one that a Franka accepts: within the velocity limit, with
a commanded acceleration and jerk within the profile, and slowing before position limits.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numba import njit

from damon_ros.core.limits import POSITION_LIMIT_MARGIN, JointLimits, curve_bound
from damon_ros.planning.trajectory import METHODS, Spline

# Fraction of the acceleration limit used for the braking curve before a position limit; the
# rest is headroom for the jerk-limited transition into braking and for tracking lag.
POSITION_BRAKE_FRACTION = 0.5
BOUND_LOOKAHEAD_RAD = 0.005
"""rad: position-dependent velocity bounds are read this much nearer the limit (3-10 mrad/s
below libfranka's curve), so the shaped command, which trails its target, stays under it."""


def _per_joint(name: str, value, n: int) -> np.ndarray:
    arr = np.asarray(value, dtype=float)
    arr = np.full(n, float(arr)) if arr.ndim == 0 else arr.copy()
    if arr.shape != (n,):
        raise ValueError(f"PID gain {name} must be a scalar or {n} values, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)) or np.any(arr < 0.0):
        raise ValueError(f"PID gain {name} must be finite and >= 0, got {arr}")
    return arr


_GAIN_FIELDS = ("p", "i", "d", "i_clamp", "ff_velocity_scale")


@dataclass
class PIDGains:
    """Per-joint PID gains producing a velocity command (rad/s) from a position error (rad).

    Defaults suit a velocity-controlled Panda at 1 kHz: the feed-forward velocity does most
    of the work, P = 15 1/s closes the loop well below the ~50 rad/s actuator bandwidth,
    a small I removes steady offsets (gravity-induced drift of the velocity loop), and its
    contribution is capped at ``i_clamp`` rad/s so it can never dominate.
    """

    p: np.ndarray = field(default_factory=lambda: np.full(7, 15.0))
    i: np.ndarray = field(default_factory=lambda: np.full(7, 1.0))
    d: np.ndarray = field(default_factory=lambda: np.full(7, 0.01))
    i_clamp: np.ndarray = field(default_factory=lambda: np.full(7, 0.1))
    ff_velocity_scale: np.ndarray = field(default_factory=lambda: np.ones(7))

    def __post_init__(self):
        values = [getattr(self, name) for name in _GAIN_FIELDS]
        n = next((np.size(v) for v in values if np.ndim(v) > 0), 7)
        for name in _GAIN_FIELDS:
            setattr(self, name, _per_joint(name, getattr(self, name), n))

    @classmethod
    def uniform(cls, n: int = 7, p: float = 15.0, i: float = 1.0, d: float = 0.01,
                i_clamp: float = 0.1, ff_velocity_scale: float = 1.0) -> PIDGains:
        """The same gains on all ``n`` joints."""
        return cls(*(np.full(n, float(v)) for v in (p, i, d, i_clamp, ff_velocity_scale)))


# ----------------------------------------------------------------------------- validation

FLOAT_EPSILON = 1.1920929e-07
"""The JTC's test for a "zero" final velocity: |v| <= float epsilon."""


def _optional_rows(name: str, rows, n_points: int, n_joints: int):
    """(array or None, reason or None) for per-point optional vectors such as velocities.

    Like a JointTrajectory, every point may leave the field empty; mixing empty and filled
    points is ambiguous (which spline order?) and is rejected.
    """
    if rows is None:
        return None, None
    rows = list(rows)
    if len(rows) != n_points:
        return None, f"{name} has {len(rows)} points, expected {n_points}"
    sizes = {len(r) for r in rows}
    if sizes <= {0}:
        return None, None
    if sizes != {n_joints}:
        return None, f"{name} must be empty or hold {n_joints} values at every point"
    arr = np.asarray(rows, dtype=float)
    if not np.all(np.isfinite(arr)):
        return None, f"{name} hold NaN or inf"
    return arr, None


def _check_names(joint_names: Sequence[str], expected_names: Sequence[str],
                 allow_partial: bool) -> str | None:
    names = list(joint_names)
    if len(set(names)) != len(names):
        return f"joint names repeat: {names}"
    unknown = sorted(set(names) - set(expected_names))
    if unknown:
        return f"unknown joints {unknown}; this controller drives {list(expected_names)}"
    if not names:
        return "no joint names"
    missing = [n for n in expected_names if n not in names]
    if missing and not allow_partial:
        return (f"missing joints {missing}; a trajectory must command all of "
                f"{list(expected_names)} (allow_partial_joints_goal is false)")
    return None


def _check_times(times) -> str | None:
    t = np.asarray(times, dtype=float)
    if t.ndim != 1:
        return "time_from_start must be one value per point"
    if not np.all(np.isfinite(t)):
        return "time_from_start holds NaN or inf"
    if t.size and t[0] < 0.0:
        return f"time_from_start must not be negative, got {t[0]}"
    if np.any(np.diff(t) <= 0.0):
        k = int(np.argmax(np.diff(t) <= 0.0))
        return f"time_from_start not strictly increasing at point {k + 1} ({t[k]} -> {t[k + 1]})"
    return None


def _check_limits(positions, velocities, limits: JointLimits, tolerance: float) -> str | None:
    low = positions < limits.lower - tolerance
    high = positions > limits.upper + tolerance
    if np.any(low | high):
        k, j = np.argwhere(low | high)[0]
        return (f"point {k} puts {limits.names[j]} at {positions[k, j]:.4f} rad, outside "
                f"[{limits.lower[j]}, {limits.upper[j]}]")
    if velocities is not None:
        fast = np.abs(velocities) > limits.velocity + tolerance
        if np.any(fast):
            k, j = np.argwhere(fast)[0]
            return (f"point {k} asks {limits.names[j]} for {velocities[k, j]:.4f} rad/s, beyond "
                    f"the limit {limits.velocity[j]}")
    return None


def _points(joint_names, expected_names, times, positions, velocities, accelerations,
            allow_partial: bool = False, fill=None):
    """Check structure and values; (positions, velocities, accelerations) in controller order.

    Joints the message leaves out (only with ``allow_partial``) get ``fill`` (the current
    position: they hold it, as in the JTC) and zero velocity and acceleration.
    """
    reason = _check_names(joint_names, expected_names, allow_partial) or _check_times(times)
    if reason:
        return reason, None
    n_points, n_joints = len(times), len(joint_names)
    rows = list(positions)
    if len(rows) != n_points:
        return f"positions has {len(rows)} points, expected {n_points}", None
    if any(len(r) != n_joints for r in rows):
        return f"every point needs {n_joints} positions", None
    pos = np.asarray(rows, dtype=float).reshape(n_points, n_joints)
    if not np.all(np.isfinite(pos)):
        return "positions hold NaN or inf", None
    vel, reason = _optional_rows("velocities", velocities, n_points, n_joints)
    if reason:
        return reason, None
    acc, reason = _optional_rows("accelerations", accelerations, n_points, n_joints)
    if reason:
        return reason, None
    if acc is not None and vel is None:
        return "accelerations given without velocities", None
    names = list(joint_names)
    if len(names) == len(expected_names):
        order = [names.index(n) for n in expected_names]
        return None, tuple(None if a is None else a[:, order] for a in (pos, vel, acc))
    if fill is None:
        return "a partial trajectory needs the current position of the other joints", None
    fill = np.asarray(fill, dtype=float)
    out = []
    for k, a in enumerate((pos, vel, acc)):
        if a is None:
            out.append(None)
            continue
        full = np.tile(fill, (n_points, 1)) if k == 0 else np.zeros((n_points, len(fill)))
        for j, name in enumerate(expected_names):
            if name in names:
                full[:, j] = a[:, names.index(name)]
        out.append(full)
    return None, tuple(out)


def validate_trajectory(joint_names: Sequence[str], expected_names: Sequence[str], times,
                        positions, velocities, accelerations, limits: JointLimits,
                        tolerance: float = 1e-6, start_time: float | None = None,
                        now: float | None = None, allow_partial: bool = False,
                        allow_nonzero_end_velocity: bool = False) -> str | None:
    """None when the trajectory is acceptable, else a one-line reason to log and ignore it.

    The JTC's rules (ros2_controllers Jazzy): at least one point; joints must match the
    controller's (any order, none unknown, none missing unless ``allow_partial``);
    time_from_start strictly increasing; no NaN or inf; consistent vector lengths; a zero
    velocity at the last point unless ``allow_nonzero_end_velocity``; with ``start_time``
    and ``now``, a stamped trajectory that would already have ended is refused. Plus ours:
    positions within the limits and velocities within the velocity limits (what happens
    between the points is `TrajectoryFollower.prepare`'s check).

    An empty trajectory is refused, as the JTC refuses it: stopping is a trajectory too
    (one point at the current position, "hold"), so that a stop means the same to every
    controller it may reach.
    """
    if len(times) == 0:
        return ("no points; an empty trajectory is not a stop (as in the JTC): to stop, send "
                "one point at the current position")
    reason, arrays = _points(joint_names, expected_names, times, positions, velocities,
                             accelerations, allow_partial, fill=np.zeros(len(expected_names)))
    if reason:
        return reason
    pos, vel, _ = arrays
    given = [list(expected_names).index(n) for n in joint_names]
    reason = _check_limits(pos[:, given], None if vel is None else vel[:, given],
                           _subset(limits, given), tolerance)
    if reason:
        return reason
    if vel is not None and not allow_nonzero_end_velocity:
        fast = np.abs(vel[-1]) > FLOAT_EPSILON
        if np.any(fast):
            j = int(np.argmax(fast))
            return (f"the last point asks {expected_names[j]} for {vel[-1, j]:.6g} rad/s, not "
                    "zero (allow_nonzero_velocity_at_trajectory_end is false)")
    if start_time is not None and now is not None and start_time > 0.0 and \
            start_time + float(times[-1]) < now:
        return (f"trajectory ends in the past (stamped {start_time:.3f} + "
                f"{float(times[-1]):.3f} s < now {now:.3f})")
    return None


def _subset(limits: JointLimits, joints: list[int]) -> JointLimits:
    """The limits of some joints only (a partial trajectory is checked on the joints it names)."""
    return JointLimits(limits.profile, tuple(limits.names[j] for j in joints),
                       *(getattr(limits, k)[joints] for k in
                         ("lower", "upper", "velocity", "acceleration", "jerk")))


def reorder_points(joint_names: Sequence[str], expected_names: Sequence[str], times, positions,
                   velocities=None, accelerations=None, fill=None):
    """(times, positions, velocities|None, accelerations|None) as arrays in controller order.

    ``fill``: positions of the controller's joints, used for those a partial trajectory
    leaves out. Call after `validate_trajectory` accepted the message; raises ValueError
    otherwise.
    """
    reason, arrays = _points(joint_names, expected_names, times, positions, velocities,
                             accelerations, allow_partial=fill is not None, fill=fill)
    if reason:
        raise ValueError(reason)
    return (np.asarray(times, dtype=float), *arrays)


# ----------------------------------------------------------------------------- command shaping

@njit(cache=True)
def _reachable_acceleration(gap: float, jerk: float, dt: float) -> float:
    """Largest acceleration for this step from which velocity can still settle within ``gap``.

    Commanding a (>= 0) for dt raises the velocity by a*dt; bringing the acceleration back
    to zero at the jerk limit then adds at most a^2 / (2 jerk), whatever the later periods
    are (a right Riemann sum of a falling ramp stays under its integral). Solving
    a*dt + a^2 / (2 jerk) = gap for a gives this bound. Once u + a^2 / (2 jerk) <= vmax
    holds, dropping a by jerk*dt keeps it true for any next dt — so the command can never
    be forced over the velocity limit, even when the control period jitters.
    """
    two_gap = 2.0 * gap  # the root in the cancellation-free form: tiny gaps close exactly
    return two_gap / (dt + math.sqrt(dt * dt + abs(two_gap) / jerk))


class CommandShaper:
    """The last stage before the arm: makes a desired velocity into an acceptable command.

    Hard constraints, given the previous command ``u`` and its acceleration ``a``: |u'| <=
    vmax, |a'| <= amax, |a' - a| / dt <= jmax. The target is clipped to +-vmax and
    approached with the largest acceleration from which the jerk limit can still bring the
    acceleration back to zero before the target. So the command never overshoots a target
    that stays put, and never the velocity limit whatever the target does: the acceleration
    window of the next step always holds a value that respects it, for any period. Position
    limits are met softly, by `position_bounds` shrinking the desired velocity before one.
    """

    def __init__(self, limits: JointLimits):
        self.lower, self.upper = limits.lower, limits.upper
        self.vmax, self.amax, self.jmax = limits.velocity, limits.acceleration, limits.jerk
        self._brake = 2.0 * POSITION_BRAKE_FRACTION * limits.acceleration
        c, none = limits.curve, np.zeros_like(limits.velocity)
        self._curve = ((True, c.c, c.k, c.p_up, c.p_lo, limits.velocity / limits.velocity_scale,
                        limits.velocity_scale) if c is not None
                       else (False, none, none, none, none, none, 1.0))
        self.warm_up()

    def warm_up(self) -> None:
        """Compile (or load from numba's disk cache) the kernels now, not in a 1 kHz tick
        (a first compile takes ~1 s)."""
        middle = 0.5 * (self.lower + self.upper)
        self.position_bounds(middle)
        self.shape(np.zeros_like(middle), np.zeros_like(middle), np.zeros_like(middle), 1e-3)

    def position_bounds(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(low, high) velocity bounds that brake to a stop `POSITION_LIMIT_MARGIN` inside the
        position limits.

        v <= sqrt(2 b d) with d the distance left and b a fraction of the acceleration limit,
        so motion toward a limit fades to zero at the limit, and none is allowed past it.
        The one velocity limit model (core.limits) applies too: on the FR3 libfranka's bound
        falls toward each position limit (-c + sqrt(k d)), below the brake curve above on
        joints 1-4 and 6; on the Panda it is the constant vmax. It is read
        BOUND_LOOKAHEAD_RAD closer to each limit: the jerk-limited command lags a falling
        target by up to ~1e-3 rad/s, which the earlier bound covers.
        """
        low, high = np.empty_like(self.vmax), np.empty_like(self.vmax)
        _position_bounds(np.asarray(q, dtype=float), self.lower, self.upper, self.vmax,
                         self._brake, *self._curve, low, high)
        return low, high

    def shape(self, target: np.ndarray, u: np.ndarray, a: np.ndarray,
              dt: float) -> tuple[np.ndarray, np.ndarray]:
        """(next velocity command, its acceleration), moving from ``u`` toward ``target``.

        ``target`` is approached as fast as the limits allow without overshooting it.
        """
        u_next, a_next = np.empty_like(self.vmax), np.empty_like(self.vmax)
        _shape(np.asarray(target, dtype=float), np.asarray(u, dtype=float),
               np.asarray(a, dtype=float), self.vmax, self.amax, self.jmax, float(dt),
               u_next, a_next)
        return u_next, a_next


# The 1 kHz shaping compiled: as numpy on 7-joint vectors `position_bounds` and `shape` cost
# ~37 and ~13 us a tick on the FR3 (a fifth of the controller's loop); compiled, ~1 us each.

@njit(cache=True)
def _position_bounds(q, lower, upper, vmax, brake, has_curve: bool, c, k, p_up, p_lo,
                     vmax_unscaled, scale: float, low, high) -> None:
    for j in range(q.size):
        up = min(math.sqrt(brake[j] * max(upper[j] - POSITION_LIMIT_MARGIN - q[j], 0.0)),
                 vmax[j])
        down = min(math.sqrt(brake[j] * max(q[j] - lower[j] - POSITION_LIMIT_MARGIN, 0.0)),
                   vmax[j])
        bound_low, bound_high = -vmax[j], vmax[j]
        if has_curve:
            bound_low = scale * curve_bound(q[j] - BOUND_LOOKAHEAD_RAD, c[j], k[j], p_up[j],
                                            p_lo[j], vmax_unscaled[j])[0]
            bound_high = scale * curve_bound(q[j] + BOUND_LOOKAHEAD_RAD, c[j], k[j], p_up[j],
                                             p_lo[j], vmax_unscaled[j])[1]
        high[j] = min(up, bound_high)
        low[j] = min(max(-down, bound_low), high[j])


@njit(cache=True)
def _shape(target, u, a, vmax, amax, jmax, dt: float, u_next, a_next) -> None:
    """`CommandShaper.shape` per joint: a NaN target (inf - inf from absurd inputs) is 0."""
    for j in range(u.size):
        goal = 0.0 if target[j] != target[j] else min(max(target[j], -vmax[j]), vmax[j])
        a_goal = _reachable_acceleration(goal - u[j], jmax[j], dt)
        jd = jmax[j] * dt
        step = min(max(a_goal, max(a[j] - jd, -amax[j])), min(a[j] + jd, amax[j]))
        u_next[j] = min(max(u[j] + step * dt, -vmax[j]), vmax[j])
        a_next[j] = (u_next[j] - u[j]) / dt


@njit(cache=True)
def _pid_step(e, e_prev, has_prev: bool, qd_ff, dt: float, step: float, integral, cap, p, i,
              d, ff, low, high, u, a, vmax, amax, jmax, cycle: float, u_next, a_next,
              integral_next) -> None:
    """One PID tick of `TrajectoryFollower`, compiled (as numpy ~25 us of the 1 kHz loop):
    feed-forward + P + I (clamped so that its term stays within ``i_clamp``) + D, clipped
    to the bounds (``low``, ``high``), then shaped from the last command (`_shape`). The
    integral is kept (anti-windup) only on joints whose raw output was not clipped and
    whose shaped command is within one step of full acceleration of the target (not
    rate-limited); a clipped raw output lies beyond the bounds and is never delivered.
    The same arithmetic in the same order as the numpy it replaces: bit-identical."""
    n = e.size
    target, kept = np.empty(n), np.empty(n)
    for j in range(n):
        integ = min(max(integral[j] + e[j] * step, -cap[j]), cap[j])
        raw = ff[j] * qd_ff[j] + p[j] * e[j] + i[j] * integ
        if has_prev:
            raw += d[j] * (e[j] - e_prev[j]) / dt
        target[j] = min(max(raw, low[j]), high[j])
        kept[j] = integ if raw == target[j] else integral[j]
    _shape(target, u, a, vmax, amax, jmax, cycle, u_next, a_next)
    for j in range(n):
        free = abs(u_next[j] - target[j]) <= amax[j] * cycle
        integral_next[j] = kept[j] if free else integral[j]


# ----------------------------------------------------------------------------- tolerances

@dataclass(frozen=True)
class Tolerances:
    """The JTC's ``constraints``: when a running trajectory is aborted and the arm held.

    ``path`` (``constraints.<joint>.trajectory``, rad): while the trajectory runs, a joint
    further than this from its desired position aborts it. ``goal``
    (``constraints.<joint>.goal``, rad) and ``stopped_velocity``
    (``constraints.stopped_velocity_tolerance``, rad/s): after the end, the goal is reached
    once every joint is within ``goal`` of the last point and moves slower than
    ``stopped_velocity``; if that has not happened ``goal_time`` s after the end
    (``constraints.goal_time``), the trajectory is aborted. 0 switches a check off, and the
    defaults are the JTC's: no path or goal check, wait for the goal for ever, 0.01 rad/s.
    Aborting holds the arm where it is measured, as the JTC does.
    """

    path: np.ndarray
    goal: np.ndarray
    goal_time: float = 0.0
    stopped_velocity: float = 0.01

    def __post_init__(self):
        for name in ("path", "goal"):
            value = np.asarray(getattr(self, name), dtype=float).reshape(-1)
            if not np.all(np.isfinite(value)) or np.any(value < 0.0):
                raise ValueError(f"{name} tolerances must be finite and >= 0, got {value}")
            object.__setattr__(self, name, value)
        if self.path.shape != self.goal.shape:
            raise ValueError("path and goal tolerances must name the same joints")
        for name in ("goal_time", "stopped_velocity"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"{name} must be finite and >= 0, got {value}")

    @classmethod
    def unchecked(cls, n: int = 7) -> Tolerances:
        """The JTC's defaults for ``n`` joints."""
        return cls(np.zeros(n), np.zeros(n))


# ----------------------------------------------------------------------------- follower

DEFAULT_VELOCITY_LEAD_S = 0.04
"""s: the feed-forward velocity is the desired one this far ahead (`TrajectoryFollower`)."""

FEASIBILITY_TOLERANCE = 1e-6
"""rad: slack of the feasibility check over the position limits (rounding of the spline)."""

VELOCITY_SLACK = 0.01
ACCELERATION_SLACK = 0.25
"""Relative slack of the feasibility check over the velocity and acceleration limits. The
quintic through the samples of a trajectory that is itself within the limits bulges between
them: measured on 400 random moves time-parameterised at full and half scale, by up to
0.2 % in velocity and 12 % in acceleration. The command shaper absorbs that much without a
visible lag; the check is there for trajectories that are really too fast (a move timed at
twice the limit), which it refuses instead of following late."""

JOIN_STEP_RAD = 0.02
"""rad: a trajectory whose first point lies this close to the arm may be joined (the desired
state steps onto it) where interpolating to it in the time given cannot be followed; beyond,
it is refused. A stop reaches the arm within a few mrad of its first point; a jump asked of
the arm in milliseconds (0.3 rad in 50 ms) is refused."""

STOPPED_COMMAND_RAD_S = 1e-6
"""rad/s: a `TrajectoryFollower.brake` ends (and the arm holds) once every command is
below this."""

VELOCITY_FILTER_S = 0.01
"""s: time constant of the measured-velocity estimate used for ``stopped_velocity``."""


@dataclass(frozen=True)
class Plan:
    """A trajectory made ready to run: its spline and the controller time of its time 0."""

    spline: Spline
    start: float
    note: str = ""  # what the controller's "accepted" line should add (a joined start)


def _feasibility(spline: Spline, limits: JointLimits) -> str | None:
    """Why the interpolated trajectory cannot be followed within the limits, or None.

    The points may be within the limits while the curve between them is not (a quintic
    through close points overshoots; a short time asks for a high speed). Followed anyway,
    the command shaper would clip it and the arm lag behind and overshoot its goal (55-61
    mrad measured before this check), so such a trajectory is refused instead. Acceleration
    is checked on cubic and quintic curves only: a linear one (positions only) steps its
    velocity at every point by definition, and the shaper rounds those steps off.
    """
    q, qd, qdd = spline.sample()
    for what, bad in (("position", (q < limits.lower - FEASIBILITY_TOLERANCE)
                       | (q > limits.upper + FEASIBILITY_TOLERANCE)),
                      ("velocity", np.abs(qd) > limits.velocity * (1.0 + VELOCITY_SLACK)),
                      ("acceleration", np.abs(qdd) > limits.acceleration
                       * (1.0 + ACCELERATION_SLACK)
                       if spline.order >= 3 else np.zeros_like(q, dtype=bool))):
        if np.any(bad):
            k, j = np.argwhere(bad)[0]
            value, limit = {"position": (q[k, j], (limits.lower[j], limits.upper[j])),
                            "velocity": (qd[k, j], limits.velocity[j]),
                            "acceleration": (qdd[k, j], limits.acceleration[j])}[what]
            return (f"cannot be followed within the limits: between its points it asks "
                    f"{limits.names[j]} for {what} {value:.4g} (limit {limit})")
    return None


class TrajectoryFollower:
    """Tracks a joint trajectory with PID + velocity feed-forward, JTC style.

    `set_trajectory` replaces whatever runs (`prepare` + `start` do the same in two steps,
    so that a caller can check a long trajectory outside its lock), and `update` is called
    at ``rate_hz`` with the measured positions and returns the velocity command. Before
    the first trajectory, and after an abort, it holds the measured position. What it
    decides by itself (a trajectory aborted on a tolerance, a goal reached, a trajectory
    refused when it was set before the first measurement) is queued as one-line events for
    the caller to log: `take_events`. Not thread-safe: the ROS adapter calls it under a lock.

    The feed-forward velocity is the desired velocity ``velocity_lead_s`` ahead. A velocity
    loop lags its command (mock_panda's first-order actuator: 20 ms, plus ~2-8 ms of
    transport and sampling in the loop); fed the velocity of *now*, the lagging arm is
    ahead of the desired position while the trajectory decelerates and overshoots the goal
    (1.3-1.5 mrad on a 0.3 rad, 1.5 s move, simulated; 1-3 mrad measured over DDS). Leading
    by more than the lag turns that into a small trail that the P term closes monotonically
    (simulated: < 0.04 mrad past the goal for 0-8 ms of loop delay); leading by less
    leaves some of the overshoot, so the default errs on the long side.
    """

    def __init__(self, limits: JointLimits, gains: PIDGains | None = None,
                 rate_hz: float = 1000.0, interpolation: str = "quintic",
                 tolerances: Tolerances | None = None,
                 velocity_lead_s: float = DEFAULT_VELOCITY_LEAD_S):
        self.limits = limits
        self.n = limits.lower.size
        self.gains = gains if gains is not None else PIDGains.uniform(self.n)
        if self.gains.p.size != self.n:
            raise ValueError(f"PID gains are for {self.gains.p.size} joints, limits for {self.n}")
        if not (math.isfinite(rate_hz) and rate_hz > 0.0):
            raise ValueError(f"rate_hz must be a positive number, got {rate_hz}")
        if interpolation not in METHODS:
            raise ValueError(f"interpolation must be one of {METHODS}, got {interpolation!r}")
        self.tolerances = tolerances if tolerances is not None else Tolerances.unchecked(self.n)
        if self.tolerances.path.size != self.n:
            raise ValueError(f"tolerances are for {self.tolerances.path.size} joints, "
                             f"limits for {self.n}")
        if not (math.isfinite(velocity_lead_s) and velocity_lead_s >= 0.0):
            raise ValueError(f"velocity_lead_s must be >= 0, got {velocity_lead_s}")
        self.velocity_lead_s = float(velocity_lead_s)
        self.rate_hz = float(rate_hz)
        self.shaper = CommandShaper(limits)
        g = self.gains  # the integral is capped so that its term stays within i_clamp
        self._integral_cap = np.divide(g.i_clamp, g.i, out=np.zeros(self.n), where=g.i > 0.0)
        self.interpolation = interpolation
        self._spline: Spline | None = None
        self._start = 0.0
        self._goal_done = False
        self._pending: tuple | None = None  # set before the first measurement: no state yet
        self._hold_q: np.ndarray | None = None
        self._hold_pending = False
        self._braking = False  # `brake`: commands fall to zero, then hold where it stopped
        self._q_last: np.ndarray | None = None
        self._t_last: float | None = None
        zeros = np.zeros(self.n)
        self._u, self._a, self._integral = zeros.copy(), zeros.copy(), zeros.copy()
        self._v_est = zeros.copy()
        self._e_prev: np.ndarray | None = None
        self._desired = (zeros.copy(), zeros.copy(), zeros.copy())
        self._error = zeros.copy()
        self._events: list[tuple[str, str]] = []
        self.last_fault: str | None = None

    # -- commands in

    def snapshot(self) -> tuple[float, np.ndarray, np.ndarray] | None:
        """(time, measured position, command) of the last update; None before the first."""
        if self._q_last is None or self._t_last is None:
            return None
        return self._t_last, self._q_last.copy(), self._u.copy()

    def prepare(self, times, positions, velocities=None, accelerations=None,
                start_time: float | None = None,
                state: tuple[float, np.ndarray, np.ndarray] | None = None) -> Plan:
        """A `Plan` of the trajectory from ``state`` (a `snapshot`), or ValueError why not.

        Pure: reads only this follower's fixed settings, so it may run outside the caller's
        lock. ``start_time`` None starts the trajectory at the state's time (a zero header
        stamp). Like the JTC, when the trajectory's first point lies ahead of that time
        (``time_from_start`` > 0, or a future stamp), the motion is interpolated from the
        current position and velocity, reaching the first point on time: a future stamp
        is approached, not waited for. Refused: a trajectory of the wrong size, outside
        the limits, or one whose interpolated curve leaves the velocity or acceleration
        limits (`_feasibility`).
        """
        if state is None:
            raise ValueError("no joint state yet: the start of the motion is unknown")
        now, q, u = state
        times = np.asarray(times, dtype=float).reshape(-1)
        if times.size == 0:
            raise ValueError("a trajectory needs at least one point")
        spline = self._checked_spline(times, positions, velocities, accelerations, start_time)
        start = now if start_time is None else float(start_time)
        ahead = times[0] - (now - start)
        if ahead <= 0.0:
            reason = _feasibility(spline, self.limits)
            if reason:
                raise ValueError(reason)
            return Plan(spline, start)
        # anchor: the current state at `now`, then the trajectory's points
        anchored = self._anchored(spline, times + (start - now), q, u)
        junction = _feasibility(anchored, self.limits)
        if junction is None:
            return Plan(anchored, now)
        # how far the first point lies from where the arm gets by then at its command: a
        # stop from a state measured a few ms ago is ahead of the arm by its speed times
        # the rest of the 10 ms to its first point (26 mrad at 2.6 rad/s), not off it
        step = float(np.max(np.abs(spline.positions[0] - (q + u * ahead))))
        if step > JOIN_STEP_RAD or _feasibility(spline, self.limits):
            raise ValueError(junction)
        # The points can be followed, and the first lies within JOIN_STEP_RAD of the arm, but
        # the arm's velocity cannot be bent onto it in the few ms given: a stop planned
        # from a state measured while the arm accelerated (refused, it left the arm on the
        # motion just judged unsafe). Joined instead: the desired state steps to the first
        # point and the command shaper ramps the arm onto it within the acceleration and
        # jerk limits, as it does for any step.
        return Plan(spline, start, f"joined at its first point {1e3 * step:.1f} mrad from "
                                   f"where the arm's command takes it, not interpolated to it in "
                                   f"{1e3 * ahead:.0f} ms "
                                   f"({junction.split(': ', 1)[-1]})")

    def _checked_spline(self, times, positions, velocities, accelerations,
                        start_time: float | None) -> Spline:
        if start_time is not None and not math.isfinite(start_time):
            raise ValueError(f"start_time must be finite, got {start_time}")
        spline = Spline(times, positions, velocities, accelerations, self.interpolation)
        dof = spline.positions.shape[1]
        if dof != self.n:
            raise ValueError(f"trajectory has {dof} joints, expected {self.n}")
        reason = _check_limits(spline.positions, spline.velocities, self.limits, 1e-6)
        if reason:
            raise ValueError(reason)
        return spline

    def start(self, plan: Plan) -> None:
        """Replace whatever runs by ``plan`` (from `prepare`)."""
        self._spline, self._start = plan.spline, plan.start
        self._pending, self._hold_q, self._hold_pending = None, None, False
        self._goal_done, self._braking = False, False
        self._e_prev = None  # the error may jump: no derivative kick

    def set_trajectory(self, times, positions, velocities=None, accelerations=None,
                       start_time: float | None = None) -> None:
        """Replace the running trajectory (controller joint order; time 0 at ``start_time``).

        `prepare` from the last update's state, then `start`; raises ValueError (and keeps
        what runs) for a trajectory that `prepare` refuses. Before the first measurement the
        trajectory waits for it (refused then, it becomes an event and the arm holds). No
        points holds the current position: a library caller's stop (the controller node
        refuses empty messages, as the JTC does).
        """
        times = np.asarray(times, dtype=float).reshape(-1)
        if times.size == 0:
            self._spline, self._pending = None, None
            self._hold_q, self._hold_pending = None, True
            return
        state = self.snapshot()
        if state is None:
            self._checked_spline(times, positions, velocities, accelerations, start_time)
            self._pending = (times, positions, velocities, accelerations, start_time)
            self._spline, self._hold_pending = None, False
            return
        self.start(self.prepare(times, positions, velocities, accelerations, start_time, state))

    def hold(self, q) -> None:
        """Stop following any trajectory and hold ``q``."""
        q = np.asarray(q, dtype=float)
        if q.shape != (self.n,) or not np.all(np.isfinite(q)):
            raise ValueError(f"hold position must be {self.n} finite values, got {q}")
        self._spline, self._pending, self._hold_pending = None, None, False
        self._hold_q, self._braking = q.copy(), False
        self._e_prev = None

    def brake(self) -> None:
        """Stop following any trajectory and brake the command to zero within the limits
        (acceleration and jerk, as `CommandShaper` shapes every command), then hold where
        the arm came to rest. For a trajectory refused because it cannot be followed from
        the arm's state: it may have been a stop, and going on with the motion it was meant
        to end is what must not happen (a soak arm kept moving that way)."""
        self._spline, self._pending, self._hold_pending = None, None, False
        self._braking = True
        self._e_prev = None

    def take_events(self) -> list[tuple[str, str]]:
        """(level, line) pairs decided inside `update` since the last call; level is
        ``info``, ``warning`` or ``error``."""
        events, self._events = self._events, []
        return events

    def _anchored(self, spline: Spline, times: np.ndarray, q: np.ndarray,
                  u: np.ndarray) -> Spline:
        """The spline with the current state prepended at time 0 (the JTC does the same);
        ``times`` are the points' times from now."""
        def prepend(first, rows):
            return None if rows is None else np.vstack((first, rows))
        return Spline(np.concatenate(([0.0], times)),
                      np.vstack((q, spline.positions)),
                      prepend(u, spline.velocities),
                      prepend(np.zeros(self.n), spline.accelerations),
                      self.interpolation)

    # -- the loop

    def update(self, t: float, q_measured) -> np.ndarray:
        """The velocity command (rad/s, controller joint order) for time ``t``.

        A measurement with NaN/inf aborts the trajectory: the command brakes to zero within
        the limits and the arm holds the last good position (`last_fault` says why).
        """
        if not math.isfinite(t):
            raise ValueError(f"controller time must be finite, got {t}")
        q = np.asarray(q_measured, dtype=float)
        if q.shape != (self.n,):
            raise ValueError(f"measured positions must be {self.n} values, got shape {q.shape}")
        cycle = 1.0 / self.rate_hz
        dt = cycle if self._t_last is None else t - self._t_last
        if dt <= 0.0:
            return self._u.copy()  # same or earlier instant: nothing new to say
        # The PID works in the time that passed; the command is shaped for one cycle of the
        # arm whatever passed: a Franka applies one command per 1 ms cycle and checks the
        # acceleration and jerk implied by consecutive commands over that cycle. Shaped for
        # the measured (jittered) interval, a late tick asked a fixed-cycle arm for up to
        # 1.48x its acceleration and 2.3x its jerk limit (mock_panda's limit monitor, camera
        # demo on the loaded 2-core machine); for a late tick this is only slower.
        if not np.isfinite(q).all():
            self._t_last = t
            return self._fault(cycle)
        if self._q_last is not None:
            alpha = dt / (VELOCITY_FILTER_S + dt)
            self._v_est += alpha * ((q - self._q_last) / dt - self._v_est)
        self._t_last = t
        self._resolve_pending(t, q)
        if self._braking:
            return self._brake_step(q, cycle)
        q_d, qd_d, qdd_d = self._desired_state(t)
        if self._spline is not None:
            self._check_tolerances(t, q, q_d - q)
            if self._spline is None:  # aborted: hold here
                q_d, qd_d, qdd_d = self._desired_state(t)
        qd_ff = qd_d
        if self._spline is not None and self.velocity_lead_s > 0.0:
            qd_ff = self._spline.evaluate(t - self._start + self.velocity_lead_s)[1]
        self._pid(q_d - q, qd_ff, dt, q, cycle)
        self._q_last = q.copy()
        self._desired = (q_d, qd_d, qdd_d)
        return self._u.copy()

    def _resolve_pending(self, t: float, q: np.ndarray) -> None:
        if self._pending is not None:
            times, pos, vel, acc, start = self._pending
            self._pending = None
            try:
                self.start(self.prepare(times, pos, vel, acc, start, (t, q, self._u.copy())))
            except ValueError as exc:
                self._events.append(("error", f"rejected trajectory: {exc}; holding"))
        if self._hold_pending or (self._spline is None and self._hold_q is None):
            self._hold_q, self._hold_pending = q.copy(), False

    def _check_tolerances(self, t: float, q: np.ndarray, e: np.ndarray) -> None:
        """The JTC's path and goal checks (`Tolerances`); an abort holds ``q``."""
        tol = self.tolerances
        end = self._start + self._spline.times[-1]
        names = self.limits.names
        if t < end:
            bad = (tol.path > 0.0) & (np.abs(e) > tol.path)
            if np.any(bad):
                j = int(np.argmax(bad))
                self.hold(q)
                self._events.append((
                    "error", f"path tolerance violated: {names[j]} is {1e3 * e[j]:+.2f} mrad "
                    f"from its desired position (constraints.{names[j]}.trajectory "
                    f"{1e3 * tol.path[j]:.2f} mrad): trajectory aborted, holding the "
                    "measured position"))
            return
        if self._goal_done:
            return
        off = (tol.goal > 0.0) & (np.abs(e) > tol.goal)
        moving = tol.stopped_velocity > 0.0 and bool(
            np.any(np.abs(self._v_est) > tol.stopped_velocity))
        if not off.any() and not moving:
            self._goal_done = True
            self._events.append(("info", f"goal reached {t - end:.3f} s after the end, largest "
                                 f"error {1e3 * np.max(np.abs(e)):.3f} mrad"))
        elif tol.goal_time > 0.0 and t - end > tol.goal_time:
            j = int(np.argmax(off)) if off.any() else int(np.argmax(np.abs(self._v_est)))
            why = (f"{names[j]} is {1e3 * e[j]:+.2f} mrad from the goal (constraints."
                   f"{names[j]}.goal {1e3 * tol.goal[j]:.2f} mrad)" if off.any() else
                   f"{names[j]} still moves at {self._v_est[j]:.4f} rad/s "
                   f"(constraints.stopped_velocity_tolerance {tol.stopped_velocity:g})")
            self.hold(q)
            self._events.append(("error", f"goal not reached within constraints.goal_time "
                                 f"{tol.goal_time:g} s: {why}; trajectory aborted, holding the "
                                 "measured position"))

    def _desired_state(self, t: float):
        if self._spline is None:
            zero = np.zeros(self.n)
            return self._hold_q.copy(), zero, zero.copy()
        return self._spline.evaluate(t - self._start)

    def _pid(self, e: np.ndarray, qd_d: np.ndarray, dt: float, q: np.ndarray,
             cycle: float) -> None:
        """PID + feed-forward clipped to the velocity and position-limit bounds, shaped into
        the next command (`CommandShaper`), with the integral's anti-windup: `_pid_step`.
        """
        g = self.gains
        step = min(dt, 10.0 / self.rate_hz)  # a stalled loop must not dump a lump into I
        low, high = self.shaper.position_bounds(q)
        u, a, integral = np.empty(self.n), np.empty(self.n), np.empty(self.n)
        sh = self.shaper
        _pid_step(e, self._e_prev if self._e_prev is not None else e,
                  self._e_prev is not None, qd_d, dt, step, self._integral,
                  self._integral_cap, g.p, g.i, g.d, g.ff_velocity_scale, low, high, self._u,
                  self._a, sh.vmax, sh.amax, sh.jmax, cycle, u, a, integral)
        self._u, self._a, self._integral = u, a, integral
        self._e_prev = self._error = e

    def _brake_step(self, q: np.ndarray, cycle: float) -> np.ndarray:
        """One tick of `brake`: the command shaped toward zero (inside the position-limit
        bounds); once it is zero, hold the measured position."""
        low, high = self.shaper.position_bounds(q)
        target = np.minimum(np.maximum(np.zeros(self.n), low), high)
        self._u, self._a = self.shaper.shape(target, self._u, self._a, cycle)
        self._integral[:] = 0.0
        self._error = np.zeros(self.n)
        self._q_last = q.copy()
        self._desired = (q.copy(), np.zeros(self.n), np.zeros(self.n))
        if float(np.max(np.abs(self._u))) <= STOPPED_COMMAND_RAD_S:
            self._braking, self._hold_q = False, q.copy()
        return self._u.copy()

    def _fault(self, cycle: float) -> np.ndarray:
        self.last_fault = "measured position holds NaN or inf: trajectory aborted, holding"
        self._spline, self._pending = None, None
        if self._q_last is not None:
            self._hold_q = self._q_last.copy()
        else:
            self._hold_pending = True
        self._integral[:] = 0.0
        self._v_est[:] = 0.0
        self._e_prev = None
        self._error = np.full(self.n, np.nan)
        self._u, self._a = self.shaper.shape(np.zeros(self.n), self._u, self._a, cycle)
        return self._u.copy()

    # -- state out

    @property
    def desired(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Desired (q, qd, qdd) of the last update, for the controller_state topic."""
        return tuple(x.copy() for x in self._desired)

    @property
    def error(self) -> np.ndarray:
        """Desired minus measured position of the last update (NaN after a bad measurement)."""
        return self._error.copy()

    @property
    def command(self) -> np.ndarray:
        return self._u.copy()

    @property
    def active(self) -> bool:
        """True while a trajectory is running or waiting to start."""
        return self._spline is not None or self._pending is not None

    def finished(self, t: float, q, tolerance: float = 1e-3) -> bool:
        """True when the trajectory's time is over and ``q`` is within ``tolerance`` of its end.

        While holding, true when ``q`` is within ``tolerance`` of the held position.
        """
        q = np.asarray(q, dtype=float)
        if self._pending is not None or self._hold_pending or self._braking:
            return False
        if self._spline is not None:
            if t < self._start + self._spline.times[-1]:
                return False
            goal = self._spline.positions[-1]
        elif self._hold_q is not None:
            goal = self._hold_q
        else:
            return False
        return bool(np.all(np.abs(q - goal) <= tolerance))
