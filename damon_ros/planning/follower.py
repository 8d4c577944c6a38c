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

from damon_ros.core.limits import POSITION_LIMIT_MARGIN, JointLimits
from damon_ros.planning.trajectory import METHODS, Spline

# Fraction of the acceleration limit used for the braking curve before a position limit; the
# rest is headroom for the jerk-limited transition into braking and for tracking lag.
POSITION_BRAKE_FRACTION = 0.5


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


def _check_names(joint_names: Sequence[str], expected_names: Sequence[str]) -> str | None:
    names = list(joint_names)
    if len(set(names)) != len(names):
        return f"joint names repeat: {names}"
    unknown = sorted(set(names) - set(expected_names))
    if unknown:
        return f"unknown joints {unknown}; this controller drives {list(expected_names)}"
    missing = [n for n in expected_names if n not in names]
    if missing:
        return f"missing joints {missing}; a trajectory must command all of {list(expected_names)}"
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


def _points(joint_names, expected_names, times, positions, velocities, accelerations):
    """Check structure and values; (positions, velocities, accelerations) in controller order."""
    reason = _check_names(joint_names, expected_names) or _check_times(times)
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
    order = [list(joint_names).index(n) for n in expected_names]
    return None, tuple(None if a is None else a[:, order] for a in (pos, vel, acc))


def validate_trajectory(joint_names: Sequence[str], expected_names: Sequence[str], times,
                        positions, velocities, accelerations, limits: JointLimits,
                        tolerance: float = 1e-6, start_time: float | None = None,
                        now: float | None = None) -> str | None:
    """None when the trajectory is acceptable, else a one-line reason to log and ignore it.

    The JTC's rules: joints must match the controller's (any order, none missing, none
    unknown), time_from_start strictly increasing, no NaN or inf, consistent vector lengths;
    plus ours: positions within the limits and velocities within the velocity limits. With
    ``start_time`` and ``now`` a trajectory that would already have ended is rejected too.
    An empty trajectory (no points) is valid: it means "stop and hold".
    """
    reason, arrays = _points(joint_names, expected_names, times, positions, velocities,
                             accelerations)
    if reason:
        return reason
    pos, vel, _ = arrays
    if pos.shape[0] == 0:
        return None
    reason = _check_limits(pos, vel, limits, tolerance)
    if reason:
        return reason
    if start_time is not None and now is not None and start_time > 0.0 and \
            start_time + float(times[-1]) < now:
        return "trajectory ends in the past"
    return None


def reorder_points(joint_names: Sequence[str], expected_names: Sequence[str], times, positions,
                   velocities=None, accelerations=None):
    """(times, positions, velocities|None, accelerations|None) as arrays in controller order.

    Call after `validate_trajectory` accepted the message; raises ValueError otherwise.
    """
    reason, arrays = _points(joint_names, expected_names, times, positions, velocities,
                             accelerations)
    if reason:
        raise ValueError(reason)
    return (np.asarray(times, dtype=float), *arrays)


# ----------------------------------------------------------------------------- command shaping

def _reachable_acceleration(gap: np.ndarray, jerk: np.ndarray, dt: float) -> np.ndarray:
    """Largest acceleration for this step from which velocity can still settle within ``gap``.

    Commanding a (>= 0) for dt raises the velocity by a*dt; bringing the acceleration back
    to zero at the jerk limit then adds at most a^2 / (2 jerk), whatever the later periods
    are (a right Riemann sum of a falling ramp stays under its integral). Solving
    a*dt + a^2 / (2 jerk) = gap for a gives this bound. Once u + a^2 / (2 jerk) <= vmax
    holds, dropping a by jerk*dt keeps it true for any next dt — so the command can never
    be forced over the velocity limit, even when the control period jitters.
    """
    two_gap = 2.0 * gap  # the root in the cancellation-free form: tiny gaps close exactly
    return two_gap / (dt + np.sqrt(dt * dt + np.abs(two_gap) / jerk))


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

    def position_bounds(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(low, high) velocity bounds that brake to a stop `POSITION_LIMIT_MARGIN` inside the
        position limits.

        v <= sqrt(2 b d) with d the distance left and b a fraction of the acceleration limit,
        so motion toward a limit fades to zero at the limit, and none is allowed past it.
        """
        room = np.maximum(np.array((self.upper - POSITION_LIMIT_MARGIN - q,
                                    q - self.lower - POSITION_LIMIT_MARGIN)), 0.0)
        up, down = np.minimum(np.sqrt(self._brake * room), self.vmax)
        return -down, up

    def shape(self, target: np.ndarray, u: np.ndarray, a: np.ndarray,
              dt: float) -> tuple[np.ndarray, np.ndarray]:
        """(next velocity command, its acceleration), moving from ``u`` toward ``target``.

        ``target`` is approached as fast as the limits allow without overshooting it.
        """
        vmax, amax = self.vmax, self.amax
        jd = self.jmax * dt
        if np.isnan(target).any():  # inf - inf from absurd inputs: no sensible target, stop
            target = np.nan_to_num(target, nan=0.0)
        target = np.minimum(np.maximum(target, -vmax), vmax)
        a_goal = _reachable_acceleration(target - u, self.jmax, dt)
        low, high = np.maximum(a - jd, -amax), np.minimum(a + jd, amax)
        a_next = np.minimum(np.maximum(a_goal, low), high)
        u_next = np.minimum(np.maximum(u + a_next * dt, -vmax), vmax)
        return u_next, (u_next - u) / dt


# ----------------------------------------------------------------------------- follower

class TrajectoryFollower:
    """Tracks a joint trajectory with PID + velocity feed-forward, JTC style.

    `set_trajectory` replaces whatever runs (an empty one holds the current position), and
    `update` is called at ``rate_hz`` with the measured positions and returns the velocity
    command. Not thread-safe: the ROS adapter calls it from one executor thread.
    """

    def __init__(self, limits: JointLimits, gains: PIDGains | None = None,
                 rate_hz: float = 1000.0, interpolation: str = "quintic"):
        self.limits = limits
        self.n = limits.lower.size
        self.gains = gains if gains is not None else PIDGains.uniform(self.n)
        if self.gains.p.size != self.n:
            raise ValueError(f"PID gains are for {self.gains.p.size} joints, limits for {self.n}")
        if not (math.isfinite(rate_hz) and rate_hz > 0.0):
            raise ValueError(f"rate_hz must be a positive number, got {rate_hz}")
        if interpolation not in METHODS:
            raise ValueError(f"interpolation must be one of {METHODS}, got {interpolation!r}")
        self.rate_hz = float(rate_hz)
        self.shaper = CommandShaper(limits)
        g = self.gains  # the integral is capped so that its term stays within i_clamp
        self._integral_cap = np.divide(g.i_clamp, g.i, out=np.zeros(self.n), where=g.i > 0.0)
        self.interpolation = interpolation
        self._spline: Spline | None = None
        self._start: float | None = None
        self._pending: tuple | None = None  # a trajectory waiting for the current state
        self._hold_q: np.ndarray | None = None
        self._hold_pending = False
        self._q_last: np.ndarray | None = None
        self._t_last: float | None = None
        zeros = np.zeros(self.n)
        self._u, self._a, self._integral = zeros.copy(), zeros.copy(), zeros.copy()
        self._e_prev: np.ndarray | None = None
        self._desired = (zeros.copy(), zeros.copy(), zeros.copy())
        self._error = zeros.copy()
        self.last_fault: str | None = None

    # -- commands in

    def set_trajectory(self, times, positions, velocities=None, accelerations=None,
                       start_time: float | None = None) -> None:
        """Replace the running trajectory (controller joint order; time 0 at ``start_time``).

        ``start_time`` None starts it at the next `update` (a zero header stamp). No points
        stops the arm and holds the current position. When the first point lies after time
        0, the motion starts from the current state, as in the JTC.
        """
        times = np.asarray(times, dtype=float).reshape(-1)
        if times.size == 0:
            self._spline, self._pending = None, None
            self._hold_q, self._hold_pending = None, True
            return
        if start_time is not None and not math.isfinite(start_time):
            raise ValueError(f"start_time must be finite, got {start_time}")
        spline = Spline(times, positions, velocities, accelerations, self.interpolation)
        dof = spline.positions.shape[1]
        if dof != self.n:
            raise ValueError(f"trajectory has {dof} joints, expected {self.n}")
        reason = _check_limits(spline.positions, spline.velocities, self.limits, 1e-6)
        if reason:
            raise ValueError(reason)
        self._pending = (spline, start_time)
        self._spline, self._hold_pending = None, False
        if self._q_last is not None and start_time is not None:
            self._activate(self._q_last)

    def hold(self, q) -> None:
        """Stop following any trajectory and hold ``q``."""
        q = np.asarray(q, dtype=float)
        if q.shape != (self.n,) or not np.all(np.isfinite(q)):
            raise ValueError(f"hold position must be {self.n} finite values, got {q}")
        self._spline, self._pending, self._hold_pending = None, None, False
        self._hold_q = q.copy()
        self._e_prev = None

    def _activate(self, q: np.ndarray, now: float | None = None) -> None:
        """Start the pending trajectory from the current state ``q``."""
        spline, start = self._pending
        self._pending = None
        self._start = now if start is None else start
        if spline.times[0] > 0.0:
            spline = self._anchored(spline, q)
        self._spline, self._hold_q = spline, None
        self._e_prev = None  # the error may jump: no derivative kick

    def _anchored(self, spline: Spline, q: np.ndarray) -> Spline:
        """The spline with the current state prepended at time 0 (the JTC does the same)."""
        def prepend(first, rows):
            return None if rows is None else np.vstack((first, rows))
        return Spline(np.concatenate(([0.0], spline.times)),
                      np.vstack((q, spline.positions)),
                      prepend(self._u, spline.velocities),
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
        self._t_last = t
        # The PID works in the time that passed; the command is shaped for one cycle of the
        # arm whatever passed: a Franka applies one command per 1 ms cycle and checks the
        # acceleration and jerk implied by consecutive commands over that cycle. Shaped for
        # the measured (jittered) interval, a late tick asked a fixed-cycle arm for up to
        # 1.48x its acceleration and 2.3x its jerk limit (mock_panda's limit monitor, camera
        # demo on the loaded 2-core machine); for a late tick this is only slower.
        if not np.isfinite(q).all():
            return self._fault(cycle)
        self._resolve_pending(t, q)
        q_d, qd_d, qdd_d = self._desired_state(t)
        target, integral = self._pid(q_d - q, qd_d, dt, q)
        self._u, self._a = self.shaper.shape(target, self._u, self._a, cycle)
        # Anti-windup: integrate only where the arm is given what the PID asked for — not
        # clipped, and not more than a step of full acceleration behind (rate-limited).
        free = np.abs(self._u - target) <= self.shaper.amax * cycle
        self._integral = np.where(free, integral, self._integral)
        self._q_last = q.copy()
        self._desired = (q_d, qd_d, qdd_d)
        return self._u.copy()

    def _resolve_pending(self, t: float, q: np.ndarray) -> None:
        if self._pending is not None:
            self._activate(q, now=t)
        if self._hold_pending or (self._spline is None and self._hold_q is None):
            self._hold_q, self._hold_pending = q.copy(), False

    def _desired_state(self, t: float):
        if self._spline is None:
            zero = np.zeros(self.n)
            return self._hold_q.copy(), zero, zero.copy()
        return self._spline.evaluate(t - self._start)

    def _pid(self, e: np.ndarray, qd_d: np.ndarray, dt: float, q: np.ndarray):
        """(PID + feed-forward clipped to the velocity and position-limit bounds, integral).

        The integral returned is clamped so that its term stays within ``i_clamp``; `update`
        keeps it only on joints whose output is not saturated, and only if it was not clipped
        here (a clipped raw output lies beyond the bounds, so it can never be delivered).
        """
        g = self.gains
        step = min(dt, 10.0 / self.rate_hz)  # a stalled loop must not dump a lump into I
        cap = self._integral_cap
        integral = np.minimum(np.maximum(self._integral + e * step, -cap), cap)
        raw = g.ff_velocity_scale * qd_d + g.p * e + g.i * integral
        if self._e_prev is not None:
            raw += g.d * (e - self._e_prev) / dt
        low, high = self.shaper.position_bounds(q)
        target = np.minimum(np.maximum(raw, low), high)
        self._e_prev = self._error = e
        return target, np.where(raw == target, integral, self._integral)

    def _fault(self, cycle: float) -> np.ndarray:
        self.last_fault = "measured position holds NaN or inf: trajectory aborted, holding"
        self._spline, self._pending = None, None
        if self._q_last is not None:
            self._hold_q = self._q_last.copy()
        else:
            self._hold_pending = True
        self._integral[:] = 0.0
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
        if self._pending is not None or self._hold_pending:
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
