"""Velocity of a moving obstacle from its recent positions: one least-squares fit for all.

Neither a colour blob nor an obstacle marker carries a velocity, yet the planner predicts
where obstacles will be. The tracker (per track) and the marker table (per ``(ns, id)``)
both estimate it the same way, here: the least-squares slope of the positions seen within
the last ``window_s`` seconds. A slope over a window rather than the last difference keeps
depth noise from turning into large velocity spikes; a motion that has just started is the
exception (`ONSET_WINDOW_S`).
"""

from __future__ import annotations

from collections import deque

import numpy as np

ONSET_WINDOW_S = 0.1
"""The samples of this last stretch of the window give a second, short slope ..."""
ONSET_SHIFT_M = 0.02
ONSET_SPEED_MPS = 0.2
ONSET_SHARE = 0.3
"""... which is taken instead when it covers more than `ONSET_SHIFT_M` (well above a still
object's jitter) and is faster than the window's slope by more than `ONSET_SPEED_MPS` and
`ONSET_SHARE` of it: an object that has just started. The window's slope then still holds
the samples at rest: a ball starting at 1.4 m/s beside the arm was reported at 0.66 m/s
0.13 s later, and the arm was hit (two cameras, S-v1-1.5-s1401-011). Slowing down keeps the
window's slope: the larger reach is the safe side."""


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
        velocity = _slope(t, p)
        recent = t >= stamp - ONSET_WINDOW_S
        if np.count_nonzero(recent) < 3:
            return velocity
        onset = _slope(t[recent], p[recent])
        speed, window_speed = float(np.linalg.norm(onset)), float(np.linalg.norm(velocity))
        started = (speed * float(np.ptp(t[recent])) > ONSET_SHIFT_M and speed > window_speed
                   and float(np.linalg.norm(onset - velocity))
                   > max(ONSET_SPEED_MPS, ONSET_SHARE * window_speed))
        return onset if started else velocity

    def since_rest(self, anchor: np.ndarray, jitter_m: float) -> np.ndarray | None:
        """The history restarted where the object was last seen at rest, at ``anchor`` (within
        ``jitter_m``), and the slope of the samples since; None when none was at rest there
        (the window's slope stands). Called when a still object starts to move: the window
        still holds its samples at rest, whose slope gives a fraction of the speed for a
        window's length. A ball starting at 0.19 m/s was reported at 0.07-0.13 m/s for
        0.1 s (below `ONSET_SHIFT_M` in `ONSET_WINDOW_S`), and a stop certified against that
        prediction was hit (generated G scene, one camera). The rest place is taken as left
        at the motion's estimated onset (`_onset`), not at the last stamp at rest."""
        h = self.history
        at_rest = [i for i, (_, p) in enumerate(h) if np.linalg.norm(p - anchor) <= jitter_m]
        if not at_rest or at_rest[-1] >= len(h) - 1:
            return None
        anchor = np.asarray(anchor, dtype=float)
        rest_s = h[at_rest[-1]][0]
        moved = list(h)[at_rest[-1] + 1:]
        h.clear()
        h.append((self._onset(rest_s, anchor, moved), anchor))
        h.extend(moved)
        t = np.array([s for s, _ in h])
        return _slope(t, np.array([x for _, x in h]))

    @staticmethod
    def _onset(rest_s: float, anchor: np.ndarray, moved: list) -> float:
        """When the object left ``anchor``: where the line through the ``moved`` samples
        (two or more) meets it, within the last stamp at rest and the first moved one;
        with one moved sample the last stamp at rest (the slope then is a lower bound). A
        ball that started between two frames and was taken to leave at the last frame at
        rest was reported at two thirds of its speed; taken to leave at its first moved
        frame, at 1.4 times it."""
        first_s = moved[0][0]
        if len(moved) < 2:
            return rest_s
        t = np.array([s for s, _ in moved])
        p = np.array([x for _, x in moved])
        velocity = _slope(t, p)
        speed = float(np.linalg.norm(velocity))
        if speed <= 0.0:
            return rest_s
        away = float(np.linalg.norm(p[0] - anchor))
        return min(max(first_s - away / speed, rest_s), first_s - 1e-3 * (first_s - rest_s))


def _slope(t: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Least-squares slope of positions ``p`` (N, 3) over stamps ``t`` (N,)."""
    dt = t - t.mean()
    return (dt @ (p - p.mean(axis=0))) / float(dt @ dt)
