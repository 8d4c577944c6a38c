"""The Panda's collision models and the obstacle geometry they are checked against.

Two collision models, both from ``example-robot-data``:

- ``mesh`` — the collision meshes of ``panda.urdf``: ground truth, used to label data, to
  certify and to score contact. Every Panda collision mesh is convex (its convex hull has
  the same vertices and volume), so each is loaded as a coal ``Convex`` (:func:`convex_meshes`):
  the same geometry, but GJK/EPA gives exact distances, penetration depth and witness points
  in a few µs per pair instead of a BVH traversal.
- ``fast`` — spheres fixed to the joint frames (:class:`SphereModel`), checked in batches by
  the compiled kernels of :mod:`damon_ros.core.sphere_kernels`. The shipped set
  (:data:`FITTED_SPHERES`, :meth:`SphereModel.fitted`) is fitted to the meshes by
  :mod:`damon_ros.core.sphere_fit`: it contains every mesh surface triangle and bulges at most
  its fit bound beyond them, then all spheres grow by :data:`FAST_MODEL_MARGIN`: "fast says
  free" implies "meshes say free". The older model — the sphere/cylinder model of
  ``panda_collision.urdf`` rebuilt as spheres, which does NOT contain the meshes (its forearm
  misses the link-5 mesh by 3 cm) and so is grown until it does (:func:`containment_inflation`)
  — is kept for comparison (``damon-ros bench-robot --margin``).

Obstacles become coal geometry (:func:`obstacle_geometry`) for the meshes and numpy signed
distance fields (:class:`Sdf`) for the spheres' witness points. The queries on these models
are :class:`damon_ros.core.robot.Robot`'s; this module only builds them. No rclpy here.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from functools import cache

import coal
import numpy as np
import pinocchio as pin

from damon_ros.core import sphere_kernels
from damon_ros.core.hull import closest_point as hull_closest_point
from damon_ros.core.hull import hull_faces, hull_signed_many, solid_points
from damon_ros.core.kinematics import FINGER_OPENING, Chain, description_dir, load_arm
from damon_ros.core.shapes import Shape

SPHERE_SPACING = 0.04
"""Largest gap (m) between the spheres that cover one cylinder of the URDF's sphere model;
each such sphere grows by ``hypot(r, gap / 2) - r`` (≤ 2.2 mm for the Panda's 9 cm links) to
cover the cylinder between sphere centres."""
FITTED_SPHERES = "panda_spheres.json"
"""The shipped sphere set fitted to the meshes (``config/``), see
:mod:`damon_ros.core.sphere_fit`; the fast model of :class:`damon_ros.core.robot.Robot`."""
FAST_MODEL_MARGIN = 0.002
"""Growth (m) of every fast-model sphere beyond containing the meshes. The fitted set
contains every mesh surface triangle exactly (not just samples of it), so this is a reserve,
not a correction: wherever the fast distance is ≥ 0 the meshes are ≥ 2 mm from the obstacle.
Measured with ``damon-ros bench-robot --margin 100000`` (random configurations, each with a
random sphere, box, cylinder or point set near a random surface point of the arm): fast ≤
mesh on every sample, see docs/BENCHMARKS.md. (The old model — ``panda_collision.urdf``
grown to contain the meshes — needed 6.5 mm here for its 2.3 mm surface sampling and its
spheres reached up to 30 mm beyond the meshes.)"""
PACKS_KEPT = 8
"""Obstacle tuples whose packed arrays a sphere model keeps (`SphereModel.packed`)."""
SURFACE_STEP = 0.004
"""Largest edge (m) of the triangles the mesh surfaces are cut into to check that the old
model's spheres contain them (:func:`containment_inflation`); every surface point is within
``SURFACE_STEP / √3`` (2.3 mm) of a checked point."""


def link_name(model: pin.Model, obj: pin.GeometryObject) -> str:
    """Name of the link (frame) a geometry object is attached to."""
    return model.frames[obj.parentFrame].name


def convex_meshes(model: pin.Model, geom: pin.GeometryModel) -> pin.GeometryModel:
    """The same geometry with every (convex) BVH mesh as a coal Convex, and the SRDF's
    disabled pairs removed from the self-collision pairs."""
    out = pin.GeometryModel()
    for obj in geom.geometryObjects:
        g = obj.geometry
        if isinstance(g, coal.BVHModelBase):
            g.buildConvexHull(True, "Qt")
            g = g.convex
        out.addGeometryObject(pin.GeometryObject(obj.name, obj.parentJoint, obj.parentFrame,
                                                 obj.placement, g))
    out.addAllCollisionPairs()
    pin.removeCollisionPairs(model, out, str(description_dir()[1] / "srdf" / "panda.srdf"))
    return out


@cache
def disabled_link_pairs() -> frozenset[frozenset[str]]:
    """Link pairs the SRDF disables (adjacent, or never able to touch)."""
    root = ET.parse(description_dir()[1] / "srdf" / "panda.srdf").getroot()
    return frozenset(frozenset((e.get("link1"), e.get("link2")))
                     for e in root.iter("disable_collisions"))


def local_vertices(g: coal.CollisionGeometry) -> np.ndarray:
    """Vertices of a convex or box geometry in its own frame (for bounding spheres)."""
    if isinstance(g, coal.Box):
        h = g.halfSide
        return np.array([[sx * h[0], sy * h[1], sz * h[2]] for sx in (-1, 1) for sy in (-1, 1)
                         for sz in (-1, 1)])
    return np.asarray(g.points(), dtype=float)


# ---- obstacles as coal geometry ---------------------------------------------------------
def obstacle_geometry(shape: Shape) -> tuple[coal.CollisionGeometry, coal.Transform3s]:
    """coal geometry and placement of an obstacle; a point set is its convex hull."""
    placement = coal.Transform3s(shape.rotation(), shape.position)
    if shape.kind == "box":
        return coal.Box(*shape.size), placement
    if shape.kind == "sphere":
        return coal.Sphere(shape.size[0]), placement
    if shape.kind == "cylinder":
        return coal.Cylinder(shape.size[0], shape.size[1]), placement
    vec = coal.StdVec_Vec3s()
    for p in solid_points(shape.points):
        vec.append(p)
    return coal.Convex.convexHull(vec, False, "Qt"), placement


# ---- vectorised signed distance of points to one obstacle -------------------------------
class Sdf:
    """Signed distance from a batch of points, laid out (3, M) as x, y, z rows, to one
    obstacle (negative inside), as :mod:`damon_ros.core.sphere_kernels` computes it: a
    point set is the convex hull of its points (:mod:`damon_ros.core.hull`; its bounding
    sphere where no hull can be built)."""

    def __init__(self, shape: Shape) -> None:
        rot = shape.rotation()
        self.kind, center = shape.kind, shape.position
        self.faces = None
        if shape.kind == "points":
            world = shape.position + shape.points @ rot.T
            center = world.mean(axis=0)
            self.kind = "sphere"
            self.radius = float(np.max(np.linalg.norm(world - center, axis=1)))
            if len(world) > 1:  # a single point is exactly its sphere of radius 0
                faces = hull_faces(world)
                self.faces = faces if len(faces) else None
        elif shape.kind == "box":
            self.half = 0.5 * np.array(shape.size)[:, None]
        elif shape.kind == "sphere":
            self.radius = shape.size[0]
        else:
            self.radius, self.half_length = shape.size[0], 0.5 * shape.size[1]
        self.center, self.rt = center[:, None], rot.T
        self.offset = self.rt @ self.center

    def __call__(self, P: np.ndarray) -> np.ndarray:
        if self.faces is not None:
            return hull_signed_many(np.ascontiguousarray(P, dtype=float), self.faces)
        if self.kind == "sphere":
            d = P - self.center
            return np.sqrt(np.einsum("im,im->m", d, d)) - self.radius
        local = self.rt @ P - self.offset
        if self.kind == "box":
            excess = np.abs(local) - self.half
            out = np.maximum(excess, 0.0)
            return np.sqrt(np.einsum("im,im->m", out, out)) + np.minimum(excess.max(axis=0), 0.0)
        radial = np.hypot(local[0], local[1]) - self.radius
        axial = np.abs(local[2]) - self.half_length
        outside = np.hypot(np.maximum(radial, 0.0), np.maximum(axial, 0.0))
        return outside + np.minimum(np.maximum(radial, axial), 0.0)

    def closest_point(self, p: np.ndarray) -> np.ndarray:
        """The obstacle's surface point nearest ``p`` (for witness points)."""
        if self.faces is not None:
            return hull_closest_point(p, self.faces)
        center = self.center[:, 0]
        if self.kind == "sphere":
            d = p - center
            return center + self.radius * d / max(float(np.linalg.norm(d)), 1e-12)
        local = self.rt @ (p - center)
        if self.kind == "box":
            half = self.half[:, 0]
            q = np.clip(local, -half, half)
            if np.all(np.abs(local) <= half):  # inside: out through the nearest face
                k = int(np.argmax(np.abs(local) - half))
                q[k] = math.copysign(half[k], local[k])
        else:
            rho = math.hypot(local[0], local[1])
            u = local[:2] / rho if rho > 1e-12 else np.array([1.0, 0.0])
            r, h = self.radius, self.half_length
            q = np.array([*(u * min(rho, r)), np.clip(local[2], -h, h)])
            if rho <= r and abs(local[2]) <= h:  # inside: out through the nearest surface
                if r - rho < h - abs(local[2]):
                    q[:2] = u * r
                else:
                    q[2] = math.copysign(h, local[2])
        return center + self.rt.T @ q


def signed_distance(points: np.ndarray, shape: Shape) -> np.ndarray:
    """Signed distance (negative inside) from points (..., 3) to an obstacle, with the fast
    model's conventions (a point set as its convex hull); the reference for
    :mod:`damon_ros.core.sphere_kernels`."""
    points = np.asarray(points, dtype=float)
    if points.shape[-1] != 3:
        raise ValueError(f"points must be (..., 3), got shape {points.shape}")
    return Sdf(shape)(points.reshape(-1, 3).T).reshape(points.shape[:-1])


# ---- the fast (sphere) model ------------------------------------------------------------
class SphereModel:
    """The fast collision model: spheres fixed to joint frames. Batches go through the
    compiled kernels of :mod:`damon_ros.core.sphere_kernels` (``kernel_args``); single states and
    witness points through :class:`~damon_ros.core.kinematics.Chain` and numpy.

    Each sphere grows by its ``inflation`` (what it takes for the spheres to contain the
    meshes, :func:`panda_inflation`), then all grow by ``margin``."""

    def __init__(self, model: pin.Model, geom: pin.GeometryModel, margin: float,
                 inflation: np.ndarray | None = None,
                 spacing: float = SPHERE_SPACING) -> None:
        centers, radii, joints, links = [], [], [], []
        for obj in geom.geometryObjects:
            for c, r in _cover(obj.geometry, obj.placement, spacing):
                centers.append(c)
                radii.append(r)
                joints.append(obj.parentJoint)
                links.append(link_name(model, obj))
        self._setup(model, np.array(joints), np.array(centers), np.array(radii), links,
                    inflation, margin)

    @classmethod
    def fitted(cls, margin: float, path: str | None = None,
               finger_opening: float = FINGER_OPENING) -> SphereModel:
        """The sphere set fitted to the meshes (:mod:`damon_ros.core.sphere_fit`), shipped as
        ``config/panda_spheres.json``: it contains the meshes by construction, so no
        containment inflation is needed, only ``margin``. The set is fitted with the fingers
        at :data:`FINGER_OPENING`; for another opening each finger's spheres move rigidly
        with their finger, as its meshes do."""
        from damon_ros.core.resources import config_file
        from damon_ros.core.sphere_set import SphereSet

        s = SphereSet.load(path or config_file(FITTED_SPHERES))
        model = load_arm("panda.urdf", finger_opening)[0]
        centers = s.centers
        if finger_opening != FINGER_OPENING:
            centers = _moved_with_links(centers, s.links, load_arm("panda.urdf")[0], model)
        out = cls.__new__(cls)
        out._setup(model, s.joints, centers, s.radii, list(s.links), None, margin)
        out.bulge = s.bulge
        return out

    def _setup(self, model: pin.Model, joints: np.ndarray, centers: np.ndarray,
               radii: np.ndarray, links: list[str], inflation: np.ndarray | None,
               margin: float) -> None:
        self.centers, self.joints, self.links = centers, joints, links
        self.chain = Chain(model)
        self.block = Chain.block(self.joints, self.centers)
        self.raw_radii = radii
        self.inflation = np.zeros(len(radii)) if inflation is None else inflation
        if self.inflation.shape != self.raw_radii.shape:
            raise ValueError(f"inflation needs {len(radii)} values, got {self.inflation.shape}")
        self.margin = margin
        self.radii = self.raw_radii + self.inflation + margin
        self.bulge: np.ndarray | None = None  # per sphere, its proven reach beyond the meshes
        self._pack_cache: list[tuple] = []  # (obstacle tuple, its packed arrays), newest first
        self.kernel_args = sphere_kernels.pack_robot(
            *sphere_kernels.joint_placements(model), self.joints, self.centers, self.radii)
        self._kernel_order = sphere_kernels.kernel_order(self.joints, self.centers)

    def packed(self, obstacles: Sequence[Shape]) -> tuple:
        """The kernels' arrays of ``obstacles``, kept for the PACKS_KEPT last (immutable)
        tuples: packing 21 shapes costs ~110 µs of Python, several times the kernel's own
        work, a search asks about the same obstacle tuple thousands of times, and a re-plan
        goes back and forth between a few (the swept obstacles, the statics, one more
        region). A list is packed afresh (it may be changed in place)."""
        if not isinstance(obstacles, tuple):
            return sphere_kernels.pack_obstacles(obstacles)
        for kept, packed in self._pack_cache:
            if kept is obstacles:
                return packed
        packed = sphere_kernels.pack_obstacles(obstacles)
        self._pack_cache = [(obstacles, packed), *self._pack_cache[:PACKS_KEPT - 1]]
        return packed

    def closest(self, q: np.ndarray, obstacles: Sequence[Shape]) -> tuple[float, int, int]:
        """(distance, sphere index, obstacle index) of the nearest sphere-obstacle pair in
        configuration q (indices into ``radii`` and ``obstacles``; -1 when none is finite)."""
        d, i, k = sphere_kernels.closest_pair(np.ascontiguousarray(q, dtype=float),
                                              *self.kernel_args, *self.packed(obstacles))
        return float(d), int(self._kernel_order[i]) if i >= 0 else -1, int(k)

    def distances(self, Q: np.ndarray, obstacles: Sequence[Shape]) -> np.ndarray:
        """(N,) minimum signed distance of configurations (N, 7) to the obstacles."""
        return sphere_kernels.batch_distances(np.ascontiguousarray(Q, dtype=float),
                                              *self.kernel_args, *self.packed(obstacles))

    def band_states(self, Q: np.ndarray, obstacles: Sequence[Shape], margin: float,
                    floor: float, budget: int) -> np.ndarray | None:
        """Indices of the configurations (N, 7) within ``margin`` of the obstacles, or None
        when one is at or below ``floor`` or more than ``budget`` are within it
        (`sphere_kernels.band_states`)."""
        return sphere_kernels.band_states(np.ascontiguousarray(Q, dtype=float), margin, floor,
                                          budget, *self.kernel_args, *self.packed(obstacles))

    def segment_clear(self, q0: np.ndarray, q1: np.ndarray, steps: int,
                      obstacles: Sequence[Shape], margin: float) -> bool:
        """All ``steps + 1`` evenly spaced states q0→q1 keep more than ``margin`` (``steps``
        0: the state q0 alone)."""
        return bool(sphere_kernels.segment_clear(q0, q1, steps, margin, *self.kernel_args,
                                                 *self.packed(obstacles)))

    def route_clear(self, path: np.ndarray, margins: np.ndarray, resolution: float,
                    obstacles: Sequence[Shape]) -> bool:
        """Every segment k of ``path`` (N, 7) keeps more than ``margins[k]`` at states at
        most ``resolution`` rad apart, in one compiled call (`sphere_kernels.route_clear`)."""
        return bool(sphere_kernels.route_clear(
            np.ascontiguousarray(path, dtype=float), np.asarray(margins, dtype=float),
            float(resolution), tuple(self.kernel_args), self.packed(obstacles)))

    def world_centers(self, Q: np.ndarray) -> np.ndarray:
        """Sphere centres (N, S, 3) of configurations (N, 7)."""
        return self.chain.positions(Q, self.block)

    def rigid_with(self, joint: int, n_probe: int = 6) -> np.ndarray:
        """Indices of the spheres that stay fixed in the frame of ``joint`` in every
        configuration: those on that joint, and those of neighbouring joints that sit on the
        axes between (found numerically on random configurations)."""
        Q = np.random.default_rng(0).uniform(-2.5, 2.5, (n_probe, 7))
        T = self.chain.transforms(Q).reshape(3, n_probe, 8, 4)
        R, p = T[:, :, joint, :3], T[:, :, joint, 3]
        world = Chain.points(self.chain.transforms(Q), self.block).reshape(3, n_probe, -1)
        local = np.einsum("inj,ins->njs", R, world - p[:, :, None])
        return np.flatnonzero(local.std(axis=0).max(axis=0) < 1e-9)


def surface_points(g: coal.CollisionGeometry, step: float = SURFACE_STEP) -> np.ndarray:
    """Points on the surface of a convex geometry (its own frame), no triangle edge between
    them longer than ``step``: every vertex and a barycentric grid on every hull face."""
    from scipy.spatial import ConvexHull

    v = local_vertices(g)
    tris = v[ConvexHull(v).simplices]
    edges = np.linalg.norm(tris - np.roll(tris, 1, axis=1), axis=2).max(axis=1)
    out = [v]
    for k in np.unique(np.maximum(1, np.ceil(edges / step).astype(int))):
        i, j = np.meshgrid(np.arange(k + 1), np.arange(k + 1), indexing="ij")
        keep = i + j <= k
        a, b = i[keep] / k, j[keep] / k
        t = tris[np.maximum(1, np.ceil(edges / step).astype(int)) == k]
        pts = (t[:, None, 0] + a[None, :, None] * (t[:, None, 1] - t[:, None, 0])
               + b[None, :, None] * (t[:, None, 2] - t[:, None, 0]))
        out.append(pts.reshape(-1, 3))
    return np.vstack(out)


def containment_inflation(spheres: SphereModel, meshes: pin.GeometryModel) -> np.ndarray:
    """Per-sphere growth (m) that makes the spheres contain every mesh surface point.

    ``panda_collision.urdf`` does not contain the meshes everywhere (its forearm cylinder
    misses the link-5 mesh by 3 cm, the base by 1 cm), so each surface point is given to the
    sphere, rigid with its link, that needs the least growth to reach it, and each sphere
    grows by the most any of its points needs. Measured: 19 of the 78 spheres grow — up to
    30 mm about the forearm and wrist (links 5, 6), up to 11 mm about the base and shoulder
    (links 0, 1) and at most 5 mm elsewhere."""
    grow = np.zeros(len(spheres.raw_radii))
    for obj in meshes.geometryObjects:
        idx = spheres.rigid_with(obj.parentJoint)
        m = obj.placement
        pts = surface_points(obj.geometry) @ m.rotation.T + m.translation
        local = _rigid_local(spheres, obj.parentJoint, idx)
        sq = (pts * pts).sum(axis=1)[:, None] - 2.0 * pts @ local.T + (local * local).sum(axis=1)
        need = np.sqrt(np.maximum(sq, 0.0)) - spheres.raw_radii[idx]
        best = need.argmin(axis=1)
        np.maximum.at(grow, idx[best], need[np.arange(len(pts)), best])
    return grow


@cache
def panda_inflation(spacing: float = SPHERE_SPACING,
                    finger_opening: float = FINGER_OPENING) -> np.ndarray:
    """:func:`containment_inflation` of the Panda's sphere model against its meshes (computed
    once per process and finger opening, ~0.3 s)."""
    model, geom = load_arm("panda_collision.urdf", finger_opening)
    meshes = convex_meshes(*load_arm("panda.urdf", finger_opening))
    grow = containment_inflation(SphereModel(model, geom, 0.0, spacing=spacing), meshes)
    grow.flags.writeable = False
    return grow


def _moved_with_links(centers: np.ndarray, links, reference: pin.Model,
                      model: pin.Model) -> np.ndarray:
    """Joint-frame points of ``links`` in ``reference`` carried to where those links sit in
    ``model`` (the same arm with the fingers locked elsewhere)."""
    out = centers.copy()
    for name in set(links):
        old = reference.frames[reference.getFrameId(name)].placement
        new = model.frames[model.getFrameId(name)].placement
        move = new * old.inverse()
        idx = [i for i, link in enumerate(links) if link == name]
        out[idx] = centers[idx] @ move.rotation.T + move.translation
    return out


def _rigid_local(spheres: SphereModel, joint: int, idx: np.ndarray) -> np.ndarray:
    """Centres of the spheres ``idx`` (rigid with ``joint``) in that joint's frame."""
    q = np.zeros((1, 7))
    T = spheres.chain.transforms(q).reshape(3, 8, 4)
    R, p = T[:, joint, :3], T[:, joint, 3]
    world = Chain.points(spheres.chain.transforms(q), spheres.block[:, idx])
    return ((world - p[:, None]).T @ R)


def _cover(g: coal.CollisionGeometry, placement: pin.SE3,
           spacing: float) -> list[tuple[np.ndarray, float]]:
    """Spheres (centre in the joint frame, radius) that contain a sphere or cylinder."""
    if isinstance(g, coal.Sphere):
        return [(placement.translation.copy(), g.radius)]
    if isinstance(g, coal.Cylinder):
        n = max(2, math.ceil(2 * g.halfLength / spacing) + 1)
        zs = np.linspace(-g.halfLength, g.halfLength, n)
        r = math.hypot(g.radius, 0.5 * (zs[1] - zs[0]))
        return [(placement.act(np.array([0.0, 0.0, z])), r) for z in zs]
    raise ValueError(f"fast model: unsupported geometry {type(g).__name__}")

