"""Static things stay static: a stationarity test with hysteresis on a track's velocity.

The least-squares velocity of a still box is not zero: its estimated centre jitters by
millimetres from frame to frame, and over a 0.3 s window that reads as centimetres per
second, which the planner sweeps along the obstacle's predicted path. A track therefore
becomes *still* once its speed has stayed below ``static_speed_mps`` for ``static_hold_s``
and then reports zero velocity, until its speed exceeds the (higher) ``moving_speed_mps`` or
its centre leaves the position it was still at by ``moving_shift_m`` (a fitted ball, whose
centre jitters by a fraction of a millimetre, by ``moving_shift_round_m``): two thresholds,
so noise near one of them does not toggle the state every frame, and a slow start is still
caught by the shift test. The still position (the anchor) is the mean of the centres over
the hold, not one noisy centre, and it is never moved while the track stays still.

An occluded view is no evidence of motion (:meth:`Stationarity.cut_in_place`): when the arm
or a passing ball hides part of a still box, the visible part's centre moves by centimetres
(and a cut-off blob gets another kind of bound), which read as motion made the planner
sweep the box and hold. A view that shows less of the object than its whole views do
(flagged partial, or fewer pixels than they had) and whose points all lie within
``moving_shift_m`` of the last whole bound's surface (neither outside it by more, nor deeper
inside) is what an occluder left of an object in place; its centre is kept out of the
velocity and the stationarity test. A moving object's surface leaves that shell within
about ``moving_shift_m`` of motion, so it is still seen to move, a few frames late at most.
Inside the bound is not enough: the visible cap of a ball that sank 10 cm behind an occluder
still lay inside its last whole bound (grown by 2 cm), so it kept zero velocity while it
sank onto the arm (10-minute soak, 62 mm of contact).
"""

from __future__ import annotations

from collections import deque

import numpy as np

from damon_ros.core.shapes import Shape, contains, grown
from damon_ros.perception.tracker_config import TrackerConfig

SHRUNK_SHARE = 0.8
"""A view with fewer pixels than this share of the whole views' typical count shows only
part of the object (a still box's pixel count varies by a few per cent from frame to frame)."""
JITTER_SHARE = 0.25
"""A centre within this share of the shift that counts as motion (``moving_shift_m``, or
``moving_shift_round_m`` for a fitted ball) of the anchor is the object at rest there
(`Stationarity.jitter_m`)."""
AREA_HISTORY = 15
"""The typical pixel count is the median of this many last whole views."""


class Stationarity:
    """Per track: whether it is still, and the velocity to report."""

    def __init__(self, config: TrackerConfig) -> None:
        self.config = config
        self.still = False
        self.anchor: np.ndarray | None = None
        self._slow_since: float | None = None
        self._slow: list[np.ndarray] = []  # the centres since _slow_since
        self.whole: Shape | None = None  # the last bound of a whole view
        self._areas: deque[int] = deque(maxlen=AREA_HISTORY)

    def cut_in_place(self, shape: Shape, partial: bool, area_px: int,
                     surface: np.ndarray | None) -> bool:
        """Whether a view shows less of the object than its whole views (flagged partial, or
        under `SHRUNK_SHARE` of their pixels) and all it shows (``surface``, base-frame
        points) lies within ``moving_shift_m`` of the last whole bound's surface: part of
        an object in place, hidden by an occluder (a visible surface is the bound's own
        surface, within the fit's margins). Any other view is remembered as whole (its
        bound ``shape`` and its pixel count, which sets what "fewer" means)."""
        ordered = sorted(self._areas)  # (a dozen ints: np.median costs 50 us a call)
        typical = float(ordered[len(ordered) // 2]) if ordered else 0.0
        cut = partial or (area_px > 0 and area_px < SHRUNK_SHARE * typical)
        if not cut:
            self.whole = shape
            if area_px > 0:
                self._areas.append(area_px)
            return False
        if self.whole is None or surface is None or not len(surface):
            return False
        shift = self.config.moving_shift_m
        return bool(np.all(contains(self.whole, surface, shift))
                    and not np.any(contains(self.whole, surface, -shift)))

    def held_bound(self, cut_bound: Shape) -> Shape:
        """The bound of an object in place that an occluder cut (`cut_in_place` was True):
        its last whole bound grown by ``moving_shift_m`` (its visible surface lies within
        that of the whole bound's), where that is a sphere, box or cylinder; else
        ``cut_bound``, the cut view's own. The cut view's bound covers only what it shows:
        a pole cut in two by a passing ball was half outside it, and a cut-off pole's
        view-extended box reached 9 cm toward the arm, which then held between it and the
        ball."""
        whole = self.whole
        if whole is None or whole.kind not in ("sphere", "box", "cylinder"):
            return cut_bound
        return grown(whole, self.config.moving_shift_m)

    def shift_m(self, round_fit: bool) -> float:
        """How far a still object's centre must leave its anchor to be moving:
        ``moving_shift_round_m`` for a fitted ball (the fit pins its centre to a fraction of
        a millimetre), else ``moving_shift_m`` (a box's fit jitters by a few)."""
        c = self.config
        return c.moving_shift_round_m if round_fit else c.moving_shift_m

    def jitter_m(self, round_fit: bool) -> float:
        """How far a still object's centre is seen from its anchor by noise alone: a
        quarter of its `shift_m`. A ball's 5 mm (a quarter of a box's shift) took its first
        frame after a start, 4.7 mm out, for rest."""
        return JITTER_SHARE * self.shift_m(round_fit)

    def update(self, stamp: float, position: np.ndarray, velocity: np.ndarray,
               round_fit: bool = False) -> np.ndarray:
        """Take one observation; the velocity to report (zero while still). ``round_fit``:
        the observation is a fitted ball (`shift_m`)."""
        c = self.config
        speed = float(np.linalg.norm(velocity))
        shift = self.shift_m(round_fit)
        if self.still:
            if speed > c.moving_speed_mps or float(
                    np.linalg.norm(position - self.anchor)) > shift:
                self.still, self._slow_since, self._slow = False, None, []
            else:
                return np.zeros(3)
        if speed < c.static_speed_mps:
            if self._slow_since is None:
                self._slow_since, self._slow = stamp, []
            self._slow.append(np.array(position, dtype=float))
            if stamp - self._slow_since >= c.static_hold_s:
                self.still, self.anchor = True, np.mean(self._slow, axis=0)
                self._slow = []
                return np.zeros(3)
        else:
            self._slow_since, self._slow = None, []
        return velocity
