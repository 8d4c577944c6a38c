"""The mock arm: a velocity-controlled joint model standing in for a Franka Panda.

The real arm's joint velocity loop follows a command with a short lag and refuses to leave
its limits; this model keeps exactly those traits and nothing else (no dynamics, no
contacts), so the controller can be tested closed-loop without hardware and the mock node,
the benchmark and the tests share one behaviour. Integration is exact for the first-order
response, so the model is stable and deterministic for any step size.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from damon_ros.core.limits import JointLimits


def _positive(name: str, value: float) -> float:
    if not (math.isfinite(value) and value > 0.0):
        raise ValueError(f"{name} must be a positive finite number, got {value}")
    return float(value)


class ArmSim:
    """Joint velocities follow the command as a first-order lag, inside the arm's limits.

    ``tau`` is the actuator time constant (s). Velocity and acceleration are clamped to the
    limits; positions stop at the position limits with the velocity into the limit zeroed.
    A command older than ``command_timeout`` is treated as zero — the arm brakes to rest
    within its acceleration limit, as a Franka does when its command stream stops.
    An optional `LimitMonitor` sees every accepted command and every new position, so
    that limit violations a real arm would refuse are counted (rejected commands, NaN
    included, never reach it).
    """

    def __init__(self, limits: JointLimits, q0, tau: float = 0.02,
                 command_timeout: float = 0.1, monitor: LimitMonitor | None = None):
        self.limits = limits
        self.n = limits.lower.size
        q0 = np.asarray(q0, dtype=float)
        if q0.shape != (self.n,) or not np.all(np.isfinite(q0)):
            raise ValueError(f"q0 must be {self.n} finite joint positions, got {q0}")
        if not limits.within(q0):
            raise ValueError(f"q0 {np.round(q0, 4).tolist()} is outside the joint limits")
        self.tau = _positive("tau", tau)
        self.command_timeout = _positive("command_timeout", command_timeout)
        self._q = q0.copy()
        self._qd = np.zeros(self.n)
        self._cmd = np.zeros(self.n)
        self._cmd_time: float | None = None
        self.last_reason: str | None = None
        self.monitor = monitor
        self._compile()

    def _compile(self) -> None:
        """Compile (or load from numba's disk cache) the step now, not in a 1 kHz tick."""
        out = np.empty(self.n), np.empty(self.n)
        _step(self._q, self._qd, self._qd, 1e-3, 0.0, self.limits.acceleration,
              self.limits.velocity, self.limits.lower, self.limits.upper, *out)

    @property
    def q(self) -> np.ndarray:
        return self._q.copy()

    @property
    def qd(self) -> np.ndarray:
        return self._qd.copy()

    def command(self, qd_cmd, t: float, sent: float | None = None) -> str | None:
        """Accept a velocity command at time ``t``; a reason string when it was rejected.

        ``sent`` (s, optional) is when the sender published it, for the monitor only.

        A rejected command (wrong length, NaN/inf) leaves the last good one in force, with
        its old time stamp, so a stream of bad commands ends in the timeout stop.
        """
        cmd = np.asarray(qd_cmd, dtype=float)
        if cmd.shape != (self.n,):
            reason = f"command must hold {self.n} velocities, got shape {cmd.shape}; ignored"
        elif not np.all(np.isfinite(cmd)) or not math.isfinite(t):
            reason = "command holds NaN or inf; ignored, keeping the last good command"
        else:
            self._cmd, self._cmd_time = cmd.copy(), float(t)
            if self.monitor is not None:
                self.monitor.command(cmd, t, sent, q=self._q)
            return None
        self.last_reason = reason
        return reason

    def _target(self, t: float) -> np.ndarray:
        if self._cmd_time is None or t - self._cmd_time > self.command_timeout:
            return np.zeros(self.n)
        vmax = self.limits.velocity
        return np.minimum(np.maximum(self._cmd, -vmax), vmax)

    def step(self, dt: float, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Advance by ``dt`` to time ``t``; returns the new (q, qd)."""
        dt = _positive("dt", dt)
        if not math.isfinite(t):
            raise ValueError(f"time must be finite, got {t}")
        lim = self.limits
        q, qd = np.empty(self.n), np.empty(self.n)
        _step(self._q, self._qd, self._target(t), dt, 1.0 - math.exp(-dt / self.tau),
              lim.acceleration, lim.velocity, lim.lower, lim.upper, q, qd)
        self._q, self._qd = q, qd
        if self.monitor is not None:
            self.monitor.position(q, t)
        return q.copy(), qd.copy()


@njit(cache=True)
def _step(q0, qd0, target, dt: float, gain: float, amax, vmax, lower, upper, q, qd) -> None:
    """`ArmSim.step` per joint, compiled (as numpy ~14 us a 1 kHz tick), the same
    arithmetic in the same order: the exact first-order step ((target - qd) shrinks by
    ``gain`` = 1 - exp(-dt / tau)) within the acceleration and velocity limits, the
    trapezoidal position update, and at a position limit a stop there with no velocity
    into it."""
    half = 0.5 * dt
    for j in range(q0.size):
        change = (target[j] - qd0[j]) * gain
        max_change = amax[j] * dt
        change = min(max(change, -max_change), max_change)
        v = min(max(qd0[j] + change, -vmax[j]), vmax[j])
        p = q0[j] + half * (qd0[j] + v)
        if p >= upper[j]:
            v, p = min(v, 0.0), upper[j]
        elif p <= lower[j]:
            v, p = max(v, 0.0), lower[j]
        q[j], qd[j] = p, v


# ----------------------------------------------------------------------------- limit monitor

@njit(cache=True)
def _peak_ratio(value: np.ndarray, limit: np.ndarray) -> tuple[float, int]:
    """(largest |value| / limit, its joint): three of these run per 1 kHz command, and as
    numpy (abs, divide, argmax) each cost ~4 us."""
    best, j = -1.0, 0
    for i in range(value.size):
        r = abs(value[i]) / limit[i]
        if r > best or r != r:  # a NaN ratio wins: it is never within the limit
            best, j = r, i
    return best, j


LIMIT_KINDS = ("velocity", "acceleration", "jerk", "position")  # what a Franka reflex stops
LATE = "late"  # a command arriving after a gap: counted apart, it is not a limit violation


class LimitMonitor:
    """Counts the commands a real Franka would refuse with a reflex, as a mock can't crash.

    A Franka checks every 1 kHz command against its joint limits: the commanded velocity,
    and the acceleration and jerk implied by consecutive commands. It applies one command
    per cycle of its own clock, so the implied acceleration is ``(u_k - u_{k-1}) / T`` with
    the nominal period ``T``, whatever interval the sender measured between its ticks; the
    monitor divides by ``T`` for that reason (a controller that shapes with a longer, late
    tick interval asks a fixed-cycle robot for more than it meant, and that is counted).
    A command arriving more than ``gap_periods`` periods after the previous one is not
    a controller's doing but a late or lost message (the robot would have missed a cycle):
    it is counted as ``late``, and no acceleration or jerk is computed across the gap.
    Arrival times alone can hide such a gap: when the receiving process stalls, a late
    command and its on-time successor arrive together. So when the publisher's send times
    are given (DDS source timestamps), a send spacing over ``gap_periods`` periods (a
    late tick or a lost message) counts as a gap as well, and so does the command right
    after a gap (a sender whose tick was stalled catches up on the elapsed time in its
    next command). Only commands the sender made about one period apart, that arrived so,
    and that follow an on-time command are checked for acceleration and jerk.

    Of the acceleration and jerk violations, those that vanish when divided by the
    sender's own spacing of the two commands instead of ``T`` are counted once more in
    `jitter`: the sender's tick came late (but within the gap bound) and it shaped for
    the time that really passed. A fixed-cycle robot still refuses them, so they stay
    violations; `jitter` only tells timing apart from a shaping error. It is a lower
    bound: the send time is stamped at publication, a little after the sender read its
    clock for the step, so part of a tick's lateness does not show in the spacing.
    ``tolerance`` (relative) absorbs float rounding only: the controller's own shaping
    stops exactly at the limits. Positions that reach or pass a position limit (where
    `ArmSim` clamps) are counted once per entry of a joint into its limit.

    Counts are per command (or per entry), not per joint. The first violation of each kind
    is kept as a message with its numbers, handed out once by `take_reports`.
    """

    def __init__(self, limits: JointLimits, period: float, tolerance: float = 1e-6,
                 gap_periods: float = 1.5):
        self.limits = limits
        self.period = _positive("period", period)
        self.tolerance = float(tolerance)
        if not (math.isfinite(self.tolerance) and self.tolerance >= 0.0):
            raise ValueError(f"tolerance must be a finite number >= 0, got {tolerance}")
        self.gap = _positive("gap_periods", gap_periods) * self.period
        self.counts = dict.fromkeys((*LIMIT_KINDS, LATE), 0)
        self.commands = 0
        self.max_gap = 0.0
        self.peak = dict.fromkeys(LIMIT_KINDS[:3], 0.0)  # largest |value| / limit seen
        self.jitter = {"acceleration": 0, "jerk": 0}  # within limits at the send spacing
        self.first: dict[str, str] = {}
        self._reported: set[str] = set()
        self._u: np.ndarray | None = None
        self._a: np.ndarray | None = None  # acceleration of the last gap-free pair
        self._a_sent: np.ndarray | None = None  # the same at the sender's own spacing
        self._after_gap = False
        self._t: float | None = None
        self._sent: float | None = None
        self._at_limit = np.zeros(limits.lower.size, dtype=bool)
        limits.velocity_bounds(0.5 * (limits.lower + limits.upper))  # compiled now, not in a tick
        _peak_ratio(limits.velocity, limits.velocity)  # the same

    @property
    def violations(self) -> int:
        """Commands and entries beyond a limit (late commands are not violations)."""
        return sum(self.counts[k] for k in LIMIT_KINDS)

    def command(self, u, t: float, sent: float | None = None,
                q: np.ndarray | None = None) -> None:
        """Check one accepted velocity command that arrived at time ``t`` (s), published
        at ``sent`` (s, the sender's clock; None: unknown), given to the arm at joint
        positions ``q`` (None: unknown, only the constant maxima are checked). With ``q``
        the velocity is checked against `JointLimits.velocity_bounds` at ``q``: the FR3's
        position-dependent bounds, the Panda's constants."""
        u = np.asarray(u, dtype=float)
        if u.shape != self.limits.velocity.shape or not np.all(np.isfinite(u)) or \
                not math.isfinite(t):
            raise ValueError("the limit monitor takes finite, accepted commands only")
        self.commands += 1
        if not self._check("velocity", u, self.limits.velocity, t) and q is not None and \
                self.limits.curve is not None:  # constant bounds: the check just made
            self._check_bounds(u, np.asarray(q, dtype=float), t)
        if self._t is not None:
            spacing = None if sent is None or self._sent is None else sent - self._sent
            gap = max(t - self._t, -math.inf if spacing is None else spacing)
            self.max_gap = max(self.max_gap, gap)
            if gap > self.gap or self._after_gap:
                self.counts[LATE] += gap > self.gap
                self._after_gap = gap > self.gap  # the next one may still catch up
                self._a = self._a_sent = None
            else:
                self._derivatives(u, t, spacing)
        self._u, self._t, self._sent = u.copy(), float(t), sent

    def _derivatives(self, u: np.ndarray, t: float, spacing: float | None) -> None:
        """Acceleration and jerk at the nominal period; at the send spacing for `jitter`."""
        lim = self.limits
        a = (u - self._u) / self.period
        own = spacing is not None and spacing > 0.0
        a_sent = (u - self._u) / spacing if own else None
        if self._check("acceleration", a, lim.acceleration, t) and own and \
                self._within(a_sent, lim.acceleration):
            self.jitter["acceleration"] += 1
        if self._a is not None and self._check("jerk", (a - self._a) / self.period, lim.jerk,
                                               t) and own and self._a_sent is not None and \
                self._within((a_sent - self._a_sent) / spacing, lim.jerk):
            self.jitter["jerk"] += 1
        self._a, self._a_sent = a, a_sent

    def _check_bounds(self, u: np.ndarray, q: np.ndarray, t: float) -> None:
        """Count a command beyond the position-dependent velocity bound at ``q``."""
        excess = self.limits.velocity_excess(q, u)
        j = int(np.argmax(excess))
        if excess[j] <= self.tolerance * self.limits.velocity[j]:
            return
        self.counts["velocity"] += 1
        lower, upper = self.limits.velocity_bounds(q)
        self._first("velocity", f"command {self.commands} asks joint {j + 1} for velocity "
                    f"{u[j]:.6g} at {q[j]:.4f} rad, outside its position-dependent bounds "
                    f"[{lower[j]:.6g}, {upper[j]:.6g}] at t = {t:.3f} s")

    def _within(self, value: np.ndarray, limit: np.ndarray) -> bool:
        return bool(np.all(np.abs(value) <= limit * (1.0 + self.tolerance)))

    def position(self, q, t: float) -> None:
        """Count joints that reached a position limit since the last call (`ArmSim.step`)."""
        q = np.asarray(q, dtype=float)
        at = (q >= self.limits.upper) | (q <= self.limits.lower)
        entered = at & ~self._at_limit
        self._at_limit = at
        if entered.any():
            self.counts["position"] += int(entered.sum())
            j = int(np.argmax(entered))
            self._first("position", f"joint {j + 1} reached its position limit at "
                        f"{q[j]:.4f} rad (range [{self.limits.lower[j]}, "
                        f"{self.limits.upper[j]}]) at t = {t:.3f} s")

    def _check(self, kind: str, value: np.ndarray, limit: np.ndarray, t: float) -> bool:
        """Count (and keep the first of) a value beyond its limit; True when it was."""
        ratio, j = _peak_ratio(value, limit)
        self.peak[kind] = max(self.peak[kind], ratio)
        if ratio <= 1.0 + self.tolerance:
            return False
        self.counts[kind] += 1
        self._first(kind, f"command {self.commands} asks joint {j + 1} for {kind} "
                    f"{value[j]:.6g} beyond the limit {limit[j]:g} "
                    f"({ratio:.4f} x) at t = {t:.3f} s")
        return True

    def _first(self, kind: str, message: str) -> None:
        self.first.setdefault(kind, message)

    def take_reports(self) -> list[str]:
        """The first violation of each kind not handed out before (log each once)."""
        new = [f"first {k} violation: {m}" for k, m in self.first.items()
               if k not in self._reported]
        self._reported.update(self.first)
        return new

    def summary(self) -> str:
        """One line of totals, for the mock arm's shutdown log."""
        kinds = ", ".join(f"{self.counts[k]} {k}" for k in LIMIT_KINDS)
        jitter = ", ".join(f"{v} {k}" for k, v in self.jitter.items())
        peaks = ", ".join(f"{k} {v:.3f}" for k, v in self.peak.items())
        return (f"limit monitor: {self.commands} commands, violations: {kinds} (of them "
                f"within the limits at the sender's own tick spacing: {jitter}); "
                f"{self.counts[LATE]} late commands (gap > {1e3 * self.gap:.2f} ms, max "
                f"{1e3 * self.max_gap:.2f} ms); peak fraction of the limit: {peaks}")
