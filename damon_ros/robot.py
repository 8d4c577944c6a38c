"""The Franka Panda: kinematics (pinocchio) and exact robot↔obstacle distances (coal GJK).

Two collision models, both from ``example-robot-data``:

- ``mesh`` — the collision meshes of ``panda.urdf``: ground truth, used to label data,
  to certify and to score contact (~150 µs per robot↔obstacle query).
- ``fast`` — the sphere/cylinder model of ``panda_collision.urdf``, rebuilt as a set of
  spheres (each cylinder is covered by overlapping spheres whose radius accounts for the
  spacing) so that whole batches of configurations are checked with numpy. It is made
  conservative with :data:`FAST_MODEL_MARGIN`: over 10,000 random configurations with a
  random obstacle near the arm, ``mesh distance ≥ fast distance`` held on every sample
  (see ``test_fast_model_is_conservative``), so "fast says free" implies "meshes say free".

Fingers are locked at :data:`FINGER_OPENING` (m per finger). Joint limits come from
:mod:`damon_ros.limits`.
"""

from __future__ import annotations

import importlib.metadata
import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import coal
import numpy as np
import pinocchio as pin

from damon_ros import fast_collision
from damon_ros.limits import JointLimits, joint_limits
from damon_ros.shapes import Shape

FINGER_OPENING = 0.04
TCP_FRAME = "panda_hand_tcp"
READY = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])
SPHERE_SPACING = 0.03  # m between the spheres that cover one cylinder of the fast model
FAST_MODEL_MARGIN = 0.02
"""Inflation (m) of every fast-model sphere. Measured here (seed 7) on 10,000 random
configurations, each with a random sphere or box within ~0.1 m of a random link: the raw
sphere model's distance exceeded the mesh distance by up to 15.7 mm (p99 −4.8 mm: usually
the spheres are larger than the meshes). With 0.02 m the worst case is −4.3 mm: on every
sample the fast model is closer than the meshes, i.e. conservative."""
REACH = 0.855 + 0.107 + 0.1034  # m from the shoulder (joint 2) to the TCP, fully stretched
SHOULDER = np.array([0.0, 0.0, 0.333])


@cache
def description_dir() -> tuple[Path, Path]:
    """(share directory for package://, panda_description directory) of the installed
    ``example-robot-data`` distribution — found through the package, never hard-coded."""
    dist = importlib.metadata.distribution("example-robot-data")
    share = Path(dist.locate_file("cmeel.prefix/share"))
    panda = share / "example-robot-data" / "robots" / "panda_description"
    if not (panda / "urdf" / "panda.urdf").is_file():
        raise FileNotFoundError(f"example-robot-data has no Panda description under {panda}")
    return share, panda


@dataclass(frozen=True)
class Clearance:
    """Minimum distance between the robot and obstacles, with witness points (base frame).

    ``distance`` < 0 is penetration depth where coal reports it; ``link`` names the robot
    geometry and ``obstacle`` indexes the obstacle list."""

    distance: float
    robot_point: np.ndarray
    obstacle_point: np.ndarray
    link: str
    obstacle: int


@dataclass(frozen=True)
class IKResult:
    success: bool
    q: np.ndarray | None
    reason: str
    position_error: float = math.inf
    orientation_error: float = math.inf


def _coal_geometry(shape: Shape) -> coal.CollisionGeometry:
    if shape.kind == "box":
        return coal.Box(*shape.size)
    if shape.kind == "sphere":
        return coal.Sphere(shape.size[0])
    if shape.kind == "cylinder":
        return coal.Cylinder(shape.size[0], shape.size[1])
    pts = shape.points
    if len(pts) < 4 or np.linalg.matrix_rank(pts[1:] - pts[0]) < 3:
        center = pts.mean(axis=0)
        radius = float(np.max(np.linalg.norm(pts - center, axis=1)))
        return _OffsetSphere(max(radius, 1e-6), center)
    vec = coal.StdVec_Vec3s()
    for p in pts:
        vec.append(np.asarray(p, float))
    return coal.Convex.convexHull(vec, False, "")


class _OffsetSphere:
    """A degenerate point set (fewer than 4 points or flat) as its bounding sphere."""

    def __init__(self, radius: float, center: np.ndarray) -> None:
        self.geometry = coal.Sphere(radius)
        self.center = center


def _transform(rotation: np.ndarray, translation: np.ndarray) -> coal.Transform3s:
    tf = coal.Transform3s()
    tf.setRotation(np.asarray(rotation, float))
    tf.setTranslation(np.asarray(translation, float))
    return tf


def _obstacle_object(shape: Shape) -> tuple[coal.CollisionGeometry, coal.Transform3s]:
    geom = _coal_geometry(shape)
    rot = shape.rotation()
    if isinstance(geom, _OffsetSphere):
        return geom.geometry, _transform(np.eye(3), shape.position + rot @ geom.center)
    return geom, _transform(rot, shape.position)


def _load(urdf_name: str, srdf: bool):
    share, panda = description_dir()
    urdf = str(panda / "urdf" / urdf_name)
    full = pin.buildModelFromUrdf(urdf)
    geom = pin.buildGeomFromUrdf(full, urdf, pin.GeometryType.COLLISION, package_dirs=[str(share)])
    q_ref = pin.neutral(full)
    fingers = [full.getJointId(f"panda_finger_joint{i}") for i in (1, 2)]
    for j in fingers:
        q_ref[full.joints[j].idx_q] = FINGER_OPENING
    model, geom = pin.buildReducedModel(full, geom, fingers, q_ref)
    if srdf:
        geom.addAllCollisionPairs()
        pin.removeCollisionPairs(model, geom, str(panda / "srdf" / "panda.srdf"))
    return model, geom


def _disabled_link_pairs() -> set[frozenset[str]]:
    """Link pairs the SRDF disables (never in contact, or always adjacent)."""
    import xml.etree.ElementTree as ET

    _, panda = description_dir()
    root = ET.parse(panda / "srdf" / "panda.srdf").getroot()
    return {frozenset((e.get("link1"), e.get("link2"))) for e in root.iter("disable_collisions")}


class _SphereModel:
    """The fast model as spheres in joint frames, with vectorised batch forward kinematics."""

    def __init__(self, model: pin.Model, geom: pin.GeometryModel, inflate: float) -> None:
        centers, radii, joints, links = [], [], [], []
        for obj in geom.geometryObjects:
            g, m = obj.geometry, obj.placement
            link = model.frames[obj.parentFrame].name
            if isinstance(g, coal.Sphere):
                local = [m.translation]
                r = g.radius
            elif isinstance(g, coal.Cylinder):
                n = max(2, math.ceil(2 * g.halfLength / SPHERE_SPACING) + 1)
                zs = np.linspace(-g.halfLength, g.halfLength, n)
                step = zs[1] - zs[0]
                local = [m.act(np.array([0.0, 0.0, z])) for z in zs]
                r = math.hypot(g.radius, 0.5 * step)
            else:
                raise ValueError(f"fast model: unsupported geometry {type(g).__name__}")
            for c in local:
                centers.append(c)
                radii.append(r + inflate)
                joints.append(obj.parentJoint)
                links.append(link)
        self.centers = np.array(centers)
        self.radii = np.array(radii)
        self.joints = np.array(joints)
        self.links = links
        self.placements = [(model.jointPlacements[j].rotation.copy(),
                            model.jointPlacements[j].translation.copy())
                           for j in range(1, model.njoints)]
        disabled = _disabled_link_pairs()
        pairs = [(a, b) for a in range(len(links)) for b in range(a + 1, len(links))
                 if links[a] != links[b] and frozenset((links[a], links[b])) not in disabled
                 and abs(int(self.joints[a]) - int(self.joints[b])) > 1]
        self.pair_a = np.array([p[0] for p in pairs], int)
        self.pair_b = np.array([p[1] for p in pairs], int)
        self._by_joint = [np.flatnonzero(self.joints == j) for j in range(model.njoints)]
        # the same model as contiguous arrays for the compiled kernels
        self.kernel_args = (np.ascontiguousarray([r for r, _ in self.placements]),
                            np.ascontiguousarray([p for _, p in self.placements]),
                            self.joints.astype(np.int64), np.ascontiguousarray(self.centers),
                            np.ascontiguousarray(self.radii))

    def world_centers(self, Q: np.ndarray) -> np.ndarray:
        """Sphere centres (N, S, 3) for configurations (N, 7); every Panda joint turns about
        its local z axis, so the chain is a product of fixed placements and z rotations."""
        n = len(Q)
        rot = np.broadcast_to(np.eye(3), (n, 3, 3))
        pos = np.zeros((n, 3))
        out = np.empty((n, len(self.centers), 3))
        self._place(out, 0, rot, pos)
        cos, sin = np.cos(Q), np.sin(Q)
        for i, (m_rot, m_pos) in enumerate(self.placements):
            pos = pos + rot @ m_pos
            rm = rot @ m_rot
            c, s = cos[:, i, None], sin[:, i, None]
            rot = np.stack([rm[:, :, 0] * c + rm[:, :, 1] * s,
                            rm[:, :, 1] * c - rm[:, :, 0] * s, rm[:, :, 2]], axis=2)
            self._place(out, i + 1, rot, pos)
        return out

    def _place(self, out: np.ndarray, joint: int, rot: np.ndarray, pos: np.ndarray) -> None:
        idx = self._by_joint[joint]
        if len(idx):
            out[:, idx] = pos[:, None, :] + np.matmul(rot, self.centers[idx].T).transpose(0, 2, 1)


def _signed_distance(points: np.ndarray, shape: Shape) -> np.ndarray:
    """Signed distance from points (..., 3) to a shape (negative inside)."""
    if shape.kind == "sphere":
        return np.linalg.norm(points - shape.position, axis=-1) - shape.size[0]
    if shape.kind == "points":
        rot = shape.rotation()
        world = shape.position + shape.points @ rot.T
        if len(world) == 1:
            return np.linalg.norm(points - world[0], axis=-1)
        center = world.mean(axis=0)  # conservative: the point set's bounding sphere
        radius = np.max(np.linalg.norm(world - center, axis=1))
        return np.linalg.norm(points - center, axis=-1) - radius
    local = (points - shape.position) @ shape.rotation()
    if shape.kind == "box":
        excess = np.abs(local) - 0.5 * np.array(shape.size)
        outside = np.linalg.norm(np.maximum(excess, 0.0), axis=-1)
        return outside + np.minimum(excess.max(axis=-1), 0.0)
    radial = np.hypot(local[..., 0], local[..., 1]) - shape.size[0]
    axial = np.abs(local[..., 2]) - 0.5 * shape.size[1]
    outside = np.hypot(np.maximum(radial, 0.0), np.maximum(axial, 0.0))
    return outside + np.minimum(np.maximum(radial, axial), 0.0)


class Robot:
    """Panda kinematics and collision queries on the chosen collision model."""

    def __init__(self, collision: str = "fast", profile: str = "panda") -> None:
        if collision not in ("fast", "mesh"):
            raise ValueError(f"collision model must be 'fast' or 'mesh', got {collision!r}")
        self.collision = collision
        self.limits: JointLimits = joint_limits(profile)
        self.model, self.mesh_geom = _load("panda.urdf", srdf=True)
        self.data = self.model.createData()
        self.mesh_data = pin.GeometryData(self.mesh_geom)
        self.tcp_id = self.model.getFrameId(TCP_FRAME)
        fast_model, fast_geom = _load("panda_collision.urdf", srdf=False)
        self.spheres = _SphereModel(fast_model, fast_geom, FAST_MODEL_MARGIN)
        self._request = coal.DistanceRequest()
        self._request.enable_signed_distance = True
        self._names = [g.name.rsplit("_", 1)[0] for g in self.mesh_geom.geometryObjects]

    # ---- kinematics -------------------------------------------------------------------
    def _check_q(self, q) -> np.ndarray:
        q = np.asarray(q, dtype=float).reshape(-1)
        if q.shape != (7,) or not np.all(np.isfinite(q)):
            raise ValueError(f"a configuration is 7 finite joint angles, got {q.tolist()}")
        return q

    def fk(self, q, frame: str = TCP_FRAME) -> np.ndarray:
        """Homogeneous 4×4 pose of ``frame`` in the base frame."""
        q = self._check_q(q)
        fid = self.tcp_id if frame == TCP_FRAME else self.model.getFrameId(frame)
        if fid >= self.model.nframes:
            raise ValueError(f"unknown frame {frame!r}")
        pin.forwardKinematics(self.model, self.data, q)
        return pin.updateFramePlacement(self.model, self.data, fid).homogeneous.copy()

    def tcp_pose(self, q) -> tuple[np.ndarray, np.ndarray]:
        """TCP position and quaternion ``[x, y, z, w]``."""
        T = self.fk(q)
        return T[:3, 3].copy(), pin.Quaternion(T[:3, :3]).coeffs().copy()

    def ik(self, position, orientation, q_near=None, obstacles: Sequence[Shape] = (),
           min_clearance: float = 0.0, n_seeds: int = 32, rng: np.random.Generator | None = None,
           position_tolerance: float = 1e-3, orientation_tolerance: float = 1e-2,
           max_solutions: int = 4) -> IKResult:
        """Joint angles that put the TCP at a pose, within limits, out of self-collision and at
        least ``min_clearance`` from ``obstacles``; the valid solution nearest ``q_near``."""
        position = np.asarray(position, float).reshape(3)
        quat = np.asarray(orientation, float).reshape(4)
        if not (np.all(np.isfinite(position)) and np.all(np.isfinite(quat))):
            return IKResult(False, None, "goal pose holds NaN or inf")
        norm = float(np.linalg.norm(quat))
        if abs(norm - 1.0) > 1e-3:
            return IKResult(False, None,
                            f"goal orientation is not a unit quaternion (norm {norm:.4f})")
        reach = float(np.linalg.norm(position - SHOULDER))
        if reach > REACH:
            return IKResult(False, None, f"position is {reach:.3f} m from the shoulder, beyond the "
                            f"Panda's reach of {REACH:.3f} m")
        target = pin.SE3(pin.Quaternion(quat[3], *quat[:3]).normalized().matrix(), position)
        rng = rng or np.random.default_rng(0)
        q_near = READY if q_near is None else self._check_q(q_near)
        seeds = [q_near] + [rng.uniform(self.limits.lower, self.limits.upper)
                            for _ in range(n_seeds - 1)]
        found, blocked, best_err = [], 0, (math.inf, math.inf)
        for seed in seeds:
            q, err_p, err_o = self._solve(target, seed)
            if err_p > position_tolerance or err_o > orientation_tolerance:
                best_err = min(best_err, (err_p, err_o))
                continue
            if self.self_collision(q) or (
                    obstacles and self.clearance(q, obstacles).distance < min_clearance):
                blocked += 1
                continue
            found.append((float(np.linalg.norm(q - q_near)), q, err_p, err_o))
            if len(found) >= max_solutions or (len(found) == 1 and seed is seeds[0]):
                break  # the solution reached from q_near itself is the nearest one we want
        if not found:
            if blocked:
                return IKResult(False, None, f"all {blocked} IK solutions collide with obstacles "
                                "or the robot itself")
            return IKResult(False, None, "no IK solution within "
                            f"{position_tolerance * 1e3:.1f} mm / {orientation_tolerance:.3f} rad "
                            f"from {len(seeds)} seeds "
                            f"(best {best_err[0] * 1e3:.1f} mm, {best_err[1]:.3f} rad)")
        _, q, err_p, err_o = min(found, key=lambda f: f[0])
        return IKResult(True, q, "", err_p, err_o)

    def _solve(self, target: pin.SE3, seed: np.ndarray, iterations: int = 80,
               damping: float = 1e-6) -> tuple[np.ndarray, float, float]:
        """Damped least squares on the SE(3) log error, clamped to the joint limits; gives up
        on a seed as soon as the error stops shrinking (a local minimum or a limit)."""
        q = seed.copy()
        lower, upper = self.limits.lower, self.limits.upper
        eye = damping * np.eye(6)
        best, stalled = math.inf, 0
        for _ in range(iterations):
            pin.forwardKinematics(self.model, self.data, q)
            current = pin.updateFramePlacement(self.model, self.data, self.tcp_id)
            err = pin.log6(current.actInv(target)).vector
            norm = float(err @ err)
            if norm < 1e-12:
                break
            stalled = stalled + 1 if norm > 0.81 * best else 0
            best = min(best, norm)
            if stalled >= 8:
                break
            J = pin.computeFrameJacobian(self.model, self.data, q, self.tcp_id, pin.LOCAL)
            q = np.clip(q + J.T @ np.linalg.solve(J @ J.T + eye, err), lower, upper)
        pin.forwardKinematics(self.model, self.data, q)
        current = pin.updateFramePlacement(self.model, self.data, self.tcp_id)
        err = pin.log6(current.actInv(target)).vector
        return q, float(np.linalg.norm(target.translation - current.translation)), float(
            np.linalg.norm(err[3:]))

    # ---- collision --------------------------------------------------------------------
    def clearance(self, q, obstacles: Sequence[Shape]) -> Clearance:
        """Exact minimum distance to the obstacles with witness points (coal GJK/EPA)."""
        q = self._check_q(q)
        if not obstacles:
            return Clearance(math.inf, np.zeros(3), np.zeros(3), "", -1)
        if self.collision == "fast":
            return self._fast_clearance(q, obstacles)
        pin.updateGeometryPlacements(self.model, self.data, self.mesh_geom, self.mesh_data, q)
        best = None
        for k, shape in enumerate(obstacles):
            geom, tf = _obstacle_object(shape)
            for i, obj in enumerate(self.mesh_geom.geometryObjects):
                placement = self.mesh_data.oMg[i]
                result = coal.DistanceResult()
                d = coal.distance(obj.geometry, _transform(placement.rotation,
                                                           placement.translation),
                                  geom, tf, self._request, result)
                if best is None or d < best[0]:
                    best = (d, result.getNearestPoint1().copy(), result.getNearestPoint2().copy(),
                            self._names[i], k)
        return Clearance(float(best[0]), best[1], best[2], best[3], best[4])

    def _fast_clearance(self, q: np.ndarray, obstacles: Sequence[Shape]) -> Clearance:
        centers = self.spheres.world_centers(q[None])[0]
        best = None
        for k, shape in enumerate(obstacles):
            d = _signed_distance(centers, shape) - self.spheres.radii
            i = int(np.argmin(d))
            if best is None or d[i] < best[0]:
                best = (float(d[i]), i, k)
        d, i, k = best
        c = centers[i]
        # witness on the obstacle: step from the sphere centre toward the obstacle surface
        grad = np.array([_signed_distance(c + h, obstacles[k]) - _signed_distance(c - h,
                         obstacles[k]) for h in np.eye(3) * 1e-6]) / 2e-6
        n = grad / max(np.linalg.norm(grad), 1e-12)
        surface = c - n * _signed_distance(c, obstacles[k])
        return Clearance(d, c - n * self.spheres.radii[i], surface, self.spheres.links[i], k)

    def distances(self, Q: np.ndarray, obstacles: Sequence[Shape]) -> np.ndarray:
        """Minimum distance for each configuration of a batch (N, 7)."""
        Q = np.atleast_2d(np.asarray(Q, float))
        if not obstacles:
            return np.full(len(Q), math.inf)
        if self.collision == "mesh":
            return np.array([self.clearance(q, obstacles).distance for q in Q])
        return fast_collision.batch_distances(Q, *self.spheres.kernel_args,
                                              *fast_collision.pack_obstacles(obstacles))

    def in_collision(self, q, obstacles: Sequence[Shape], margin: float = 0.0) -> bool:
        return bool(self.distances(self._check_q(q)[None], obstacles)[0] <= margin)

    def self_collision(self, q) -> bool:
        """Self-collision of the exact meshes, ignoring the SRDF's disabled pairs."""
        q = self._check_q(q)
        return bool(pin.computeCollisions(self.model, self.data, self.mesh_geom, self.mesh_data,
                                          q, True))

    def self_collision_fast(self, Q: np.ndarray) -> np.ndarray:
        """Conservative self-collision of the sphere model for a batch (N, 7)."""
        c = self.spheres.world_centers(np.atleast_2d(Q))
        a, b = self.spheres.pair_a, self.spheres.pair_b
        gap = np.linalg.norm(c[:, a] - c[:, b], axis=-1) - (self.spheres.radii[a]
                                                             + self.spheres.radii[b])
        return (gap <= -2 * FAST_MODEL_MARGIN).any(axis=1)

    def segment_free(self, q0, q1, obstacles: Sequence[Shape], margin: float = 0.0,
                     resolution: float = 0.02) -> bool:
        """True when every state on the straight joint-space segment, sampled at most
        ``resolution`` rad apart (max norm), keeps ``margin`` from every obstacle."""
        q0, q1 = np.asarray(q0, float), np.asarray(q1, float)
        n = max(1, math.ceil(float(np.max(np.abs(q1 - q0))) / resolution))
        if not obstacles:
            return True
        if self.collision == "mesh":
            Q = q0 + np.linspace(0.0, 1.0, n + 1)[:, None] * (q1 - q0)
            return bool(np.all(self.distances(Q, obstacles) > margin))
        return bool(fast_collision.segment_clear(q0, q1, n, margin, *self.spheres.kernel_args,
                                                 *fast_collision.pack_obstacles(obstacles)))

    def segment_self_collision_free(self, q0, q1, resolution: float = 0.1) -> bool:
        """No self-collision of the exact meshes along a straight segment, sampled at most
        ``resolution`` rad apart (the SRDF's disabled pairs ignored)."""
        q0, q1 = np.asarray(q0, float), np.asarray(q1, float)
        n = max(1, math.ceil(float(np.max(np.abs(q1 - q0))) / resolution))
        return not any(self.self_collision(q0 + s * (q1 - q0))
                       for s in np.linspace(0.0, 1.0, n + 1))
