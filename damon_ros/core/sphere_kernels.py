"""Compiled kernels of the fast (sphere) collision model: the planner's hot path.

Re-routing within a camera frame means certifying a whole path — hundreds of joint states
against every obstacle — in about a millisecond. numpy spends most of that on small-array
overhead, so the forward kinematics of the sphere centres and the sphere↔shape signed
distances are compiled with numba (cached on disk after the first call). The maths is the
same as :func:`damon_ros.core.collision.signed_distance`; tests compare the two.

Obstacles are packed as arrays: ``kind`` (0 sphere, 1 box, 2 cylinder, 3 hull of a point
set), ``position`` (K, 3), ``rotation`` (K, 3, 3), ``params`` (K, 3) — sphere radius; box
half extents; cylinder radius and half length; a hull's bounding-sphere radius and its
first and end row in ``hull`` — and ``hull`` (F, 13), the face rows of every point set
(:mod:`damon_ros.core.hull`). A hull is its bounding sphere for the bound tests and exact
for a sphere's own distance.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numba import njit

from damon_ros.core.hull import FACE_WIDTH, hull_faces, hull_signed
from damon_ros.core.shapes import Shape

SPHERE, BOX, CYLINDER, HULL = 0, 1, 2, 3


def pack_obstacles(obstacles: Sequence[Shape]):
    """Shapes → (kind, position, rotation, params, hull) arrays for the kernels."""
    k = len(obstacles)
    kind = np.zeros(k, np.int64)
    pos = np.zeros((k, 3))
    rot = np.zeros((k, 3, 3))
    params = np.zeros((k, 3))
    faces = [np.zeros((0, FACE_WIDTH))]
    rows = 0
    for i, s in enumerate(obstacles):
        rot[i] = s.rotation()
        pos[i] = s.position
        if s.kind == "sphere":
            kind[i], params[i, 0] = SPHERE, s.size[0]
        elif s.kind == "box":
            kind[i], params[i] = BOX, 0.5 * np.asarray(s.size)
        elif s.kind == "cylinder":
            kind[i], params[i, :2] = CYLINDER, (s.size[0], 0.5 * s.size[1])
        elif len(s.points) == 1:  # a single point: exactly a sphere of radius 0
            kind[i], pos[i] = SPHERE, s.position + rot[i] @ s.points[0]
        else:  # points: the hull, bounded by the sphere about the points' mean
            world = s.position + s.points @ rot[i].T
            center = world.mean(axis=0)
            f = hull_faces(world)
            kind[i], pos[i] = HULL, center
            # the bound must contain the hull, which `hull_faces` may thicken by 1e-7 m
            params[i] = (float(np.max(np.linalg.norm(world - center, axis=1))) + 1e-6, rows,
                         rows + len(f))
            faces.append(f)
            rows += len(f)
    return kind, pos, rot, params, np.ascontiguousarray(np.vstack(faces))


@njit(cache=True, fastmath=False)
def _signed(px, py, pz, kind, pos, rot, params, hull, k):
    """Signed distance from p to obstacle k, a hull's as its bounding sphere (a lower bound:
    the bound tests); :func:`_signed_tight` is exact for a hull too."""
    dx, dy, dz = px - pos[k, 0], py - pos[k, 1], pz - pos[k, 2]
    if kind[k] == SPHERE or kind[k] == HULL:
        return math.sqrt(dx * dx + dy * dy + dz * dz) - params[k, 0]
    # into the shape's frame: local = R^T (p - c)
    lx = rot[k, 0, 0] * dx + rot[k, 1, 0] * dy + rot[k, 2, 0] * dz
    ly = rot[k, 0, 1] * dx + rot[k, 1, 1] * dy + rot[k, 2, 1] * dz
    lz = rot[k, 0, 2] * dx + rot[k, 1, 2] * dy + rot[k, 2, 2] * dz
    if kind[k] == BOX:
        ex, ey, ez = abs(lx) - params[k, 0], abs(ly) - params[k, 1], abs(lz) - params[k, 2]
        ox, oy, oz = max(ex, 0.0), max(ey, 0.0), max(ez, 0.0)
        return math.sqrt(ox * ox + oy * oy + oz * oz) + min(max(ex, max(ey, ez)), 0.0)
    radial = math.sqrt(lx * lx + ly * ly) - params[k, 0]
    axial = abs(lz) - params[k, 1]
    orad, oax = max(radial, 0.0), max(axial, 0.0)
    return math.sqrt(orad * orad + oax * oax) + min(max(radial, axial), 0.0)


@njit(cache=True)
def _signed_tight(px, py, pz, kind, pos, rot, params, hull, k, need=math.inf):
    """Signed distance from p to obstacle k, exact for a hull (no faces: its sphere); for a
    hull, a lower bound of at least ``need`` where that settles it (`hull_signed`)."""
    d = _signed(px, py, pz, kind, pos, rot, params, hull, k)
    if kind[k] != HULL or params[k, 2] <= params[k, 1] or d >= need:
        return d
    return max(d, hull_signed(px, py, pz, hull, int(params[k, 1]), int(params[k, 2]), need))


GROUP_SIZE = 12
"""Spheres per bounding group: a joint's spheres are cut into runs of at most this many
along their principal axis. One group per joint had ~150 spheres on the base and ~70 on the
forearm of the first fitted set, all checked whenever an obstacle came near any of them;
under the joint-level bounds, 12 planned MotionBenchMaker problems fastest of 6-48."""


def _groups(joints: np.ndarray, centers: np.ndarray, size: int) -> tuple[np.ndarray, ...]:
    """Sphere order and (joint, start, end) of each group: spheres of one joint, contiguous,
    sorted along the joint's principal axis and cut into runs of ≤ ``size``."""
    order, gj, start, end = [], [], [], []
    for j in np.unique(joints):
        idx = np.flatnonzero(joints == j)
        c = centers[idx] - centers[idx].mean(axis=0)
        axis = np.linalg.svd(c, full_matrices=False)[2][0] if len(idx) > 1 else np.zeros(3)
        idx = idx[np.argsort(c @ axis, kind="stable")]
        for chunk in np.array_split(idx, max(1, -(-len(idx) // size))):
            gj.append(j)
            start.append(len(order))
            order.extend(chunk.tolist())
            end.append(len(order))
    return (np.array(order, np.int64), np.array(gj, np.int64), np.array(start, np.int64),
            np.array(end, np.int64))


def kernel_order(joints: np.ndarray, centers: np.ndarray,
                 group_size: int = GROUP_SIZE) -> np.ndarray:
    """Sphere indices in the order :func:`pack_robot` lays them out."""
    return _groups(np.asarray(joints), np.asarray(centers), group_size)[0]


def pack_robot(rotations: np.ndarray, translations: np.ndarray, joints: np.ndarray,
               centers: np.ndarray, radii: np.ndarray, group_size: int = GROUP_SIZE) -> tuple:
    """Kernel arguments for a sphere model: the joint placements, the spheres sorted by the
    joint that carries them, and one bounding sphere per group of neighbouring spheres (a
    group whose bound keeps the margin needs none of its spheres checked — most of the arm,
    most of the time)."""
    order, groups, start, end = _groups(np.asarray(joints), np.asarray(centers), group_size)
    sj, sc, sr = np.asarray(joints)[order].astype(np.int64), centers[order], radii[order]
    gc = np.array([sc[a:b].mean(axis=0) for a, b in zip(start, end, strict=True)])
    gr = np.array([np.max(np.linalg.norm(sc[a:b] - gc[i], axis=1) + sr[a:b])
                   for i, (a, b) in enumerate(zip(start, end, strict=True))])
    jb = np.zeros((len(rotations) + 1, 4))  # per joint frame: bounding sphere of its spheres
    for j in np.unique(sj):
        c = sc[sj == j]
        jb[j, :3] = 0.5 * (c.min(axis=0) + c.max(axis=0))
        jb[j, 3] = np.max(np.linalg.norm(c - jb[j, :3], axis=1) + sr[sj == j])
    return (np.ascontiguousarray(rotations, dtype=float),
            np.ascontiguousarray(translations, dtype=float), sj, np.ascontiguousarray(sc),
            np.ascontiguousarray(sr), groups.astype(np.int64), start, end,
            np.ascontiguousarray(gc), np.ascontiguousarray(gr), jb)


def joint_placements(model) -> tuple[np.ndarray, np.ndarray]:
    """Rotations (7, 3, 3) and translations (7, 3) of a pinocchio model's joints in their
    parents: the ``jr``, ``jp`` that `_frames` (and `pack_robot`) take."""
    joints = range(1, model.njoints)
    return (np.ascontiguousarray([model.jointPlacements[j].rotation for j in joints], float),
            np.ascontiguousarray([model.jointPlacements[j].translation for j in joints], float))


@njit(cache=True)
def _frames(q, jr, jp, fr, fp):
    """Rotations/positions of every joint frame (explicit loops: numba's small matrix
    products call BLAS and cost more than the arithmetic); every joint turns about z."""
    for a in range(3):
        fp[0, a] = 0.0
        for b in range(3):
            fr[0, a, b] = 1.0 if a == b else 0.0
    for i in range(jr.shape[0]):
        c, s = math.cos(q[i]), math.sin(q[i])
        for a in range(3):
            fp[i + 1, a] = fp[i, a] + (fr[i, a, 0] * jp[i, 0] + fr[i, a, 1] * jp[i, 1]
                                       + fr[i, a, 2] * jp[i, 2])
            m0 = fr[i, a, 0] * jr[i, 0, 0] + fr[i, a, 1] * jr[i, 1, 0] + fr[i, a, 2] * jr[i, 2, 0]
            m1 = fr[i, a, 0] * jr[i, 0, 1] + fr[i, a, 1] * jr[i, 1, 1] + fr[i, a, 2] * jr[i, 2, 1]
            m2 = fr[i, a, 0] * jr[i, 0, 2] + fr[i, a, 1] * jr[i, 1, 2] + fr[i, a, 2] * jr[i, 2, 2]
            fr[i + 1, a, 0] = m0 * c + m1 * s
            fr[i + 1, a, 1] = m1 * c - m0 * s
            fr[i + 1, a, 2] = m2


@njit(cache=True, inline="always")
def _placed(fr, fp, j, c):
    """World position of point ``c`` (its first three entries) fixed in joint frame ``j``."""
    return (fp[j, 0] + fr[j, 0, 0] * c[0] + fr[j, 0, 1] * c[1] + fr[j, 0, 2] * c[2],
            fp[j, 1] + fr[j, 1, 0] * c[0] + fr[j, 1, 1] * c[1] + fr[j, 1, 2] * c[2],
            fp[j, 2] + fr[j, 2, 0] * c[0] + fr[j, 2, 1] * c[1] + fr[j, 2, 2] * c[2])


@njit(cache=True)
def _distance_below(q, limit, jr, jp, sj, sc, sr, gj, gs, ge, gc, gr, jb, kind, pos, rot,
                    params, hull, fr, fp, where, stop=-np.inf, first_group=0, offset=None):
    """min(signed distance, limit) of one configuration, through two levels of bounds: a
    joint's spheres are skipped for an obstacle whose distance to the joint's bounding
    sphere (``jb``) is at least the best so far, then a group's (the signed distance is
    1-Lipschitz, so a bound is a true lower bound of every sphere inside it). Without the
    joint level, group tests were 200-590 of a state's ~600 tests among MotionBenchMaker's
    7-21 shapes. Returns at the first sphere at or below ``stop`` (a yes/no question: that
    sphere's distance, not the minimum). Groups before ``first_group`` are left out
    (`fixed_groups`: the base's, already checked). ``where`` receives (sphere, obstacle) of
    the best pair, or -1. ``offset`` (K,), optional: obstacle k's distances less
    ``offset[k]`` (its own required clearance: one call for obstacles that each need a
    different one, the space-time check's movers)."""
    _frames(q, jr, jp, fr, fp)
    best = limit
    where[0], where[1] = -1, -1
    near = np.empty(kind.shape[0], np.bool_)
    g = first_group
    while g < gj.shape[0]:
        j = gj[g]
        g_end = g + 1
        while g_end < gj.shape[0] and gj[g_end] == j:
            g_end += 1
        x, y, z = _placed(fr, fp, j, jb[j])
        any_near = False
        for k in range(kind.shape[0]):
            near[k] = _signed(x, y, z, kind, pos, rot, params, hull, k) - jb[j, 3] - (
                0.0 if offset is None else offset[k]) < best
            any_near = any_near or near[k]
        if not any_near:
            g = g_end
            continue
        for h in range(g, g_end):
            x, y, z = _placed(fr, fp, j, gc[h])
            for k in range(kind.shape[0]):
                off = 0.0 if offset is None else offset[k]
                if not near[k] or \
                        _signed(x, y, z, kind, pos, rot, params, hull, k) - gr[h] - off >= best:
                    continue
                for s_i in range(gs[h], ge[h]):
                    cx, cy, cz = _placed(fr, fp, j, sc[s_i])
                    d = _signed_tight(cx, cy, cz, kind, pos, rot, params, hull, k,
                                      best + sr[s_i] + off) - sr[s_i] - off
                    if d < best:
                        best = d
                        where[0], where[1] = s_i, k
                        if best <= stop:
                            return best
        g = g_end
    return best


@njit(cache=True)
def fixed_groups(gj):
    """Groups carried by the base (joint 0, first in the order): their spheres stand still,
    so their distance to a static obstacle is the same in every configuration. A segment
    whose first state passed needs them no more; the base carries a quarter of the fitted
    spheres, and beside a table every one of its groups came within the bound test."""
    n = 0
    while n < gj.shape[0] and gj[n] == 0:
        n += 1
    return n


@njit(cache=True)
def fixed_clearance(sj, sc, sr, kind, pos, rot, params, hull):
    """Least signed distance of the base's spheres (joint 0: the world frame) to the
    obstacles, the same in every configuration."""
    best = np.inf
    for s_i in range(sj.shape[0]):
        if sj[s_i] != 0:
            continue
        for k in range(kind.shape[0]):
            best = min(best, _signed_tight(sc[s_i, 0], sc[s_i, 1], sc[s_i, 2], kind, pos,
                                           rot, params, hull, k) - sr[s_i])
    return best


@njit(cache=True)
def batch_distances(Q, jr, jp, sj, sc, sr, gj, gs, ge, gc, gr, jb, kind, pos, rot, params, hull):
    """Minimum signed distance of each configuration of Q (N, 7) to the packed obstacles."""
    out = np.empty(Q.shape[0])
    fr = np.empty((jr.shape[0] + 1, 3, 3))
    fp = np.empty((jr.shape[0] + 1, 3))
    where = np.empty(2, np.int64)
    for n in range(Q.shape[0]):
        out[n] = _distance_below(Q[n], np.inf, jr, jp, sj, sc, sr, gj, gs, ge, gc, gr, jb, kind,
                                 pos, rot, params, hull, fr, fp, where)
    return out


@njit(cache=True)
def band_states(Q, margin, floor, budget, jr, jp, sj, sc, sr, gj, gs, ge, gc, gr, jb, kind, pos,
                rot, params, hull):
    """The states of Q (N, 7) within ``margin`` of the obstacles, or None when one is at or
    below ``floor`` or more than ``budget`` are within it: the fast model's side of the
    exact band (`Robot._exact_band`), with each state's distance bounded by the margin and
    cut short at the floor instead of computed in full (`batch_distances`: ~1 ms a
    segment among a mover's swept shapes, where nothing beyond the margin matters)."""
    fr = np.empty((jr.shape[0] + 1, 3, 3))
    fp = np.empty((jr.shape[0] + 1, 3))
    where = np.empty(2, np.int64)
    near = np.empty(Q.shape[0], np.int64)
    n = 0
    for i in range(Q.shape[0]):
        d = _distance_below(Q[i], margin + 1e-12, jr, jp, sj, sc, sr, gj, gs, ge, gc, gr, jb,
                            kind, pos, rot, params, hull, fr, fp, where, floor)
        if d <= floor:
            return None
        if d <= margin:
            if n == budget:
                return None
            near[n] = i
            n += 1
    return near[:n]


@njit(cache=True)
def closest_pair(q, jr, jp, sj, sc, sr, gj, gs, ge, gc, gr, jb, kind, pos, rot, params, hull):
    """(distance, sphere in kernel order, obstacle) of the nearest pair in one configuration:
    witness points need only that one pair (numpy over every sphere and obstacle took ~1.3
    ms a call, several calls a plan)."""
    fr = np.empty((jr.shape[0] + 1, 3, 3))
    fp = np.empty((jr.shape[0] + 1, 3))
    where = np.empty(2, np.int64)
    d = _distance_below(q, np.inf, jr, jp, sj, sc, sr, gj, gs, ge, gc, gr, jb, kind, pos, rot,
                        params, hull, fr, fp, where)
    return d, where[0], where[1]


@njit(cache=True)
def segment_clear(q0, q1, steps, margin, jr, jp, sj, sc, sr, gj, gs, ge, gc, gr, jb, kind, pos,
                  rot, params, hull):
    """True when all ``steps + 1`` evenly spaced states from q0 to q1 keep ``margin``.

    States are visited coarse to fine (ends, middle, quarters, ...) so a blocked segment is
    usually found after a few states; each state stops at the first sphere within margin."""
    fr = np.empty((jr.shape[0] + 1, 3, 3))
    fp = np.empty((jr.shape[0] + 1, 3))
    q = np.empty(q0.shape[0])
    where = np.empty(2, np.int64)
    order = np.empty(steps + 1, np.int64)
    visited = np.zeros(steps + 1, np.bool_)
    n = 0
    for index in (0, steps):
        if not visited[index]:
            visited[index] = True
            order[n] = index
            n += 1
    stride = steps
    while stride > 1:
        half = stride // 2
        for index in range(half, steps, stride):
            if not visited[index]:
                visited[index] = True
                order[n] = index
                n += 1
        stride = half
    for index in range(steps + 1):  # strides that were not powers of two leave gaps
        if not visited[index]:
            order[n] = index
            n += 1
    first, base = 0, fixed_groups(gj)
    for i in range(n):
        t = order[i] / steps if steps > 0 else 0.0
        for a in range(q0.shape[0]):
            q[a] = q0[a] + (q1[a] - q0[a]) * t
        # the limit sits just above the margin: "nothing below it" is distinguishable from
        # "a sphere exactly at the margin" (which blocks)
        if _distance_below(q, margin + 1e-12, jr, jp, sj, sc, sr, gj, gs, ge, gc, gr, jb, kind, pos,
                           rot, params, hull, fr, fp, where, margin, first) <= margin:
            return False
        first = base  # the base passed once: it passes in every state
    return True


@njit(cache=True)
def motion_steps(a, b, resolution):
    """Steps from a to b with no joint moving more than ``resolution`` rad in one."""
    steps = 0
    for i in range(a.shape[0]):
        steps = max(steps, int(math.ceil(abs(b[i] - a[i]) / resolution)))
    return steps


@njit(cache=True)
def motion_clear(a, b, margin, resolution, robot, obstacles):
    """`segment_clear` with its states ``resolution`` rad apart (max norm) and the model and
    obstacles as the tuples `pack_robot` and `pack_obstacles` return: the searches' call."""
    steps = motion_steps(a, b, resolution)
    jr, jp, sj, sc, sr, gj, gs, ge, gc, gr, jb = robot
    kind, pos, rot, params, hull = obstacles
    return segment_clear(a, b, steps, margin, jr, jp, sj, sc, sr, gj, gs, ge, gc, gr, jb, kind,
                         pos, rot, params, hull)


@njit(cache=True)
def route_clear(path, margins, resolution, robot, obstacles):
    """Every segment k of ``path`` (N, 7) keeps ``margins[k]`` at states ``resolution`` rad
    apart: `motion_clear` of each, the segments' end states first (a stored route that no
    longer passes usually fails at one of its waypoints, found before any segment is walked
    in full). The same answer as the segments one by one."""
    for k in range(path.shape[0] - 1):  # a segment of no length: its one state
        if not motion_clear(path[k + 1], path[k + 1], margins[k], resolution, robot, obstacles):
            return False
    for k in range(path.shape[0] - 1):
        if not motion_clear(path[k], path[k + 1], margins[k], resolution, robot, obstacles):
            return False
    return True
