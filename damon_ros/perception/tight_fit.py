"""Tight shapes from the visible surface: an upright box from its faces, a cylinder from
its side, or a hull.

The view-extended bound of :mod:`damon_ros.perception.shape_fit` assumes every obstacle is as
deep as it is wide, which swallows goals near thin boxes. Here what the camera shows is used
instead, and only what it cannot show is bounded by a prior:

* **box** (:func:`fit_box`): a yaw-only (upright) box. Its yaw is the minimum-area rectangle
  of the points seen from above (front and side faces project to edges of the footprint,
  a visible top face fills it). A face is *visible* when enough points lie on its plane and
  it faces the camera. The extent along an axis is *seen* when a face parallel to that axis
  is visible (such a face spans the axis completely); otherwise only the front face is
  known and the box is extended behind it to the class's ``max_thickness_m``.
* **cylinder** (:func:`fit_cylinder`): any axis; the side's points are an arc of a circle
  across it, the side is seen to both ends, the hidden back is the circle's other half.
* **blob** (:func:`hull_points`): anything that fits no primitive (an L-shaped tool, a
  cylinder seen end-on) becomes the convex hull of its visible points together with the same points
  pushed back along their rays by the blob prior: every hidden part of the object lies on a
  ray through the silhouette, behind the visible surface and (by the prior) within that
  depth of it.

Margins are what the sampling cannot see, not a blanket inflation: a face's own plane is
measured (the extreme of noisy points lies outside it), a silhouette edge is known to one
sample spacing on the image plane, stretched by the obliquity of the face it is seen on,
beyond the last samples where their rays meet their face's plane
(:mod:`damon_ros.perception.face_planes`), and the box's turn and yaw against its frame are
what its faces' planes show together, plus their standard errors.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import cv2
import numpy as np
from scipy.spatial import ConvexHull, QhullError
from scipy.spatial.transform import Rotation

from damon_ros.core.shapes import Shape
from damon_ros.perception.camera import Camera, project
from damon_ros.perception.face_cover import (
    HOLE_SHARE,
    MIN_COSINE,
    face_corners,
    uncovered_share,
)
from damon_ros.perception.face_planes import (
    FacePlane,
    FaceReach,
    Settled,
    farthest,
    fit_face_planes,
    on_faces,
    settle,
    trusted,
    turn_bounds,
    yaw_bound,
)
from damon_ros.perception.fit_kernels import (
    circle_refine,
    cylinder_misfit,
    cylinder_refine,
    cylinder_spread,
    face_counts,
    face_line,
    face_tilts,
    median,
    near_planes,
    robust_ends,
    roundest_axis,
)
from damon_ros.perception.tracker_config import TrackerConfig

FACE_SHARE = 0.04
"""A face is visible when at least this share of the points (and 8) lie on its plane."""
BOX_SHARE = 0.92
"""A blob is a box when at least this share of its points lie on the fitted box's faces."""
YAW_ERROR_RAD = 0.006
"""Residual yaw error after the face fit (about a third of a degree, several times what depth
noise leaves on a face of a few hundred points), where no side face's plane measures it
(`face_planes.yaw_bound`), and for a turned box's frame."""
YAW_NOISE_M = 0.0025
"""Depth noise on a face turns into a yaw error of about this over the face's width."""
MAX_YAW_ERROR_RAD = 0.06
MAX_FACE_TILT_RAD = 0.05
"""A face whose points lie on a plane tilted more than this from the box's is no face of an
upright box (several times what depth noise leaves on a face of a few dozen points)."""
TILT_SIGMAS = 2.0
"""An upright box is grown for a turn (about x and y: `_turns`; about z: `_skewed`'s yaw
error) up to what its faces' planes show, pooled, plus this many standard errors of it
(`face_planes.turn_bounds`, `face_planes.yaw_bound`). The side camera alone on the held +
stress scenes (seed 2106): with the tilt alone a 6 x 6 x 11 cm box tilted 3 deg stuck out
0.6-0.9 mm in 2 of 4,879 whole views; with 1, 2 or 3 standard errors of each face's tilt
none did. Pooled over the faces (two or three pin the turn that one left at ~0.3-1 deg),
every whole box view of four seeds stayed contained, with one camera, two, or the side
camera alone, and the boxes' median excess fell by 4-6 points."""
MIN_FACING = 0.1
"""A face counts as seen only when the camera is at least this sine of an angle off its plane."""
CUT_END_BAND_M = 0.01
"""A cut view's points this close to an end of the box (along its axis, beyond the depth
noise) are its last points there, which must lie away from what may hide it."""
CUT_REACH_STEPS = 3
"""... more than this many segmentation steps (pixels at full resolution: 6 at the shipped
downsample of 2) from an occluding pixel or the image border: the outline and the ring of
occluding pixels are a step or two apart where they meet."""
EDGE_SAMPLES = math.sqrt(2.0)
"""A silhouette edge lies within this many sample spacings (the diagonal of the sampling
grid) beyond the last sample that saw the surface, on the image plane."""
OCTAHEDRON = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]],
                      dtype=float) * math.sqrt(3.0)
"""Offsets whose hull (an octahedron of vertex distance sqrt(3)) contains the unit ball."""


class BoxFit(NamedTuple):
    """An upright box bound and what was seen of it: ``seen[k]`` is True when the extent
    along axis ``k`` (box x, y, z) was observed, False when the prior bounds it."""

    shape: Shape
    seen: tuple[bool, bool, bool]
    hidden_m: tuple[float, float, float]


def _face_yaw(points: np.ndarray, near_low: np.ndarray, near_high: np.ndarray,
              yaw: float) -> tuple[float, float]:
    """The yaw of the best-populated vertical face, by a total-least-squares line through its
    points seen from above (``yaw`` itself when no face has enough points), and the face's
    width (the yaw of a narrow face is uncertain)."""
    face, normal, width = face_line(points, near_low, near_high)  # compiled: every box
    if face < 0:
        return yaw, 0.0
    # the face is across box axis face // 2: its normal is that axis
    angle = normal - (0.0 if face // 2 == 0 else 0.5 * math.pi)
    # the same axes modulo a quarter turn, nearest the rectangle's estimate
    return yaw + (angle - yaw + 0.25 * math.pi) % (0.5 * math.pi) - 0.25 * math.pi, width


def spacing_m(camera: Camera, config: TrackerConfig, depth: float) -> float:
    """Distance between neighbouring samples of a blob's outline on the image plane at
    ``depth``: one pixel (segmentation refines the outline to full resolution)."""
    return depth / camera.K[0, 0]


def fit_box(camera: Camera, points: np.ndarray, config: TrackerConfig,
            name: str = "", partial: bool = False,
            occluders: np.ndarray | None = None) -> BoxFit | None:
    """The upright box of base-frame ``points`` (N x 3), or None when they are no box.
    ``partial``, ``occluders``: the view is flagged partial and where it may be cut
    (`fit_box_seen`'s ``cut`` and ``occluders``)."""
    return fit_box_seen([(camera, points)], config, name, [partial],
                        None if occluders is None else [occluders])


def fit_box_seen(views: Sequence[tuple[Camera, np.ndarray]], config: TrackerConfig,
                 name: str = "", cut: Sequence[bool] | None = None,
                 occluders: Sequence[np.ndarray] | None = None) -> BoxFit | None:
    """The upright box of the base-frame points several cameras saw of one object at one
    instant (``views``: each camera and its points), or None when they are no box. A face
    is visible when it has points and some camera faces it; each point's ray is its own
    camera's. ``cut[v]``: view ``v`` is flagged partial (an occluder or the image border
    may cut its silhouette): its points and faces count, its silhouette bounds nothing, and
    an end that only such views could bound makes the points no box. With ``occluders[v]``
    (view ``v``'s occluding pixels, `segmentation.Blob.occluders`) a cut view's silhouette
    bounds each end where one of its last points lies away from them and from the image
    border (`_BoxView.bounds_end`: an end of a box is a face's plane, which one point of
    its edge in plain view places), and an end no silhouette bounds then lies at most the
    class prior (``max_thickness_m.box``) beyond the last point seen there."""
    cut = [False] * len(views) if cut is None else list(cut)
    points = np.vstack([p for _, p in views])
    if len(points) < config.min_points:
        return None
    xy = np.ascontiguousarray(points[:, :2], dtype=np.float32)
    (_, _), (_, _), angle = cv2.minAreaRect(xy)
    tol = config.face_tolerance_m
    yaw, axes, local, near_low, near_high, face_width = _box_frame(points, math.radians(angle), tol)
    on_face = (near_low | near_high).any(axis=1)
    if on_face.mean() < BOX_SHARE:
        # Two faces and no top (a camera level with the box) leave an L-shaped footprint,
        # whose minimum-area rectangle need not be aligned with either face: search the yaw
        yaw, axes, local, near_low, near_high, face_width = _box_frame(
            points, _best_face_yaw(points, tol), tol)
        on_face = (near_low | near_high).any(axis=1)
        if on_face.mean() < BOX_SHARE:
            return None
    bound = bound_in_frame(views, cut, axes, local, near_low, near_high, config, occluders,
                           upright=True)
    if bound is None:
        return None
    lo, hi, seen, hidden, ends_by, error = bound
    # the faces' planes show what yaw error the frame has left; the face width's noise
    # bounds it where they cannot
    lo, hi = _skewed(local, near_low, near_high, lo, hi, ends_by,
                     frame_error(face_width) if error is None else error)
    centre = axes @ (0.5 * (lo + hi))
    q = np.array([0.0, 0.0, math.sin(0.5 * yaw), math.cos(0.5 * yaw)])
    shape = Shape("box", tuple(hi - lo), centre, q, name=name)
    return BoxFit(shape, tuple(seen), tuple(hidden))


def frame_error(width: float) -> float:
    """The remaining angle error of a box frame fitted to a face ``width`` wide: depth
    noise over the width, within [`YAW_ERROR_RAD`, `MAX_YAW_ERROR_RAD`]."""
    return min(max(YAW_ERROR_RAD, YAW_NOISE_M / max(width, 1e-3)), MAX_YAW_ERROR_RAD)

def bound_in_frame(views: Sequence[tuple[Camera, np.ndarray]], cut: Sequence[bool],
                   axes: np.ndarray, local: np.ndarray, near_low: np.ndarray,
                   near_high: np.ndarray, config: TrackerConfig,
                   occluders: Sequence[np.ndarray] | None = None,
                   upright: bool = False) -> tuple | None:
    """The box bound of the views' points in a box frame (``axes``: its axes as columns,
    ``local`` the points in it, ``near_low`` / ``near_high`` which lie near its robust
    planes), before the frame's own error is allowed for: ``(lo, hi, seen, hidden,
    ends_by, yaw)``, each axis bounded by a visible face's plane, a silhouette or the
    class prior (`fit_box_seen`; ``ends_by[k][side]`` for the horizontal axes says which,
    for `_skewed`; ``yaw``: how far an upright frame may be turned about the vertical, as
    its faces' planes show it, `face_planes.yaw_bound`, or None), or None when the faces do
    not make a box. ``occluders``: `fit_box_seen`. ``upright``: the frame is an upright
    box's, whose faces may show a small tilt (`_tilt_allowance`; a tilted frame allows for
    its own error)."""
    tol = config.face_tolerance_m
    low, high = local.min(axis=0), local.max(axis=0)
    need = max(8, int(FACE_SHARE * len(local)))
    # visible[k, 0] / [k, 1]: the face at low / high of axis k faces a camera (by more than
    # MIN_FACING: an edge-on face's "points" are the rim of another face) and has points
    owner = np.repeat(np.arange(len(views)), [len(p) for _, p in views])
    per_view = [_BoxView(camera, axes, owner == v, local, near_low, near_high, low, high,
                         config, not cut[v], None if occluders is None else occluders[v])
                for v, (camera, _) in enumerate(views)]
    # (its own points: those near another face's plane too are mostly that face's rim,
    # and a face seen edge-on by every camera had only those)
    edge = on_other_faces(near_low, near_high)
    visible = np.logical_or.reduce([w.facing for w in per_view]) & np.column_stack(
        [(near_low & ~edge).sum(axis=0) >= need, (near_high & ~edge).sum(axis=0) >= need])
    if not visible.any():
        return None
    tilts, tilt_bounds = _face_tilts(local, near_low, near_high, visible)
    if tilts.max() > MAX_FACE_TILT_RAD or _holed_face(per_view, near_low, near_high, axes):
        return None  # (the cheap test first: a face's image costs ~0.4 ms)
    faces = fit_face_planes(local, near_low, near_high, edge, visible, tol)
    for w in per_view:
        w.settled = settle(faces, w.eye, w.facing, w.mask, w.local)
    # an upright box may be turned a little about x and y (`_tilt_allowance`)
    measured = upright and trusted(faces, tol)  # the planes' slopes show the turn
    turns = _turns(faces, tilt_bounds, measured) if upright else None
    exempt = np.zeros((3, 2), dtype=bool)  # ends that allow for the turn themselves
    silhouettes = np.zeros((3, 2), dtype=bool)  # ends a whole silhouette bounds
    margin_face = config.surface_margin_m
    prior = config.max_thickness_m["box"]
    seen, hidden = [], []
    # how each end of each horizontal axis is bounded (`_skewed`): "face", "corner", "prior"
    ends_by = [["prior", "prior"] for _ in range(2)]
    # a visible face is its fitted plane, not its farthest noisy point (~3 sigma of depth
    # noise beyond it on each face, ~6 mm a face): the plane bounds it (plane-bounded faces)
    low, high = _face_planes(local, near_low, near_high, edge, visible, low, high, tol)
    lo, hi = low.copy(), high.copy()
    for k in range(3):
        others = [j for j in range(3) if j != k and visible[j].any()]
        if others:
            # One sample on the image plane is 1 / cos of it on a face seen obliquely: a
            # face's far edge, seen at grazing incidence, lies that far beyond its last
            # sample (a 4x cap left the far 3-4 cm of a top face seen from the side out),
            # with the obliquity of the rays there: at a far edge the face is seen more
            # grazingly than on average (the last samples along the axis, 5 % and 3)
            # (several cameras: each one's silhouette bounds the object, the tightest holds)
            tilted = None if turns is None or k < 2 else (turns, 0.5 * (hi - lo))
            ends = [_silhouette(per_view, local, k, sign, others, tilted)
                    if not visible[k, side] else None for side, sign in ((0, -1), (1, 1))]
            # only cut views show that silhouette: an occluder or the image border may hide
            # the rest, which the class prior bounds beyond the last point seen there
            cut_ends = [e is not None and not math.isfinite(e[0]) for e in ends]
            if any(cut_ends) and occluders is None:
                return None
            ends = [(low[k] - prior, False, False) if cut and sign < 0 else
                    (high[k] + prior, False, False) if cut else e
                    for e, cut, sign in zip(ends, cut_ends, (-1, 1), strict=True)]
            lo[k] = lo[k] - margin_face if ends[0] is None else ends[0][0] - margin_face
            hi[k] = hi[k] + margin_face if ends[1] is None else ends[1][0] + margin_face
            if k < 2:
                ends_by[k] = ["face" if e is None else "corner" if e[1] else "prior"
                              for e in ends]
            exempt[k] = [e is not None and e[2] for e in ends]
            silhouettes[k] = [e is not None and not cut for e, cut in zip(ends, cut_ends,
                                                                           strict=True)]
            seen.append(not any(cut_ends))
            hidden.append(prior * sum(cut_ends))
            continue
        # Only a face across this axis is seen: its depth is the prior's.
        if visible[k, 0]:
            lo[k] -= margin_face
            extra = max(0.0, low[k] + prior - high[k])
            hi[k] += extra + margin_face
        elif visible[k, 1]:
            hi[k] += margin_face
            extra = max(0.0, low[k] - (high[k] - prior))
            lo[k] -= extra + margin_face
        else:
            return None
        seen.append(False)
        hidden.append(extra)
    yaw = yaw_bound(faces, TILT_SIGMAS) if measured else None
    if yaw is not None:
        turned = np.array([turns[0], turns[1], yaw])
        _side_ends(per_view, local, lo, hi, turned, visible, silhouettes, ends_by, exempt,
                   margin_face)
    if upright:
        lo, hi = _tilt_allowance(lo, hi, turns, exempt)
    return lo, hi, seen, hidden, ends_by, yaw


def _holed_face(views: list[_BoxView], near_low: np.ndarray, near_high: np.ndarray,
                axes: np.ndarray) -> bool:
    """Whether a whole view shows a face with gaps that no box's face has: the points are
    no box, and a box closed behind them could leave out what stands behind the gaps
    (`face_cover`). Faces seen at a grazing angle are not judged."""
    for w in views:
        if not w.whole:
            continue
        for k, side in zip(*np.nonzero(w.visible), strict=True):
            on = (near_high if side else near_low)[w.mask][:, k]
            if np.median(w.cosines[on, k]) < MIN_COSINE:
                continue
            corners = face_corners(w.local[on], k) @ axes.T
            if uncovered_share(w.camera, w.points[on], corners) > HOLE_SHARE:
                return True
    return False


def _side_ends(views: list[_BoxView], local: np.ndarray, lo: np.ndarray, hi: np.ndarray,
               turns: np.ndarray, visible: np.ndarray, silhouettes: np.ndarray,
               ends_by: list[list[str]], exempt: np.ndarray, margin: float) -> None:
    """An upright box's silhouette ends across the footprint (``silhouettes[k]``, k = x, y)
    bounded again by each face that spans them alone (`_silhouette` with the turn
    ``turns`` about x, y and z: `_side_face_end`), where that is tighter: ``lo`` and ``hi``
    change in place, and such an end then needs neither the yaw skew (``ends_by``
    "corner") nor the tilt allowance (``exempt``). The bound from all the points at once
    took the farthest point of any face and needed both allowances; a side face seen
    squarely bounds such an end more tightly on its own than a top face's far edge seen at
    grazing incidence (one camera, held scenes of seed 2207: the median back side 12.7 ->
    11.7 mm and the far side 8.2 -> 6.2 mm beyond the box)."""
    half = 0.5 * (hi - lo)
    for k in range(2):
        others = [j for j in range(3) if j != k and visible[j].any()]
        for side, sign in ((0, -1), (1, 1)):
            if not silhouettes[k, side]:
                continue
            end, _, turned = _silhouette(views, local, k, sign, others, (turns, half))
            if not turned:
                continue
            if side == 1 and end + margin < hi[k]:
                hi[k] = end + margin
            elif side == 0 and end - margin > lo[k]:
                lo[k] = end - margin
            else:
                continue
            ends_by[k][side] = "corner"
            exempt[k, side] = True


def _turns(faces: list[FacePlane], tilts: np.ndarray, measured: bool) -> np.ndarray:
    """How far an upright box may be turned about its x and y axes (rad; 0 about z): every
    face's slopes pooled (`face_planes.turn_bounds`, plus `TILT_SIGMAS` standard errors).
    Where no plane was fitted, or (not ``measured``) a plane's slant flattened
    (`face_planes.trusted`), each turn is at most the tilt bound of a face across either
    other axis (``tilts``, `_face_tilts`, where measured: above 0; otherwise the largest)."""
    about = turn_bounds(faces, TILT_SIGMAS) if measured else None
    if about is None:
        fallback = float(tilts.max())
        about = np.array([min([tilts[a] for a in range(3) if a != i and tilts[a] > 0.0],
                              default=fallback) for i in range(2)] + [0.0])
    return about


def _tilt_allowance(lo: np.ndarray, hi: np.ndarray, turns: np.ndarray,
                    exempt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """An upright box's bound grown for the turn its faces showed (below
    `MAX_FACE_TILT_RAD`, taken as none by the frame). Turned by ``turns`` about x and y
    (`_turns`), a corner moves along axis ``k`` by at most ``|w_i| e_j + |w_j| e_i``
    (``e``: the half extents across it). The turn about the vertical is the frame's yaw
    error, which `_skewed` allows for. Ends marked ``exempt`` (3 x 2) were bounded with
    the turn allowed for already. A 6 x 6 x 11 cm box tilted 2.6 deg passed as upright
    and its corners stuck out 0.6 mm beyond the face planes (stress scene
    S-v0.6-1-s2106-000, in 15 of 60 frames)."""
    turn = np.tan(turns)
    half = 0.5 * (hi - lo)
    grow = np.array([turn[i] * half[j] + turn[j] * half[i]
                     for i, j in ((1, 2), (0, 2), (0, 1))])
    return lo - np.where(exempt[:, 0], 0.0, grow), hi + np.where(exempt[:, 1], 0.0, grow)


def _box_frame(points: np.ndarray, yaw: float, tol: float) -> tuple:
    """The box frame at ``yaw`` refined once by its best-populated face (`_face_yaw`):
    (yaw, axes, the points in it, which lie near the low / high robust planes of each axis,
    the face's width)."""
    for refine in (True, False):
        c, s = math.cos(yaw), math.sin(yaw)
        axes = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])  # columns: box x, y, z
        local = points @ axes
        near_low, near_high = _near_planes(local, tol)
        if refine:  # the rectangle's yaw rests on a few noisy extremes; a face's on all
            yaw, face_width = _face_yaw(points, near_low, near_high, yaw)
    return yaw, axes, local, near_low, near_high, face_width


def _near_planes(local: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Which of the points (rows of ``local``) lie within ``tol`` of the low / high robust
    plane of each box axis. Depth noise spreads a face's points over several sigma; the
    face test is against robust planes (1st / 99th percentiles), the bound against the
    extremes. Compiled (`fit_kernels.near_planes`): it runs on every box candidate."""
    return near_planes(np.ascontiguousarray(local, dtype=float), tol)


YAW_SEARCH_STEP_RAD = math.radians(3.0)
"""Grid of the yaw search (`_best_face_yaw`): a face of 0.3 m turned by half a step lies
within ~4 mm of its plane, inside the face tolerance, so the best yaw is found to a step
and the face fit refines it."""


YAW_SEARCH_POINTS = 256
"""The yaw search looks at at most this many of the points (evenly thinned): it runs on
every blob that is no box at the rectangle's yaw (a pole, a ball that is not round), and a
share of the points on the faces needs no more."""


def _best_face_yaw(points: np.ndarray, tol: float) -> float:
    """The yaw (a quarter turn, on a `YAW_SEARCH_STEP_RAD` grid) that puts the most points
    within ``tol`` of the robust planes of the horizontal axes: where two faces lie."""
    xy = np.ascontiguousarray(points[::max(1, len(points) // YAW_SEARCH_POINTS), :2],
                              dtype=float)
    yaws = np.arange(0.0, 0.5 * math.pi, YAW_SEARCH_STEP_RAD)
    return float(yaws[int(np.argmax(face_counts(xy, yaws, tol)))])


def _skewed(local: np.ndarray, near_low: np.ndarray, near_high: np.ndarray, lo: np.ndarray,
            hi: np.ndarray, ends_by: list[list[str]],
            error: float) -> tuple[np.ndarray, np.ndarray]:
    """``lo`` and ``hi`` grown across each horizontal axis by what a yaw ``error`` of the
    box's frame moves the true corners beyond each end (``ends_by[k][side]``, `fit_box_seen`):

    * ``"face"``, a fitted face plane: a face turned by the error crosses its plane (the
      median of its points) where the median of its points along the other axis lies, so
      its ends stand out by the error times the farther end's distance from there (half
      the other extent for a face seen evenly; all of it for one seen at one end only);
    * ``"corner"``, a silhouette from a camera that saw the top (or bottom) face whole: the
      footprint's corners are among its samples, in this frame, so the extreme of the
      samples already bounds them (the edge margin covers the last sample spacing);
    * ``"prior"``, anything else (a face extended by the class prior, a silhouette seen only
      from the side, where a back corner hides behind the front one): the error times the
      whole other extent."""
    lo, hi = lo.copy(), hi.copy()
    for k in range(2):
        j = 1 - k
        extent = float(hi[j] - lo[j])
        grow = []
        for side, near in ((0, near_low), (1, near_high)):
            how = ends_by[k][side]
            if how == "face":
                along = local[near[:, k], j]
                middle = min(max(median(along), float(lo[j])), float(hi[j]))
                grow.append(error * max(float(hi[j]) - middle, middle - float(lo[j])))
            else:
                grow.append(0.0 if how == "corner" else error * extent)
        lo[k] -= grow[0]
        hi[k] += grow[1]
    return lo, hi


class _BoxView:
    """What one camera shows of a box fit: its points (``mask`` of the union), the faces
    it faces and has points on (``visible``), its sample spacing at its farthest point,
    how squarely its rays meet each axis's faces (``cosines``), and whether its
    silhouette is whole (not flagged partial)."""

    def __init__(self, camera: Camera, axes: np.ndarray, mask: np.ndarray, local: np.ndarray,
                 near_low: np.ndarray, near_high: np.ndarray, low: np.ndarray,
                 high: np.ndarray, config: TrackerConfig, whole: bool = True,
                 occluders: np.ndarray | None = None) -> None:
        self.mask, self.whole = mask, whole
        self.camera, self.occluders = camera, occluders
        self.reach_px = CUT_REACH_STEPS * config.downsample
        eye = self.eye = camera.position @ axes
        reach = MIN_FACING * float(np.linalg.norm(eye - 0.5 * (low + high)))
        self.facing = np.column_stack([eye < low - reach, eye > high + reach])
        need = max(8, int(FACE_SHARE * np.count_nonzero(mask)))
        self.visible = self.facing & np.column_stack(
            [near_low[mask].sum(axis=0) >= need, near_high[mask].sum(axis=0) >= need])
        self.local = local[mask]
        self.settled: list[Settled] = []  # its points on the face planes (`bound_in_frame`)
        points = self.points = self.local @ axes.T
        self.delta = spacing_m(camera, config, float(np.max((points - camera.position)
                                                            @ camera.rotation[:, 2])))
        rays = points - camera.position
        rays /= np.sqrt((rays * rays).sum(axis=1))[:, None]
        self.cosines = np.abs(rays @ axes)

    def bounds_end(self, along: np.ndarray, sign: int,
                   subset: np.ndarray | None = None) -> bool:
        """Whether this view's silhouette bounds the ``sign`` end of the axis whose
        coordinates of the view's points are ``along``: a whole view's does; a cut one's
        where one of its points within `CUT_END_BAND_M` of that end lies more than
        ``reach_px`` from every occluding pixel and from the image border. That end of a
        box is a face's plane: one of its edge's points in plain view places it. (Where the
        whole edge is hidden, the last points seen are those next to what hides it, and so
        are all within the band, a few pixels, of them.) ``subset``: only these of the
        view's points (one face's, ``along`` theirs): whether that face's own silhouette
        bounds the end."""
        if self.whole:
            return True
        if self.occluders is None or not len(along):
            return False
        points = self.points if subset is None else self.points[subset]
        end = sign * along >= np.max(sign * along) - CUT_END_BAND_M
        uv = project(self.camera, (points[end]))
        r, cam = self.reach_px, self.camera
        clear = np.isfinite(uv).all(axis=1) & np.all(uv >= r, axis=1) & (
            uv[:, 0] <= cam.width - 1 - r) & (uv[:, 1] <= cam.height - 1 - r)
        if len(self.occluders) and clear.any():
            gap = np.abs(uv[clear][:, None, :] - self.occluders[None, :, :]).max(axis=2)
            clear[clear] = gap.min(axis=1) > r
        return bool(clear.any())


def _silhouette(views: list[_BoxView], local: np.ndarray, k: int, sign: int,
                others: list[int],
                tilted: tuple[np.ndarray, np.ndarray] | None = None
                ) -> tuple[float, bool, bool]:
    """Where the box ends at the ``sign`` end of axis ``k`` when no face there is seen: a
    sample spacing (`_edge`) beyond the last point of a camera that sees a face spanning
    the axis, the tightest of these cameras (each whole silhouette bounds the object), never
    inside a point any camera saw; infinite when only cut-off views could bound it. A point
    counts where its ray meets the face plane it lies on (`face_planes.on_faces`), not at
    its noisy depth. And whether that camera saw the top or bottom face (its samples then
    reach the footprint's corners: `_skewed`), and whether the bound allows for the box's
    turn itself.

    ``tilted`` (an upright box's turn bounds about x, y and z, and its half extents): each
    face that spans the axis alone bounds the end, with what the turn may put the box's
    farthest corner beyond that face's own (`_side_face_end`); the bound then needs no
    tilt allowance (nor, across the footprint, yaw skew)."""
    along = local[:, k]
    reach = np.empty(len(local))
    per_face = [on_faces(w.settled, w.local, k, sign) for w in views]
    for w, reaches in zip(views, per_face, strict=True):
        reach[w.mask] = farthest(reaches, w.local, k, sign)
    extreme = float(np.max(reach))
    bounds = []
    for w, reaches in zip(views, per_face, strict=True):
        spans = [j for j in range(3) if j != k and w.visible[j].any()]
        if not spans or not np.any(w.mask) or not w.bounds_end(along[w.mask], sign):
            continue
        if tilted is not None:
            bounds += [(_side_face_end(f, w, k, *tilted), False, True) for f in reaches
                       if w.bounds_end(sign * f.reach, sign, f.index)]
            continue
        mine = reach[w.mask]
        bounds.append((float(np.max(mine)) + _edge(w.cosines, mine, spans, w.delta),
                       bool(w.visible[2].any()), False))
    if not bounds and not all(w.whole for w in views):
        return sign * math.inf, False, False
    if not bounds:  # no single camera saw a spanning face: all of them together did
        both = np.vstack([w.cosines for w in views])
        order = np.concatenate([np.flatnonzero(w.mask) for w in views])
        cosines = np.empty_like(both)
        cosines[order] = both
        bounds.append((extreme + _edge(cosines, reach, others, max(w.delta for w in views)),
                       False, False))
    bound, corner, turned = min(bounds)
    return sign * max(bound, extreme), corner, turned


def _side_face_end(face: FaceReach, view: _BoxView, k: int, turns: np.ndarray,
                   half: np.ndarray) -> float:
    """How far an upright box reaches along axis ``k`` (toward the end ``face.reach``
    measures) by the silhouette of one face that spans that axis: its last sample, a sample
    spacing beyond it (`_edge`), and twice the turn about the third axis (``turns``: about
    x, y, z) times the half extent across the face. The face spans the axis, and the turn
    about its normal slants it with the box, but a turn about the third axis moves the face
    across from it along ``k`` by that much relative to this one."""
    j = face.plane.axis
    slant = 2.0 * math.tan(float(turns[3 - j - k])) * float(half[j])
    return (float(np.max(face.reach)) + slant
            + _edge(view.cosines[face.index], face.reach, [j], view.delta))


def on_other_faces(near_low: np.ndarray, near_high: np.ndarray) -> np.ndarray:
    """N x 3: whether each point lies near a plane of an axis other than each axis."""
    near = near_low | near_high
    return np.column_stack([near[:, [1, 2]].any(axis=1), near[:, [0, 2]].any(axis=1),
                            near[:, [0, 1]].any(axis=1)])


def _face_planes(local: np.ndarray, near_low: np.ndarray, near_high: np.ndarray,
                 edge: np.ndarray, visible: np.ndarray, low: np.ndarray, high: np.ndarray,
                 tol: float) -> tuple[np.ndarray, np.ndarray]:
    """``low`` and ``high`` with each visible face's extreme replaced by its plane: the
    median of the points near it, then of those within ``tol`` of that (the first window,
    around the robust extreme, is lopsided; the second is centred on the face; a mean of
    it left a grazing top face's far points out). Only the face's own points count where
    it has 8 of them: those near another face's plane too are mostly that face's, within
    ``tol`` of the edge and inside this plane, and a small face seen obliquely (a tumbling
    box's) had its plane pulled 1-2 mm inward by them (``edge``: `on_other_faces`)."""
    low, high = low.copy(), high.copy()
    for k in range(3):
        for side, near, out in ((0, near_low, low), (1, near_high, high)):
            if visible[k, side]:
                own = near[:, k] & ~edge[:, k]
                values = local[own if np.count_nonzero(own) >= 8 else near[:, k], k]
                plane = median(values)
                out[k] = median(values[np.abs(values - plane) <= tol])
    return low, high


def _edge(cosines: np.ndarray, reach: np.ndarray, faces: list[int], delta: float) -> float:
    """How far an edge lies beyond the farthest of samples that reach ``reach`` toward it:
    one sample spacing ``delta`` over the cosine of the most squarely seen face of
    ``faces`` (the axes of the visible faces that span it), at the most grazing of the last
    samples (5 % and at least 3)."""
    count = min(max(3, len(reach) // 20), len(reach))
    last = np.argpartition(reach, len(reach) - count)[-count:]  # (a set: no sort)
    best = max(float(cosines[last, j].min()) for j in faces)
    return delta / max(best, MIN_FACING)


def _face_tilts(local: np.ndarray, near_low: np.ndarray, near_high: np.ndarray,
                visible: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per axis, the largest angle (rad) between a visible face across it (its own points'
    plane, not those on another face too) and the frame's, and the largest that angle may
    be: plus `TILT_SIGMAS` of its standard errors; 0 where none was measured. Over
    `MAX_FACE_TILT_RAD` the box is no box of this frame (a small tilted box puts enough of
    its points within the face tolerance of upright planes to pass as one, and its hidden
    corners then stick out of the upright bound); below it, `_tilt_allowance` grows the
    bound by what the turn may be (`_turns`: these bounds only where no face plane was
    fitted). (The tilt alone was too little: a 6 cm face's error is 0.6-1.3 deg, and a box
    tilted 3 deg, measured below that, stuck out 0.9 mm.)"""
    cosines, errors = face_tilts(np.ascontiguousarray(local), near_low, near_high, visible)
    tilts = np.arccos(np.minimum(cosines, 1.0))  # unmeasured faces give 1.0: 0 rad, 0 error
    return tilts.max(axis=1), (tilts + TILT_SIGMAS * errors).max(axis=1)


def hull_points(camera: Camera, points_optical: np.ndarray, config: TrackerConfig,
                name: str = "") -> Shape:
    """Convex point-set bound of a blob: the hull of the visible points and of the same
    points pushed back by the blob prior along their rays, grown by the sampling margin."""
    p = np.asarray(points_optical, dtype=float)
    # the grid samples alone: its margin is a downsampled step (below), which the outline's
    # refinement does not shrink, and the refined pixels only made the hulls larger
    K = camera.K
    u = np.rint(p[:, 0] / p[:, 2] * K[0, 0] + K[0, 2]) % config.downsample
    v = np.rint(p[:, 1] / p[:, 2] * K[1, 1] + K[1, 2]) % config.downsample
    if np.count_nonzero((u == 0) & (v == 0)) >= 4:
        p = p[(u == 0) & (v == 0)]
    ranges = np.linalg.norm(p, axis=1)
    far = p * (1.0 + config.max_thickness_m["blob"] / ranges)[:, None]
    cloud = np.vstack([p, far])
    # a step and a half of the downsampled grid: the opening (segmentation) cuts the sharp
    # corners of a silhouette by more than the outline's refinement reaches
    depth = median(np.ascontiguousarray(p[:, 2]))
    margin = spacing_m(camera, config, depth) * 1.5 * config.downsample + config.surface_margin_m
    try:
        cloud = cloud[ConvexHull(cloud).vertices]
    except (QhullError, ValueError):
        pass
    grown = (cloud[:, None, :] + margin * OCTAHEDRON[None]).reshape(-1, 3)
    try:
        grown = grown[ConvexHull(grown).vertices]
    except (QhullError, ValueError):
        pass
    base = grown @ camera.rotation.T + camera.position
    centre = base.mean(axis=0)
    return Shape("points", (), centre, points=base - centre, name=name)


CYLINDER_SHARE = 0.92
"""A blob is a cylinder when this share of its points lie on the fitted side or on an end."""
MIN_ARC_RAD = 1.2
"""The side must be seen over at least this arc (rad) for its circle to fix the axis."""
CYLINDER_SIGMAS = 4.0
"""A fitted side is grown by this many standard errors of its surface at the worst place
(`cylinder_spread`; 4: a one-sided normal tail of 3e-5, as for balls). It was 3.5 fit
residuals plus the last axis step over half the length: 6-7 mm on the generated poles,
whose fit places the surface to about a millimetre."""
MISFIT_SIGMAS = 3.0
"""A patch's mean residual counts as the object's shape, not noise, beyond this many of its
standard errors (balls and poles alike)."""
MIN_PATCH_POINTS = 5
MISFIT_SECTORS = 12
MISFIT_SLICES = 4
"""A side's patches (`cylinder_misfit`): 30 deg sectors round the axis times quarters of
the length seen."""
SIDE_RMS_SHARE = 0.3
"""A side fits a cylinder when all its points (away from the ends) leave a residual of at
most this share of the face tolerance: 1.4-1.6 mm on generated poles (2 mm depth noise),
3.4-4.2 mm on small boxes whose faces a trimmed fit turned into an arc."""
CAP_POINTS = 20
"""An end face is measured when this many points lie on it (their mean then places it to
a fraction of the noise, and their spread estimates that fraction)."""
SPREAD_ANGLES = 16
"""Directions round the axis at which `cylinder_spread` asks the surface's error."""
AXIS_ITERATIONS = 3
"""Gauss-Newton steps of the five-parameter fit from the grid's axis (it settles in two)."""
SIDE_ROUNDS = 2
"""The side's points are chosen again around the refined fit: the grid's circle leaves
residuals of 4-7 mm (its axis ~1 deg off), too loose a band to leave the ends out."""
AXIS_STEPS_RAD = (0.08, 0.02, 0.005)
"""The axis is searched on 5 x 5 grids of tilts about the principal direction, each this
step, around the best of the previous one; the five-parameter fit (`_refine_axis`) then
finishes it."""
MAX_FIT_POINTS = 400


def _refine_circle(xy: np.ndarray, centre: np.ndarray, radius: float,
                   iterations: int = 5) -> tuple[np.ndarray, float, float]:
    """Geometric circle fit (Gauss-Newton on |p - c| - r) from an algebraic start: the
    algebraic fit of a short noisy arc comes out several millimetres too small. Compiled
    (`fit_kernels.circle_refine`): numpy spent ~0.3 ms a cylinder on its small steps."""
    cx, cy, radius, rms = circle_refine(np.ascontiguousarray(xy, dtype=float),
                                        float(centre[0]), float(centre[1]), radius, iterations)
    if not math.isfinite(rms):
        raise np.linalg.LinAlgError("the side's points fix no circle")
    return np.array([cx, cy]), radius, rms


_GRID = np.array([[a, b] for a in range(-2, 3) for b in range(-2, 3)], dtype=float)
"""The 5 x 5 grid of tilts of `_best_axis`, in steps."""


def _best_axis(points: np.ndarray) -> tuple[np.ndarray, tuple] | None:
    """The axis (frame) whose cross-section of ``points`` is the roundest, and its circle,
    starting from their principal direction. Compiled (`fit_kernels.roundest_axis`): the
    grids' numpy steps cost ~0.4 ms a blob, and every blob that is no box is tried."""
    centred = points - points.mean(axis=0)
    _, vectors = np.linalg.eigh(centred.T @ centred)
    frame, cx, cy, radius, rms, ok = roundest_axis(
        np.ascontiguousarray(centred), np.ascontiguousarray(vectors[:, 2]), _GRID,
        np.array(AXIS_STEPS_RAD))
    return (frame, (np.array([cx, cy]), radius, rms)) if ok else None


def _refine_axis(side: np.ndarray, frame: np.ndarray, centre2: np.ndarray,
                 radius: float) -> tuple[np.ndarray, np.ndarray]:
    """The frame turned onto the axis that a five-parameter fit of the side's points
    (``side``: N x 3 in ``frame``) finds, and the axis's point across it. The grid search
    leaves the axis up to ~1 deg off (measured on generated poles), which smears the circle
    across the length: the fit's covariance can then bound the surface (`cylinder_spread`)."""
    cx, cy, ax, ay, _, ok = cylinder_refine(np.ascontiguousarray(side), float(centre2[0]),
                                            float(centre2[1]), radius, AXIS_ITERATIONS)
    if not ok or not math.isfinite(ax * ay * cx * cy):
        raise np.linalg.LinAlgError("the side's points fix no axis")
    axis = frame @ np.array([ax, ay, 1.0])
    axis /= np.linalg.norm(axis)
    u = frame[:, 0] - (frame[:, 0] @ axis) * axis
    u /= np.linalg.norm(u)
    v = np.array([axis[1] * u[2] - axis[2] * u[1], axis[2] * u[0] - axis[0] * u[2],
                  axis[0] * u[1] - axis[1] * u[0]])  # axis x u (np.cross: ~20 us a call)
    turned = np.column_stack([u, v, axis])
    through = frame @ np.array([cx, cy, 0.0])
    return turned, (turned.T @ through)[:2]


def _side_points(local: np.ndarray, dist: np.ndarray, radius: float, rms: float,
                 tol: float) -> np.ndarray:
    """Which points (``local``: N x 3 in the axis frame, ``dist`` from the axis) fit the
    side: near the circle (within 2 residuals) and a face tolerance away from either end.
    An end face seen lies inside the circle up to its rim; its points pulled the fitted side
    in by 1.5-5.7 mm (generated poles), more than the fit's own error."""
    return (np.abs(dist - radius) <= max(2.0 * rms, 0.25 * tol)) & _away_from_ends(local, tol)


def _on_end_faces(local: np.ndarray, dist: np.ndarray, radius: float,
                  tol: float) -> np.ndarray:
    """Which points (N x 3 in the axis frame) lie within ``tol`` of the plane of an end face
    seen (`CAP_POINTS` inside the rim near an end), whatever its angle to the frame. The
    band across the axis leaves out an end face only while the axis is right: on short,
    wide poles the points near the rim of a face 2-4 deg off the band stayed in the side
    and held the axis there (random poles, front camera: 0.4 mm out)."""
    out = np.zeros(len(local), dtype=bool)
    for end in robust_ends(np.ascontiguousarray(local[:, 2])):
        on = (np.abs(local[:, 2] - end) <= 2.0 * tol) & (dist <= radius - tol)
        if np.count_nonzero(on) < CAP_POINTS:
            continue
        face = local[on]
        middle = face.mean(axis=0)
        normal = np.linalg.svd(face - middle, full_matrices=False)[2][2]
        out |= np.abs((local - middle) @ normal) <= tol
    return out


def _away_from_ends(local: np.ndarray, tol: float) -> np.ndarray:
    """Which points (N x 3 in the axis frame) lie more than ``tol`` from both ends (the 1st
    and 99th percentiles along the axis)."""
    low, high = robust_ends(np.ascontiguousarray(local[:, 2]))
    return (local[:, 2] - low > tol) & (high - local[:, 2] > tol)


class SideFit(NamedTuple):
    """A pole's side fitted to its points: ``local`` are the points in ``frame`` (columns
    u, v, axis; base frame) about ``origin``; the axis passes through ``centre2`` across
    it; ``fitted`` marks the points the circle was fitted to."""

    origin: np.ndarray
    frame: np.ndarray
    local: np.ndarray
    centre2: np.ndarray
    radius: float
    rms: float
    fitted: np.ndarray


def fit_side(points: np.ndarray, origin: np.ndarray, frame: np.ndarray, centre2: np.ndarray,
             radius: float, rms: float, config: TrackerConfig) -> SideFit | None:
    """The side of base-frame ``points`` fitted from a first guess (a frame whose z is near
    the axis, and the circle across it), or None when they fit no side: its points chosen
    (`_side_points`), its circle refined, the axis refined by all five parameters
    (`_refine_axis`), `SIDE_ROUNDS` times; then its circle in the final frame. All its
    points away from the ends must fit it within `SIDE_RMS_SHARE` of the face tolerance.
    One camera's points (`fit_cylinder`) or several cameras' (`joint_fit`)."""
    tol = config.face_tolerance_m
    faces = np.zeros(len(points), dtype=bool)  # the end faces' points (`_on_end_faces`)
    try:
        for turn in range(SIDE_ROUNDS + 1):
            local = (points - origin) @ frame
            dist = np.linalg.norm(local[:, :2] - centre2, axis=1)
            if turn == 1:  # once the first fit has the circle: their planes need no more
                faces = _on_end_faces(local, dist, radius, tol)
            fitted = _side_points(local, dist, radius, rms, tol) & ~faces
            if fitted.sum() < config.min_points:
                return None
            centre2, radius, rms = _refine_circle(local[fitted, :2], centre2, radius)
            if turn < SIDE_ROUNDS:
                frame, centre2 = _refine_axis(local[fitted], frame, centre2, radius)
    except np.linalg.LinAlgError:
        return None  # the points are no cylinder's side
    residual = np.linalg.norm(local[:, :2] - centre2, axis=1)[_away_from_ends(local, tol)]
    residual -= radius
    if residual @ residual > (SIDE_RMS_SHARE * tol) ** 2 * len(residual):
        return None
    return SideFit(origin, frame, local, centre2, radius, rms, fitted)


def side_bound(fit: SideFit, low: float, high: float,
               config: TrackerConfig) -> tuple[float, float]:
    """The radius that bounds the pole from its fitted side, and the standard error of the
    axis's direction (rad): the fitted radius grown by the surface margin,
    `CYLINDER_SIGMAS` standard errors of the surface at its worst place between ``low``
    and ``high`` along the axis (`cylinder_spread`) and what the side's points showed of a
    shape other than a cylinder (`cylinder_misfit`: a lump, a bend); inf when the points
    fix no cylinder."""
    tol = config.face_tolerance_m
    local, (cx, cy) = fit.local, (float(fit.centre2[0]), float(fit.centre2[1]))
    spread, tilt = cylinder_spread(np.ascontiguousarray(local[fit.fitted]), cx, cy, fit.radius,
                                   fit.rms, low, high, SPREAD_ANGLES)
    dist = np.linalg.norm(local[:, :2] - fit.centre2, axis=1)
    side = local[(np.abs(dist - fit.radius) <= tol) & _away_from_ends(local, tol)]
    misfit = cylinder_misfit(np.ascontiguousarray(side), cx, cy, fit.radius, fit.rms, low, high,
                             MISFIT_SIGMAS, MIN_PATCH_POINTS, MISFIT_SECTORS, MISFIT_SLICES)
    return fit.radius + config.surface_margin_m + CYLINDER_SIGMAS * spread + misfit, tilt


def fit_cylinder(camera: Camera, points: np.ndarray, config: TrackerConfig,
                 name: str = "") -> Shape | None:
    """The cylinder of base-frame ``points`` (N x 3), any axis, or None when they are none.

    Its axis is the direction across which the points are most nearly a circle's arc (a
    grid search about their principal direction, then a fit of all five parameters); the
    arc must span `MIN_ARC_RAD` and face the camera. The radius is the fitted one grown by
    the surface margin, `CYLINDER_SIGMAS` standard errors of the fitted surface at its
    worst place (`cylinder_spread`: a short arc leaves the centre's depth and the radius
    uncertain together) and the side's misfit (`cylinder_misfit`). The length is what was seen,
    grown at each end by a sample (the side is seen to its ends) or, where the end face is
    seen, to the face's plane (`_cap_plane`) grown by its errors.
    """
    if len(points) < config.min_points:
        return None
    sample = points[::max(1, len(points) // MAX_FIT_POINTS)]
    found = _best_axis(sample)
    if found is None:
        return None
    frame, (centre2, radius, rms) = found
    tol = config.face_tolerance_m
    fit = fit_side(points, sample.mean(axis=0), frame, centre2, radius, rms, config)
    if fit is None:
        return None
    mean, frame, local, centre2, radius, rms, _ = fit
    dist = np.linalg.norm(local[:, :2] - centre2, axis=1)
    on_side = np.abs(dist - radius) <= tol
    on_end = ~_away_from_ends(local, tol) & (dist <= radius + tol)
    if (on_side | on_end).mean() < CYLINDER_SHARE:
        return None
    eye = (camera.position - mean) @ frame
    toward = eye[:2] - centre2
    if np.linalg.norm(toward) <= radius:
        return None  # the camera would be inside it
    side_local = local[on_side & ~on_end]  # (an end face's rim runs all round)
    if len(side_local) < config.min_points:
        return None
    side = side_local[:, :2] - centre2
    angles = np.arctan2(side[:, 1], side[:, 0])
    facing = np.cos(angles - math.atan2(toward[1], toward[0]))
    if float(np.ptp(angles)) < MIN_ARC_RAD or np.mean(facing > 0.0) < 0.95:
        return None  # too little arc to fix the axis, or a hollow seen from inside
    low, high = float(local[:, 2].min()), float(local[:, 2].max())
    depth = float(np.max((points - camera.position) @ camera.rotation[:, 2]))
    # an end is seen as where the side's samples stop: within a sample (grid diagonal) on
    # the image plane, which along the axis is 1 / sin of the angle between axis and view
    ray = eye - np.array([*centre2, 0.5 * (low + high)])
    sine = math.sqrt(max(0.0, 1.0 - (ray[2] / float(np.linalg.norm(ray))) ** 2))
    edge = (spacing_m(camera, config, depth) * EDGE_SAMPLES / max(sine, MIN_FACING)
            + config.surface_margin_m)
    bound, tilt = side_bound(fit, low, high, config)
    if not math.isfinite(bound + tilt):
        return None
    # an end face seen is a plane across the axis, placed by its points' mean: grown by
    # its standard errors and what the axis's error tilts it by at the rim
    bottom = _cap_plane(local, dist, radius, low, eye[2] < low, tol)
    top = _cap_plane(local, dist, radius, high, eye[2] > high, tol)
    cap = config.surface_margin_m + CYLINDER_SIGMAS * tilt * bound
    low = low - edge if bottom is None else bottom[0] - cap - CYLINDER_SIGMAS * bottom[1]
    high = high + edge if top is None else top[0] + cap + CYLINDER_SIGMAS * top[1]
    centre = mean + frame @ np.array([*centre2, 0.5 * (low + high)])
    q = Rotation.from_matrix(frame).as_quat()
    return Shape("cylinder", (bound, high - low), centre, q, name=name)


def _cap_plane(local: np.ndarray, dist: np.ndarray, radius: float, end: float, facing: bool,
               tol: float) -> tuple[float, float] | None:
    """Where the end face near ``end`` (along the axis) lies, and its standard error: the
    mean of the points on it inside the rim (the side's last points lie on the rim), or
    None unless it faces the camera with at least `CAP_POINTS` of them."""
    if not facing:
        return None
    z = local[(np.abs(local[:, 2] - end) <= tol) & (dist <= radius - tol), 2]
    if len(z) < CAP_POINTS:
        return None
    return float(z.mean()), float(z.std()) / math.sqrt(len(z))
