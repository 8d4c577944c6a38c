"""The Franka Panda facade: kinematics (pinocchio), IK, and robot↔obstacle distances.

:class:`Robot` answers every question the planner, the tools and the tests ask of the arm
(FK, IK, clearance, batched distances, segment and self-collision checks) on one of the two
collision models of :mod:`damon_ros.core.collision`: ``mesh`` (exact, coal GJK/EPA on the
convex meshes) or ``fast`` (the inflated sphere model, conservative: "fast says free"
implies "meshes say free"). The model itself is loaded by :mod:`damon_ros.core.kinematics`.
Joint limits come from :mod:`damon_ros.core.limits`; the kinematics are the Panda's for both
limit profiles. No rclpy here.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import coal
import numpy as np
import pinocchio as pin

from damon_ros.core.collision import (
    FAST_MODEL_MARGIN,
    Sdf,
    SphereModel,
    convex_meshes,
    link_name,
    local_vertices,
    obstacle_geometry,
)
from damon_ros.core.kinematics import FINGER_OPENING, TCP_FRAME, Chain, load_arm
from damon_ros.core.limits import IK_LIMIT_MARGIN, READY, JointLimits, joint_limits
from damon_ros.core.self_collision import SelfCollisionScreen
from damon_ros.core.shapes import Shape

SELF_FREE_KEPT = 4096
"""Segments whose self-collision answer `Robot.segment_self_collision_free` keeps."""


def _history_free(data: pin.GeometryData) -> pin.GeometryData:
    """``data`` with GJK's warm start from the previous query switched off for every pair:
    with it, a state whose meshes nearly touch got either answer depending on which state
    the pair was asked about before, and a collected chunk depended on the chunks its worker
    had made before it (seen once the link-box screen left most states unasked). ~20 µs a
    query instead of ~16."""
    with warnings.catch_warnings():  # coal deprecates the flag, but has no other switch yet
        warnings.simplefilter("ignore", DeprecationWarning)
        for request in data.collisionRequests:
            request.enable_cached_gjk_guess = False
    return data


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
    SRDF's disabled pairs). ``profile`` picks the joint limits (``"panda"`` or ``"fr3"``);
    ``finger_opening`` where each finger is locked (m, both models). ``exact_budget`` caps
    the mesh queries one fast segment check may spend on states the spheres refuse by less
    than their own excess (:meth:`_exact_band`; 0 turns it off)."""

    def __init__(self, collision: str = "fast", profile: str = "panda",
                 fast_margin: float = FAST_MODEL_MARGIN,
                 finger_opening: float = FINGER_OPENING, exact_budget: int = 64) -> None:
        if collision not in ("fast", "mesh"):
            raise ValueError(f"collision model must be 'fast' or 'mesh', got {collision!r}")
        if not 0.0 <= fast_margin < 0.1:
            raise ValueError(f"fast_margin must be in [0, 0.1) m, got {fast_margin}")
        self.collision = collision
        self.limits: JointLimits = joint_limits(profile)
        if not 0.0 <= finger_opening <= 0.1:
            raise ValueError(f"finger_opening must be in [0, 0.1] m, got {finger_opening}")
        self.finger_opening = finger_opening
        model, mesh_geom = load_arm("panda.urdf", finger_opening)
        self.model, self.data = model, model.createData()
        self.mesh_geom = convex_meshes(model, mesh_geom)
        self.mesh_data = _history_free(pin.GeometryData(self.mesh_geom))
        self._self_screen = SelfCollisionScreen(model, self.mesh_geom)
        self._mesh_links = [link_name(model, o) for o in self.mesh_geom.geometryObjects]
        self._mesh_bounds()
        self.tcp_id = model.getFrameId(TCP_FRAME)
        if self.tcp_id >= model.nframes:
            raise ValueError(f"the Panda description has no {TCP_FRAME} frame")
        self.fast_margin = fast_margin
        self.exact_budget = exact_budget
        self.shoulder, self.reach = _reach_bound(model, self.tcp_id)
        self._request = coal.DistanceRequest()
        self._request.enable_signed_distance = True
        self._self_free: dict[tuple[bytes, bytes, float], bool] = {}  # segment_self_…

    @cached_property
    def spheres(self) -> SphereModel:
        """The fast model, built on first use (a mesh-only robot never needs it): the sphere
        set fitted to the meshes (``config/panda_spheres.json``), grown by ``fast_margin``,
        its finger spheres moved to ``finger_opening``."""
        return SphereModel.fitted(self.fast_margin, finger_opening=self.finger_opening)

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

    @cached_property
    def _tcp_chain(self) -> tuple[Chain, np.ndarray]:
        """Batched FK of this model and the block placing its TCP, built on first use."""
        chain = Chain(self.model)
        return chain, chain.frame_block([TCP_FRAME])

    def tcp_positions(self, Q) -> np.ndarray:
        """TCP positions (N, 3) of configurations Q (N, 7), batched: the planner places its
        20k graph vertices at start-up (one `tcp_pose` each took ~0.9 s)."""
        chain, block = self._tcp_chain
        return chain.positions(self._check_batch(Q), block)[:, 0]

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
           max_solutions: int = 3, time_budget_s: float | None = None,
           avoid: np.ndarray | None = None, avoid_rad: float = 0.3) -> IKResult:
        """Joint angles that put the TCP at a pose (``orientation`` is ``[x, y, z, w]``),
        within the joint limits, out of self-collision and at least ``min_clearance`` from
        ``obstacles`` (on this robot's collision model).

        The seed ``q_near`` (default: the ready pose) is tried first; if it converges to a
        valid solution that one is returned at once, because Newton steps from ``q_near``
        reach the nearby solution with the least joint motion. Otherwise random seeds are
        tried until ``max_solutions`` valid ones are found (or ``n_seeds`` / the time
        budget run out) and the one nearest ``q_near`` is returned. ``avoid``: a solution
        within ``avoid_rad`` of it in every joint does not count (another solution of the
        same pose is wanted: `GraphPlanner.resolve_goal`)."""
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
            if avoid is not None and float(np.max(np.abs(q - avoid))) < avoid_rad:
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

    def mesh_distance(self, q: np.ndarray, geometry: tuple, position: np.ndarray,
                      bound: float) -> float:
        """The distance of :meth:`clearance` on the meshes (the same coal calls, so the same
        number to the bit) to one obstacle prepared once by :func:`obstacle_geometry`
        (``geometry``), centred at ``position`` within ``bound`` of it; without witness
        points or input checks: the collector labels millions of (q, obstacle) pairs and
        these were a third of its time."""
        pin.updateGeometryPlacements(self.model, self.data, self.mesh_geom, self.mesh_data, q)
        oMg, oMi = self.mesh_data.oMg, self.data.oMi
        joints = np.hstack([oMi[j].homogeneous[:3] for j in range(8)])
        centers = (joints @ self._mesh_block).T
        objs = self.mesh_geom.geometryObjects
        geom, tf = geometry
        lower = np.linalg.norm(centers - position, axis=1) - self._mesh_radii - bound
        best = math.inf
        for i in map(int, np.argsort(lower)):
            if lower[i] >= best:
                break
            d = coal.distance(objs[i].geometry, coal.Transform3s(oMg[i].rotation,
                                                                 oMg[i].translation),
                              geom, tf, self._request, coal.DistanceResult())
            best = min(best, d)
        return float(best)

    def _fast_clearance(self, q: np.ndarray, obstacles: Sequence[Shape]) -> Clearance:
        """The nearest pair from the kernels, witness points from that pair alone."""
        distance, i, k = self.spheres.closest(q, obstacles)
        if i < 0:  # no finite distance (NaN or infinite obstacles)
            return Clearance(distance, np.zeros(3), np.zeros(3), "", -1)
        center, radius = self.spheres.world_centers(q[None])[0, i], self.spheres.radii[i]
        surface = Sdf(obstacles[k]).closest_point(center)
        away = center - surface
        inside = distance + radius < 0.0
        u = (-away if inside else away) / max(float(np.linalg.norm(away)), 1e-12)
        return Clearance(distance, center - u * radius, surface, self.spheres.links[i], k)

    def distances(self, Q, obstacles: Sequence[Shape]) -> np.ndarray:
        """Minimum signed distance to the obstacles for each configuration of (N, 7)."""
        Q = self._check_batch(Q)
        if not obstacles:
            return np.full(len(Q), math.inf)
        if self.collision == "mesh":
            return np.array([self._mesh_clearance(q, obstacles).distance for q in Q])
        return self.spheres.distances(Q, obstacles)

    def in_collision(self, q, obstacles: Sequence[Shape], margin: float = 0.0) -> bool:
        """True when the robot comes within ``margin`` of an obstacle (touching counts); on
        the meshes the decision alone (`_mesh_keeps`), not a whole clearance."""
        q = self._check_q(q)
        if self.collision == "mesh":
            return bool(obstacles) and not self._mesh_keeps(q, obstacles, margin)
        return bool(self.distances(q[None], obstacles)[0] <= margin)

    # ---- self-collision ---------------------------------------------------------------
    def self_collision(self, q, checked: bool = True) -> bool:
        """Exact self-collision of the meshes, ignoring the SRDF's disabled pairs (adjacent
        links and pairs that can never touch). ``checked=False`` skips the input check for
        callers that made ``q`` themselves (the collector, a million times). A state whose
        links' boxes keep apart (`SelfCollisionScreen`) is free without the meshes."""
        q = self._check_q(q) if checked else q
        if self._self_screen.clear(q[None])[0]:
            return False
        return self._mesh_self_collision(q)

    def _mesh_self_collision(self, q: np.ndarray) -> bool:
        return bool(pin.computeCollisions(self.model, self.data, self.mesh_geom, self.mesh_data,
                                          q, True))

    # ---- segments ---------------------------------------------------------------------
    @staticmethod
    def steps(q0: np.ndarray, q1: np.ndarray, resolution: float) -> int:
        """Number of intervals that keep every joint step at most ``resolution`` rad."""
        if not resolution > 0.0:
            raise ValueError(f"resolution must be positive, got {resolution}")
        return max(1, math.ceil(float(np.max(np.abs(q1 - q0))) / resolution))

    def state_free(self, q: np.ndarray, obstacles: Sequence[Shape], margin: float = 0.0) -> bool:
        """One state keeps more than ``margin`` from every obstacle: a sampling planner's
        validity check. The fast model stops at the first sphere within the margin instead of
        computing the whole distance; a refusal inside its contact band goes to the meshes."""
        if not obstacles:
            return True
        if self.collision == "mesh":
            return self._mesh_clearance(q, obstacles).distance > margin
        return self.spheres.segment_clear(q, q, 0, obstacles, margin) or \
            self._exact_band(q[None], obstacles, margin)

    def segment_free(self, q0, q1, obstacles: Sequence[Shape], margin: float = 0.0,
                     resolution: float = 0.02, exact_band: bool = True) -> bool:
        """True when every state on the straight joint-space segment, sampled at most
        ``resolution`` rad apart (max norm, ends included), keeps more than ``margin`` from
        every obstacle. Self-collision is separate (:meth:`segment_self_collision_free`).
        ``exact_band`` False: the fast model's refusal is final (no mesh queries), for
        optional improvements such as shortcuts, where a refusal costs nothing."""
        q0, q1 = self._check_q(q0), self._check_q(q1)
        n = self.steps(q0, q1, resolution)
        if not obstacles:
            return True
        if self.collision == "mesh":
            Q = q0 + np.linspace(0.0, 1.0, n + 1)[:, None] * (q1 - q0)
            return all(self._mesh_clearance(q, obstacles).distance > margin for q in Q)
        if self.spheres.segment_clear(q0, q1, n, obstacles, margin):
            return True
        if not exact_band:
            return False
        return self._exact_band(q0 + np.linspace(0.0, 1.0, n + 1)[:, None] * (q1 - q0),
                                obstacles, margin)

    @property
    def contact_band(self) -> float:
        """How far (m) the fast model can under-state the mesh distance: its fit bound (the
        largest bulge of a sphere beyond the meshes) plus its margin. A fast refusal by less
        than this may be wrong, so :meth:`_exact_band` lets the meshes decide it."""
        bulge = self.spheres.bulge
        return 0.0 if bulge is None else float(np.max(bulge) + self.fast_margin) + 1e-4

    def _exact_band(self, Q: np.ndarray, obstacles: Sequence[Shape], margin: float) -> bool:
        """Exact decisions near contact: states the fast model refuses by less than
        :attr:`contact_band` are decided by the meshes (coal), each must keep more than
        ``margin`` there. A state refused by more is refused outright, and at most
        :attr:`exact_budget` mesh queries are spent per call (beyond that: refused), so the
        mesh query only runs in that thin band."""
        if self.exact_budget <= 0:
            return False
        near = self.spheres.band_states(Q, obstacles, margin, margin - self.contact_band,
                                        self.exact_budget)
        return near is not None and all(self._mesh_keeps(Q[i], obstacles, margin)
                                        for i in near)

    def _mesh_keeps(self, q: np.ndarray, obstacles: Sequence[Shape], margin: float) -> bool:
        """Every mesh keeps more than ``margin`` from every obstacle: the decision alone, so
        only mesh–obstacle pairs whose bounding spheres come within the margin are measured,
        and the first pair inside it ends the query (a whole clearance among MotionBenchMaker's
        21 shapes cost 2.4 ms a state)."""
        pin.updateGeometryPlacements(self.model, self.data, self.mesh_geom, self.mesh_data, q)
        oMg, oMi = self.mesh_data.oMg, self.data.oMi
        joints = np.hstack([oMi[j].homogeneous[:3] for j in range(8)])
        centers = (joints @ self._mesh_block).T
        objs = self.mesh_geom.geometryObjects
        for shape in obstacles:
            lower = (np.linalg.norm(centers - shape.position, axis=1) - self._mesh_radii
                     - shape.bounding_radius())
            near = np.flatnonzero(lower <= margin)
            if not len(near):
                continue
            geom, tf = obstacle_geometry(shape)
            for i in map(int, near):
                d = coal.distance(objs[i].geometry, coal.Transform3s(oMg[i].rotation,
                                                                     oMg[i].translation),
                                  geom, tf, self._request, coal.DistanceResult())
                if d <= margin:
                    return False
        return True

    def path_free(self, path, obstacles: Sequence[Shape], margin: float = 0.0,
                  resolution: float = 0.02) -> bool:
        """:meth:`segment_free` for every segment of a (K, 7) waypoint path."""
        path = self._check_batch(path)
        if len(path) == 1:
            if not obstacles or bool(self.distances(path, obstacles)[0] > margin):
                return True
            return self.collision == "fast" and self._exact_band(path, obstacles, margin)
        return all(self.segment_free(a, b, obstacles, margin, resolution)
                   for a, b in zip(path[:-1], path[1:], strict=True))

    def segment_self_collision_free(self, q0, q1, resolution: float = 0.1) -> bool:
        """No self-collision of the exact meshes along a straight segment, sampled at most
        ``resolution`` rad apart (the SRDF's disabled pairs ignored). The answers for the
        last SELF_FREE_KEPT segments are kept: it depends on the arm alone, and a planner
        re-certifies the same segments (a stored route, a path's re-check) at every
        re-plan, ~60 us a state on the meshes."""
        q0, q1 = self._check_q(q0), self._check_q(q1)
        key = (q0.tobytes(), q1.tobytes(), float(resolution))
        known = self._self_free.get(key)
        if known is None:
            n = self.steps(q0, q1, resolution)
            Q = q0 + np.linspace(0.0, 1.0, n + 1)[:, None] * (q1 - q0)
            # the meshes only where the links' boxes meet (`SelfCollisionScreen`)
            known = not any(self._mesh_self_collision(q)
                            for q in Q[~self._self_screen.clear(Q)])
            if len(self._self_free) >= SELF_FREE_KEPT:
                self._self_free.clear()
            self._self_free[key] = known
        return known
