"""The compiled fit kernels against the numpy arithmetic they replace, and against geometry."""

from __future__ import annotations

import math

import numpy as np
import pytest

from damon_ros.perception.fit_kernels import (
    cap_misfit,
    circle_refine,
    cylinder_misfit,
    cylinder_refine,
    cylinder_spread,
    face_plane,
    face_tilts,
    near_planes,
    roundest_axis,
    sphere_spread,
)


@pytest.mark.parametrize("n", [1, 2, 3, 7, 50, 99, 100, 101, 256, 257, 1000, 2001])
def test_face_planes_are_numpys_percentiles(n):
    rng = np.random.default_rng(n)
    for values in (rng.normal(size=(n, 3)), np.round(rng.normal(size=(n, 3)), 1)):  # ties
        tol = 0.05
        near_low, near_high = near_planes(np.ascontiguousarray(values), tol)
        low, high = np.percentile(values, [1.0, 99.0], axis=0)
        assert np.array_equal(near_low, np.abs(values - low) <= tol)
        assert np.array_equal(near_high, np.abs(values - high) <= tol)


def _numpy_refine(xy, centre, radius, iterations):
    """Gauss-Newton on |p - c| - r with numpy's solver: the kernel's reference."""
    for _ in range(iterations):
        d = xy - centre
        dist = np.maximum(np.linalg.norm(d, axis=1), 1e-9)
        jac = np.column_stack([-d / dist[:, None], -np.ones(len(xy))])
        step = np.linalg.solve(jac.T @ jac, jac.T @ (radius - dist))
        centre, radius = centre + step[:2], radius + step[2]
    rms = math.sqrt(np.mean((np.linalg.norm(xy - centre, axis=1) - radius) ** 2))
    return centre, radius, rms


def test_circle_refinement_is_the_geometric_fit_of_a_noisy_arc():
    rng = np.random.default_rng(3)
    angles = rng.uniform(-0.8, 0.8, 300)  # a short arc: the algebraic start is biased
    xy = 0.04 * np.column_stack([np.cos(angles), np.sin(angles)]) + [0.3, -0.1]
    xy += rng.normal(scale=0.001, size=xy.shape)
    start = (np.array([0.31, -0.1]), 0.03)
    cx, cy, radius, rms = circle_refine(xy, start[0][0], start[0][1], start[1], 5)
    centre, ref_radius, ref_rms = _numpy_refine(xy, *start, 5)
    assert np.allclose([cx, cy, radius, rms], [*centre, ref_radius, ref_rms], atol=1e-12)
    assert abs(radius - 0.04) < 0.003 and rms < 0.0015


def test_circle_refinement_of_coincident_points_reports_no_circle():
    xy = np.zeros((20, 2))
    assert math.isnan(circle_refine(xy, 0.0, 0.0, 0.05, 3)[3])


def test_the_roundest_axis_of_a_tilted_cylinder_side_is_its_axis():
    rng = np.random.default_rng(5)
    axis = np.array([0.15, -0.1, 1.0])
    axis /= np.linalg.norm(axis)
    u = np.cross(axis, [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(axis, u)
    angles = rng.uniform(-1.2, 1.2, 400)  # the visible side of a pole: an arc
    heights = rng.uniform(-0.15, 0.15, 400)
    points = (0.05 * (np.cos(angles)[:, None] * u + np.sin(angles)[:, None] * v)
              + heights[:, None] * axis + rng.normal(scale=0.0005, size=(400, 3)))
    centred = points - points.mean(axis=0)
    grid = np.array([[a, b] for a in range(-2, 3) for b in range(-2, 3)], dtype=float)
    start = np.array([0.0, 0.0, 1.0])  # 0.18 rad off the truth
    frame, _, _, radius, rms, ok = roundest_axis(centred, start, grid,
                                                 np.array([0.08, 0.02, 0.005]))
    assert ok
    assert math.acos(min(1.0, abs(float(frame[:, 2] @ axis)))) < 0.01
    assert abs(radius - 0.05) < 0.005 and rms < 0.002
    assert np.allclose(frame.T @ frame, np.eye(3), atol=1e-12)
    assert np.linalg.det(frame) > 0.0


def test_the_sphere_spread_is_the_fit_covariance_numpy_gives():
    """`sphere_spread` is sqrt(var r) + sqrt(largest eigenvalue of cov(centre)) of
    ``rms^2 (J^T J)^-1``, as numpy computes it; points that fix no sphere give inf."""
    rng = np.random.default_rng(2)
    points = rng.normal(size=(200, 3))
    points = 0.07 * points / np.linalg.norm(points, axis=1)[:, None] + [0.4, 0.1, 0.9]
    centre, rms = np.array([0.401, 0.099, 0.9]), 0.0015
    d = points - centre
    jacobian = np.column_stack([d / np.linalg.norm(d, axis=1)[:, None], np.ones(len(d))])
    cov = rms**2 * np.linalg.inv(jacobian.T @ jacobian)
    expected = math.sqrt(cov[3, 3]) + math.sqrt(np.linalg.eigvalsh(cov[:3, :3])[-1])
    assert sphere_spread(points, centre, rms) == pytest.approx(expected, rel=1e-9)
    assert sphere_spread(np.tile(points[:1], (10, 1)), centre, rms) == math.inf


CAP = math.cos(math.radians(20.0))


@pytest.mark.parametrize("axis", [[1.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
def test_a_lump_outside_the_sphere_is_its_misfit_and_noise_is_none(axis):
    """`cap_misfit`: noise around a sphere gives 0; a lump 3 mm outside it gives 1.5-3 mm
    (3 mm less three of its standard errors, diluted a little where a cap reaches past the
    lump). Caps are centred on the points farthest out, so a lump on a cube's corner
    direction (where fixed squares on the cube's faces split it in three) is measured as
    well as one in a face's middle."""
    rng = np.random.default_rng(3)
    directions = rng.normal(size=(3000, 3))
    directions /= np.linalg.norm(directions, axis=1)[:, None]
    rms = 0.001
    points = directions * (0.05 + rng.normal(scale=rms, size=len(directions)))[:, None]
    assert cap_misfit(points, np.zeros(3), 0.05, rms, 3.0, 5, CAP, 1000, 64) == 0.0
    lump = directions @ (np.asarray(axis) / np.linalg.norm(axis)) > 0.95
    points[lump] += 0.003 * directions[lump]
    misfit = cap_misfit(points, np.zeros(3), 0.05, rms, 3.0, 5, CAP, 1000, 64)
    assert 0.0015 < misfit < 0.003


def _side_arc(rng, n: int, radius: float, slopes, centre, noise: float) -> np.ndarray:
    """Points of a pole's visible side (a 2.4 rad arc, 0.3 m long) in a frame whose z is
    off its axis by ``slopes`` (x, y per unit z) and whose origin is ``centre`` off it."""
    angles = rng.uniform(-1.2, 1.2, n)
    z = rng.uniform(-0.15, 0.15, n)
    r = radius + rng.normal(scale=noise, size=n)
    return np.column_stack([centre[0] + slopes[0] * z + r * np.cos(angles),
                            centre[1] + slopes[1] * z + r * np.sin(angles), z])


def test_the_cylinder_fit_finds_the_axis_the_grid_left_off():
    """`cylinder_refine` from zero slopes (the grid's axis, 1 deg off) to the pole's axis,
    centre and radius, each to well within the noise (1.5 mm over 500 points)."""
    rng = np.random.default_rng(7)
    side = _side_arc(rng, 500, 0.05, (0.012, -0.008), (0.003, -0.002), 0.0015)
    cx, cy, ax, ay, radius, ok = cylinder_refine(side, 0.0, 0.0, 0.045, 3)
    assert ok
    assert abs(ax - 0.012) < 0.002 and abs(ay + 0.008) < 0.002
    assert abs(cx - 0.003) < 0.0005 and abs(cy + 0.002) < 0.0005
    assert abs(radius - 0.05) < 0.0005
    assert not cylinder_refine(np.zeros((20, 3)), 0.0, 0.0, 0.05, 3)[5]


def test_the_cylinder_spread_is_the_fit_covariance_numpy_gives():
    """`cylinder_spread`: the surface's worst standard error over both ends and the
    directions round the axis, and the axis's, from ``rms^2 (J^T J)^-1`` as numpy computes
    it; points that fix no cylinder give inf."""
    rng = np.random.default_rng(8)
    side = _side_arc(rng, 300, 0.05, (0.0, 0.0), (0.0, 0.0), 0.0015)
    rms, low, high = 0.0015, -0.15, 0.15
    d = side[:, :2]
    dist = np.linalg.norm(d, axis=1)
    jacobian = np.column_stack([-d / dist[:, None], -d * side[:, 2:3] / dist[:, None],
                                -np.ones(len(d))])
    cov = rms**2 * np.linalg.inv(jacobian.T @ jacobian)
    worst = max(g @ cov @ g for z in (low, high)
                for a in 2 * np.pi * np.arange(16) / 16
                for g in [np.array([np.cos(a), np.sin(a), np.cos(a) * z, np.sin(a) * z, 1.0])])
    surface, tilt = cylinder_spread(side, 0.0, 0.0, 0.05, rms, low, high, 16)
    assert surface == pytest.approx(math.sqrt(worst), rel=1e-9)
    assert tilt == pytest.approx(math.sqrt(np.linalg.eigvalsh(cov[2:4, 2:4])[-1]), rel=1e-9)
    # a short arc ties the centre's depth to the radius: far more than rms / sqrt(n)
    assert surface > 3.0 * rms / math.sqrt(len(side))
    assert cylinder_spread(np.zeros((10, 3)), 0.0, 0.0, 0.05, rms, low, high, 16)[0] == math.inf


def test_a_lump_on_the_side_is_its_misfit_and_noise_is_none():
    """`cylinder_misfit`: noise around the side gives ~0 (a fraction of its rms: 48
    patches at three standard errors); a band 3 mm proud of it over a quarter of the
    length (a sleeve) gives up to 3 mm, less three standard errors."""
    rng = np.random.default_rng(9)
    side = _side_arc(rng, 3000, 0.05, (0.0, 0.0), (0.0, 0.0), 0.001)
    args = (0.0, 0.0, 0.05, 0.001, -0.15, 0.15, 3.0, 5, 12, 4)
    assert cylinder_misfit(side, *args) < 0.1 * 0.001
    sleeve = (side[:, 2] > 0.075) & (np.abs(np.arctan2(side[:, 1], side[:, 0])) < 0.5)
    side[sleeve, :2] *= (1.0 + 0.003 / 0.05)
    assert 0.0015 < cylinder_misfit(side, *args) <= 0.003


def test_a_tilted_faces_tilt_and_its_standard_error():
    """`face_tilts`: a face of 600 points over 6 x 6 cm with 1.5 mm noise, tilted 2 deg
    about x: its tilt to within its standard error, which is the residual over the face's
    spread (numpy's plane fit); a face not visible reads as not tilted, with no error."""
    rng = np.random.default_rng(4)
    n, tilt, noise = 600, math.radians(2.0), 0.0015
    yz = rng.uniform(-0.03, 0.03, (n, 2))
    x = 0.05 + yz[:, 0] * math.tan(tilt) + rng.normal(0.0, noise, n)  # the face at +x
    local = np.column_stack([x, yz])
    near_high = np.zeros((n, 3), np.bool_)
    near_high[:, 0] = True
    near_low = np.zeros((n, 3), np.bool_)
    visible = np.zeros((3, 2), np.bool_)
    visible[0, 1] = True
    cosines, errors = face_tilts(local, near_low, near_high, visible)
    measured = math.acos(min(1.0, cosines[0, 1]))
    centred = local - local.mean(axis=0)
    spread = np.linalg.svd(centred, compute_uv=False)
    expected = spread[2] / math.sqrt(n - 3) / spread[1]
    assert errors[0, 1] == pytest.approx(expected, rel=1e-6)
    assert abs(measured - tilt) < 3.0 * errors[0, 1]
    assert 0.002 < errors[0, 1] < 0.005  # ~ 1.5 mm / (sqrt(600) * 1.7 cm): 0.0036
    assert cosines[1, 0] == 1.0 and errors[1, 0] == 0.0


@pytest.mark.parametrize("k", [0, 1, 2])
def test_a_face_plane_is_numpys_least_squares_fit(k):
    """`face_plane`: the plane through a face's own points within the tolerance of their
    median, its slopes' standard errors and its offset's at the worst of the points near it,
    against numpy's lstsq and the covariance of its solution; an outlier beyond the
    tolerance is left out, and too few points fix nothing."""
    rng = np.random.default_rng(k)
    n = 400
    others = [a for a in range(3) if a != k]
    local = np.empty((n, 3))
    local[:, others] = rng.uniform(-0.05, 0.05, (n, 2))
    local[:, k] = 0.1 + 0.02 * local[:, others[0]] - 0.01 * local[:, others[1]] \
        + rng.normal(0.0, 0.002, n)
    local[0, k] += 0.05  # beyond the tolerance
    own = np.ones(n, np.bool_)
    near = own.copy()
    coef, slope_se, offset_se, ok = face_plane(local, own, near, k, 0.008)
    kept = np.abs(local[:, k] - np.median(local[:, k])) <= 0.008
    assert not kept[0]
    design = np.column_stack([np.ones(np.count_nonzero(kept)), local[kept][:, others]])
    expected, *_ = np.linalg.lstsq(design, local[kept, k], rcond=None)
    residual = local[kept, k] - design @ expected
    sigma = math.sqrt(residual @ residual / (len(residual) - 3))
    inverse = np.linalg.inv(design.T @ design)
    at = np.column_stack([np.ones(n), local[:, others]])
    worst = np.max(np.einsum("ij,jk,ik->i", at, inverse, at))
    assert ok
    assert np.allclose(coef, expected, atol=1e-12)
    assert np.allclose(slope_se, sigma * np.sqrt(np.diag(inverse)[1:]), rtol=1e-9)
    assert offset_se == pytest.approx(sigma * math.sqrt(worst), rel=1e-9)
    assert abs(coef[1] - 0.02) < 4 * slope_se[0] and abs(coef[2] + 0.01) < 4 * slope_se[1]
    few = np.zeros(n, np.bool_)
    few[:7] = True
    assert not face_plane(local, few, near, k, 0.008)[3]
