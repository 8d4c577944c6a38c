"""A box's visible faces as fitted planes, and its points moved onto them along their rays.

A depth camera measures where each pixel's ray meets the surface, and only the distance along
the ray is noisy: the ray itself is exact (the pixel's). A point on a face whose plane is
fitted to hundreds of points therefore lies, to the plane's own error, where its ray meets
that plane. A silhouette end of a box (:mod:`damon_ros.perception.tight_fit`) bounded by the
last samples' noisy positions carried their depth noise outward (2 mm along a ray: the last
row of a front face lay ~1 mm below the true bottom, and the bound a sample spacing below
that); the last samples' rays met with the face's plane place them to a fraction of a
millimetre, and the sample spacing beyond them is then all that is left to allow.

The same planes say how far the box is turned against its frame. Each face's slopes measure
the turn about two axes; pooled over the two or three faces in view (`turn_bounds`,
`yaw_bound`), they pin it more tightly than any one face's tilt did (0.2-1.9 deg on upright
boxes).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from damon_ros.perception.fit_kernels import face_plane

PLANE_SIGMAS = 4.0
"""A face's fitted plane is trusted to this many standard errors at its worst-placed point
(4: a one-sided normal tail of 3e-5, as for balls and poles)."""
MIN_FACE_POINTS = 8


class FacePlane(NamedTuple):
    """A visible face across box axis ``axis`` (at its low end: ``side`` 0; high: 1) in a
    box frame: its points' coordinate along ``axis`` is ``coef[0] + coef[1] * u + coef[2] *
    w`` (``u``, ``w``: the other two axes in order), ``error`` the plane's offset error
    (m, `PLANE_SIGMAS` standard errors) at the worst-placed of ``near`` (the points near its
    plane, over all points), ``slope_se`` the standard errors of ``coef[1:]``, ``span``
    the extent of its own points along ``u`` and ``w``."""

    axis: int
    side: int
    coef: np.ndarray
    error: float
    near: np.ndarray
    slope_se: np.ndarray
    span: np.ndarray


def fit_face_planes(local: np.ndarray, near_low: np.ndarray, near_high: np.ndarray,
                    edge: np.ndarray, visible: np.ndarray, tol: float) -> list[FacePlane]:
    """The planes of the visible faces (``visible[k, side]``) of the box-frame points
    ``local``, each fitted by least squares to its own points (those near no other face's
    plane, ``edge``, where it has `MIN_FACE_POINTS`) within ``tol`` of their median: a
    tilted face (a box turned a fraction of a degree off upright) keeps its tilt. Compiled
    (`fit_kernels.face_plane`)."""
    planes = []
    points = np.ascontiguousarray(local, dtype=float)
    for k in range(3):
        for side, near in ((0, near_low), (1, near_high)):
            if not visible[k, side]:
                continue
            on = np.ascontiguousarray(near[:, k])
            own = on & ~edge[:, k]
            if np.count_nonzero(own) < MIN_FACE_POINTS:
                own = on
            coef, slope_se, offset_se, ok = face_plane(points, own, on, k, tol)
            if ok:
                span = np.ptp(points[own][:, [a for a in range(3) if a != k]], axis=0)
                planes.append(FacePlane(k, side, coef, PLANE_SIGMAS * offset_se, on, slope_se,
                                        span))
    return planes


def trusted(planes: list[FacePlane], tol: float) -> bool:
    """Whether every plane's slopes can be taken as measured: a face slanted against its
    frame by more than half the face tolerance over its extent has points beyond the
    tolerance band that picked it (`fit_kernels.near_planes`), and the fit to the rest
    flattens the slant (a frame forced 2.3 deg off a 24 cm face: the yaw read was too
    small, and the box's far corner stuck out)."""
    return all(float(np.abs(p.coef[1:]) @ p.span) <= 0.5 * tol for p in planes)


class Settled(NamedTuple):
    """A view's points near one face plane moved onto it along their rays: which (``index``
    into the view's points), where they land (``at``, N x 3, NaN where a ray meets the
    plane at grazing incidence or behind the camera) and how far the plane's error may
    move them along each axis (``spread``, N x 3)."""

    plane: FacePlane
    index: np.ndarray
    at: np.ndarray
    spread: np.ndarray


class FaceReach(NamedTuple):
    """What one face plane says of a view's points near it: which (``index`` into the
    view's points) and how far each may reach along an axis (``reach``, `on_faces`)."""

    plane: FacePlane
    index: np.ndarray
    reach: np.ndarray


# A small turn w of the box about its axes tilts the face across x by (n_y, n_z) = (w_z, -w_y),
# the face across y by (n_x, n_z) = (-w_z, w_x), the face across z by (n_x, n_y) = (w_y, -w_x);
# a plane x_j = c0 + c1 x_u + c2 x_w has the normal (1, -c1, -c2). Hence which slope of which
# face measures the turn about x and about y, and with which sign:
_TURN_SLOPES = {0: ((2, 1, 1.0),), 1: ((2, 0, -1.0),), 2: ((1, 1, -1.0), (2, 0, 1.0))}
"""Per face axis: (slope index into ``coef``, turn axis, sign) for each slope measuring a
turn about a horizontal axis (the turn about the vertical is the frame's yaw error)."""


def turn_bounds(planes: list[FacePlane], sigmas: float) -> np.ndarray | None:
    """How far the box may be turned about its x and y axes (rad; 0 about z), from every
    visible face at once: per axis the inverse-variance mean of the faces' slopes measuring
    that turn, plus ``sigmas`` of its standard error. An axis no face measures gets the
    largest bound of the measured ones (a front face alone shows no turn about its normal).
    None when no face measures either. Pooled, two or three faces pin the turn that each
    alone left at ~0.3-1 deg."""
    weight, total = np.zeros(2), np.zeros(2)
    for plane in planes:
        for slope, axis, sign in _TURN_SLOPES[plane.axis]:
            se = float(plane.slope_se[slope - 1])
            if se > 0.0 and np.isfinite(se):
                weight[axis] += 1.0 / se ** 2
                total[axis] += sign * float(plane.coef[slope]) / se ** 2
    if not weight.any():
        return None
    measured = weight > 0.0
    bound = np.zeros(3)
    mean = total[measured] / weight[measured]
    bound[:2][measured] = np.arctan(np.abs(mean)) + sigmas / np.sqrt(weight[measured])
    bound[:2][~measured] = bound[:2][measured].max()
    return bound


def yaw_bound(planes: list[FacePlane], sigmas: float) -> float | None:
    """How far an upright box's frame may be turned about the vertical from the box (rad):
    the side faces' slopes across the vertical pooled (inverse-variance mean, a turn ``w_z``
    tilts the face across x by ``n_y = w_z`` and the face across y by ``n_x = -w_z``), plus
    ``sigmas`` standard errors; None when no side face was fitted."""
    weight = total = 0.0
    for plane in planes:
        if plane.axis == 2:
            continue
        se = float(plane.slope_se[0])
        if se > 0.0 and np.isfinite(se):
            sign = -1.0 if plane.axis == 0 else 1.0
            weight += 1.0 / se ** 2
            total += sign * float(plane.coef[1]) / se ** 2
    if weight == 0.0:
        return None
    return float(np.arctan(abs(total / weight))) + sigmas / float(np.sqrt(weight))


def settle(planes: list[FacePlane], eye: np.ndarray, facing: np.ndarray, mask: np.ndarray,
           points: np.ndarray) -> list[Settled]:
    """A view's points (``points``: ``local[mask]``, seen from ``eye``, the camera's centre
    in the box frame) moved along their rays onto each face plane they lie near, for each
    plane of a face this camera faces (``facing[axis, side]``; its points near another
    face's plane are the rim of a face it sees)."""
    out = []
    for plane in planes:
        j = plane.axis
        if not facing[j, plane.side]:
            continue
        index = np.flatnonzero(plane.near[mask])
        if not len(index):
            continue
        u, w = [a for a in range(3) if a != j]
        ray = points[index] - eye
        # eye + t * ray on the plane: x_j = c0 + c1 x_u + c2 x_w
        across = ray[:, j] - plane.coef[1] * ray[:, u] - plane.coef[2] * ray[:, w]
        offset = plane.coef[0] + plane.coef[1] * eye[u] + plane.coef[2] * eye[w] - eye[j]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = offset / across
            at = eye + t[:, None] * ray
            # the plane's offset error moves a point along its ray by error / |across| rays
            spread = plane.error * np.abs(ray / across[:, None])
        at[~(np.isfinite(t) & (t > 0.0))] = np.nan
        out.append(Settled(plane, index, at, spread))
    return out


def on_faces(settled: list[Settled], points: np.ndarray, k: int, sign: int) -> list[FaceReach]:
    """Per settled face plane (`settle`) not across axis ``k``: how far (``sign`` times the
    coordinate along ``k``) each of the view's points near it (``points``) may reach once
    on the plane, the plane's error included; a point whose ray misses the plane keeps its
    measured coordinate."""
    out = []
    for face in settled:
        if face.plane.axis == k:
            continue
        with np.errstate(invalid="ignore"):
            reach = sign * face.at[:, k] + face.spread[:, k]
        measured = sign * points[face.index, k]
        out.append(FaceReach(face.plane, face.index,
                             np.where(np.isfinite(reach), reach, measured)))
    return out


def farthest(reaches: list[FaceReach], points: np.ndarray, k: int, sign: int) -> np.ndarray:
    """How far each of a view's ``points`` may reach (``sign`` times its coordinate along
    ``k``): the largest over the faces it lies near (it lies on one of them), and no
    farther than it was measured. Near an edge a point's ray may meet the other face's
    plane at grazing incidence, where that plane's error along the ray is several times
    the depth noise: the measurement is then the closer estimate."""
    measured = sign * points[:, k]
    best = np.full(len(measured), -np.inf)
    for face in reaches:
        best[face.index] = np.maximum(best[face.index], face.reach)
    return np.where(np.isfinite(best), np.minimum(best, measured), measured)
