"""Exact signed distance to the convex hull of a point set, for the fast collision model.

A point set (a tracked blob, an amorphous object) is its convex hull for the exact meshes
(coal builds that hull). The fast model used to stand in for it with one primitive, the
set's bounding sphere or principal box: cheap, but a blob of twelve points 3 cm across
seen from a sphere next to one of its corners was up to 56 mm closer than it is
(`damon-ros bench-robot --margin`, point sets). Here the hull's triangles are kept, and the
kernels use the bounding sphere only to skip what is far, then this exact distance.

Faces are rows of 13 numbers: the triangle's corners a, b, c, its outward unit normal n
and offset o (inside ⇔ n·x + o ≤ 0 for every face). Inside, the signed distance is the
largest face value (exact for a convex polytope); outside it is the distance to the
nearest triangle, and only faces that see the point (value > 0) can hold that nearest
point. No rclpy here.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

FACE_WIDTH = 13
"""Numbers per face row: corners a, b, c, outward normal, offset."""


def solid_points(points: np.ndarray, eps: float = 1e-7) -> np.ndarray:
    """A point set with a 3-D hull: flat or collinear sets get ±eps copies across their
    missing directions, so a hull of the set within eps can be built."""
    if len(points) >= 4:
        _, s, vt = np.linalg.svd(points - points.mean(axis=0))
        if s[2] > 1e-9:
            return points
    else:
        _, s, vt = np.linalg.svd(np.vstack([points - points.mean(axis=0), np.zeros((3, 3))]))
    extra = [points]
    for k in range(3):
        if s[k] <= 1e-9:
            extra += [points + eps * vt[k], points - eps * vt[k]]
    return np.vstack(extra)


def hull_faces(points: np.ndarray, eps: float = 1e-7) -> np.ndarray:
    """(F, 13) face rows of the convex hull of world points (N, 3); a flat, collinear or
    single-point set is thickened by ``eps`` (m) first, which only makes it larger (the
    safe side). Empty (0, 13) when no hull can be built: callers keep their bound."""
    from scipy.spatial import ConvexHull, QhullError

    try:
        hull = ConvexHull(solid_points(np.asarray(points, float), eps))
    except (QhullError, ValueError):
        return np.zeros((0, FACE_WIDTH))
    corners = hull.points[hull.simplices]  # (F, 3, 3)
    normals, offsets = hull.equations[:, :3], hull.equations[:, 3]
    return np.hstack([corners.reshape(-1, 9), normals, offsets[:, None]])


DOP_DIRECTIONS = np.array([[x, y, z] for x in (-1, 0, 1) for y in (-1, 0, 1)
                           for z in (-1, 0, 1) if (x, y, z) != (0, 0, 0)], dtype=float)
DOP_DIRECTIONS /= np.linalg.norm(DOP_DIRECTIONS, axis=1, keepdims=True)
"""The 26 directions of a 26-DOP: the axes, the face diagonals and the corner diagonals."""
MAX_HULL_VERTICES = 48
"""A hull with more vertices is replaced by its 26-DOP, which has at most 48 (26 faces)."""


def few_vertices(points: np.ndarray) -> np.ndarray:
    """Points whose hull contains the hull of ``points`` (N, 3) and has at most
    `MAX_HULL_VERTICES` vertices: ``points`` themselves when there are no more, else the
    vertices of their 26-DOP (the 26 half-spaces of `DOP_DIRECTIONS` that touch them).
    Every query against a point set runs over its hull's triangles: two cameras' fused view
    of an L-shaped part had 130-150 vertices, and a re-route around it took 0.2-1.7 s."""
    from scipy.spatial import HalfspaceIntersection, QhullError

    points = np.asarray(points, float)
    if len(points) <= MAX_HULL_VERTICES:
        return points
    reach = (points @ DOP_DIRECTIONS.T).max(axis=0)
    halfspaces = np.hstack([DOP_DIRECTIONS, -reach[:, None]])  # n.x - reach <= 0
    centre = points.mean(axis=0)
    try:
        corners = HalfspaceIntersection(halfspaces, centre).intersections
    except (QhullError, ValueError):  # flat or degenerate: keep the points
        return points
    # each corner lies on its planes to rounding: pushed out by a micrometre to stay outside
    away = corners - centre
    return corners + 1e-6 * away / np.maximum(np.linalg.norm(away, axis=1, keepdims=True),
                                              1e-12)


@njit(cache=True)
def _closest_on_triangle(px, py, pz, f):
    """The point of the triangle in face row ``f`` nearest p, by its closest-point regions
    (the corners, the edges, the interior)."""
    ax, ay, az = f[0], f[1], f[2]
    abx, aby, abz = f[3] - ax, f[4] - ay, f[5] - az
    acx, acy, acz = f[6] - ax, f[7] - ay, f[8] - az
    apx, apy, apz = px - ax, py - ay, pz - az
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    if d1 <= 0.0 and d2 <= 0.0:
        return ax, ay, az
    bpx, bpy, bpz = px - f[3], py - f[4], pz - f[5]
    d3 = abx * bpx + aby * bpy + abz * bpz
    d4 = acx * bpx + acy * bpy + acz * bpz
    if d3 >= 0.0 and d4 <= d3:
        return f[3], f[4], f[5]
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        v = d1 / (d1 - d3)
        return ax + v * abx, ay + v * aby, az + v * abz
    cpx, cpy, cpz = px - f[6], py - f[7], pz - f[8]
    d5 = abx * cpx + aby * cpy + abz * cpz
    d6 = acx * cpx + acy * cpy + acz * cpz
    if d6 >= 0.0 and d5 <= d6:
        return f[6], f[7], f[8]
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        w = d2 / (d2 - d6)
        return ax + w * acx, ay + w * acy, az + w * acz
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and d4 - d3 >= 0.0 and d5 - d6 >= 0.0:
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return f[3] + w * (f[6] - f[3]), f[4] + w * (f[7] - f[4]), f[5] + w * (f[8] - f[5])
    s = f[9] * px + f[10] * py + f[11] * pz + f[12]  # interior: onto the face's plane
    return px - s * f[9], py - s * f[10], pz - s * f[11]


@njit(cache=True)
def hull_signed(px, py, pz, faces, start, end, need=math.inf):
    """Signed distance from p to the hull of face rows ``faces[start:end]`` (negative
    inside); +inf for an empty range. Where the largest face value, a lower bound of the
    distance outside, is at least ``need``, that bound is returned instead: a caller that
    only asks whether p is nearer than ``need`` skips the triangles (a path beside a
    tracked point set spent 0.1-0.3 s of a re-route in them)."""
    if end <= start:
        return math.inf
    top = -math.inf
    for i in range(start, end):
        f = faces[i]
        top = max(top, f[9] * px + f[10] * py + f[11] * pz + f[12])
    if top <= 0.0 or top >= need:
        return top
    best = math.inf
    for i in range(start, end):
        f = faces[i]
        if f[9] * px + f[10] * py + f[11] * pz + f[12] > 0.0:
            x, y, z = _closest_on_triangle(px, py, pz, f)
            best = min(best, (px - x) ** 2 + (py - y) ** 2 + (pz - z) ** 2)
    return math.sqrt(best)


@njit(cache=True)
def hull_signed_many(P, faces):
    """Signed distances of points laid out (3, M) to one hull (all of ``faces``)."""
    out = np.empty(P.shape[1])
    for m in range(P.shape[1]):
        out[m] = hull_signed(P[0, m], P[1, m], P[2, m], faces, 0, faces.shape[0])
    return out


def closest_point(p: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """The hull's surface point nearest ``p`` (witness points; one point)."""
    best, out = math.inf, p
    values = faces[:, 9:12] @ p + faces[:, 12]
    inside = bool(np.all(values <= 0.0))
    for f, value in zip(faces, values, strict=True):
        if inside:  # out through the nearest face plane
            d, q = -value, p - value * f[9:12]
        else:
            if value <= 0.0:
                continue
            q = np.array(_closest_on_triangle(p[0], p[1], p[2], f))
            d = float(np.linalg.norm(p - q))
        if d < best:
            best, out = d, q
    return out
