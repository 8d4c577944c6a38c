"""Joint trajectories: time parameterisation of certified paths, and spline interpolation.

The planner certifies the *straight joint-space segments* between its waypoints as
collision-free, so the executed motion must stay on those segments. `time_parameterize`
therefore moves rest-to-rest along each segment with a phase-synchronised, jerk-limited
profile: every joint follows the same normalised profile, so the arm never leaves the line.

Why a one-DoF ruckig problem instead of ruckig's seven-DoF ``Synchronization.Phase``:
ruckig scales the profile of the slowest joint onto the others and, when that scaled
profile would break another joint's acceleration or jerk limit, silently falls back to
time synchronisation, which leaves the line (measured up to 0.13 rad off on random Panda
segments). Moving along the line is a one-DoF problem in the arc parameter ``s``: the joint
limits become ``min_i(limit_i / |u_i|)`` with ``u`` the unit (max-norm) direction. Its
ruckig solution is exactly the phase-synchronised, time-optimal straight-line profile —
identical to ruckig's Phase result whenever that one succeeds — and is on the line by
construction.

`Spline` / `interpolate` reproduce ros2_controllers' joint_trajectory_controller between
JointTrajectory points: linear with positions only, cubic with velocities, quintic with
velocities and accelerations.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass, field

import numpy as np
from numba import njit
from ruckig import ControlInterface, InputParameter, Result, Ruckig
from ruckig import Trajectory as _RuckigTrajectory

from damon_ros.core.limits import JointLimits

METHODS = ("quintic", "cubic", "linear")
# Waypoints closer than this (rad, max-norm) are one waypoint: a move that small would need
# a microsecond-long segment whose spline coefficients divide by its duration to the fifth.
_SAME_WAYPOINT = 1e-9


def _as_matrix(name: str, value, rows: int | None, cols: int | None) -> np.ndarray:
    """A finite float matrix of the given shape, or ValueError naming ``name``."""
    arr = np.asarray(value, dtype=float)
    if arr.ndim != 2 or (rows is not None and arr.shape[0] != rows) or (
        cols is not None and arr.shape[1] != cols
    ):
        raise ValueError(f"{name} must have shape ({rows or 'N'}, {cols or 'n'}), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} holds NaN or inf")
    return arr


def _check_times(times) -> np.ndarray:
    """Times must be finite, 1-D and strictly increasing: the spline divides by their gaps."""
    t = np.asarray(times, dtype=float)
    if t.ndim != 1 or t.size == 0:
        raise ValueError(f"times must be a non-empty 1-D array, got shape {t.shape}")
    if not np.all(np.isfinite(t)):
        raise ValueError("times hold NaN or inf")
    if np.any(np.diff(t) <= 0.0):
        raise ValueError("times must be strictly increasing")
    return t


class Spline:
    """Piecewise polynomial through trajectory points, precomputed for fast evaluation.

    The controller evaluates it at 1 kHz, so the per-segment coefficients are built once;
    `evaluate` is then one bisection and one small matrix product.
    """

    def __init__(self, times, positions, velocities=None, accelerations=None,
                 method: str = "quintic"):
        if method not in METHODS:
            raise ValueError(f"interpolation method must be one of {METHODS}, got {method!r}")
        self.times = _check_times(times)
        n_pts = self.times.size
        self.positions = _as_matrix("positions", positions, n_pts, None)
        dof = self.positions.shape[1]
        vel = None if velocities is None else _as_matrix("velocities", velocities, n_pts, dof)
        acc = None if accelerations is None else _as_matrix(
            "accelerations", accelerations, n_pts, dof)
        # Like the JTC: the order is limited by what the points carry and by the method.
        if vel is None or method == "linear":
            self.order, vel, acc = 1, None, None
        elif acc is None or method == "cubic":
            self.order, acc = 3, None
        else:
            self.order = 5
        self.velocities = vel
        self.accelerations = acc
        self._coeffs = self._build(vel, acc)  # (segments, 6, dof)
        self._knots = self.times.tolist()

    def _build(self, vel, acc) -> np.ndarray:
        p, t = self.positions, self.times
        seg = max(t.size - 1, 0)
        c = np.zeros((seg, 6, p.shape[1]))
        if seg == 0:
            return c
        h = np.diff(t)[:, None]
        dp = p[1:] - p[:-1]
        c[:, 0] = p[:-1]
        if self.order == 1:
            c[:, 1] = dp / h
            return c
        v0, v1 = vel[:-1], vel[1:]
        c[:, 1] = v0
        if self.order == 3:
            c[:, 2] = (3.0 * dp - (2.0 * v0 + v1) * h) / h**2
            c[:, 3] = (-2.0 * dp + (v0 + v1) * h) / h**3
            return c
        a0, a1 = acc[:-1], acc[1:]
        c[:, 2] = 0.5 * a0
        c[:, 3] = (20.0 * dp - (8.0 * v1 + 12.0 * v0) * h - (3.0 * a0 - a1) * h**2) / (2 * h**3)
        c[:, 4] = (-30.0 * dp + (14.0 * v1 + 16.0 * v0) * h + (3.0 * a0 - 2.0 * a1) * h**2) / (
            2 * h**4)
        c[:, 5] = (12.0 * dp - 6.0 * (v1 + v0) * h - (a0 - a1) * h**2) / (2 * h**5)
        return c

    @property
    def duration(self) -> float:
        return self._knots[-1] - self._knots[0]

    def evaluate(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(q, qd, qdd) at time ``t``, holding the end points (zero rates) outside the span.

        Outside the span the arm is meant to stand still, so rates are zero there rather
        than the end point's stored rates (which a well-formed trajectory has zero anyway).
        """
        knots = self._knots
        if not knots[0] <= t <= knots[-1] or len(knots) == 1:  # NaN lands here too
            return self._hold(0 if not t > knots[0] else -1)
        i = min(bisect.bisect_right(knots, t) - 1, len(knots) - 2)
        s = t - knots[i]
        s2, s3 = s * s, s * s * s
        basis = np.array((
            (1.0, s, s2, s3, s2 * s2, s3 * s2),
            (0.0, 1.0, 2.0 * s, 3.0 * s2, 4.0 * s3, 5.0 * s2 * s2),
            (0.0, 0.0, 2.0, 6.0 * s, 12.0 * s2, 20.0 * s3),
        ))
        q, qd, qdd = basis @ self._coeffs[i]
        return q, qd, qdd

    def _hold(self, index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        q = self.positions[index].copy()
        return q, np.zeros_like(q), np.zeros_like(q)

    def sample(self, per_segment: int = 64) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(q, qd, qdd), each (samples, dof): ``per_segment`` evenly spaced samples of every
        segment, both ends included, vectorised.

        For checking a whole trajectory at once (the controller refuses one it cannot
        follow): `evaluate` point by point would take ~10 us a sample.
        """
        if self.times.size < 2:
            q = self.positions.copy()
            return q, np.zeros_like(q), np.zeros_like(q)
        s = np.linspace(0.0, 1.0, per_segment)[None, :] * np.diff(self.times)[:, None]
        powers = s[..., None] ** np.arange(6)  # (segments, samples, 6)
        k = np.arange(6, dtype=float)
        d1 = np.concatenate((np.zeros_like(s[..., None]), powers[..., :5] * k[1:]), axis=-1)
        d2 = np.concatenate((np.zeros_like(powers[..., :2]),
                             powers[..., :4] * (k[2:] * k[1:5])), axis=-1)
        dof = self.positions.shape[1]
        out = (np.einsum("smk,skd->smd", b, self._coeffs).reshape(-1, dof)
               for b in (powers, d1, d2))
        return tuple(out)


def interpolate(times, positions, velocities, accelerations, t: float,
                method: str = "quintic") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(q, qd, qdd) at ``t`` between JointTrajectory points, as ros2_controllers' JTC does.

    Linear with positions only, cubic when velocities are given, quintic when accelerations
    are given too (``method`` caps the order: "cubic" ignores accelerations). Before the
    first and after the last point the end point is held. Build a `Spline` instead when
    evaluating the same points many times.
    """
    return Spline(times, positions, velocities, accelerations, method).evaluate(t)


@dataclass
class Trajectory:
    """A sampled joint trajectory starting at t = 0; rows are samples, columns joints."""

    times: np.ndarray
    positions: np.ndarray
    velocities: np.ndarray
    accelerations: np.ndarray
    _spline: Spline | None = field(default=None, init=False, repr=False, compare=False)

    def __post_init__(self):
        self.times = _check_times(self.times)
        if self.times[0] != 0.0:
            raise ValueError(f"times must start at 0, got {self.times[0]}")
        n = self.times.size
        self.positions = _as_matrix("positions", self.positions, n, None)
        dof = self.positions.shape[1]
        self.velocities = _as_matrix("velocities", self.velocities, n, dof)
        self.accelerations = _as_matrix("accelerations", self.accelerations, n, dof)

    @classmethod
    def _built(cls, times, positions, velocities, accelerations) -> Trajectory:
        """A trajectory of arrays joined here from valid trajectories (`concatenate`,
        `held_until`: increasing times from 0, finite rows by construction), without
        `__post_init__`'s checks again (~0.1 ms each, several a re-plan)."""
        out = object.__new__(cls)
        out.times, out.positions = times, positions
        out.velocities, out.accelerations = velocities, accelerations
        out._spline = None
        return out

    @property
    def duration(self) -> float:
        return float(self.times[-1])

    def sample(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(q, qd, qdd) at ``t``, quintic between samples, clamped to the ends."""
        if self._spline is None:
            self._spline = Spline(self.times, self.positions, self.velocities,
                                  self.accelerations, "quintic")
        return self._spline.evaluate(float(t))

    def resample(self, dt: float) -> Trajectory:
        """The same motion sampled every ``dt`` seconds (the end sample is always kept)."""
        times = time_grid(self.duration, dt)
        rows = [self.sample(t) for t in times]
        return Trajectory(times, *(np.array([r[k] for r in rows]) for k in range(3)))


def time_grid(duration: float, dt: float) -> np.ndarray:
    """0, dt, 2dt, ... and ``duration`` itself, with no gap below dt/1000 but the first."""
    if not (np.isfinite(dt) and dt > 0.0):
        raise ValueError(f"dt must be a positive finite number, got {dt}")
    if not (np.isfinite(duration) and duration >= 0.0):
        raise ValueError(f"duration must be finite and >= 0, got {duration}")
    grid = np.arange(0.0, duration, dt)
    if grid.size > 1 and duration - grid[-1] < 1e-3 * dt:
        grid = grid[:-1]
    return np.append(grid, duration) if duration > 0.0 else np.zeros(1)


def _with_knots(grid: np.ndarray, knots: np.ndarray, dt: float) -> np.ndarray:
    """The grid plus every waypoint time, so that no sample interval straddles a corner.

    A spline between two samples on different segments would cut the corner and leave the
    certified lines; with the waypoint times in the grid every interval lies on one line.
    """
    if knots.size == 0:
        return grid
    near = np.min(np.abs(grid[:, None] - knots[None, :]), axis=1) < 1e-3 * dt
    keep = grid[~near | (grid == grid[-1]) | (grid == 0.0)]
    return np.unique(np.concatenate((keep, knots)))


@dataclass(frozen=True)
class _Segment:
    """One rest-to-rest straight move: q(t) = start + s(t) * direction, s from 0 to length.

    s(t) is ruckig's seven-phase constant-jerk profile, kept as its phase table (durations,
    jerks and the state at each phase start) so that sampling is vectorised rather than a
    Python call to ruckig per sample.
    """

    start: np.ndarray
    direction: np.ndarray  # max-norm 1
    phase_start: np.ndarray  # (7,) times at which the phases begin
    jerk: np.ndarray  # (7,) per phase
    state: np.ndarray  # (3, 8): s, sd, sdd at each phase boundary
    duration: float

    @classmethod
    def from_ruckig(cls, start, direction, trajectory: _RuckigTrajectory) -> _Segment:
        profile = trajectory.profiles[0][0]
        if profile.brake.duration > 0.0 or profile.accel.duration > 0.0:
            raise ValueError("unexpected ruckig brake/accel pre-profile on a rest-to-rest move")
        t = np.asarray(profile.t, dtype=float)
        state = np.array([profile.p, profile.v, profile.a], dtype=float)
        starts = np.concatenate(([0.0], np.cumsum(t)[:-1]))
        return cls(start, direction, starts, np.asarray(profile.j, dtype=float), state,
                   float(trajectory.duration))

    def at(self, times: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(q, qd, qdd), each (len(times), dof), at segment-local ``times`` (clamped)."""
        t = np.clip(np.asarray(times, dtype=float), 0.0, self.duration)
        k = np.searchsorted(self.phase_start, t, side="right") - 1
        h = t - self.phase_start[k]
        s0, v0, a0 = self.state[:, k]
        j = self.jerk[k]
        s = s0 + h * (v0 + h * (a0 / 2.0 + h * j / 6.0))
        sd = v0 + h * (a0 + h * j / 2.0)
        sdd = a0 + h * j
        u = self.direction
        return self.start + np.outer(s, u), np.outer(sd, u), np.outer(sdd, u)


def _line_profile(a: np.ndarray, b: np.ndarray, vmax, amax, jmax, otg: Ruckig,
                  slow: float = 1.0) -> _Segment:
    """The time-optimal jerk-limited rest-to-rest move from ``a`` to ``b`` along the line;
    ``slow`` < 1 scales its velocity by ``slow`` and its acceleration by ``slow**2``."""
    delta = b - a
    length = float(np.max(np.abs(delta)))
    u = delta / length
    moving = np.abs(u) > 0.0
    scale = np.abs(u[moving])
    inp = InputParameter(1)
    inp.current_position = [0.0]
    inp.target_position = [length]
    inp.max_velocity = [slow * float(np.min(vmax[moving] / scale))]
    inp.max_acceleration = [slow * slow * float(np.min(amax[moving] / scale))]
    inp.max_jerk = [float(np.min(jmax[moving] / scale))]
    profile = _RuckigTrajectory(1)
    result = otg.calculate(inp, profile)
    if result != Result.Working:
        raise ValueError(f"ruckig could not time-parameterise a segment: {result}")
    return _Segment.from_ruckig(a, u, profile)


def _check_scale(name: str, value: float) -> float:
    if not (np.isfinite(value) and 0.0 < value <= 1.0):
        raise ValueError(f"{name} must be in (0, 1], got {value}")
    return float(value)


def time_parameterize(path, limits: JointLimits, velocity_scale: float = 1.0,
                      acceleration_scale: float = 1.0, jerk_scale: float = 1.0,
                      dt: float = 0.01) -> Trajectory:
    """Rest-to-rest, jerk-limited motion along a piecewise-linear joint path, sampled at dt.

    Each straight segment is its own rest-to-rest move, so the arm stops at every waypoint
    and never cuts a corner off the certified lines. Repeated waypoints are skipped.
    """
    scales = [_check_scale(n, s) for n, s in (("velocity_scale", velocity_scale),
                                              ("acceleration_scale", acceleration_scale),
                                              ("jerk_scale", jerk_scale))]
    dof = limits.lower.size
    pts = _as_matrix("path", path, None, dof)
    if pts.shape[0] == 0:
        raise ValueError("path must hold at least one waypoint")
    if not all(limits.within(q, 1e-9) for q in pts):
        raise ValueError("path has a waypoint outside the joint position limits")
    lim = limits.scaled(*scales)
    segments = _segments(pts, lim)
    return _sample_segments(segments, pts[-1], dt)


def _segments(pts: np.ndarray, lim: JointLimits) -> list[_Segment]:
    otg = Ruckig(1)
    return [
        _within_velocity_bounds(a, b, lim, otg)
        for a, b in zip(pts[:-1], pts[1:], strict=True)
        if np.max(np.abs(b - a)) > _SAME_WAYPOINT
    ]


RETIME_CHECK_S = 0.002
"""Spacing (s) of the states at which a segment is checked against position-dependent
velocity bounds: 2 ms of motion at 2.6 rad/s is 5 mrad, where the bound changes little."""


def _within_velocity_bounds(a: np.ndarray, b: np.ndarray, lim: JointLimits,
                            otg: Ruckig) -> _Segment:
    """The line move from ``a`` to ``b``, re-timed until no state of it is faster than
    `JointLimits.velocity_bounds` (the FR3's bounds fall toward each position limit, so a
    move planned with the constant maxima would command up to 0.9 rad/s above them there).

    Each round slows the whole segment by the worst ratio bound / velocity found (a little
    more, for the states between checks); a rest-to-rest move approaches its end at
    ~sqrt(2 a d), so scaling acceleration by the square of the velocity factor slows the
    states near a limit as much as the cruise. Constant bounds need no check: ruckig keeps
    to them by construction.
    """
    seg = _line_profile(a, b, lim.velocity, lim.acceleration, lim.jerk, otg)
    if lim.curve is None:
        return seg
    slow = 1.0
    for _ in range(40):
        t = np.linspace(0.0, seg.duration, max(8, int(seg.duration / RETIME_CHECK_S) + 2))
        q, qd, _ = seg.at(t)
        lower, upper = lim.velocity_bounds(q)
        bound = np.where(qd > 0.0, upper, -lower)  # room in the direction of motion
        speed = np.abs(qd)
        fast = speed > np.maximum(bound, 0.0)  # at rest in libfranka's band: not ours
        if not fast.any():
            return seg
        ratio = np.divide(np.maximum(bound, 0.0), speed, out=np.ones_like(speed), where=fast)
        worst = float(np.min(ratio))
        if worst <= 0.0:  # moving into the band by a limit, where only leaving it is allowed
            break
        slow *= max(0.98 * worst, 0.5)
        seg = _line_profile(a, b, lim.velocity, lim.acceleration, lim.jerk, otg, slow)
    raise ValueError(f"cannot time the segment {a.tolist()} -> {b.tolist()} within the "
                     "position-dependent velocity bounds (a waypoint too close to a limit)")


def _sample_segments(segments: list[_Segment], goal: np.ndarray, dt: float) -> Trajectory:
    """Concatenate the segments in time and sample them; the last sample is ``goal`` exactly."""
    ends = np.cumsum([s.duration for s in segments]) if segments else np.zeros(0)
    total = float(ends[-1]) if segments else 0.0
    times = _with_knots(time_grid(total, dt), ends, dt)
    q = np.tile(goal, (times.size, 1))
    qd = np.zeros_like(q)
    qdd = np.zeros_like(q)
    starts = np.concatenate(([0.0], ends[:-1]))
    # Samples on a waypoint time belong to the segment ending there (they are equal anyway).
    index = np.searchsorted(ends, times, side="left")
    bounds = np.searchsorted(index, np.arange(len(segments) + 1), side="left")  # sorted: runs
    for i, seg in enumerate(segments):
        rows = slice(bounds[i], bounds[i + 1])
        q[rows], qd[rows], qdd[rows] = seg.at(times[rows] - starts[i])
    q[-1], qd[-1], qdd[-1] = goal, 0.0, 0.0
    return Trajectory(times, q, qd, qdd)


# ----------------------------------------------------------------------------- stops

HOLD_S = 0.1
"""s: time_from_start of a one-point hold. JTC needs it > 0 (it interpolates from its
current state to the point over that time); 0.1 s stops an arm creeping at 0.01 rad/s with
0.1 rad/s^2."""
AT_REST_RAD_S = 0.01
"""rad/s: below this on every joint an arm is stopped by a one-point hold, not a brake."""


def stop_trajectory(q, qd, limits: JointLimits, coast_s: float = 0.0,
                    dt: float = 0.01) -> Trajectory:
    """The motion that stops an arm at ``q`` moving at ``qd``, as a trajectory every joint
    trajectory controller executes (Jazzy JTC rejects an empty one and keeps going).

    At rest (or ``qd`` None, unknown): a hold at ``q`` reached after `HOLD_S`. Moving: it
    coasts at ``qd`` for ``coast_s`` (the time until the trajectory reaches the controller:
    the arm is there by then), then brakes to rest at ``limits``' acceleration and jerk,
    phase-synchronised — every joint's velocity is ``qd`` times one jerk-limited profile
    falling from 1 to 0 — so the arm stays on the straight line along ``qd`` that the
    planner certifies (`GraphPlanner.braking_point` is this trajectory's end). Velocities
    start clipped to the limits (a measured overshoot must not make a controller refuse the
    stop); the last point has zero velocity and acceleration, as JTC requires.
    """
    q = np.asarray(q, dtype=float)
    if qd is None or not np.all(np.isfinite(qd)) or np.max(np.abs(qd)) < AT_REST_RAD_S:
        zero = np.zeros((2, q.size))
        return Trajectory(np.array([0.0, HOLD_S]), np.vstack((q, q)), zero, zero.copy())
    qd = np.clip(np.asarray(qd, dtype=float), -limits.velocity, limits.velocity)
    moving = np.abs(qd) > 0.0
    speed = np.abs(qd[moving])
    inp = InputParameter(1)
    inp.control_interface = ControlInterface.Velocity
    inp.current_position, inp.current_velocity, inp.current_acceleration = [0.0], [1.0], [0.0]
    inp.target_velocity, inp.target_acceleration = [0.0], [0.0]
    inp.max_velocity = [1.0]
    inp.max_acceleration = [float(np.min(limits.acceleration[moving] / speed))]
    inp.max_jerk = [float(np.min(limits.jerk[moving] / speed))]
    brake = _RuckigTrajectory(1)
    if Ruckig(1).calculate(inp, brake) != Result.Working:
        raise ValueError("ruckig could not compute a braking profile")
    coast_s = max(float(coast_s), 0.0)
    total = coast_s + float(brake.duration)
    times = _with_knots(time_grid(total, dt), np.array([coast_s]) if coast_s else
                        np.zeros(0), dt)
    s, sd, sdd = np.empty(times.size), np.empty(times.size), np.empty(times.size)
    for k, t in enumerate(times):
        if t <= coast_s:
            s[k], sd[k], sdd[k] = t, 1.0, 0.0
        else:
            p, v, a = brake.at_time(t - coast_s)[:3]
            s[k], sd[k], sdd[k] = coast_s + p[0], v[0], a[0]
    sd[-1] = sdd[-1] = 0.0
    positions = np.clip(q + np.outer(s, qd), limits.lower, limits.upper)
    return Trajectory(times, positions, np.outer(sd, qd), np.outer(sdd, qd))


def swerve_trajectory(lead: Trajectory, branch_s: float, target, limits: JointLimits,
                      dt: float = 0.01) -> Trajectory | None:
    """``lead`` (a stop, `stop_trajectory`) until its first sample at or after ``branch_s``,
    then the time-optimal jerk-limited motion from that state to rest at ``target`` without
    stopping first (ruckig, every joint from its velocity and acceleration there;
    time-synchronised, so it leaves the straight lines the planner certifies: the caller
    certifies its sampled states). None where it would leave the position limits or exceed
    a position-dependent velocity limit on the way (a move whose velocity heads into a limit
    overshoots toward it before it turns back).

    Why: braking on the line along the arm's velocity and then moving is the only escape a
    stop allows, and a ball diving onto that line where a fast arm would stop left no such
    move clear of it (generated G scenes); turning while braking does. The stop is followed
    until ``branch_s`` because it is already on its way to the controller when a threat is
    found: a turn computed meanwhile must continue what the arm did, not restart from the
    state it was in."""
    k = min(int(np.searchsorted(lead.times, branch_s - 1e-9)), len(lead.times) - 1)
    dof = lead.positions.shape[1]
    inp = InputParameter(dof)
    inp.current_position = list(lead.positions[k])
    inp.current_velocity = list(lead.velocities[k])
    inp.current_acceleration = list(np.clip(lead.accelerations[k], -limits.acceleration,
                                            limits.acceleration))
    inp.target_position = list(np.asarray(target, dtype=float))
    inp.target_velocity = [0.0] * dof
    inp.target_acceleration = [0.0] * dof
    inp.max_velocity = list(limits.velocity)
    inp.max_acceleration = list(limits.acceleration)
    inp.max_jerk = list(limits.jerk)
    motion = _RuckigTrajectory(dof)
    if Ruckig(dof).calculate(inp, motion) != Result.Working:
        return None
    branch = float(lead.times[k])
    times = branch + time_grid(float(motion.duration), dt)
    n = times.size
    positions, velocities = np.empty((n, dof)), np.empty((n, dof))
    accelerations = np.empty((n, dof))
    for i, t in enumerate(times):
        positions[i], velocities[i], accelerations[i] = motion.at_time(t - branch)[:3]
    velocities[-1] = accelerations[-1] = 0.0
    if not limits.within(positions, 1e-9) or np.any(
            limits.velocity_excess(positions, velocities) > 1e-9):
        return None
    return Trajectory(np.concatenate([lead.times[:k], times]),
                      np.vstack([lead.positions[:k], positions]),
                      np.vstack([lead.velocities[:k], velocities]),
                      np.vstack([lead.accelerations[:k], accelerations]))


def braking_states(q, qd, limits: JointLimits, coast_s: float = 0.0,
                   per_phase: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """(times, positions) of `stop_trajectory` from ``q`` moving at ``qd``, a few samples a
    phase, in closed form: the same coast, then the time-optimal jerk-limited brake of the
    normalised speed from 1 to 0 (jerk down, constant deceleration if the limit is reached,
    jerk up), scaled by ``qd``. For checks that must ask "can the arm stop from here?" at
    many states: Ruckig and the 10 ms sampling of the real stop cost ~0.5 ms a state, this
    a few us (compiled, `braking_kernel`: the certified-stop check runs it for every checked
    state of a trajectory in one call); the checker subdivides between samples by its own
    resolution rules. At rest (below AT_REST_RAD_S): the hold, one state."""
    q = np.asarray(q, dtype=float)
    if qd is None or not np.all(np.isfinite(qd)):
        return np.array([0.0, HOLD_S]), np.vstack((q, q))
    return braking_kernel(q, np.asarray(qd, dtype=float), limits.velocity, limits.acceleration,
                          limits.jerk, limits.lower, limits.upper, max(float(coast_s), 0.0),
                          per_phase)


@njit(cache=True)
def braking_kernel(q, qd, vmax, amax, jmax, lower, upper, coast_s, per_phase):
    """`braking_states` of a finite ``qd`` (``coast_s`` >= 0), compiled: the same arithmetic
    as the closed form in numpy it replaces, sample for sample."""
    dof = q.shape[0]
    fastest = 0.0
    for a in range(dof):
        fastest = max(fastest, abs(qd[a]))
    if fastest < AT_REST_RAD_S:
        held = np.empty((2, dof))
        held[0], held[1] = q, q
        return np.array([0.0, HOLD_S]), held
    v_clip = np.empty(dof)
    acc, jerk = np.inf, np.inf
    for a in range(dof):
        v_clip[a] = min(max(qd[a], -vmax[a]), vmax[a])
        if v_clip[a] != 0.0:
            acc = min(acc, amax[a] / abs(v_clip[a]))
            jerk = min(jerk, jmax[a] / abs(v_clip[a]))
    ramp = min(acc / jerk, math.sqrt(1.0 / jerk))  # the deceleration's rise (and fall) time
    peak = jerk * ramp
    cruise = max(0.0, (1.0 - peak * ramp) / peak)
    durations = (ramp, cruise, ramp)
    jerks = (-jerk, 0.0, jerk)
    times = np.empty(2 + 3 * per_phase)
    s = np.empty(2 + 3 * per_phase)
    times[0], s[0], times[1], s[1] = 0.0, 0.0, coast_s, coast_s
    n = 2
    x, v, acc_now, t = coast_s, 1.0, 0.0, coast_s
    for p in range(3):
        duration, j = durations[p], jerks[p]
        if duration > 0:
            step = duration / per_phase  # np.linspace(0, duration, per_phase + 1)[1:]
            for i in range(1, per_phase + 1):
                tau = duration if i == per_phase else i * step
                times[n] = t + tau
                s[n] = x + v * tau + acc_now * tau ** 2 / 2 + j * tau ** 3 / 6
                n += 1
        x, v, acc_now = (x + v * duration + acc_now * duration ** 2 / 2 + j * duration ** 3 / 6,
                         v + acc_now * duration + j * duration ** 2 / 2, acc_now + j * duration)
        t += duration
    keep = np.zeros(n, np.bool_)
    keep[0] = True
    kept = 1
    for i in range(1, n):
        keep[i] = times[i] - times[i - 1] > 1e-9
        kept += keep[i]
    out_t = np.empty(kept)
    out_q = np.empty((kept, dof))
    m = 0
    for i in range(n):
        if keep[i]:
            out_t[m] = times[i]
            for a in range(dof):
                out_q[m, a] = min(max(q[a] + s[i] * v_clip[a], lower[a]), upper[a])
            m += 1
    return out_t, out_q


def held_until(traj: Trajectory, end_s: float) -> Trajectory:
    """``traj`` with its last point repeated at ``end_s`` when it ends before (at rest)."""
    if end_s <= traj.duration + 1e-9:
        return traj
    if not math.isfinite(end_s):
        raise ValueError(f"end_s must be finite, got {end_s}")
    zero = np.zeros((1, traj.positions.shape[1]))
    return Trajectory._built(np.append(traj.times, float(end_s)),
                             np.vstack((traj.positions, traj.positions[-1:])),
                             np.vstack((traj.velocities, zero)),
                             np.vstack((traj.accelerations, zero)))


def concatenate(first: Trajectory, second: Trajectory) -> Trajectory:
    """``second`` after ``first`` (which must end where ``second`` starts, both at rest)."""
    if np.max(np.abs(first.positions[-1] - second.positions[0])) > 1e-9:
        raise ValueError("trajectories to concatenate must meet")
    times = np.concatenate((first.times, first.duration + second.times[1:]))
    if np.any(np.diff(times) <= 0.0):  # a shift by the duration can merge close samples
        raise ValueError("times must be strictly increasing")
    return Trajectory._built(times, *(np.vstack((a, b[1:])) for a, b in (
        (first.positions, second.positions), (first.velocities, second.velocities),
        (first.accelerations, second.accelerations))))
