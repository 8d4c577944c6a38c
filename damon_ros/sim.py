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

from damon_ros.limits import JointLimits


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
    """

    def __init__(self, limits: JointLimits, q0, tau: float = 0.02,
                 command_timeout: float = 0.1):
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

    @property
    def q(self) -> np.ndarray:
        return self._q.copy()

    @property
    def qd(self) -> np.ndarray:
        return self._qd.copy()

    def command(self, qd_cmd, t: float) -> str | None:
        """Accept a velocity command at time ``t``; a reason string when it was rejected.

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
        target = self._target(t)
        # Exact first-order step: (target - qd) shrinks by exp(-dt / tau).
        change = (target - self._qd) * (1.0 - math.exp(-dt / self.tau))
        max_change = lim.acceleration * dt
        change = np.minimum(np.maximum(change, -max_change), max_change)
        qd = np.minimum(np.maximum(self._qd + change, -lim.velocity), lim.velocity)
        q = self._q + (0.5 * dt) * (self._qd + qd)
        high, low = q >= lim.upper, q <= lim.lower
        if high.any() or low.any():  # at a limit: stop there, no velocity into it
            qd = np.where(high, np.minimum(qd, 0.0), np.where(low, np.maximum(qd, 0.0), qd))
            q = np.minimum(np.maximum(q, lim.lower), lim.upper)
        self._q, self._qd = q, qd
        return q.copy(), qd.copy()
