"""Several cameras, one fit: one shape fitted to what every camera saw of an object at once.

Intersecting the bounds that each camera made alone (:mod:`damon_ros.perception.fusion`)
keeps the worst of each: every bound carries its own camera's edge margins and, where its
camera saw no depth, its class prior, and the intersection of two boxes that differ in yaw
by a fraction of a degree is a polytope with the corners of both. Cameras synchronised to
one instant see one object in one place, so their points (in the base frame) are one
surface: here one primitive is fitted to the union. A box then has its faces from whichever
camera saw them (the front camera's face, the side camera's depth), each a fitted plane,
and no prior where some camera saw the extent. A ball gets one sphere fitted to all its
points, a pole one side fitted to all its points (its ends where the cameras' own
cylinders end). A pole or ball whose points fit no one shape keeps the smallest of the
cameras' own bounds that the other cameras' points agree with (what the intersection
gave, made without the polytope of tangent planes). Anything else (a blob,
mixed kinds, views all flagged partial, frames of different instants) keeps the fused bound.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from damon_ros.core.shapes import Shape, contains, volume
from damon_ros.perception.camera import Camera
from damon_ros.perception.shape_fit import (
    FIT_POINTS,
    fit_sphere,
    small_residual,
    sphere_margin,
)
from damon_ros.perception.tight_fit import fit_box_seen, fit_side, side_bound
from damon_ros.perception.tilted_box import fit_tilted_box
from damon_ros.perception.tracker_config import TrackerConfig


def _smallest(agreed: list[Shape]) -> Shape | None:
    """The smallest of the whole views' own spheres or cylinders that every camera's points
    agree with (`_agreed`), or None. What the intersection of the views gave
    (:func:`fusion.fuse` keeps the smallest primitive unless the polytope is far smaller,
    which it was not for balls and poles seen from two sides), without making the polytope."""
    return min(agreed, key=volume) if agreed else None


def _agreed(seen: Sequence[tuple[Camera, Shape, np.ndarray, bool]], points: np.ndarray,
            config: TrackerConfig) -> list[Shape]:
    """The whole views' own bounds that leave none of ``points`` (every camera's) out by
    more than ``face_tolerance_m`` (noise). One that does rests on what its camera could not
    see: a pole seen nearly end-on by the side camera ended 4 cm short of the far end
    that the front camera saw."""
    return [shape for _, shape, _, cut in seen
            if not cut and bool(np.all(contains(shape, points, config.face_tolerance_m)))]


def _joint_sphere(seen: Sequence[tuple[Camera, Shape, np.ndarray, bool]], points: np.ndarray,
                  config: TrackerConfig, name: str) -> Shape | None:
    """One sphere fitted to every camera's points of a ball, or None when they are not one
    ball's (the fit's residual fails the round test of `shape_fit`). Caps seen from two
    sides pin the centre and the radius that one cap leaves tied together, so its margin
    (`shape_fit.sphere_margin`) is a fraction of each view's own: on the held + stress
    scenes the balls' excess fell from 16 % to 10 %, every whole view contained. Each view
    is thinned to `shape_fit.FIT_POINTS`, as a view's own fit is."""
    fitted = np.vstack([p[::max(1, len(p) // FIT_POINTS)] for _, _, p, _ in seen])
    try:
        centre, radius, rms = fit_sphere(fitted)
    except ValueError:
        return None
    if not small_residual(config, radius, rms):
        return None
    # each camera's own ball bounds what it saw: the one fit must lie inside every one of
    # them, or the views disagree (an object lumpy on a side only one camera sees)
    if any(float(np.linalg.norm(centre - s.position)) + radius > s.size[0]
           for _, s, _, cut in seen if not cut):
        return None
    margin = sphere_margin(points, centre, radius, rms, config, fitted)
    if not np.isfinite(margin):
        return None
    return Shape("sphere", (radius + margin,), centre, name=name)


def _joint_cylinder(points: np.ndarray, whole: list[Shape], config: TrackerConfig,
                    name: str) -> Shape | None:
    """One side fitted to every camera's ``points`` of a pole (`tight_fit.fit_side`, from the
    smallest of ``whole``, the agreed whole views' own cylinders, `_agreed`), or None when
    they fit no one side or the fit does not lie inside every agreed view's own cylinder
    (views that disagree). Arcs seen from two sides pin the circle that one arc leaves tied to its
    depth. Its ends are where the agreed views' own cylinders end along its axis (each
    camera's measured end face or silhouette edge: the tighter wins)."""
    if not whole:
        return None
    start = min(whole, key=volume)
    fit = fit_side(points, start.position, start.rotation(), np.zeros(2), start.size[0],
                   0.25 * config.face_tolerance_m, config)
    if fit is None:
        return None
    low, high = -np.inf, np.inf
    for own in whole:  # where its points lie along the joint axis (its end disks slant)
        centre = (own.position - fit.origin) @ fit.frame
        along = float((own.rotation()[:, 2] @ fit.frame)[2])
        reach = abs(along) * 0.5 * own.size[1] + own.size[0] * np.sqrt(max(0.0, 1.0 - along**2))
        low, high = max(low, centre[2] - reach), min(high, centre[2] + reach)
    bound, _ = side_bound(fit, low, high, config)
    if not np.isfinite(bound) or high <= low:
        return None
    ends = fit.origin + np.outer([low, high], fit.frame[:, 2]) + fit.frame[:, :2] @ fit.centre2
    for own in whole:  # the joint side must lie inside what each camera bounded alone
        axis = own.rotation()[:, 2]
        offset = ends - own.position
        across = np.linalg.norm(offset - np.outer(offset @ axis, axis), axis=1)
        if float(across.max()) + bound > own.size[0]:
            return None
    centre = fit.origin + fit.frame @ np.array([*fit.centre2, 0.5 * (low + high)])
    q = Rotation.from_matrix(fit.frame).as_quat()
    return Shape("cylinder", (bound, high - low), centre, q, name=name)


def joint_fit(views: Sequence[tuple[Camera, Shape, np.ndarray, bool]], config: TrackerConfig,
              name: str = "") -> Shape | None:
    """One shape for what several cameras saw of one object at one instant, or None.

    ``views``: per camera, its own bound of the object, the base-frame points it saw and
    whether its view is flagged partial (its points count, its silhouette bounds nothing).
    Spheres in every whole view give one sphere fitted to all points (`_joint_sphere`),
    cylinders one side (`_joint_cylinder`); where that fails, the smallest of the views'
    own that all points agree with. The points of a view cut by an occluder count too,
    whatever its kind: a tight pole grown into a polytope by the noise of a cut view's
    points was no longer held whole while a ball crossed it. Boxes (or hulls) give the
    upright box of the union (`tight_fit.fit_box_seen`), else its box in any orientation
    (`tilted_box.fit_tilted_box`). None when fewer than two views have points or the union
    fits no such shape: the caller keeps its fused bound.
    """
    seen = [(c, s, p, cut) for c, s, p, cut in views if p is not None and len(p)]
    if len(seen) < 2 or all(cut for *_, cut in seen):
        return None
    kinds = {s.kind for _, s, _, _ in seen}
    # a view cut by an occluder or the border bounds only what it shows, whatever kind it
    # became, but its points are the object's: the whole views say what the object is
    whole = {s.kind for _, s, _, cut in seen if not cut}
    if whole == {"sphere"}:
        points = np.vstack([p for _, _, p, _ in seen])
        return _joint_sphere(seen, points, config, name) or _smallest(
            _agreed(seen, points, config))
    if whole == {"cylinder"}:
        points = np.vstack([p for _, _, p, _ in seen])
        agreed = _agreed(seen, points, config)  # the joint side's start and ends, or the bound
        return _joint_cylinder(points, agreed, config, name) or _smallest(agreed)
    if kinds <= {"box", "points"}:
        points, cuts = [(c, p) for c, _, p, _ in seen], [cut for *_, cut in seen]
        fit = fit_box_seen(points, config, name, cuts)
        if fit is None:  # no upright box: a box turned about a horizontal axis?
            fit = fit_tilted_box(points, config, name, cuts)
        return None if fit is None else fit.shape
    return None
