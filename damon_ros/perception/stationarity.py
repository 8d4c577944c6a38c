"""Static things stay static: a stationarity test with hysteresis on a track's velocity.

The least-squares velocity of a still box is not zero: its estimated centre jitters by
millimetres from frame to frame, and over a 0.3 s window that reads as centimetres per
second, which the planner sweeps along the obstacle's predicted path. A track therefore
becomes *still* once its speed has stayed below ``static_speed_mps`` for ``static_hold_s``
and then reports zero velocity, until its speed exceeds the (higher) ``moving_speed_mps`` or
its centre leaves the position it was still at by ``moving_shift_m``: two thresholds, so
noise near one of them does not toggle the state every frame, and a slow start is still
caught by the shift test.
"""

from __future__ import annotations

import numpy as np

from damon_ros.perception.tracker_config import TrackerConfig


class Stationarity:
    """Per track: whether it is still, and the velocity to report."""

    def __init__(self, config: TrackerConfig) -> None:
        self.config = config
        self.still = False
        self.anchor: np.ndarray | None = None
        self._slow_since: float | None = None

    def update(self, stamp: float, position: np.ndarray, velocity: np.ndarray) -> np.ndarray:
        """Take one observation; the velocity to report (zero while still)."""
        c = self.config
        speed = float(np.linalg.norm(velocity))
        if self.still:
            if speed > c.moving_speed_mps or float(
                    np.linalg.norm(position - self.anchor)) > c.moving_shift_m:
                self.still, self._slow_since = False, None
            else:
                return np.zeros(3)
        if speed < c.static_speed_mps:
            self._slow_since = stamp if self._slow_since is None else self._slow_since
            if stamp - self._slow_since >= c.static_hold_s:
                self.still, self.anchor = True, np.array(position, dtype=float)
                return np.zeros(3)
        else:
            self._slow_since = None
        return velocity
