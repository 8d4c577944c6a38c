"""Compiled inner loops of the shape fits (numba).

A frame's fits run on a few hundred points each, where numpy spends more time dispatching
its many small reductions than computing them: the cylinder's axis search took ~2 ms a blob
and a sphere fit ~0.2 ms, most of the tracker's per-frame budget. These kernels do the same
arithmetic in one pass over the points. Each returns what the numpy version returned (to
rounding); the callers keep the decisions.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

SINGULAR = 1e-12
"""A 3x3 or 4x4 normal matrix whose pivot falls below this (relative to its diagonal) has no
solution: the points do not fix the fit (collinear for a circle, coplanar for a sphere)."""


@njit(cache=True)
def _solve(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, bool]:
    """``a x = b`` by Gaussian elimination with partial pivoting (a small dense system);
    ``ok`` False when a pivot is (relatively) zero."""
    n = len(b)
    m = a.copy()
    x = b.copy()
    scale = 0.0
    for i in range(n):
        scale = max(scale, abs(m[i, i]))
    if scale == 0.0:
        return x, False
    for col in range(n):
        pivot = col
        for row in range(col + 1, n):
            if abs(m[row, col]) > abs(m[pivot, col]):
                pivot = row
        if abs(m[pivot, col]) <= SINGULAR * scale:
            return x, False
        if pivot != col:
            for j in range(n):
                m[col, j], m[pivot, j] = m[pivot, j], m[col, j]
            x[col], x[pivot] = x[pivot], x[col]
        for row in range(col + 1, n):
            f = m[row, col] / m[col, col]
            for j in range(col, n):
                m[row, j] -= f * m[col, j]
            x[row] -= f * x[col]
    for col in range(n - 1, -1, -1):
        s = x[col]
        for j in range(col + 1, n):
            s -= m[col, j] * x[j]
        x[col] = s / m[col, col]
    return x, True


@njit(cache=True)
def circle_fits(points: np.ndarray, u_axes: np.ndarray,
                v_axes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Algebraic least-squares circles of centred ``points`` (N x 3) projected on each of K
    planes (``u_axes[k]``, ``v_axes[k]``: the plane's axes): centres (K x 2), radii (K; NaN
    where the fit has none) and the rms of ``|p - c| - r``.

    The fit ``|p|^2 = 2 p.c + (r^2 - |c|^2)`` by its 3 x 3 normal equations (moments of the
    projected points; well conditioned because the points are centred).
    """
    n_pts, k_all = points.shape[0], u_axes.shape[0]
    centres = np.empty((k_all, 2))
    radii = np.empty(k_all)
    rms = np.empty(k_all)
    x = np.empty(n_pts)
    y = np.empty(n_pts)
    normal = np.empty((3, 3))
    right = np.empty(3)
    for k in range(k_all):
        sx = sy = sxx = syy = sxy = sxr = syr = sr = 0.0
        for i in range(n_pts):
            px, py, pz = points[i, 0], points[i, 1], points[i, 2]
            xi = px * u_axes[k, 0] + py * u_axes[k, 1] + pz * u_axes[k, 2]
            yi = px * v_axes[k, 0] + py * v_axes[k, 1] + pz * v_axes[k, 2]
            x[i], y[i] = xi, yi
            r = xi * xi + yi * yi
            sx += xi
            sy += yi
            sxx += xi * xi
            syy += yi * yi
            sxy += xi * yi
            sxr += xi * r
            syr += yi * r
            sr += r
        normal[0, 0], normal[1, 1], normal[2, 2] = 4.0 * sxx, 4.0 * syy, float(n_pts)
        normal[0, 1] = normal[1, 0] = 4.0 * sxy
        normal[0, 2] = normal[2, 0] = 2.0 * sx
        normal[1, 2] = normal[2, 1] = 2.0 * sy
        right[0], right[1], right[2] = 2.0 * sxr, 2.0 * syr, sr
        sol, ok = _solve(normal, right)
        cx, cy = sol[0], sol[1]
        r2 = sol[2] + cx * cx + cy * cy
        centres[k, 0], centres[k, 1] = cx, cy
        if not ok or not r2 > 0.0:
            radii[k] = rms[k] = np.nan
            continue
        radius = math.sqrt(r2)
        sq = 0.0
        for i in range(n_pts):
            d = math.sqrt((x[i] - cx) ** 2 + (y[i] - cy) ** 2) - radius
            sq += d * d
        radii[k] = radius
        rms[k] = math.sqrt(sq / n_pts)
    return centres, radii, rms


@njit(cache=True)
def circle_refine(xy: np.ndarray, cx: float, cy: float, radius: float,
                  iterations: int) -> tuple[float, float, float, float]:
    """Geometric circle fit of ``xy`` (N x 2): Gauss-Newton on ``|p - c| - r`` from the given
    circle, by its 3 x 3 normal equations; the centre, radius and rms residual (the start
    again, rms NaN, when a step's equations are singular)."""
    n = xy.shape[0]
    normal = np.empty((3, 3))
    right = np.empty(3)
    row = np.empty(3)
    for _ in range(iterations):
        normal[:] = 0.0
        right[:] = 0.0
        for i in range(n):
            dx, dy = xy[i, 0] - cx, xy[i, 1] - cy
            dist = max(math.sqrt(dx * dx + dy * dy), 1e-9)
            row[0], row[1], row[2] = -dx / dist, -dy / dist, -1.0
            _accumulate(normal, right, row, radius - dist)
        step, ok = _solve(normal, right)
        if not ok:
            return cx, cy, radius, np.nan
        cx, cy, radius = cx + step[0], cy + step[1], radius + step[2]
    sq = 0.0
    for i in range(n):
        d = math.sqrt((xy[i, 0] - cx) ** 2 + (xy[i, 1] - cy) ** 2) - radius
        sq += d * d
    return cx, cy, radius, math.sqrt(sq / n)


@njit(cache=True)
def _unit_frame(axis: np.ndarray) -> np.ndarray:
    """Columns u, v, axis (normalised): a right-handed frame around ``axis`` whose u is
    across the base x axis (the y axis when ``axis`` is nearly along x)."""
    a = axis / math.sqrt(axis @ axis)
    helper = np.zeros(3)
    helper[0 if abs(a[0]) < 0.9 else 1] = 1.0
    u = np.array([a[1] * helper[2] - a[2] * helper[1], a[2] * helper[0] - a[0] * helper[2],
                  a[0] * helper[1] - a[1] * helper[0]])
    u /= math.sqrt(u @ u)
    frame = np.empty((3, 3))
    frame[:, 0] = u
    frame[:, 1] = np.array([a[1] * u[2] - a[2] * u[1], a[2] * u[0] - a[0] * u[2],
                            a[0] * u[1] - a[1] * u[0]])
    frame[:, 2] = a
    return frame


@njit(cache=True)
def roundest_axis(centred: np.ndarray, axis: np.ndarray, grid: np.ndarray,
                  steps: np.ndarray) -> tuple[np.ndarray, float, float, float, float, bool]:
    """The frame (columns u, v, axis) across whose plane the centred points (N x 3) are the
    roundest, by coarse-to-fine grids of tilts about ``axis`` (``grid``: K x 2 tilts in
    steps, each of ``steps`` in turn around the best so far), with that plane's algebraic
    circle (`circle_fits`): frame, centre x, y, radius, rms, and False when no tilt had a
    circle."""
    frame = _unit_frame(axis)
    k_all = grid.shape[0]
    u_axes, v_axes = np.empty((k_all, 3)), np.empty((k_all, 3))
    frames = np.empty((k_all, 3, 3))
    best = (0.0, 0.0, 0.0, 0.0)
    for step in steps:
        for k in range(k_all):
            tilt = np.array([math.tan(grid[k, 0] * step), math.tan(grid[k, 1] * step), 1.0])
            frames[k] = _unit_frame(frame @ tilt)
            u_axes[k], v_axes[k] = frames[k][:, 0], frames[k][:, 1]
        centres, radii, rms = circle_fits(centred, u_axes, v_axes)
        chosen = -1
        for k in range(k_all):
            if math.isfinite(radii[k]) and (chosen < 0 or rms[k] < rms[chosen]):
                chosen = k
        if chosen < 0:
            return frame, 0.0, 0.0, 0.0, 0.0, False
        frame = frames[chosen].copy()
        best = (centres[chosen, 0], centres[chosen, 1], radii[chosen], rms[chosen])
    return frame, best[0], best[1], best[2], best[3], True


@njit(cache=True)
def _accumulate(normal: np.ndarray, right: np.ndarray, row: np.ndarray, b: float) -> None:
    """Add one equation ``row . x = b`` to the normal equations ``normal x = right``."""
    for a in range(len(row)):
        right[a] += row[a] * b
        for c in range(len(row)):
            normal[a, c] += row[a] * row[c]


@njit(cache=True)
def sphere_fit(points: np.ndarray, iterations: int) -> tuple[np.ndarray, float, float, bool]:
    """Least-squares sphere of ``points`` (N x 3, N >= 4): centre, radius, rms residual, and
    False when the points fix none (coplanar).

    The algebraic fit (linear in the centre and ``r^2 - |c|^2``) on the centred points
    starts Gauss-Newton on the geometric distance ``|p - c| - r``.
    """
    n = points.shape[0]
    mean = np.zeros(3)
    for i in range(n):
        for j in range(3):
            mean[j] += points[i, j]
    mean /= n
    q = points - mean
    normal = np.zeros((4, 4))
    right = np.zeros(4)
    row = np.empty(4)
    for i in range(n):
        row[0], row[1], row[2], row[3] = 2.0 * q[i, 0], 2.0 * q[i, 1], 2.0 * q[i, 2], 1.0
        _accumulate(normal, right, row, q[i, 0] ** 2 + q[i, 1] ** 2 + q[i, 2] ** 2)
    sol, ok = _solve(normal, right)
    if not ok:
        return mean, 0.0, 0.0, False
    centre = sol[:3].copy()
    radius = math.sqrt(max(sol[3] + centre @ centre, 1e-12))
    for _ in range(iterations):
        normal[:] = 0.0
        right[:] = 0.0
        for i in range(n):
            dx, dy, dz = q[i, 0] - centre[0], q[i, 1] - centre[1], q[i, 2] - centre[2]
            dist = max(math.sqrt(dx * dx + dy * dy + dz * dz), 1e-12)
            row[0], row[1], row[2], row[3] = dx / dist, dy / dist, dz / dist, 1.0
            _accumulate(normal, right, row, dist - radius)
        step, ok = _solve(normal, right)
        if not ok:
            break
        centre += step[:3]
        radius += step[3]
    sq = 0.0
    for i in range(n):
        dx, dy, dz = q[i, 0] - centre[0], q[i, 1] - centre[1], q[i, 2] - centre[2]
        d = math.sqrt(dx * dx + dy * dy + dz * dz) - radius
        sq += d * d
    return centre + mean, abs(radius), math.sqrt(sq / n), True


@njit(cache=True)
def _covariance(normal: np.ndarray, rms: float) -> tuple[np.ndarray, bool]:
    """A least-squares fit's covariance ``rms^2 normal^-1`` (``normal = J^T J``), column by
    column; False when the normal matrix is singular (the points fix no fit)."""
    n = normal.shape[0]
    cov = np.empty((n, n))
    for k in range(n):
        unit = np.zeros(n)
        unit[k] = 1.0
        column, ok = _solve(normal, unit)
        if not ok:
            return cov, False
        cov[:, k] = column * (rms * rms)
    return cov, True


@njit(cache=True)
def sphere_spread(points: np.ndarray, centre: np.ndarray, rms: float) -> float:
    """Standard error of the radius plus that of the centre along its least certain axis,
    from the covariance ``rms^2 (J^T J)^-1`` of a sphere fit at ``centre``; inf when the
    points fix no sphere."""
    normal = np.zeros((4, 4))
    unused = np.zeros(4)
    row = np.empty(4)
    for i in range(points.shape[0]):
        dx, dy, dz = points[i, 0] - centre[0], points[i, 1] - centre[1], points[i, 2] - centre[2]
        dist = max(math.sqrt(dx * dx + dy * dy + dz * dz), 1e-12)
        row[0], row[1], row[2], row[3] = dx / dist, dy / dist, dz / dist, 1.0
        _accumulate(normal, unused, row, 0.0)
    cov, ok = _covariance(normal, rms)
    if not ok:
        return np.inf
    spread = np.linalg.eigvalsh(cov[:3, :3])[2]
    return math.sqrt(max(cov[3, 3], 0.0)) + math.sqrt(max(spread, 0.0))


@njit(cache=True)
def _worst_patch(sums: np.ndarray, counts: np.ndarray, rms: float, sigmas: float,
                 min_count: int) -> float:
    """The largest patch mean residual (``sums / counts``) less ``sigmas`` of its standard
    error (``rms`` over the root of its count), over patches of ``min_count`` points or
    more; 0 when none is beyond its noise."""
    best = 0.0
    for k in range(len(sums)):
        if counts[k] >= min_count:
            best = max(best, sums[k] / counts[k] - sigmas * rms / math.sqrt(counts[k]))
    return best


@njit(cache=True)
def cap_misfit(points: np.ndarray, centre: np.ndarray, radius: float, rms: float,
               sigmas: float, min_count: int, cos_radius: float, max_members: int,
               max_caps: int) -> float:
    """The largest mean residual ``|p - c| - r`` of the points in a cap of the sphere's
    surface, less ``sigmas`` of its standard error (``rms`` over the root of its count), or
    0. A cap is every other point whose direction from the centre lies within
    ``acos(cos_radius)`` of one point's; caps count from ``min_count`` points. The points
    are thinned to at most ``max_members``, and caps are centred on the ``max_caps`` of those
    farthest out (a lump's, where there is one; the cost is their product). The point a cap
    is centred on is left out of its mean, which it would bias outwards."""
    n = points.shape[0]
    step = max(1, -(-n // max_members))
    m = -(-n // step)
    units = np.empty((m, 3))
    residuals = np.empty(m)
    for k in range(m):
        i = k * step
        dx, dy, dz = points[i, 0] - centre[0], points[i, 1] - centre[1], points[i, 2] - centre[2]
        dist = max(math.sqrt(dx * dx + dy * dy + dz * dz), 1e-12)
        units[k, 0], units[k, 1], units[k, 2] = dx / dist, dy / dist, dz / dist
        residuals[k] = dist - radius
    order = np.argsort(residuals)
    best = 0.0
    for a in order[max(0, m - max_caps):]:
        total, count = 0.0, 0
        for b in range(m):
            if b != a and (units[a, 0] * units[b, 0] + units[a, 1] * units[b, 1]
                           + units[a, 2] * units[b, 2]) >= cos_radius:
                total += residuals[b]
                count += 1
        if count >= min_count:
            best = max(best, total / count - sigmas * rms / math.sqrt(count))
    return best


@njit(cache=True)
def _cylinder_row(row: np.ndarray, p: np.ndarray, cx: float, cy: float, ax: float,
                  ay: float) -> float:
    """The Jacobian row (d/d cx, cy, ax, ay, r) of a point's distance to the axis line
    ``(cx + ax z, cy + ay z, z)`` less the radius, with that distance (slopes are small:
    the distance is taken across the frame's z, off by a relative ``slope^2 / 2``)."""
    dx, dy = p[0] - cx - ax * p[2], p[1] - cy - ay * p[2]
    dist = max(math.sqrt(dx * dx + dy * dy), 1e-9)
    row[0], row[1] = -dx / dist, -dy / dist
    row[2], row[3], row[4] = row[0] * p[2], row[1] * p[2], -1.0
    return dist


@njit(cache=True)
def cylinder_refine(local: np.ndarray, cx: float, cy: float, radius: float,
                    iterations: int) -> tuple[float, float, float, float, float, bool]:
    """Gauss-Newton on a cylinder's five parameters from a circle across the frame's z
    (``local``: N x 3 side points): axis point ``cx, cy`` at z = 0, axis slopes ``ax, ay``
    and radius; False when a step's equations are singular."""
    normal = np.empty((5, 5))
    right = np.empty(5)
    row = np.empty(5)
    ax = ay = 0.0
    for _ in range(iterations):
        normal[:] = 0.0
        right[:] = 0.0
        for i in range(local.shape[0]):
            dist = _cylinder_row(row, local[i], cx, cy, ax, ay)
            _accumulate(normal, right, row, radius - dist)
        step, ok = _solve(normal, right)
        if not ok:
            return cx, cy, ax, ay, radius, False
        cx, cy, ax, ay, radius = (cx + step[0], cy + step[1], ax + step[2], ay + step[3],
                                  radius + step[4])
    return cx, cy, ax, ay, radius, True


@njit(cache=True)
def cylinder_spread(local: np.ndarray, cx: float, cy: float, radius: float, rms: float,
                    low: float, high: float, angles: int) -> tuple[float, float]:
    """Standard errors of a fitted cylinder: of its surface at the worst place, and of its
    axis's direction (rad, the least certain way). The first is the largest, over both
    ends (``low``, ``high`` along the axis; the variance is convex in between) and
    ``angles`` directions round the axis, of ``g^T C g`` with ``C = rms^2 (J^T J)^-1`` the
    five-parameter fit's covariance at ``cx, cy`` (zero slopes) and ``g`` how a surface
    point there moves with each parameter; inf when the points fix no cylinder."""
    normal = np.zeros((5, 5))
    unused = np.zeros(5)
    row = np.empty(5)
    for i in range(local.shape[0]):
        _cylinder_row(row, local[i], cx, cy, 0.0, 0.0)
        _accumulate(normal, unused, row, 0.0)
    cov, ok = _covariance(normal, rms)
    if not ok:
        return np.inf, np.inf
    worst = 0.0
    g = np.empty(5)
    for z in (low, high):
        for k in range(angles):
            c, s = math.cos(2.0 * math.pi * k / angles), math.sin(2.0 * math.pi * k / angles)
            g[0], g[1], g[2], g[3], g[4] = c, s, c * z, s * z, 1.0
            worst = max(worst, g @ (cov @ g))
    tilt = np.linalg.eigvalsh(cov[2:4, 2:4])[1]
    return math.sqrt(worst), math.sqrt(max(tilt, 0.0))


@njit(cache=True)
def cylinder_misfit(local: np.ndarray, cx: float, cy: float, radius: float, rms: float,
                    low: float, high: float, sigmas: float, min_count: int, angle_cells: int,
                    length_cells: int) -> float:
    """The largest mean residual (distance to the axis less the radius) of a patch of the
    side, less ``sigmas`` of its standard error, or 0; patches are ``angle_cells`` sectors
    round the axis times ``length_cells`` slices of ``low``..``high``, and count from
    ``min_count`` points."""
    patches = angle_cells * length_cells
    sums = np.zeros(patches)
    counts = np.zeros(patches, np.int64)
    span = max(high - low, 1e-9)
    for i in range(local.shape[0]):
        dx, dy = local[i, 0] - cx, local[i, 1] - cy
        a = (math.atan2(dy, dx) + math.pi) / (2.0 * math.pi)
        ia = min(int(a * angle_cells), angle_cells - 1)
        iz = min(max(int((local[i, 2] - low) / span * length_cells), 0), length_cells - 1)
        sums[ia * length_cells + iz] += math.sqrt(dx * dx + dy * dy) - radius
        counts[ia * length_cells + iz] += 1
    return _worst_patch(sums, counts, rms, sigmas, min_count)


@njit(cache=True)
def _smallest(values: np.ndarray, sign: float, count: int) -> np.ndarray:
    """The ``count`` smallest of ``sign * values``, ascending: one pass with a sorted buffer
    (a percentile near an end needs only a handful of values; a full partition of a copy
    cost several times the pass on every axis of every box candidate)."""
    buffer = np.empty(count)
    size = 0
    for i in range(len(values)):
        x = sign * values[i]
        if size == count and x >= buffer[count - 1]:
            continue
        j = size if size < count else count - 1
        while j > 0 and buffer[j - 1] > x:
            buffer[j] = buffer[j - 1]
            j -= 1
        buffer[j] = x
        size = min(size + 1, count)
    return buffer


@njit(cache=True)
def robust_ends(values: np.ndarray) -> tuple[float, float]:
    """The 1st and 99th percentiles of ``values`` (linear interpolation, as np.percentile)
    from the few values at each end (`_smallest`)."""
    n = len(values)
    out = np.empty(2)
    for i, q in enumerate((0.01, 0.99)):
        index = q * (n - 1)
        low = int(math.floor(index))
        high = min(low + 1, n - 1)
        w = index - low
        if q < 0.5:
            few = _smallest(values, 1.0, high + 1)
            a, b = few[low], few[high]
        else:  # the top values, counted from the top
            few = _smallest(values, -1.0, n - low)
            a, b = -few[n - 1 - low], -few[n - 1 - high]
        out[i] = a + (b - a) * w if w < 0.5 else b - (b - a) * (1.0 - w)
    return out[0], out[1]


@njit(cache=True)
def near_planes(local: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Which points (rows of ``local``, N x D) lie within ``tol`` of the low / high robust
    plane (1st / 99th percentile) of each of the D axes: two N x D masks."""
    n, dims = local.shape
    near_low = np.empty((n, dims), np.bool_)
    near_high = np.empty((n, dims), np.bool_)
    column = np.empty(n)
    for k in range(dims):
        for i in range(n):
            column[i] = local[i, k]
        low, high = robust_ends(column)
        for i in range(n):
            near_low[i, k] = abs(local[i, k] - low) <= tol
            near_high[i, k] = abs(local[i, k] - high) <= tol
    return near_low, near_high


@njit(cache=True)
def face_counts(xy: np.ndarray, yaws: np.ndarray, tol: float) -> np.ndarray:
    """For each yaw, how many of the horizontal points ``xy`` (N x 2) lie within ``tol`` of
    a robust plane (`near_planes`) of either horizontal axis of the frame turned by it."""
    n = xy.shape[0]
    counts = np.zeros(len(yaws), np.int64)
    local = np.empty((n, 2))
    for j in range(len(yaws)):
        c, s = math.cos(yaws[j]), math.sin(yaws[j])
        for i in range(n):
            local[i, 0] = c * xy[i, 0] + s * xy[i, 1]
            local[i, 1] = c * xy[i, 1] - s * xy[i, 0]
        near_low, near_high = near_planes(local, tol)
        for i in range(n):
            if near_low[i, 0] or near_low[i, 1] or near_high[i, 0] or near_high[i, 1]:
                counts[j] += 1
    return counts


@njit(cache=True)
def median(values: np.ndarray) -> float:
    """``np.median`` of a non-empty 1-D array (numpy's generic machinery costs ~50 us a call,
    several times the work on a blob's few hundred values)."""
    return np.median(values)



@njit(cache=True)
def face_line(points: np.ndarray, near_low: np.ndarray,
              near_high: np.ndarray) -> tuple[int, float, float]:
    """The best-populated vertical face of a box frame (the low / high planes of the box's x
    and y axes, `near_planes`) seen from above: its index (``2 * axis + side``; -1 when no
    face has 10 points), the direction of its normal (rad, in the base's xy plane; the least
    spread direction of its points, a total-least-squares line) and its width (the spread
    along the line). Its points that also lie on the top or bottom plane are left out when
    10 remain without them."""
    n = points.shape[0]
    counts = np.zeros(4, np.int64)
    for i in range(n):
        for f in range(4):
            if (near_low if f % 2 == 0 else near_high)[i, f // 2]:
                counts[f] += 1
    best = 0
    for f in range(1, 4):
        if counts[f] > counts[best]:
            best = f
    if counts[best] < 10:
        return -1, 0.0, 0.0
    mask = (near_low if best % 2 == 0 else near_high)[:, best // 2]
    only = mask.copy()
    for i in range(n):
        only[i] = mask[i] and not (near_low[i, 2] or near_high[i, 2])
    if only.sum() >= 10:
        mask = only
    count = mask.sum()
    mx = my = 0.0
    for i in range(n):
        if mask[i]:
            mx += points[i, 0]
            my += points[i, 1]
    mx /= count
    my /= count
    sxx = syy = sxy = 0.0
    for i in range(n):
        if mask[i]:
            dx, dy = points[i, 0] - mx, points[i, 1] - my
            sxx += dx * dx
            syy += dy * dy
            sxy += dx * dy
    major = 0.5 * math.atan2(2.0 * sxy, sxx - syy)  # the direction of most spread
    c, s = math.cos(major), math.sin(major)
    low, high = np.inf, -np.inf
    for i in range(n):
        if mask[i]:
            along = (points[i, 0] - mx) * c + (points[i, 1] - my) * s
            low, high = min(low, along), max(high, along)
    return best, major + 0.5 * math.pi, high - low


@njit(cache=True)
def face_tilts(local: np.ndarray, near_low: np.ndarray, near_high: np.ndarray,
               visible: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per face of a box frame (3 axes x low / high), the |component along its own axis| of
    the normal of the plane through its own points (those on no other face), or 1.0 (not
    tilted) for a face not visible or with fewer than 10 such points; and the standard
    error (rad) of that normal the least certain way (0 where not measured): the residual
    over the points' spread along the face's narrower direction."""
    n = local.shape[0]
    out = np.ones((3, 2))
    errors = np.zeros((3, 2))
    only = np.empty(n, np.bool_)
    for k in range(3):
        for side in range(2):
            if not visible[k, side]:
                continue
            near = near_low if side == 0 else near_high
            count = 0
            for i in range(n):
                other = False
                for j in range(3):
                    if j != k and (near_low[i, j] or near_high[i, j]):
                        other = True
                only[i] = near[i, k] and not other
                count += only[i]
            if count < 10:
                continue
            mean = np.zeros(3)
            for i in range(n):
                if only[i]:
                    for j in range(3):
                        mean[j] += local[i, j]
            mean /= count
            scatter = np.zeros((3, 3))
            for i in range(n):
                if only[i]:
                    for a in range(3):
                        for b in range(3):
                            scatter[a, b] += (local[i, a] - mean[a]) * (local[i, b] - mean[b])
            spread, vectors = np.linalg.eigh(scatter)  # least spread: the normal
            out[k, side] = abs(vectors[k, 0])
            errors[k, side] = math.sqrt(max(spread[0], 0.0) / (count - 3) / max(spread[1],
                                                                                 1e-18))
    return out, errors


@njit(cache=True)
def face_plane(local: np.ndarray, own: np.ndarray, near: np.ndarray, k: int,
               tol: float) -> tuple[np.ndarray, np.ndarray, float, bool]:
    """The least-squares plane ``x_k = c0 + c1 x_u + c2 x_w`` (``u``, ``w``: the other two
    axes in order) of the points ``own`` within ``tol`` of their median along ``k``: its
    coefficients, the standard errors of ``c1`` and ``c2``, and its offset's standard
    error at the worst-placed of the points ``near`` (the largest leverage); ``ok`` False
    when fewer than 8 points are kept or they fix no plane. numpy's fit (lstsq, pinv,
    einsum) cost ~0.7 ms a box."""
    u = 1 if k == 0 else 0
    w = 1 if k == 2 else 2
    n = local.shape[0]
    values = np.empty(n)
    m = 0
    for i in range(n):
        if own[i]:
            values[m] = local[i, k]
            m += 1
    coef, se = np.zeros(3), np.zeros(2)
    if m < 8:
        return coef, se, 0.0, False
    middle = np.median(values[:m])
    normal = np.zeros((3, 3))
    right = np.zeros(3)
    row = np.empty(3)
    kept = 0
    for i in range(n):
        if own[i] and abs(local[i, k] - middle) <= tol:
            row[0], row[1], row[2] = 1.0, local[i, u], local[i, w]
            _accumulate(normal, right, row, local[i, k])
            kept += 1
    if kept < 8:
        return coef, se, 0.0, False
    coef, ok = _solve(normal, right)
    if not ok:
        return coef, se, 0.0, False
    rss = 0.0
    for i in range(n):
        if own[i] and abs(local[i, k] - middle) <= tol:
            r = local[i, k] - coef[0] - coef[1] * local[i, u] - coef[2] * local[i, w]
            rss += r * r
    sigma = math.sqrt(rss / max(kept - 3, 1))
    inverse = np.empty((3, 3))
    for j in range(3):
        unit = np.zeros(3)
        unit[j] = 1.0
        column, ok = _solve(normal, unit)
        if not ok:
            return coef, se, 0.0, False
        inverse[:, j] = column
    se[0] = sigma * math.sqrt(max(inverse[1, 1], 0.0))
    se[1] = sigma * math.sqrt(max(inverse[2, 2], 0.0))
    worst = 0.0
    for i in range(n):
        if near[i]:
            row[0], row[1], row[2] = 1.0, local[i, u], local[i, w]
            q = 0.0
            for a in range(3):
                for b in range(3):
                    q += row[a] * inverse[a, b] * row[b]
            worst = max(worst, q)
    return coef, se, sigma * math.sqrt(worst), True


def warm_up() -> None:
    """Compile (or load from numba's disk cache) every kernel now: a first compile takes
    ~10 s, which must not fall on a tracker's first frame."""
    points = np.random.default_rng(0).normal(size=(16, 3))
    sphere_fit(points, 1)
    sphere_spread(points, np.zeros(3), 1.0)
    cap_misfit(points, np.zeros(3), 1.0, 0.1, 3.0, 5, 0.9, 16, 4)
    circle_fits(points, points[:2].copy(), points[2:4].copy())
    circle_refine(np.ascontiguousarray(points[:, :2]), 0.0, 0.0, 1.0, 1)
    cylinder_refine(points, 0.0, 0.0, 1.0, 1)
    cylinder_spread(points, 0.0, 0.0, 1.0, 0.1, -1.0, 1.0, 8)
    cylinder_misfit(points, 0.0, 0.0, 1.0, 0.1, -1.0, 1.0, 3.0, 5, 6, 3)
    roundest_axis(points, points[0].copy(), np.zeros((1, 2)), np.ones(1))
    near_planes(points, 0.01)
    face_counts(np.ascontiguousarray(points[:, :2]), np.arange(0.0, 1.0, 0.5), 0.01)
    median(points[:, 0].copy())
    near = np.ones((16, 3), np.bool_)
    face_line(points, near, near)
    face_tilts(points, near, near, np.ones((3, 2), np.bool_))
    face_plane(points, near[:, 0].copy(), near[:, 0].copy(), 0, 10.0)
    robust_ends(points[:, 0].copy())
