"""Velocity of a moving obstacle from its recent positions: one least-squares fit for all.

Neither a colour blob nor an obstacle marker carries a velocity, yet the planner predicts
where obstacles will be. The tracker (per track) and the marker table (per ``(ns, id)``)
both estimate it the same way, here: the least-squares slope of the positions seen within
the last ``window_s`` seconds. A slope over a window rather than the last difference keeps
depth noise from turning into large velocity spikes.
"""

from __future__ import annotations

from collections import deque

import numpy as np


class VelocityWindow:
    """The ``(stamp, position)`` samples of the last ``window_s`` seconds, and their slope.

    A stamp older than the newest one (clock restart) or further than the window after it
    (the obstacle was away) starts a new history, so stale motion is never carried. The same
    stamp again replaces that sample (a republished marker, not a new view).
    """

    def __init__(self, window_s: float) -> None:
        self.window_s = float(window_s)
        self.history: deque[tuple[float, np.ndarray]] = deque()

    def add(self, stamp: float, position: np.ndarray) -> np.ndarray | None:
        """Take one sample; the least-squares velocity, or None below two samples."""
        h = self.history
        if h and (stamp < h[-1][0] or stamp - h[-1][0] > self.window_s):
            h.clear()
        if h and stamp == h[-1][0]:
            h.pop()
        h.append((stamp, position))
        while h[0][0] < stamp - self.window_s:
            h.popleft()
        if len(h) < 2:
            return None
        t = np.array([s for s, _ in h])
        p = np.array([x for _, x in h])
        dt = t - t.mean()
        return (dt @ (p - p.mean(axis=0))) / float(dt @ dt)
