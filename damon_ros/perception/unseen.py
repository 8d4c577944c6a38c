"""Honest refusals: is a goal refused only because of what no camera saw?

A tracked obstacle is a bound: the surface the cameras saw plus a hidden extent behind it,
sized by a prior (``max_thickness_m``) and shrunk by other views. A goal a few centimetres
behind a seen face is refused when the prior reaches it, although the real object may well
end before it. Saying "all IK solutions collide" hides that; this module tells the two
cases apart, so that the refusal names the unseen part and the goal may wait a bounded
time for a view that shows it (a second camera, the object turning, the arm's motion).

The test is the planner's own goal check (``resolve``: IK with clearance, self-collision,
the exact-mesh margin) run once more with each estimate replaced by its seen surface: if
that finds a goal configuration, what was seen does not block the goal, and the estimates
that configuration touches are named. The result only explains a refusal; the goal is
still planned against the whole bounds, never against the seen parts.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import NamedTuple

import numpy as np

from damon_ros.core.shapes import Shape


class Estimate(NamedTuple):
    """One obstacle as the planner has it: a name for messages, its bound and (when the
    tracker gave one) the surface that was seen of it."""

    name: str
    shape: Shape
    seen: Shape | None


def unseen_blockers(resolve: Callable[[list[Shape]], tuple[np.ndarray | None, str]],
                    distance: Callable[[np.ndarray, Shape], float], margin: float,
                    estimates: Sequence[Estimate]) -> list[str] | None:
    """Names of the estimates whose unseen part alone blocks a refused goal, else None.

    ``resolve(obstacles)`` is the planner's goal check (``(q_goal, reason)``, q_goal None
    when refused); ``distance(q, shape)`` the robot's clearance to one shape (the model the
    check used), ``margin`` the clearance it requires. None: no estimate has a seen part,
    the goal is refused with the seen parts as well, or no single estimate is to blame.
    """
    if not any(e.seen is not None for e in estimates):
        return None
    q, _ = resolve([e.shape if e.seen is None else e.seen for e in estimates])
    if q is None:
        return None
    names = [e.name for e in estimates
             if e.seen is not None and distance(q, e.shape) <= margin]
    return names or None


def unseen_reason(reason: str, names: Sequence[str]) -> str:
    """The refusal reason completed with the unseen part that causes it."""
    return (f"{reason} — only with the unseen part of {', '.join(names)} (the tracker's "
            "bound of what lies behind the surface the cameras saw; the goal is clear of that "
            "surface)")
