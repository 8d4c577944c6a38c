"""Several cameras, one fit: one shape fitted to what every camera saw of an object at once.

Intersecting the bounds that each camera made alone (:mod:`damon_ros.perception.fusion`)
keeps the worst of each: every bound carries its own camera's edge margins and, where its
camera saw no depth, its class prior, and the intersection of two boxes that differ in yaw
by a fraction of a degree is a polytope with the corners of both. Cameras synchronised to
one instant see one object in one place, so their points (in the base frame) are one
surface: here one primitive is fitted to the union. A box then has its faces from whichever
camera saw them (the front camera's face, the side camera's depth), each a fitted plane,
and no prior where some camera saw the extent; a ball's cap from two sides fixes its centre
and radius better than either cap. Anything else (a cylinder, a blob, views all flagged
partial, frames of different instants) keeps the fused bound.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from damon_ros.core.shapes import Shape
from damon_ros.perception.camera import Camera
from damon_ros.perception.shape_fit import FIT_POINTS, SPHERE_SIGMAS, fit_sphere
from damon_ros.perception.tight_fit import fit_box_seen
from damon_ros.perception.tracker_config import TrackerConfig


def _sphere(points: np.ndarray, config: TrackerConfig, name: str) -> Shape | None:
    """The sphere fitted to the union, grown by `SPHERE_SIGMAS` residuals, or None when the
    union is no sphere (residual above the tracker's roundness test)."""
    stride = max(1, len(points) // FIT_POINTS)
    try:
        centre, radius, rms = fit_sphere(points[::stride])
    except ValueError:
        return None
    if rms > config.sphere_rms_ratio * radius + config.sphere_rms_floor_m:
        return None
    return Shape("sphere", (radius + max(SPHERE_SIGMAS * rms, config.surface_margin_m),),
                 centre, name=name)


def joint_fit(views: Sequence[tuple[Camera, Shape, np.ndarray, bool]], config: TrackerConfig,
              name: str = "") -> Shape | None:
    """One shape for what several cameras saw of one object at one instant, or None.

    ``views``: per camera, its own bound of the object, the base-frame points it saw and
    whether its view is flagged partial (its points count, its silhouette bounds nothing).
    Spheres in every view give the sphere of the union; boxes (or hulls) the upright box of
    the union (`tight_fit.fit_box_seen`). None when fewer than two views have points or the
    union fits no such shape: the caller keeps its fused bound.
    """
    seen = [(c, s, p, cut) for c, s, p, cut in views if p is not None and len(p)]
    if len(seen) < 2 or all(cut for *_, cut in seen):
        return None
    kinds = {s.kind for _, s, _, _ in seen}
    if kinds == {"sphere"}:
        # each whole view's own sphere holds the ball too: the smallest of them all
        joint = _sphere(np.vstack([p for _, _, p, _ in seen]), config, name)
        spheres = [s for _, s, _, cut in seen if not cut] + ([joint] if joint else [])
        return min(spheres, key=lambda s: s.size[0]) if spheres else None
    if kinds <= {"box", "points"}:
        fit = fit_box_seen([(c, p) for c, _, p, _ in seen], config, name,
                           [cut for *_, cut in seen])
        return None if fit is None else fit.shape
    return None
