"""A box in any orientation from its visible faces: a tumbling mover, a box knocked over.

:func:`tight_fit.fit_box_seen` fits upright boxes only (any yaw). A box turned about a
horizontal axis fits no upright box, and fell through to the blob bound: the hull of its
points pushed back by the blob prior, several times its volume for a box of a few
centimetres (stress movers one camera sees: 574 % median excess). Its faces are still
planes at right angles, so here the frame comes from the faces themselves:

* the largest plane among the points (RANSAC over point triples) gives the first axis;
* the largest plane of the rest that is at right angles to it (pairs of points and the
  first axis span its candidates) gives the second; with one face seen, the second axis
  is the minimum-area rectangle of that face's points;
* each axis is then refined by the plane through its face's own points, and the three
  made orthonormal again (the rotation nearest them, weighted by their points).

A blob whose largest face is a disk (a pole seen end-on) is no box (`_round_face`).
In that frame the box is bounded exactly as an upright one (`tight_fit.bound_in_frame`:
visible faces by their planes, unseen extents by silhouettes or the class prior), and each
face is grown by what the frame's remaining angle error moves its corners.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import cv2
import numpy as np
from scipy.spatial import ConvexHull, QhullError
from scipy.spatial.transform import Rotation

from damon_ros.core.shapes import Shape
from damon_ros.perception.camera import Camera
from damon_ros.perception.fit_kernels import near_planes
from damon_ros.perception.tight_fit import (
    BOX_SHARE,
    FACE_SHARE,
    BoxFit,
    bound_in_frame,
    frame_error,
    on_other_faces,
)
from damon_ros.perception.tracker_config import TrackerConfig

FRAME_POINTS = 256
"""The frame's plane search looks at at most this many of the points (evenly thinned)."""
HYPOTHESES = 48
"""Candidate planes per search: a face holding a third of the points is among the
candidates' best with probability 1 - (1 - 1/27)^48 > 0.8 for triples, and one search
failing only leaves the blob bound."""
ROUND_FILL = 0.8
ROUND_MIN_POINTS = 20
"""A face of at least this many points is a disk (`_round_face`) when its hull fills this
share of the circle through its farthest corner (a rectangle at most 2 / pi = 0.64)."""
INLIER_SHARE = 0.5
"""A candidate plane's inliers lie within this share of the face tolerance of it."""


def fit_tilted_box(views: Sequence[tuple[Camera, np.ndarray]], config: TrackerConfig,
                   name: str = "", cut: Sequence[bool] | None = None) -> BoxFit | None:
    """The box, in any orientation, of the base-frame points several cameras saw of one
    object at one instant (``views``: each camera and its points; ``cut[v]``: view ``v`` is
    flagged partial), or None when they are no box."""
    cut = [False] * len(views) if cut is None else list(cut)
    points = np.vstack([p for _, p in views])
    if len(points) < config.min_points:
        return None
    tol = config.face_tolerance_m
    axes = _frame(points, tol)
    if axes is None:
        return None
    local = np.ascontiguousarray(points @ axes)
    near_low, near_high = near_planes(local, tol)
    if (near_low | near_high).any(axis=1).mean() < BOX_SHARE or _round_face(
            local, near_low, near_high):
        return None
    bound = bound_in_frame(views, cut, axes, local, near_low, near_high, config)
    if bound is None:
        return None
    lo, hi, seen, hidden, *_ = bound
    half = 0.5 * (hi - lo)
    error = frame_error(float(np.sort(hi - lo)[1]))  # the narrowest face's wider side
    # a face turned by the error stands out of its fitted plane (through the middle of its
    # points) by the error times its corners' distance from there: at most the half-diagonal
    grow = error * np.sqrt([half[1] ** 2 + half[2] ** 2, half[0] ** 2 + half[2] ** 2,
                            half[0] ** 2 + half[1] ** 2])
    lo, hi = lo - grow, hi + grow
    centre = axes @ (0.5 * (lo + hi))
    shape = Shape("box", tuple(hi - lo), centre, Rotation.from_matrix(axes).as_quat(),
                  name=name)
    return BoxFit(shape, tuple(seen), tuple(hidden))


def _round_face(local: np.ndarray, near_low: np.ndarray, near_high: np.ndarray) -> bool:
    """Whether the face with the most points is a disk, not a rectangle: its points' hull
    fills at least `ROUND_FILL` of the circle about the middle of their extent through its
    farthest corner. A rectangle fills at most 2 / pi of it (a square; its corners are on
    that circle), a disk nearly all. A pole seen 6 deg off its axis shows its end face, a
    disk, which passed as a box's face; its hidden length then lay outside the box by
    4 mm (side camera, generated G scene)."""
    counts = np.concatenate([near_low.sum(axis=0), near_high.sum(axis=0)])
    best = int(np.argmax(counts))
    k = best % 3
    face = (near_low if best < 3 else near_high)[:, k]
    if np.count_nonzero(face) < ROUND_MIN_POINTS:
        return False
    xy = local[face][:, [j for j in range(3) if j != k]]
    try:
        hull = ConvexHull(xy)
    except (QhullError, ValueError):
        return False
    middle = 0.5 * (xy.min(axis=0) + xy.max(axis=0))
    reach = float(np.max(np.linalg.norm(xy[hull.vertices] - middle, axis=1)))
    return bool(hull.volume >= ROUND_FILL * math.pi * reach * reach)


def _frame(points: np.ndarray, tol: float) -> np.ndarray | None:
    """Box axes (columns, a rotation) from the faces among ``points``, or None."""
    rng = np.random.default_rng(0)  # the same points give the same frame
    sample = points[::max(1, len(points) // FRAME_POINTS)]
    first, on_first = _plane(sample, tol, rng)
    if first is None:
        return None
    rest = sample[~on_first]
    second = None
    need = max(8, FACE_SHARE * len(sample))  # as many points as a visible face has
    if len(rest) >= need:
        second, on_second = _plane(rest, tol, rng, across=first)
        if np.count_nonzero(on_second) < need:
            # a few points off the one face seen (its rim, mixed pixels) are no second
            # face: 8 of them turned a single face's frame 40 deg about its normal, a
            # stress box then bounded at 4 times its volume
            second = None
    if second is None:
        second = _rectangle_axis(sample[on_first], first)
    axes = np.column_stack([first, second, np.cross(first, second)])
    return _refined(points, axes, tol)


def _plane(points: np.ndarray, tol: float, rng: np.random.Generator,
           across: np.ndarray | None = None) -> tuple[np.ndarray | None, np.ndarray]:
    """The unit normal of the plane with the most of ``points`` within ``INLIER_SHARE *
    tol`` of it and which points those are; ``across``: only planes whose normal is at
    right angles to it (planes containing that direction). (None, no points) when the
    points span no plane."""
    n = len(points)
    picks = rng.integers(0, n, size=(HYPOTHESES, 3 if across is None else 2))
    a, b = points[picks[:, 0]], points[picks[:, 1]]
    if across is None:
        normals = np.cross(b - a, points[picks[:, 2]] - a)
    else:
        normals = np.cross(b - a, across)
    norms = np.linalg.norm(normals, axis=1)
    ok = norms > 1e-9
    if not ok.any():
        return None, np.zeros(n, bool)
    normals, a = normals[ok] / norms[ok, None], a[ok]
    offsets = np.abs(points @ normals.T - (a * normals).sum(axis=1))
    inliers = offsets <= INLIER_SHARE * tol
    best = int(np.argmax(inliers.sum(axis=0)))
    if inliers[:, best].sum() < 3:
        return None, np.zeros(n, bool)
    return normals[best], inliers[:, best]


def _rectangle_axis(face: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """An in-plane axis of a single seen face: the minimum-area rectangle of its points."""
    u = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    xy = np.ascontiguousarray(np.column_stack([face @ u, face @ v]), dtype=np.float32)
    angle = math.radians(cv2.minAreaRect(xy)[2]) if len(xy) >= 3 else 0.0
    return math.cos(angle) * u + math.sin(angle) * v


def _refined(points: np.ndarray, axes: np.ndarray, tol: float,
             rounds: int = 2) -> np.ndarray:
    """``axes`` refined: each axis replaced by the normal of the plane through the points
    of its better-populated face (those on no other face), then the rotation nearest these
    normals (weighted by their points; the previous frame holds what no face fixes)."""
    for _ in range(rounds):
        local = np.ascontiguousarray(points @ axes)
        near_low, near_high = near_planes(local, tol)
        target = 1.0 * axes  # the previous frame, with a weight of one point per axis
        edge = on_other_faces(near_low, near_high)
        for k in range(3):
            face = max((near_low[:, k] & ~edge[:, k], near_high[:, k] & ~edge[:, k]),
                       key=np.count_nonzero)
            if np.count_nonzero(face) < 8:
                continue
            on = points[face] - points[face].mean(axis=0)
            normal = np.linalg.svd(on, full_matrices=False)[2][2]
            if normal @ axes[:, k] < 0.0:
                normal = -normal
            target[:, k] += np.count_nonzero(face) * normal
        u, _, vt = np.linalg.svd(target)
        axes = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    return axes
