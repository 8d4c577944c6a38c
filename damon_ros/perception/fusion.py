"""Several cameras, one world: detections of one object from several views, intersected.

Each camera's bound contains the object (the safety rule of :mod:`shape_fit` and
:mod:`tight_fit`), so the intersection of the bounds of one object from several cameras
contains it too — and is smaller: the depth one camera cannot see is what another sees from
the side, so the hidden extent shrinks to what no camera sees. Every bound is convex (box,
sphere, cylinder, point-set hull), so the intersection is a convex polytope: the half-spaces
of each bound (curved ones by tangent planes, which contain the curve) are intersected and
the vertices become a point-set obstacle. A cut-off (partial) detection bounds only what it
shows and would cut the object: it is only used when no view saw the object whole.

Unsynchronised cameras (the tracker node) fuse a new frame with the other cameras' latest
frames, taken up to a few milliseconds earlier: such an older bound is first grown by how
far the object can have moved since (``slack``, the maximum obstacle speed times the age),
so it still contains the object at the new frame's time.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from scipy.optimize import linprog
from scipy.spatial import ConvexHull, HalfspaceIntersection, QhullError

from damon_ros.core.hull import DOP_DIRECTIONS
from damon_ros.core.shapes import Shape, enclosing_vertices, grown, volume

MARGIN_M = 0.005
"""Added to each half-space of a bound that another camera's points showed too short:
such a bound rests on a prior the object breaks a little (a pole seen nearly end-on is
deeper than ``max_thickness_m``), and it cuts the object where no camera saw, too. On the
G family (front + side camera) fused poles were contained in 81 % of frames without it,
95 % with 2 mm, 96 % with 5 mm (the front camera alone: 97.6 %)."""
POLYTOPE_GAIN = 0.8
"""The intersection of several views replaces the smallest view's primitive bound (sphere,
box, cylinder) only when its volume is below this share of the primitive's."""
MIN_DEPTH_M = 1e-4
"""Bounds whose intersection holds no ball of this radius do not overlap (other objects)."""


def halfspaces(shape: Shape) -> np.ndarray:
    """``[n, b]`` rows with ``n . p + b <= 0`` inside, whose intersection contains ``shape``."""
    R = shape.rotation()
    if shape.kind == "sphere":
        n = DOP_DIRECTIONS
        return np.column_stack([n, -(n @ shape.position) - shape.size[0]])
    if shape.kind == "box":
        half = 0.5 * np.asarray(shape.size)
        n = np.vstack([R.T, -R.T])  # rows: the box axes in the base frame, both signs
        return np.column_stack([n, -(n @ shape.position) - np.concatenate([half, half])])
    vertices = enclosing_vertices(shape)  # a cylinder's prism or a point set's vertices
    hull = ConvexHull(vertices)
    return hull.equations


def _interior(hs: np.ndarray, guesses: Sequence[np.ndarray] = ()) -> np.ndarray | None:
    """A point at least `MIN_DEPTH_M` inside every half-space, or None when there is none
    (then the bounds were not of one object).

    The guesses (the bounds' centres and their midpoint: bounds of one object overlap
    around it) are tried first; only when none is that deep inside is the Chebyshev centre
    solved for (a linear program, ~1.7 ms against ~10 us): the answer, a point or None, is
    the linear program's either way, since a guess that deep inside proves one exists."""
    norms = np.linalg.norm(hs[:, :3], axis=1)
    if len(guesses):
        points = np.asarray(guesses, dtype=float)
        depth = -(points @ hs[:, :3].T + hs[:, 3]) / norms  # distance inside each plane
        best = int(np.argmax(depth.min(axis=1)))
        if depth[best].min() >= MIN_DEPTH_M:
            return points[best]
    c = np.array([0.0, 0.0, 0.0, -1.0])  # maximise the radius of the inscribed ball
    A = np.column_stack([hs[:, :3], norms])
    result = linprog(c, A_ub=A, b_ub=-hs[:, 3], bounds=[(None, None)] * 3 + [(0, None)],
                     method="highs")
    if not result.success or result.x[3] < MIN_DEPTH_M:
        return None
    return result.x[:3]


class _Planes:
    """`halfspaces` of each shape once per `fuse` call (a point set's takes a hull)."""

    def __init__(self) -> None:
        self._known: dict[int, tuple[Shape, np.ndarray]] = {}  # the shape keeps its id

    def __call__(self, shape: Shape) -> np.ndarray:
        found = self._known.get(id(shape))
        if found is None:
            found = self._known[id(shape)] = (shape, halfspaces(shape))
        return found[1]


def _moved_out(planes: np.ndarray, grow) -> np.ndarray:
    """Half-spaces moved out by ``grow`` (m; one value or one per row)."""
    hs = planes.copy()
    hs[:, 3] -= grow
    return hs


def _overlap(shapes: list[Shape], slack: Sequence, planes=halfspaces) -> bool:
    """Whether the bounds (grown by ``slack``) overlap, as `intersect` decides it, without
    making their polytope (grouping only needs the answer; the polytope is made when the
    object's bound is, and not at all when a joint fit gives it)."""
    hs = np.vstack([_moved_out(planes(s), g) for s, g in zip(shapes, slack, strict=True)])
    centres = [s.position for s in shapes]
    return _interior(hs, [*centres, np.mean(centres, axis=0)]) is not None


def intersect(shapes: list[Shape], name: str = "", slack: Sequence | None = None,
              planes=halfspaces) -> Shape | None:
    """The convex intersection of several bounds of one object as a point set, or None
    when they do not overlap. ``slack[i]`` (m) grows bound ``i`` first: every one of its
    half-spaces moves out by it (a value, which contains the bound's Minkowski sum with a
    ball, or one value per half-space of `halfspaces`)."""
    slack = [0.0] * len(shapes) if slack is None else list(slack)
    if len(shapes) == 1 and np.max(slack[0]) <= 0.0:
        return shapes[0]
    hs = np.vstack([_moved_out(planes(s), g) for s, g in zip(shapes, slack, strict=True)])
    centres = [s.position for s in shapes]
    centre = _interior(hs, [*centres, np.mean(centres, axis=0)])
    if centre is None:
        return None
    try:
        vertices = HalfspaceIntersection(hs, centre).intersections
        vertices = vertices[ConvexHull(vertices).vertices]
    except (QhullError, ValueError):
        return None
    mid = vertices.mean(axis=0)
    return Shape("points", (), mid, points=vertices - mid, name=name or shapes[0].name)


def fuse(views: list[list[tuple[Shape, bool]]], gate_m: float,
         slack: Sequence[float] | None = None, anchored: bool = False,
         seen: list[list[np.ndarray | None]] | None = None, tolerance_m: float = 0.008,
         refit: Callable[[list[tuple[int, int]]], Shape | None] | None = None
         ) -> list[tuple[Shape, bool, list[tuple[int, int]]]]:
    """Detections of one colour class from several cameras -> one bound per object.

    ``views[c]`` holds camera ``c``'s ``(shape, partial)`` pairs; ``slack[c]`` (m, default
    0) grows camera ``c``'s bounds before they are used (an older frame: see the module
    text). Detections of different cameras are one object when their bounds overlap and
    their centres are within ``gate_m`` (greedy, in camera order; a partial view's centre
    is not gated, its bound only has to overlap: the check below keeps an object it was
    wrongly joined with, since the partial's points then leave the other bound out, and
    the partial bound is what remains); each object's bound is
    the intersection of its whole views (of its partial ones when it has no whole view). A
    fused object is partial only when every view of it is. ``anchored``: only the objects
    camera 0 sees are returned (the other views only tighten them; an object seen only in
    an older frame is reported when its own camera's frame is processed). Each object
    comes as ``(bound, partial, members)``, ``members`` its ``(camera, detection)`` indices.

    ``seen[c][i]``: the points camera ``c`` saw of detection ``i`` (N x 3, optional). A bound must
    hold what the other cameras saw: one that leaves a seen point out by more than
    ``tolerance_m`` rests on a prior the object breaks (a pole seen end-on is deeper than
    ``max_thickness_m``) and is left out of the intersection; one that leaves it out by
    less (depth noise) is grown by that much. Without this check such a bound cut the
    object that another camera saw whole.

    ``refit(members)``: one shape fitted to all the views of an object at once
    (:mod:`joint_fit`), or None; where it gives one, that is the object's bound and no
    intersection is made (the views' polytope costs ~1 ms a frame).
    """
    slack = [0.0] * len(views) if slack is None else list(slack)
    seen = [[None] * len(v) for v in views] if seen is None else seen
    planes = _Planes()
    groups: list[list[tuple[Shape, bool, float]]] = []
    members: list[list[tuple[int, int]]] = []
    pairs: dict[tuple[int, int, int], tuple] = {}  # (group, camera, index): its first & it
    for c, (detections, grow) in enumerate(zip(views, slack, strict=True)):
        taken: set[int] = set()
        for i, (shape, partial) in enumerate(detections):
            best, best_d = None, gate_m + grow
            for g, group in enumerate(groups):
                if g in taken:
                    continue
                first, first_partial, first_grow = group[0]
                d = float(np.linalg.norm(first.position - shape.position))
                if d > best_d and not (partial or first_partial):
                    continue  # (a cut-off view's centre says little: overlap decides)
                if _overlap([first, shape], [first_grow, grow], planes):
                    best, best_d = g, d
                    pairs[(g, c, i)] = (first, shape, first_grow, grow)  # made if needed
            if best is None:
                if anchored and c > 0:
                    continue
                groups.append([(shape, partial, grow)])
                members.append([(c, i)])
                taken.add(len(groups) - 1)
            else:
                groups[best].append((shape, partial, grow))
                members[best].append((c, i))
                taken.add(best)
    out = []
    for g, (group, m) in enumerate(zip(groups, members, strict=True)):
        fitted = None if refit is None or len(m) < 2 else refit(m)
        if fitted is not None:
            out.append((fitted, all(partial for _, partial, _ in group), m))
            continue
        surfaces = [seen[c][i] for c, i in m]
        checked = _consistent(group, surfaces, tolerance_m, planes)
        # two views of the same status: their intersection was found while grouping
        unchanged = len(checked) == 2 and all(
            np.ndim(c[2]) == 0 and c[2] == x[2] for c, x in zip(checked, group, strict=False))
        found = (pairs.get((g, *m[1])) if len(m) == 2 and group[0][1] == group[1][1]
                 and unchanged else None)
        pair = None if found is None else intersect(
            [found[0], found[1]], slack=[found[2], found[3]], planes=planes)
        motion = {id(shape): grow for shape, _, grow in group}
        out.append((*_fused(checked, pair, planes, motion), m))
    return out


def _consistent(group: list[tuple[Shape, bool, float]], surfaces: list[np.ndarray | None],
                tolerance_m: float, planes=halfspaces) -> list[tuple[Shape, bool, float]]:
    """The group's views whose bounds hold what the others saw (`fuse`), each grown by the
    little it missed; a view whose bound misses more is left out (never all of them)."""
    if len(group) < 2 or all(s is None for s in surfaces):
        return group
    kept = []
    for k, (shape, partial, grow) in enumerate(group):
        others = [s for j, s in enumerate(surfaces) if j != k and s is not None]
        if not others:
            kept.append((shape, partial, grow))
            continue
        hs = planes(shape)
        excess = np.max(np.vstack(others) @ hs[:, :3].T + hs[:, 3], axis=0) - grow
        if excess.max() <= 0.0:
            kept.append((shape, partial, grow))
        elif excess.max() <= tolerance_m:  # only the planes that missed move out
            kept.append((shape, partial, grow + np.where(excess > 0.0, excess + MARGIN_M, 0.0)))
    return kept or group


def _box_meet(boxes: list[Shape]) -> Shape | None:
    """A box that holds the intersection of several boxes (None below two, or when they do
    not overlap): each box cut to the box, in its own axes, around each other's corners,
    the smallest of these. Two upright boxes of one object from two cameras differ in yaw
    by a fraction of a degree, so this is about their intersection, and a primitive: the
    hidden depth of the front camera's box cut by what the side camera saw."""
    best = None
    for a in boxes if len(boxes) > 1 else []:
        R = a.rotation()
        hi = 0.5 * np.asarray(a.size, dtype=float)
        lo = -hi
        for b in boxes:
            if b is not a:
                corners = (enclosing_vertices(b) - a.position) @ R
                lo, hi = np.maximum(lo, corners.min(axis=0)), np.minimum(hi, corners.max(axis=0))
        if np.any(hi <= lo):
            return None
        box = Shape("box", tuple(hi - lo), a.position + R @ (0.5 * (lo + hi)), a.orientation,
                    name=a.name)
        if best is None or volume(box) < volume(best):
            best = box
    return best


def _fused(group: list[tuple[Shape, bool, float]], pair: Shape | None = None,
           planes=halfspaces, motion: dict[int, float] | None = None) -> tuple[Shape, bool]:
    """One object's bound from its views: the intersection of the whole ones (or of the
    partial ones when none is whole), each grown by its slack (``pair``: that intersection
    of a group of two, already known)."""
    whole = [(s, g) for s, p, g in group if not p]
    members = whole or [(s, g) for s, _, g in group]
    shape = pair if pair is not None else intersect([s for s, _ in members],
                                                    slack=[g for _, g in members],
                                                    planes=planes)
    if shape is None:  # views that overlap pairwise but not all together: keep one
        s, g = min(members, key=lambda m: m[0].bounding_radius() + np.max(m[1]))
        # the smallest bound of a whole view still contains the object
        shape = s if np.max(g) <= 0.0 else intersect([s], slack=[g])
        if shape is None:  # qhull failed on the grown bound: its bounding sphere, grown
            shape = Shape("sphere", (s.bounding_radius() + np.max(g),), s.position,
                          name=s.name)
    elif len(members) > 1:
        # every view's bound holds the object too: a sphere's polytope of tangent planes is
        # larger than the sphere, so two fitted spheres intersect into more than either;
        # and a primitive is certified far faster than a polytope of dozens of vertices
        # (G family, front + side: plans of 250-500 ms against 15 ms), so the polytope
        # must be clearly smaller to be kept
        # alone, a view's bound is as good as with one camera: grown for motion only
        motion = motion or {}
        alone = [grown(s, motion.get(id(s), g)) for s, g in members if s.kind != "points"]
        meet = _box_meet([grown(s, g) for s, g in members if s.kind == "box"])
        if meet is not None:  # several boxes: one box holds their intersection
            alone.append(meet)
        if alone:
            sizes = [volume(a) for a in alone]  # primitives: closed forms
            primitive = alone[int(np.argmin(sizes))]
            if volume(shape) > POLYTOPE_GAIN * min(sizes):
                shape = primitive
    return shape, not whole
