"""Shape estimation: a blob's depth pixels -> a conservative bounding shape in the base frame.

Each blob's depth pixels are deprojected with K and depth outliers are dropped by a
median/MAD test (:func:`blob_points`); then a *conservative* bounding shape is estimated
(:func:`estimate_shape`): a round blob gets a least-squares sphere (the visible cap fixes
the centre), any other a bound that assumes the hidden depth is at most the largest visible
width. Everything is inflated by a margin, because the planner certifies paths against
these shapes.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from scipy.spatial.transform import Rotation

from damon_ros.core.shapes import Shape
from damon_ros.perception.camera import Camera
from damon_ros.perception.fit_kernels import cap_misfit, median, sphere_fit, sphere_spread
from damon_ros.perception.segmentation import Blob
from damon_ros.perception.tight_fit import (
    MIN_PATCH_POINTS,
    MISFIT_SIGMAS,
    fit_box,
    fit_cylinder,
    hull_points,
)
from damon_ros.perception.tilted_box import fit_tilted_box
from damon_ros.perception.tracker_config import TrackerConfig

MAD_TO_SIGMA = 1.4826
"""MAD of a normal distribution times this is its standard deviation."""


def blob_points(camera: Camera, blob: Blob, config: TrackerConfig) -> np.ndarray:
    """Optical-frame points of a blob: in range, thinned to ``max_points``, MAD-filtered."""
    z = blob.depth_mm.astype(np.float64) * 1e-3
    keep = (z >= config.min_depth_m) & (z <= config.max_depth_m)
    u, v, z = blob.u[keep], blob.v[keep], z[keep]
    if z.size > config.max_points:
        stride = int(math.ceil(z.size / config.max_points))
        thin = np.zeros(z.size, dtype=bool)
        thin[::stride] = True
        if blob.edge is not None:  # the outline stays whole: it sets the extent
            thin |= blob.edge[keep]
        u, v, z = u[thin], v[thin], z[thin]
    if z.size == 0:
        return np.empty((0, 3))
    middle = median(z)
    mad = median(np.abs(z - middle))
    fx, fy, cx, cy = camera.K[0, 0], camera.K[1, 1], camera.K[0, 2], camera.K[1, 2]
    # A convex surface is about as deep as the blob is wide: a face seen at a grazing angle
    # (a box's top from a camera beside it) spans ~0.2 m of depth with a MAD of ~2 cm, and
    # a cut at the MAD alone dropped its far third (side camera: 55 % of boxes contained).
    # Bleeding background lies a metre or more away: still far beyond this.
    lateral = max(float(np.ptp(u)) / fx, float(np.ptp(v)) / fy) * middle
    reach = max(config.mad_k * MAD_TO_SIGMA * mad, config.mad_floor_m, lateral)
    inlier = _depth_run(z, middle - reach, middle + reach, config.mad_floor_m)
    z = z[inlier]
    return np.stack([(u[inlier] - cx) / fx * z, (v[inlier] - cy) / fy * z, z], axis=1)


def _depth_run(z: np.ndarray, low: float, high: float, gap: float) -> np.ndarray:
    """Which depths ``z`` lie in ``[low, high]``, or run on from it with no step over
    ``gap`` between neighbouring depths. A surface is continuous in depth: a pole seen
    nearly end-on is several times as deep as it is wide, and the window alone dropped its
    far half (the side camera's cylinder then ended 4 cm short). Bleeding background lies
    a metre or more away, across a step."""
    order = np.argsort(z)
    ranked = z[order]
    start = int(np.searchsorted(ranked, low, side="left"))
    stop = int(np.searchsorted(ranked, high, side="right"))
    if stop <= start:
        return np.zeros(len(z), dtype=bool)
    steps = np.flatnonzero(np.diff(ranked) > gap)  # a step between ranked[i] and [i + 1]
    below = steps[steps < start]
    above = steps[steps >= stop - 1]
    first = int(below[-1]) + 1 if len(below) else 0
    last = int(above[0]) + 1 if len(above) else len(z)
    keep = np.zeros(len(z), dtype=bool)
    keep[order[first:last]] = True
    return keep


def fit_sphere(points: np.ndarray, iterations: int = 2) -> tuple[np.ndarray, float, float]:
    """Least-squares sphere ``(centre, radius, rms residual)`` through points (N >= 4).

    An algebraic fit (linear in centre and ``r^2 - |c|^2``) starts Gauss-Newton on the
    geometric distance; the visible cap of a sphere seen from outside is close to a
    hemisphere, which constrains the centre well in all three directions. Compiled
    (`fit_kernels.sphere_fit`): every blob of every frame is tried as a sphere first.
    """
    p = np.ascontiguousarray(points, dtype=float).reshape(-1, 3)
    if len(p) < 4:
        raise ValueError(f"a sphere fit needs at least 4 points, got {len(p)}")
    centre, radius, rms, ok = sphere_fit(p, iterations)
    if not ok:
        raise ValueError("a sphere fit needs points that are not coplanar")
    return centre, float(radius), float(rms)


def sphere_error(points: np.ndarray, centre: np.ndarray, rms: float) -> float:
    """Standard error (m) of a fitted sphere's surface in its worst direction: that of the
    radius plus that of the centre along its least certain axis, from the fit's covariance
    ``rms^2 (J^T J)^-1`` (``J``: the Jacobian of the distances ``|p - c| - r``).

    Why not the residual alone: how far the fitted surface may be off is the noise times
    how well the points pin the fit. A cap seen from one side ties the centre's depth to
    the radius (the error is several times the residual over the number of points); caps
    seen from two sides fix both, and the same margin would be several times too large.
    Compiled (`fit_kernels.sphere_spread`): numpy took ~30 us a ball.
    """
    p = np.ascontiguousarray(points, dtype=float).reshape(-1, 3)
    return float(sphere_spread(p, np.asarray(centre, dtype=float), float(rms)))


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product of two 3-vectors (np.cross costs microseconds of dispatch per call)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2],
                     a[0] * b[1] - a[1] * b[0]])


def view_basis(camera: Camera, direction: np.ndarray) -> np.ndarray:
    """Optical-frame axes (columns) ``[side, down, view]`` of a frame looking along ``direction``.

    ``side`` is horizontal in the base frame, so boxes built in this frame stand upright.
    """
    view = direction / math.sqrt(direction @ direction)
    side = _cross(camera.rotation[2], view)  # base z ("up") expressed in the optical frame
    norm = math.sqrt(side @ side)
    if norm < 1e-6:  # looking straight up or down
        side = np.array([1.0, 0.0, 0.0]) - view[0] * view
        norm = math.sqrt(side @ side)
    side = side / norm
    return np.column_stack([side, _cross(view, side), view])


class Estimate(NamedTuple):
    """A detection's bounding shape in the base frame, and whether it was fitted as round."""

    shape: Shape
    round: bool


FIT_POINTS = 300
"""The sphere fit uses at most about this many points: a cap of a few hundred pixels fixes the
centre far below a millimetre, and big blobs (near boxes) would otherwise dominate the cost."""


def small_residual(config: TrackerConfig, radius: float, rms: float) -> bool:
    """The residual of a sphere fit is no more than a ball's points leave (the round test's
    first part; `joint_fit` asks it of one fit to several cameras' points)."""
    return rms <= config.sphere_rms_ratio * radius + config.sphere_rms_floor_m


def _is_round(config: TrackerConfig, radius: float, rms: float, width: float,
              centre_depth: float, surface_depth: float) -> bool:
    """A sphere fit describes the blob: small residual, radius ~ half width, centre behind."""
    return (
        small_residual(config, radius, rms)
        and abs(radius - 0.5 * width) <= config.sphere_width_ratio * 0.5 * width
        and centre_depth > surface_depth
    )


SPHERE_SIGMAS = 4.0
"""A fitted sphere (``shape: auto``) is grown by the surface margin, this many standard
errors of its surface (`sphere_error`; 4: a one-sided normal tail of 3e-5) and its misfit
(`sphere_misfit`). On the held + stress scenes (`damon-ros bench-tracker`, eighteenth
session) every whole view of a ball stayed contained with one camera and with two, and
the balls' excess fell from 16-19 % (the earlier margin, 2.5 fit residuals) to 13-16 % with
one camera and 9-11 % with two (`joint_fit`)."""


def _round_fit(points: np.ndarray, local: np.ndarray, basis: np.ndarray, width: float,
               config: TrackerConfig) -> tuple[np.ndarray, float, float] | None:
    """Centre, radius (reaching every point) and safety margin of the blob's sphere, or None
    if not round.

    ``points`` are N x 3 in the optical frame, ``local`` the same as 3 x N view coordinates.
    """
    if len(points) < 4:
        return None
    stride = max(1, len(points) // FIT_POINTS)
    try:
        centre, radius, rms = fit_sphere(points[::stride])
    except ValueError:
        return None
    if not _is_round(config, radius, rms, width, float(centre @ basis[:, 2]),
                     float(local[2].mean())):
        return None
    if config.shape == "auto":
        # The fit, not the noisy points, says where the surface is: the farthest point
        # reaches ~3.5 noise sigmas past it, which adds a third to a small ball's volume;
        # so did a fixed 5 mm inflation (the rms is ~1.5 mm of 2 mm depth noise)
        margin = sphere_margin(points, centre, radius, rms, config, points[::stride])
        return (centre, radius, margin) if math.isfinite(margin) else None
    return centre, max(radius, _reach(local, basis.T @ centre)), config.inflation_m


CAP_RADIUS_RAD = math.radians(20.0)
"""A lump is looked for in caps of the surface this wide (angle from the fitted centre)
around each point's direction (`fit_kernels.cap_misfit`)."""
MISFIT_MEMBERS = 1000
"""`sphere_misfit` thins a blob's points to at most this many ..."""
MISFIT_CAPS = 64
"""... and centres caps on this many of them farthest outside the fit: ~0.1 ms a ball.
With 400 points and caps centred on a quarter of them, a 3 mm lump on a ball measured
0-1 mm where all 3,000 points measured 2.2-2.4 mm; now 1.3-2.6 mm."""


def sphere_misfit(points: np.ndarray, centre: np.ndarray, radius: float, rms: float) -> float:
    """How far (m) the points of some cap of the surface lie outside the fitted sphere
    beyond their noise: the largest cap mean residual less `MISFIT_SIGMAS` of its standard
    errors, or 0.

    Why: a ball's residuals are noise, the same on every side; a lumpy object that passes
    the round test (two balls of one colour 15 mm apart, generated stress scenes) leaves
    its lump as a patch of points all outside the fit, which the fit's standard error does
    not cover: such frames were not contained (S-v0.6-1-s2106-001). The caps are centred
    on the points themselves, so a lump is measured whole wherever it lies: squares fixed
    on a cube around the centre (before) split a lump on their borders, and two cameras
    left 10 of 33 views of a lumpy ball seen whole out (seed 2106, 0.2-1.1 mm)."""
    p = np.ascontiguousarray(points, dtype=float).reshape(-1, 3)
    return float(cap_misfit(p, np.asarray(centre, dtype=float), float(radius), float(rms),
                            MISFIT_SIGMAS, MIN_PATCH_POINTS, math.cos(CAP_RADIUS_RAD),
                            MISFIT_MEMBERS, MISFIT_CAPS))


def sphere_margin(points: np.ndarray, centre: np.ndarray, radius: float, rms: float,
                  config: TrackerConfig, fitted: np.ndarray) -> float:
    """What a sphere fitted to ``fitted`` (``points`` or a thinning of them) is grown by so
    that it contains the object: the surface margin, `SPHERE_SIGMAS` standard errors of the fit
    (`sphere_error`) and what the object showed of a shape other than a ball
    (`sphere_misfit` over all ``points``); inf when the points pin no sphere."""
    return (config.surface_margin_m + SPHERE_SIGMAS * sphere_error(fitted, centre, rms)
            + sphere_misfit(points, centre, radius, rms))


def _reach(local: np.ndarray, centre: np.ndarray) -> float:
    """Largest distance from ``centre`` to the 3 x N points ``local``."""
    diff = local - centre[:, None]
    return math.sqrt(float(np.max((diff * diff).sum(axis=0))))


def estimate_shape(camera: Camera, points: np.ndarray, config: TrackerConfig,
                   name: str = "", partial: bool = False,
                   occluders: np.ndarray | None = None) -> Estimate:
    """Conservative bounding shape (base frame) of an obstacle seen as optical-frame points.

    Round blobs: the fitted sphere, radius ``max(fit, farthest point) + inflation`` (``auto``:
    the fit's radius plus `sphere_margin`). Others:
    each visible point is extended along its ray by the largest visible width (the hidden
    depth of a compact obstacle is at most that), and the bound covers both ends: a sphere
    about the middle of that cloud, or the box of it in the view-aligned frame.
    """
    points_t = points.T
    basis = view_basis(camera, points_t.mean(axis=1))
    local = basis.T @ points_t  # 3 x N [side, down, view] coordinates
    low, high = local.min(axis=1), local.max(axis=1)
    width = float(max(high[0] - low[0], high[1] - low[1]))
    inflate = config.inflation_m
    R, t = camera.rotation, camera.position
    fit = _round_fit(points, local, basis, width, config)
    if fit is not None:
        centre, radius = R @ fit[0] + t, fit[1] + fit[2]
        if config.shape == "box":
            return Estimate(Shape("box", (2 * radius,) * 3, centre, name=name), True)
        return Estimate(Shape("sphere", (radius,), centre, name=name), True)
    if config.shape == "auto" and partial and occluders is not None:
        # A cut-off box: its seen faces bound it, and where only the cut silhouette could,
        # the class prior beyond the last point seen (not the view-extended bound below,
        # whose depth is the largest visible width: boxes touching another object in a
        # generated E scene were 10 times their volume, and swallowed goals beside them)
        box = fit_box(camera, points @ R.T + t, config, name, True, occluders)
        if box is not None:
            return Estimate(box.shape, False)
    elif config.shape == "auto" and not partial:
        # What is fully in view gets a tight shape (tight_fit); a cut-off blob that is no
        # box keeps the view-extended bound below, which does not rely on its silhouette.
        base = points @ R.T + t
        box = fit_box(camera, base, config, name)
        if box is not None:
            return Estimate(box.shape, False)
        cylinder = fit_cylinder(camera, base, config, name)
        if cylinder is not None:
            return Estimate(cylinder, False)
        tilted = fit_tilted_box([(camera, base)], config, name)
        if tilted is not None:  # a box turned about a horizontal axis
            return Estimate(tilted.shape, False)
        return Estimate(hull_points(camera, points, config, name), False)
    ranges = np.sqrt((points_t * points_t).sum(axis=0))
    far = local * (1.0 + width / ranges)  # each point pushed back along its ray by width
    low = np.minimum(low, far.min(axis=1))
    high = np.maximum(high, far.max(axis=1))
    mid = 0.5 * (low + high)
    centre = R @ (basis @ mid) + t
    if config.shape == "sphere":
        radius = max(_reach(local, mid), _reach(far, mid)) + inflate
        return Estimate(Shape("sphere", (radius,), centre, name=name), False)
    orientation = Rotation.from_matrix(R @ basis).as_quat()
    size = tuple(high - low + 2.0 * inflate)
    return Estimate(Shape("box", size, centre, orientation, name=name), False)
