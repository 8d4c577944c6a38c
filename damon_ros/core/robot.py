"""The Franka Panda: kinematics (pinocchio), IK, and robot↔obstacle distances (coal GJK).

Two collision models, both from ``example-robot-data``:

- ``mesh`` — the collision meshes of ``panda.urdf``: ground truth, used to label data, to
  certify and to score contact. Every Panda collision mesh is convex (its convex hull has
  the same vertices and volume), so each is loaded as a coal ``Convex``: the same geometry,
  but GJK/EPA gives exact distances, penetration depth and witness points in a few µs per
  pair instead of a BVH traversal.
- ``fast`` — the sphere/cylinder model of ``panda_collision.urdf``, rebuilt as spheres (each
  cylinder covered by overlapping spheres) and checked in batches by the compiled kernels of
  :mod:`damon_ros.core.sphere_kernels`. That model does NOT contain the meshes everywhere (its
  forearm misses the link-5 mesh by 3 cm), so spheres first grow until they contain every
  mesh surface point (:func:`containment_inflation`), then all grow by
  :data:`FAST_MODEL_MARGIN`: "fast says free" implies "meshes say free".

Fingers are locked at :data:`FINGER_OPENING` m each (fully open: the largest, hence most
conservative, hand). Joint limits come from :mod:`damon_ros.core.limits`; the kinematics are the
Panda's for both limit profiles. No rclpy here.
"""

from __future__ import annotations

import importlib.metadata
import math
import time
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cache, cached_property
from pathlib import Path

import coal
import numpy as np
import pinocchio as pin

from damon_ros.core import sphere_kernels
from damon_ros.core.limits import READY, JointLimits, joint_limits
from damon_ros.core.shapes import Shape

FINGER_OPENING = 0.04
TCP_FRAME = "panda_hand_tcp"
SPHERE_SPACING = 0.04
"""Largest gap (m) between the spheres that cover one cylinder of the fast model; each such
sphere grows by ``hypot(r, gap / 2) - r`` (≤ 2.2 mm for the Panda's 9 cm links) to cover
the cylinder between sphere centres."""
FAST_MODEL_MARGIN = 0.0065
"""Growth (m) of every fast-model sphere beyond containing the meshes. Containment is checked
on surface points at most 2.3 mm from any mesh point (:data:`SURFACE_STEP`), so wherever the
fast distance is ≥ 0 the meshes are ≥ 4 mm from the obstacle by construction. Measured with
``damon-ros bench-robot --margin 10000`` (10,000 random configurations, each with a random
sphere or box near a random surface point of the arm; the meshes touch it in 4,600): the
URDF's spheres as they are exceed the mesh distance by up to 8.5 mm and say "free" (+8.6 mm)
where the meshes touch; after the containment growth and before this margin, fast − mesh
is at most −1.3 mm (median −28 mm) where apart and fast ≤ −2.5 mm where the meshes touch:
"fast > 0 ⇒ mesh > 0" held on every sample, with this margin as reserve."""
SURFACE_STEP = 0.004
IK_LIMIT_MARGIN = 0.02  # rad: IK solutions keep this far inside the joint limits (and
# outside control.POSITION_LIMIT_MARGIN, where the controller brakes to a stop)
"""Largest edge (m) of the triangles the mesh surfaces are cut into to check that the fast
model's spheres contain them; every surface point is within ``SURFACE_STEP / √3`` (2.3 mm)
of a checked point, which :data:`FAST_MODEL_MARGIN` covers."""


@cache
def description_dir() -> tuple[Path, Path]:
    """(share directory for ``package://``, ``panda_description`` directory) of the installed
    ``example-robot-data`` distribution — found through the package, never hard-coded."""
    dist = importlib.metadata.distribution("example-robot-data")
    share = Path(str(dist.locate_file("cmeel.prefix/share")))
    panda = share / "example-robot-data" / "robots" / "panda_description"
    if not (panda / "urdf" / "panda.urdf").is_file():
        raise FileNotFoundError(f"example-robot-data has no Panda description under {panda}")
    return share, panda


@dataclass(frozen=True)
class Clearance:
    """Minimum distance between the robot and obstacles, with witness points (base frame).

    ``distance`` < 0 is penetration depth; ``link`` names the robot link and ``obstacle``
    indexes the obstacle list (-1 and ``inf`` when there were no obstacles)."""

    distance: float
    robot_point: np.ndarray
    obstacle_point: np.ndarray
    link: str
    obstacle: int

    @property
    def in_collision(self) -> bool:
        return self.distance <= 0.0


@dataclass(frozen=True)
class IKResult:
    """Outcome of :meth:`Robot.ik`; ``reason`` says why it failed (empty on success)."""

    success: bool
    q: np.ndarray | None
    reason: str
    position_error: float = math.inf
    orientation_error: float = math.inf
    seeds_tried: int = 0


# ---- loading ----------------------------------------------------------------------------
def load_arm(urdf_name: str) -> tuple[pin.Model, pin.GeometryModel]:
    """The 7-joint arm (fingers locked at FINGER_OPENING) with its collision geometry."""
    share, panda = description_dir()
    urdf = str(panda / "urdf" / urdf_name)
    full = pin.buildModelFromUrdf(urdf)
    geom = pin.buildGeomFromUrdf(full, urdf, pin.GeometryType.COLLISION, package_dirs=[str(share)])
    q_ref = pin.neutral(full)
    fingers = [full.getJointId(f"panda_finger_joint{i}") for i in (1, 2)]
    for j in fingers:
        q_ref[full.joints[j].idx_q] = FINGER_OPENING
    return pin.buildReducedModel(full, geom, fingers, q_ref)


def _link_name(model: pin.Model, obj: pin.GeometryObject) -> str:
    return model.frames[obj.parentFrame].name


def _convex_meshes(model: pin.Model, geom: pin.GeometryModel) -> pin.GeometryModel:
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
def _solid_points(points: np.ndarray, eps: float = 1e-7) -> np.ndarray:
    """A point set with a 3-D hull: flat or collinear sets get ±eps copies across their
    missing directions, so coal can build a hull that is the set within eps."""
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
    for p in _solid_points(shape.points):
        vec.append(p)
    return coal.Convex.convexHull(vec, False, "Qt"), placement


# ---- vectorised signed distance of points to one obstacle -------------------------------
class _Sdf:
    """Signed distance from a batch of points, laid out (3, M) as x, y, z rows, to one
    obstacle (negative inside). As in :mod:`damon_ros.core.sphere_kernels`, a point set counts as
    its bounding sphere about its mean (which contains its hull, so distances to it never
    exceed the true ones) and a single point exactly."""

    def __init__(self, shape: Shape) -> None:
        rot = shape.rotation()
        self.kind, center = shape.kind, shape.position
        if shape.kind == "points":
            world = shape.position + shape.points @ rot.T
            center = world.mean(axis=0)
            self.kind = "sphere"
            self.radius = float(np.max(np.linalg.norm(world - center, axis=1)))
        elif shape.kind == "box":
            self.half = 0.5 * np.array(shape.size)[:, None]
        elif shape.kind == "sphere":
            self.radius = shape.size[0]
        else:
            self.radius, self.half_length = shape.size[0], 0.5 * shape.size[1]
        self.center, self.rt = center[:, None], rot.T
        self.offset = self.rt @ self.center

    def __call__(self, P: np.ndarray) -> np.ndarray:
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
    model's conventions (a point set as its bounding sphere); the numpy reference for
    :mod:`damon_ros.core.sphere_kernels`."""
    points = np.asarray(points, dtype=float)
    if points.shape[-1] != 3:
        raise ValueError(f"points must be (..., 3), got shape {points.shape}")
    return _Sdf(shape)(points.reshape(-1, 3).T).reshape(points.shape[:-1])


# ---- batched forward kinematics ---------------------------------------------------------
class Chain:
    """Forward kinematics of many configurations at once.

    Every Panda joint turns about its local z axis, so the placement of joint k relative to
    its parent is ``P_k Rz(q_k) = A_k + cos q_k B_k + sin q_k C_k`` with constant A, B, C:
    one small matrix product per joint for the whole batch. :meth:`transforms` returns the
    3×4 poses of the base and the 7 joints side by side, laid out (3, N, 32) (rows x, y, z
    first), so that points fixed to joints are placed by one matrix product with a (32, K)
    block of their homogeneous local coordinates (:meth:`block`, :meth:`points`)."""

    def __init__(self, model: pin.Model) -> None:
        if model.njoints != 8:
            raise ValueError(f"expected a 7-joint arm, got {model.njoints - 1} joints")
        z = np.zeros((4, 4))
        z[0, 1], z[1, 0] = -1.0, 1.0
        self.abc = []
        for j in range(1, 8):
            p = model.jointPlacements[j].homogeneous
            self.abc.append(np.hstack([p @ np.diag([0.0, 0.0, 1.0, 1.0]),
                                       p @ np.diag([1.0, 1.0, 0.0, 0.0]), p @ z]))
        self.first = [m[:3, None, :] for m in np.split(self.abc[0], 3, axis=1)]
        self.model, self.data = model, model.createData()

    def transforms(self, Q: np.ndarray) -> np.ndarray:
        n = len(Q)
        out = np.empty((3, n, 8, 4))
        out[:, :, 0] = np.eye(3, 4)[:, None]
        if n == 1:  # one configuration: pinocchio's C++ is cheaper than the numpy calls
            pin.forwardKinematics(self.model, self.data, Q[0])
            for j in range(1, 8):
                out[:, 0, j] = self.data.oMi[j].homogeneous[:3]
            return out.reshape(3, 1, 32)
        c, s = np.cos(Q).T[:, None, :, None], np.sin(Q).T[:, None, :, None]
        a, b, cc = self.first
        t = a + c[0] * b + s[0] * cc
        out[:, :, 1] = t
        for k in range(1, 7):
            x = (t.reshape(3 * n, 4) @ self.abc[k]).reshape(3, n, 12)
            t = x[:, :, 0:4] + c[k] * x[:, :, 4:8] + s[k] * x[:, :, 8:12]
            out[:, :, k + 1] = t
        return out.reshape(3, n, 32)

    @staticmethod
    def points(T: np.ndarray, block: np.ndarray) -> np.ndarray:
        """World positions (3, N·K) of the K points of ``block`` in each of the N states."""
        return (T.reshape(-1, 32) @ block).reshape(3, -1)

    @staticmethod
    def block(joints: np.ndarray, local: np.ndarray) -> np.ndarray:
        """(32, K) matrix placing point k, fixed at ``local[k]`` in joint ``joints[k]``."""
        b = np.zeros((32, len(joints)))
        for k, (j, p) in enumerate(zip(joints, local, strict=True)):
            b[4 * j:4 * j + 3, k] = p
            b[4 * j + 3, k] = 1.0
        return b


# ---- the fast (sphere) model ------------------------------------------------------------
class SphereModel:
    """The fast collision model: spheres fixed to joint frames. Batches go through the
    compiled kernels of :mod:`damon_ros.core.sphere_kernels` (``kernel_args``); single states and
    witness points through :class:`Chain` and numpy.

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
                links.append(_link_name(model, obj))
        self.centers, self.joints, self.links = np.array(centers), np.array(joints), links
        self.chain = Chain(model)
        self.block = Chain.block(self.joints, self.centers)
        self.raw_radii = np.array(radii)
        self.inflation = np.zeros(len(radii)) if inflation is None else inflation
        if self.inflation.shape != self.raw_radii.shape:
            raise ValueError(f"inflation needs {len(radii)} values, got {self.inflation.shape}")
        self.margin = margin
        self.radii = self.raw_radii + self.inflation + margin
        self.kernel_args = sphere_kernels.pack_robot(
            np.array([model.jointPlacements[j].rotation for j in range(1, 8)]),
            np.array([model.jointPlacements[j].translation for j in range(1, 8)]),
            self.joints, self.centers, self.radii)

    def distances(self, Q: np.ndarray, obstacles: Sequence[Shape]) -> np.ndarray:
        """(N,) minimum signed distance of configurations (N, 7) to the obstacles."""
        return sphere_kernels.batch_distances(np.ascontiguousarray(Q, dtype=float),
                                              *self.kernel_args,
                                              *sphere_kernels.pack_obstacles(obstacles))

    def segment_clear(self, q0: np.ndarray, q1: np.ndarray, steps: int,
                      obstacles: Sequence[Shape], margin: float) -> bool:
        """All ``steps + 1`` evenly spaced states q0→q1 keep more than ``margin``."""
        return bool(sphere_kernels.segment_clear(q0, q1, steps, margin, *self.kernel_args,
                                                 *sphere_kernels.pack_obstacles(obstacles)))

    def world_centers(self, Q: np.ndarray) -> np.ndarray:
        """Sphere centres (N, S, 3) of configurations (N, 7)."""
        T = self.chain.transforms(Q)
        return Chain.points(T, self.block).reshape(3, len(Q), -1).transpose(1, 2, 0)

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
def panda_inflation(spacing: float = SPHERE_SPACING) -> np.ndarray:
    """:func:`containment_inflation` of the Panda's sphere model against its meshes (computed
    once per process, ~0.3 s)."""
    model, geom = load_arm("panda_collision.urdf")
    meshes = _convex_meshes(*load_arm("panda.urdf"))
    grow = containment_inflation(SphereModel(model, geom, 0.0, spacing=spacing), meshes)
    grow.flags.writeable = False
    return grow


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


# ---- the robot --------------------------------------------------------------------------
def _reach_bound(model: pin.Model, tcp: int) -> tuple[np.ndarray, float]:
    """(shoulder position, upper bound on shoulder→TCP distance): the sum of the lengths of
    the rigid links shoulder→elbow→wrist→TCP, by the triangle inequality."""
    data = model.createData()
    pin.forwardKinematics(model, data, pin.neutral(model))
    pin.updateFramePlacements(model, data)
    shoulder, elbow, wrist = (data.oMi[j].translation for j in (2, 4, 6))
    tcp_pos = data.oMf[tcp].translation
    return shoulder.copy(), float(np.linalg.norm(elbow - shoulder) + np.linalg.norm(
        wrist - elbow) + np.linalg.norm(tcp_pos - wrist))


class Robot:
    """Panda kinematics, IK and collision queries on the chosen collision model.

    ``collision`` picks the model that :meth:`clearance`, :meth:`distances`,
    :meth:`in_collision`, :meth:`segment_free` and :meth:`path_free` use: ``"mesh"`` (exact)
    or ``"fast"`` (conservative spheres). Kinematics, :meth:`ik` and the self-collision
    checks are the same for both (self-collision is always on the exact meshes, with the
    SRDF's disabled pairs). ``profile`` picks the joint limits (``"panda"`` or ``"fr3"``)."""

    def __init__(self, collision: str = "fast", profile: str = "panda",
                 fast_margin: float = FAST_MODEL_MARGIN) -> None:
        if collision not in ("fast", "mesh"):
            raise ValueError(f"collision model must be 'fast' or 'mesh', got {collision!r}")
        if not 0.0 <= fast_margin < 0.1:
            raise ValueError(f"fast_margin must be in [0, 0.1) m, got {fast_margin}")
        self.collision = collision
        self.limits: JointLimits = joint_limits(profile)
        model, mesh_geom = load_arm("panda.urdf")
        self.model, self.data = model, model.createData()
        self.mesh_geom = _convex_meshes(model, mesh_geom)
        self.mesh_data = pin.GeometryData(self.mesh_geom)
        self._mesh_links = [_link_name(model, o) for o in self.mesh_geom.geometryObjects]
        self._mesh_bounds()
        self.tcp_id = model.getFrameId(TCP_FRAME)
        if self.tcp_id >= model.nframes:
            raise ValueError(f"the Panda description has no {TCP_FRAME} frame")
        self.fast_margin = fast_margin
        self.shoulder, self.reach = _reach_bound(model, self.tcp_id)
        self._request = coal.DistanceRequest()
        self._request.enable_signed_distance = True

    @cached_property
    def spheres(self) -> SphereModel:
        """The fast model, built on first use (a mesh-only robot never needs it)."""
        model, geom = load_arm("panda_collision.urdf")
        return SphereModel(model, geom, self.fast_margin, inflation=panda_inflation())

    def _mesh_bounds(self) -> None:
        """Bounding sphere of each mesh (centre fixed in its joint's frame), to skip GJK on
        meshes that cannot be the closest."""
        centers, radii, joints = [], [], []
        for obj in self.mesh_geom.geometryObjects:
            v = local_vertices(obj.geometry)
            c = 0.5 * (v.min(axis=0) + v.max(axis=0))
            centers.append(obj.placement.act(c))
            radii.append(float(np.max(np.linalg.norm(v - c, axis=1))))
            joints.append(obj.parentJoint)
        self._mesh_block = Chain.block(np.array(joints), np.array(centers))
        self._mesh_radii = np.array(radii)

    # ---- kinematics -------------------------------------------------------------------
    @staticmethod
    def _check_q(q) -> np.ndarray:
        q = np.asarray(q, dtype=float).reshape(-1)
        if q.shape != (7,) or not np.all(np.isfinite(q)):
            raise ValueError(f"a configuration is 7 finite joint angles, got {q.tolist()}")
        return q

    @staticmethod
    def _check_batch(Q) -> np.ndarray:
        Q = np.asarray(Q, dtype=float)
        Q = Q.reshape(1, -1) if Q.ndim == 1 else Q
        if Q.ndim != 2 or Q.shape[1] != 7 or not np.all(np.isfinite(Q)):
            raise ValueError(f"configurations must be a finite (N, 7) array, got shape {Q.shape}")
        return Q

    def fk(self, q, frame: str = TCP_FRAME) -> np.ndarray:
        """Homogeneous 4×4 pose of ``frame`` in the base frame."""
        q = self._check_q(q)
        fid = self.tcp_id if frame == TCP_FRAME else self.model.getFrameId(frame)
        if fid >= self.model.nframes:
            raise ValueError(f"unknown frame {frame!r}")
        pin.forwardKinematics(self.model, self.data, q)
        return pin.updateFramePlacement(self.model, self.data, fid).homogeneous.copy()

    def tcp_pose(self, q) -> tuple[np.ndarray, np.ndarray]:
        """TCP position (3,) and quaternion ``[x, y, z, w]`` (4,)."""
        T = self.fk(q)
        return T[:3, 3].copy(), pin.Quaternion(T[:3, :3]).coeffs().copy()

    def frame_positions(self, q) -> dict[str, np.ndarray]:
        """Positions of the link frames ``panda_link0..8``, hand and TCP (e.g. to draw)."""
        q = self._check_q(q)
        pin.forwardKinematics(self.model, self.data, q)
        pin.updateFramePlacements(self.model, self.data)
        names = [f"panda_link{i}" for i in range(9)] + ["panda_hand", TCP_FRAME]
        return {n: self.data.oMf[self.model.getFrameId(n)].translation.copy() for n in names}

    # ---- inverse kinematics -----------------------------------------------------------
    def ik(self, position, orientation, q_near=None, obstacles: Sequence[Shape] = (),
           min_clearance: float = 0.0, n_seeds: int = 32, rng: np.random.Generator | None = None,
           position_tolerance: float = 1e-3, orientation_tolerance: float = 1e-2,
           max_solutions: int = 3, time_budget_s: float | None = None) -> IKResult:
        """Joint angles that put the TCP at a pose (``orientation`` is ``[x, y, z, w]``),
        within the joint limits, out of self-collision and at least ``min_clearance`` from
        ``obstacles`` (on this robot's collision model).

        The seed ``q_near`` (default: the ready pose) is tried first; if it converges to a
        valid solution that one is returned at once, because Newton steps from ``q_near``
        reach the nearby solution with the least joint motion. Otherwise random seeds are
        tried until ``max_solutions`` valid ones are found (or ``n_seeds`` / the time
        budget run out) and the one nearest ``q_near`` is returned."""
        t_end = math.inf if time_budget_s is None else time.perf_counter() + time_budget_s
        target, problem = self._ik_target(position, orientation)
        if problem:
            return IKResult(False, None, problem)
        q_near = READY if q_near is None else self.limits.clip(self._check_q(q_near))
        rng = rng if rng is not None else np.random.default_rng(0)
        found, blocked, best, tried = [], 0, (math.inf, math.inf), 0
        while tried < max(1, n_seeds) and len(found) < max_solutions:
            if tried and time.perf_counter() > t_end:
                break
            seed = q_near if tried == 0 else rng.uniform(self.limits.lower, self.limits.upper)
            tried += 1
            q, err_p, err_o = self._solve(target, seed)
            if err_p > position_tolerance or err_o > orientation_tolerance:
                best = min(best, (err_p, err_o))
                continue
            if not self._ik_valid(q, obstacles, min_clearance):
                blocked += 1
                continue
            found.append((float(np.linalg.norm(q - q_near)), q, err_p, err_o))
            if tried == 1:
                break
        if found:
            _, q, err_p, err_o = min(found, key=lambda f: f[0])
            return IKResult(True, q, "", err_p, err_o, tried)
        if blocked:
            return IKResult(False, None, f"all {blocked} IK solutions found from {tried} seeds "
                            "collide: self-collision or closer than "
                            f"{min_clearance:.3f} m to an obstacle", seeds_tried=tried)
        why = (f"no IK solution within {position_tolerance * 1e3:.1f} mm / "
               f"{orientation_tolerance:.3f} rad from {tried} seeds (best {best[0] * 1e3:.1f} mm, "
               f"{best[1]:.3f} rad); the pose is likely unreachable with this orientation")
        return IKResult(False, None, why, *best, seeds_tried=tried)

    def _ik_target(self, position, orientation) -> tuple[pin.SE3 | None, str]:
        position = np.asarray(position, float).reshape(-1)
        quat = np.asarray(orientation, float).reshape(-1)
        if position.shape != (3,) or quat.shape != (4,):
            return None, "goal pose needs a 3-vector position and an [x, y, z, w] quaternion"
        if not (np.all(np.isfinite(position)) and np.all(np.isfinite(quat))):
            return None, "goal pose holds NaN or inf"
        norm = float(np.linalg.norm(quat))
        if abs(norm - 1.0) > 1e-3:
            return None, f"goal orientation is not a unit quaternion (norm {norm:.4f})"
        reach = float(np.linalg.norm(position - self.shoulder))
        if reach > self.reach:
            return None, (f"position is {reach:.3f} m from the shoulder (joint 2), beyond the "
                          f"Panda's reach of {self.reach:.3f} m")
        rot = pin.Quaternion(quat[3], *quat[:3]).normalized().matrix()
        return pin.SE3(rot, position), ""

    def _ik_valid(self, q: np.ndarray, obstacles: Sequence[Shape], min_clearance: float) -> bool:
        if self.self_collision(q):
            return False
        return not obstacles or self.clearance(q, obstacles).distance >= min_clearance

    def _solve(self, target: pin.SE3, seed: np.ndarray, iterations: int = 60,
               damping: float = 1e-8, max_step: float = 0.6) -> tuple[np.ndarray, float, float]:
        """Levenberg–Marquardt on the SE(3) log error (with its exact Jacobian ``Jlog6``),
        each step capped at ``max_step`` rad and clamped to the joint limits. Damping grows
        with the error, so far from the goal steps are short and near it they are Newton
        steps; a seed is dropped as soon as its error stops shrinking (local minimum or a
        limit in the way)."""
        model, data, fid = self.model, self.data, self.tcp_id
        # clamped a little inside the limits: an IK goal on a limit is a motion that ends
        # on it, and a Franka stops with a reflex there (mock_panda's monitor counted one)
        lower, upper = self.limits.lower + IK_LIMIT_MARGIN, self.limits.upper - IK_LIMIT_MARGIN
        q, best, stalled = np.clip(seed, lower, upper), math.inf, 0
        for _ in range(iterations):
            pin.forwardKinematics(model, data, q)
            error_se3 = pin.updateFramePlacement(model, data, fid).actInv(target)
            err = pin.log6(error_se3).vector
            norm = float(err @ err)
            if norm < 1e-14:
                break
            stalled = stalled + 1 if norm > 0.9 * best else 0
            best = min(best, norm)
            if stalled >= 6:
                break
            J = pin.Jlog6(error_se3.inverse()) @ pin.computeFrameJacobian(model, data, q, fid,
                                                                          pin.LOCAL)
            A = J @ J.T
            A[np.diag_indices(6)] += damping + 1e-3 * norm
            dq = J.T @ np.linalg.solve(A, err)
            step = float(np.max(np.abs(dq)))
            if step > max_step:
                dq *= max_step / step
            q = np.clip(q + dq, lower, upper)
        pin.forwardKinematics(model, data, q)
        current = pin.updateFramePlacement(model, data, fid)
        err = pin.log6(current.actInv(target)).vector
        return q, float(np.linalg.norm(target.translation - current.translation)), float(
            np.linalg.norm(err[3:]))

    # ---- obstacle distances -----------------------------------------------------------
    def clearance(self, q, obstacles: Sequence[Shape]) -> Clearance:
        """Minimum signed distance to the obstacles with witness points: exact (coal GJK/EPA)
        for the mesh model; the inflated spheres' distance for the fast model."""
        q = self._check_q(q)
        if not obstacles:
            return Clearance(math.inf, np.zeros(3), np.zeros(3), "", -1)
        if self.collision == "fast":
            return self._fast_clearance(q, obstacles)
        return self._mesh_clearance(q, obstacles)

    def _mesh_clearance(self, q: np.ndarray, obstacles: Sequence[Shape]) -> Clearance:
        pin.updateGeometryPlacements(self.model, self.data, self.mesh_geom, self.mesh_data, q)
        oMg, oMi = self.mesh_data.oMg, self.data.oMi
        joints = np.hstack([oMi[j].homogeneous[:3] for j in range(8)])
        centers = (joints @ self._mesh_block).T
        objs = self.mesh_geom.geometryObjects
        best = (math.inf, None, None, "", -1)
        for k, shape in enumerate(obstacles):
            geom, tf = obstacle_geometry(shape)
            lower = (np.linalg.norm(centers - shape.position, axis=1) - self._mesh_radii
                     - shape.bounding_radius())
            for i in map(int, np.argsort(lower)):
                if lower[i] >= best[0]:
                    break
                result = coal.DistanceResult()
                d = coal.distance(objs[i].geometry, coal.Transform3s(oMg[i].rotation,
                                                                     oMg[i].translation),
                                  geom, tf, self._request, result)
                if d < best[0]:
                    best = (d, result.getNearestPoint1().copy(),
                            result.getNearestPoint2().copy(), self._mesh_links[i], k)
        return Clearance(float(best[0]), *best[1:])

    def _fast_clearance(self, q: np.ndarray, obstacles: Sequence[Shape]) -> Clearance:
        centers = self.spheres.world_centers(q[None])[0].T
        sdfs = [_Sdf(s) for s in obstacles]
        per = np.stack([sdf(centers) for sdf in sdfs]) - self.spheres.radii
        k, i = (int(v) for v in np.unravel_index(int(np.argmin(per)), per.shape))
        center, radius = centers[:, i], self.spheres.radii[i]
        surface = sdfs[k].closest_point(center)
        away = center - surface
        inside = per[k, i] + radius < 0.0
        u = (-away if inside else away) / max(float(np.linalg.norm(away)), 1e-12)
        return Clearance(float(per[k, i]), center - u * radius, surface, self.spheres.links[i], k)

    def distances(self, Q, obstacles: Sequence[Shape]) -> np.ndarray:
        """Minimum signed distance to the obstacles for each configuration of (N, 7)."""
        Q = self._check_batch(Q)
        if not obstacles:
            return np.full(len(Q), math.inf)
        if self.collision == "mesh":
            return np.array([self._mesh_clearance(q, obstacles).distance for q in Q])
        return self.spheres.distances(Q, obstacles)

    def in_collision(self, q, obstacles: Sequence[Shape], margin: float = 0.0) -> bool:
        """True when the robot comes within ``margin`` of an obstacle (touching counts)."""
        return bool(self.distances(self._check_q(q)[None], obstacles)[0] <= margin)

    # ---- self-collision ---------------------------------------------------------------
    def self_collision(self, q) -> bool:
        """Exact self-collision of the meshes, ignoring the SRDF's disabled pairs (adjacent
        links and pairs that can never touch)."""
        q = self._check_q(q)
        return bool(pin.computeCollisions(self.model, self.data, self.mesh_geom, self.mesh_data,
                                          q, True))

    # ---- segments ---------------------------------------------------------------------
    @staticmethod
    def steps(q0: np.ndarray, q1: np.ndarray, resolution: float) -> int:
        """Number of intervals that keep every joint step at most ``resolution`` rad."""
        if not resolution > 0.0:
            raise ValueError(f"resolution must be positive, got {resolution}")
        return max(1, math.ceil(float(np.max(np.abs(q1 - q0))) / resolution))

    def segment_free(self, q0, q1, obstacles: Sequence[Shape], margin: float = 0.0,
                     resolution: float = 0.02) -> bool:
        """True when every state on the straight joint-space segment, sampled at most
        ``resolution`` rad apart (max norm, ends included), keeps more than ``margin`` from
        every obstacle. Self-collision is separate (:meth:`segment_self_collision_free`)."""
        q0, q1 = self._check_q(q0), self._check_q(q1)
        n = self.steps(q0, q1, resolution)
        if not obstacles:
            return True
        if self.collision == "mesh":
            Q = q0 + np.linspace(0.0, 1.0, n + 1)[:, None] * (q1 - q0)
            return all(self._mesh_clearance(q, obstacles).distance > margin for q in Q)
        return self.spheres.segment_clear(q0, q1, n, obstacles, margin)

    def path_free(self, path, obstacles: Sequence[Shape], margin: float = 0.0,
                  resolution: float = 0.02) -> bool:
        """:meth:`segment_free` for every segment of a (K, 7) waypoint path."""
        path = self._check_batch(path)
        if len(path) == 1:
            return not obstacles or bool(self.distances(path, obstacles)[0] > margin)
        return all(self.segment_free(a, b, obstacles, margin, resolution)
                   for a, b in zip(path[:-1], path[1:], strict=True))

    def segment_self_collision_free(self, q0, q1, resolution: float = 0.1) -> bool:
        """No self-collision of the exact meshes along a straight segment, sampled at most
        ``resolution`` rad apart (the SRDF's disabled pairs ignored)."""
        q0, q1 = self._check_q(q0), self._check_q(q1)
        n = self.steps(q0, q1, resolution)
        return not any(self.self_collision(q0 + s * (q1 - q0))
                       for s in np.linspace(0.0, 1.0, n + 1))
