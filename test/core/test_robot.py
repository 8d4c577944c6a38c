"""The Panda model: FK against Franka's DH table, IK, exact distances, the conservative fast
model, self-collision with the SRDF, segment checks and the micro-benchmark."""

from __future__ import annotations

import math

import coal
import numpy as np
import pinocchio as pin
import pytest

from damon_ros.core.collision import (
    FAST_MODEL_MARGIN,
    Sdf,
    disabled_link_pairs,
    obstacle_geometry,
    signed_distance,
    surface_points,
)
from damon_ros.core.kinematics import Chain, load_arm, pose_error
from damon_ros.core.limits import READY, joint_limits
from damon_ros.core.robot import Robot
from damon_ros.core.shapes import Shape, point
from damon_ros.tools import bench_robot

# Franka's published modified (Craig) DH parameters: (a, d, alpha) per joint, then the flange.
DH = [(0.0, 0.333, 0.0), (0.0, 0.0, -math.pi / 2), (0.0, 0.316, math.pi / 2),
      (0.0825, 0.0, math.pi / 2), (-0.0825, 0.384, -math.pi / 2), (0.0, 0.0, math.pi / 2),
      (0.088, 0.0, math.pi / 2)]


def _craig(a: float, d: float, alpha: float, theta: float) -> np.ndarray:
    ca, sa, ct, st = math.cos(alpha), math.sin(alpha), math.cos(theta), math.sin(theta)
    return np.array([[ct, -st, 0, a], [st * ca, ct * ca, -sa, -d * sa],
                     [st * sa, ct * sa, ca, d * ca], [0, 0, 0, 1]])


def dh_tcp(q: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    for (a, d, alpha), theta in zip(DH, q, strict=True):
        T = T @ _craig(a, d, alpha, theta)
    T = T @ _craig(0.0, 0.107, 0.0, 0.0)  # flange
    T = T @ _craig(0.0, 0.0, 0.0, -math.pi / 4)  # hand mounted at -45° about z
    return T @ _craig(0.0, 0.1034, 0.0, 0.0)  # TCP between the fingertips


def _random_free(robot: Robot, rng, n: int) -> list[np.ndarray]:
    out = []
    while len(out) < n:
        q = rng.uniform(robot.limits.lower, robot.limits.upper)
        if not robot.self_collision(q):
            out.append(q)
    return out


# ---- kinematics ---------------------------------------------------------------------------
def test_limits_profiles():
    panda, fr3 = joint_limits("panda"), joint_limits("fr3", prefix="fr3_")
    assert panda.names[0] == "panda_joint1" and fr3.names[6] == "fr3_joint7"
    assert np.allclose(panda.velocity, [2.175] * 4 + [2.61] * 3)
    assert not np.allclose(fr3.velocity, panda.velocity)
    assert Robot("mesh", profile="fr3").limits.profile == "fr3"
    with pytest.raises(ValueError, match="unknown limit profile"):
        Robot(profile="ur5")


def test_fk_matches_franka_dh_table(mesh):
    rng = np.random.default_rng(0)
    for _ in range(100):
        q = rng.uniform(mesh.limits.lower, mesh.limits.upper)
        T, ref = mesh.fk(q), dh_tcp(q)
        assert np.allclose(T[:3, 3], ref[:3, 3], atol=1e-6)
        assert np.allclose(T[:3, :3], ref[:3, :3], atol=1e-6)
        position, quat = mesh.tcp_pose(q)
        assert np.allclose(position, ref[:3, 3], atol=1e-6)
        assert np.isclose(np.linalg.norm(quat), 1.0)


def test_frame_positions_and_batched_chain_agree_with_pinocchio(fast):
    rng = np.random.default_rng(5)
    Q = rng.uniform(fast.limits.lower, fast.limits.upper, (8, 7))
    frames = fast.frame_positions(Q[0])
    assert np.allclose(frames["panda_link0"], 0.0)
    assert np.allclose(frames["panda_hand_tcp"], fast.fk(Q[0])[:3, 3])
    centers = fast.spheres.world_centers(Q)  # numpy batch chain
    for q, c in zip(Q, centers, strict=True):
        assert np.allclose(fast.spheres.world_centers(q[None])[0], c, atol=1e-12)  # pinocchio


@pytest.mark.parametrize("urdf", ["panda.urdf", "panda_collision.urdf"])
def test_batched_chain_equals_pinocchio_fk(urdf):
    """The one batched FK (collision spheres, mesh bounds, the collector's arm skeleton) gives
    pinocchio's joint poses and frame positions, for batches and single configurations."""
    model, _ = load_arm(urdf)
    data, chain = model.createData(), Chain(model)
    frames = [f"panda_link{i}" for i in range(2, 9)] + ["panda_hand", "panda_hand_tcp"]
    block = chain.frame_block(frames)
    Q = np.random.default_rng(9).uniform(-2.9, 2.9, (64, 7))
    for Qb in (Q, Q[:1]):
        T = chain.transforms(Qb).reshape(3, len(Qb), 8, 4)
        P = chain.positions(Qb, block)
        for n, q in enumerate(Qb):
            pin.forwardKinematics(model, data, q)
            pin.updateFramePlacements(model, data)
            for j in range(8):
                assert np.allclose(T[:, n, j], data.oMi[j].homogeneous[:3], atol=1e-12)
            want = [data.oMf[model.getFrameId(f)].translation for f in frames]
            assert np.allclose(P[n], want, atol=1e-12)


def test_bad_input_raises_value_error_naming_the_problem(mesh):
    with pytest.raises(ValueError, match="unknown frame"):
        mesh.fk(READY, "no_such_frame")
    with pytest.raises(ValueError, match="7 finite"):
        mesh.fk([0.0] * 6)
    with pytest.raises(ValueError, match="7 finite"):
        mesh.clearance([math.nan] * 7, [])
    with pytest.raises(ValueError, match=r"\(N, 7\)"):
        mesh.distances(np.zeros((3, 6)), [point([0.5, 0, 0.5])])
    with pytest.raises(ValueError, match="resolution"):
        mesh.segment_free(READY, READY, [], resolution=0.0)
    with pytest.raises(ValueError, match="collision model"):
        Robot("exact")
    with pytest.raises(ValueError, match="fast_margin"):
        Robot(fast_margin=-0.01)


# ---- inverse kinematics -------------------------------------------------------------------
def _check_solution(robot: Robot, result, position, quat) -> None:
    p, o = robot.tcp_pose(result.q)
    p_err, o_err = pose_error(p, o, position, quat)
    assert p_err <= 1e-3 and o_err <= 0.01
    assert robot.limits.within(result.q) and not robot.self_collision(result.q)


def test_ik_reaches_99_percent_of_random_reachable_poses_cold(fast):
    """No seed near the answer: the ready pose first, then random seeds."""
    rng = np.random.default_rng(1)
    reached = 0
    for q in _random_free(fast, rng, 200):
        position, quat = fast.tcp_pose(q)
        result = fast.ik(position, quat, rng=rng)
        if result.success:
            _check_solution(fast, result, position, quat)
            reached += 1
    assert reached >= 198


def test_ik_with_a_warm_seed_returns_the_nearby_solution(fast):
    rng = np.random.default_rng(2)
    for q in _random_free(fast, rng, 50):
        position, quat = fast.tcp_pose(q)
        seed = fast.limits.clip(q + rng.normal(scale=0.05, size=7))
        result = fast.ik(position, quat, q_near=seed)
        assert result.success, result.reason
        _check_solution(fast, result, position, quat)
        assert result.seeds_tried == 1
        assert np.max(np.abs(result.q - seed)) < 0.5  # the same branch, not a far one
    position, quat = fast.tcp_pose(READY)
    result = fast.ik(position, quat, q_near=READY)
    assert result.success and np.linalg.norm(result.q - READY) < 1e-3


def test_ik_works_under_the_fr3_limits():
    fr3 = Robot("fast", profile="fr3")
    rng = np.random.default_rng(3)
    q = fr3.limits.clip(rng.uniform(fr3.limits.lower, fr3.limits.upper))
    position, quat = fr3.tcp_pose(q)
    result = fr3.ik(position, quat, rng=rng)
    assert result.success and fr3.limits.within(result.q)


def test_ik_says_clearly_when_a_pose_is_unreachable(fast):
    result = fast.ik([1.5, 0.0, 0.5], [1.0, 0.0, 0.0, 0.0])
    assert not result.success and "beyond the Panda's reach" in result.reason
    assert "1.509 m" in result.reason  # the distance from the shoulder
    result = fast.ik([0.4, 0.0, 0.4], [0.0, 0.0, 0.0, 2.0])
    assert not result.success and "unit quaternion" in result.reason
    result = fast.ik([0.4, math.nan, 0.4], [1.0, 0.0, 0.0, 0.0])
    assert not result.success and "NaN" in result.reason
    # within the reach bound, but the flange would have to sit inside the base column
    result = fast.ik([0.0, 0.0, 0.05], [1.0, 0.0, 0.0, 0.0], n_seeds=8,
                     rng=np.random.default_rng(0))
    assert not result.success and result.q is None
    assert "no IK solution" in result.reason or "collide" in result.reason


def test_ik_respects_minimum_clearance(fast):
    position, quat = fast.tcp_pose(READY)
    # a ball above the forearm: the ready pose is too close, the elbow must move away
    ball = Shape("sphere", (0.05,), fast.fk(READY, "panda_link4")[:3, 3] + [0.0, 0.0, 0.15])
    assert fast.clearance(READY, [ball]).distance < 0.05
    result = fast.ik(position, quat, q_near=READY, obstacles=[ball], min_clearance=0.05,
                     rng=np.random.default_rng(4))
    assert result.success, result.reason
    _check_solution(fast, result, position, quat)
    assert fast.clearance(result.q, [ball]).distance >= 0.05
    engulf = Shape("sphere", (0.3,), position)  # the TCP itself inside the obstacle
    result = fast.ik(position, quat, q_near=READY, obstacles=[engulf], n_seeds=6)
    assert not result.success and "collide" in result.reason


def test_ik_time_budget_is_honoured(fast):
    position, quat = fast.tcp_pose(READY)
    engulf = Shape("sphere", (0.3,), position)  # no valid solution: every seed is tried
    result = fast.ik(position, quat, obstacles=[engulf], n_seeds=500, time_budget_s=0.005)
    assert not result.success and result.seeds_tried < 500


# ---- distances ----------------------------------------------------------------------------
def test_point_and_sphere_distances_agree_analytically(mesh):
    rng = np.random.default_rng(2)
    checked = 0
    for q in _random_free(mesh, rng, 10):
        c = mesh.fk(q, "panda_link4")[:3, 3] + rng.normal(scale=0.25, size=3)
        d_point = mesh.clearance(q, [point(c)])
        if d_point.distance < 0.08:
            continue
        assert np.allclose(d_point.obstacle_point, c, atol=1e-6)
        d_sphere = mesh.clearance(q, [Shape("sphere", (0.05,), c)])
        assert d_sphere.distance == pytest.approx(d_point.distance - 0.05, abs=1e-4)
        # witness points: on the sphere's surface, as far apart as the distance
        assert np.linalg.norm(d_sphere.obstacle_point - c) == pytest.approx(0.05, abs=1e-4)
        gap = np.linalg.norm(d_sphere.robot_point - d_sphere.obstacle_point)
        assert gap == pytest.approx(d_sphere.distance, abs=1e-4)
        checked += 1
    assert checked >= 3


def test_box_distance_matches_the_face_geometry(mesh):
    tcp = mesh.fk(READY)[:3, 3]
    # a wide thin plate below the gripper: the nearest robot point is the lowest mesh point
    plate = Shape("box", (0.25, 0.25, 0.02), [tcp[0], tcp[1], 0.40])
    c = mesh.clearance(READY, [plate])
    assert c.obstacle_point[2] == pytest.approx(0.41, abs=1e-4)  # on the top face
    assert c.distance == pytest.approx(c.robot_point[2] - 0.41, abs=1e-4)
    assert c.link in ("panda_leftfinger", "panda_rightfinger")
    rotated = Shape("box", (0.25, 0.25, 0.02), [tcp[0], tcp[1], 0.40],
                    [0, 0, 0.3826834, 0.9238795])  # turned about the face normal
    assert mesh.clearance(READY, [rotated]).distance == pytest.approx(c.distance, abs=1e-4)
    inside = Shape("box", (0.3, 0.3, 0.3), tcp)
    assert mesh.clearance(READY, [inside]).distance < 0.0  # penetration is negative


def test_point_sets_are_their_convex_hull(mesh):
    q = READY
    center = mesh.fk(q)[:3, 3] + [0.25, 0.1, 0.0]
    corners = np.array([[x, y, z] for x in (-0.05, 0.05) for y in (-0.1, 0.1)
                        for z in (-0.04, 0.04)])
    box = Shape("box", (0.1, 0.2, 0.08), center)
    cloud = Shape("points", (), center, points=np.vstack([corners, 0.3 * corners]))
    assert mesh.clearance(q, [cloud]).distance == pytest.approx(
        mesh.clearance(q, [box]).distance, abs=1e-6)
    flat = Shape("points", (), center, points=corners[corners[:, 2] > 0])  # one face only
    thin = Shape("box", (0.1, 0.2, 1e-6), center + [0.0, 0.0, 0.04])
    assert mesh.clearance(q, [flat]).distance == pytest.approx(
        mesh.clearance(q, [thin]).distance, abs=1e-5)


def test_numpy_signed_distance_matches_coal_for_every_kind():
    """The fast model's closed-form distances (and witness points) against coal's GJK."""
    rng = np.random.default_rng(6)
    request = coal.DistanceRequest()
    request.enable_signed_distance = True
    shapes = [Shape("sphere", (0.1,), [0.3, 0.1, 0.4]),
              Shape("box", (0.1, 0.2, 0.3), [0.3, -0.2, 0.5], rng.normal(size=4)),
              Shape("cylinder", (0.06, 0.3), [0.4, 0.2, 0.3], rng.normal(size=4))]
    for shape in shapes:
        sdf = Sdf(shape)
        geom, tf = obstacle_geometry(shape)
        P = shape.position + rng.uniform(-0.4, 0.4, (60, 3))
        ours = sdf(P.T)
        for p, d in zip(P, ours, strict=True):
            if d < 0.0:
                continue  # coal's EPA depth is the same quantity, but only for convex pairs
            result = coal.DistanceResult()
            ref = coal.distance(coal.Sphere(1e-9), coal.Transform3s(np.eye(3), p), geom, tf,
                                request, result)
            assert d == pytest.approx(ref, abs=1e-6)
            assert np.allclose(sdf.closest_point(p), result.getNearestPoint2(), atol=1e-5)
        assert np.allclose(signed_distance(P.reshape(6, 10, 3), shape), ours.reshape(6, 10))


def test_fast_distance_is_the_nearest_inflated_sphere(fast):
    """For a point obstacle the fast distance is exactly min over spheres |p - c| - R."""
    rng = np.random.default_rng(7)
    for q in _random_free(fast, rng, 5):
        p = fast.fk(q, "panda_link5")[:3, 3] + rng.normal(scale=0.2, size=3)
        centers = fast.spheres.world_centers(q[None])[0]
        expected = float(np.min(np.linalg.norm(centers - p, axis=1) - fast.spheres.radii))
        c = fast.clearance(q, [point(p)])
        assert c.distance == pytest.approx(expected, abs=1e-9)
        assert np.allclose(c.obstacle_point, p)
        assert np.linalg.norm(c.robot_point - p) == pytest.approx(abs(c.distance), abs=1e-9)


def test_batch_equals_single(mesh, fast):
    rng = np.random.default_rng(3)
    Q = np.array(_random_free(mesh, rng, 6))
    obstacles = [Shape("sphere", (0.05,), [0.5, 0.0, 0.5]),
                 Shape("box", (0.1, 0.2, 0.3), [0.4, 0.3, 0.3], [0.1, 0.2, 0.0, 0.97]),
                 Shape("cylinder", (0.05, 0.4), [0.3, -0.4, 0.4]),
                 point([0.2, 0.2, 0.9]),
                 Shape("points", (), [0.6, -0.1, 0.2], points=rng.normal(scale=0.05,
                                                                          size=(12, 3)))]
    for robot in (mesh, fast):
        batch = robot.distances(Q, obstacles)
        single = [robot.clearance(q, obstacles).distance for q in Q]
        assert np.allclose(batch, single, atol=1e-9)
        assert all(robot.in_collision(q, obstacles, margin=d + 1e-9) for q, d in zip(
            Q, batch, strict=True))
        assert not any(robot.in_collision(q, obstacles, margin=d - 1e-6) for q, d in zip(
            Q, batch, strict=True))
    assert np.all(fast.distances(Q, obstacles) <= mesh.distances(Q, obstacles))
    assert np.all(np.isinf(mesh.distances(Q, [])))
    assert math.isinf(fast.clearance(READY, []).distance)


def test_fast_spheres_contain_every_mesh_point(mesh, fast):
    """The containment the margin rests on, checked in the world frame: every mesh surface
    point lies at least FAST_MODEL_MARGIN inside a sphere (the fitted set contains every
    surface triangle exactly; test_sphere_fit checks it densely)."""
    import pinocchio as pin

    rng = np.random.default_rng(8)
    pts = [surface_points(o.geometry, 0.01) for o in mesh.mesh_geom.geometryObjects]
    for q in rng.uniform(mesh.limits.lower, mesh.limits.upper, (2, 7)):
        pin.updateGeometryPlacements(mesh.model, mesh.data, mesh.mesh_geom, mesh.mesh_data, q)
        centers = fast.spheres.world_centers(q[None])[0]
        for p, m in zip(pts, mesh.mesh_data.oMg, strict=True):  # one mesh at a time: memory
            world = p @ m.rotation.T + m.translation
            inside = (np.linalg.norm(world[:, None] - centers[None], axis=2)
                      - fast.spheres.radii).min(axis=1)
            assert inside.max() <= -FAST_MODEL_MARGIN + 1e-9  # so fast ≥ 0 ⇒ meshes ≥ 2 mm


def test_fast_model_is_conservative_on_random_obstacles():
    """Where the meshes are apart from an obstacle the fitted model is never farther; where
    they touch it the fast model says so too; on self-collision likewise. The fitted set is
    much tighter than the old grown URDF model. (``bench-robot --margin 100000`` runs the
    same with 100,000 samples.)"""
    report = bench_robot.measure_margin(samples=400, seed=11, self_samples=40)
    assert report.touching > 20 and report.samples - report.touching > 100
    fitted = report.models["fitted (config/)"]
    old = report.models["old: urdf grown to contain"]
    urdf = report.models["panda_collision.urdf as is"]
    assert fitted.excess_max <= 0.0 and fitted.max_when_touching <= 0.0
    assert old.excess_max <= 0.0 and old.max_when_touching <= 0.0
    assert urdf.required > 0.0  # the URDF's spheres alone are not conservative
    assert fitted.bulge_median < 0.5 * old.bulge_median
    assert report.self_models["fitted (config/)"].required <= 0.0
    for kind in ("sphere", "box", "cylinder", "points"):
        assert report.by_kind[kind]["fitted (config/)"].required <= 0.0


# ---- self-collision -----------------------------------------------------------------------
def test_srdf_disabled_pairs_are_ignored(mesh):
    import pinocchio as pin

    # adjacent link meshes interpenetrate in the ready pose ...
    pin.updateGeometryPlacements(mesh.model, mesh.data, mesh.mesh_geom, mesh.mesh_data, READY)
    names = [mesh.model.frames[o.parentFrame].name for o in mesh.mesh_geom.geometryObjects]
    i, j = names.index("panda_link1"), names.index("panda_link2")
    geoms, oMg = mesh.mesh_geom.geometryObjects, mesh.mesh_data.oMg
    depth = coal.distance(geoms[i].geometry, coal.Transform3s(oMg[i].rotation, oMg[i].translation),
                          geoms[j].geometry, coal.Transform3s(oMg[j].rotation, oMg[j].translation),
                          mesh._request, coal.DistanceResult())
    assert depth < 0.0
    # ... but the pair is disabled, so the ready pose is not a self-collision
    assert frozenset(("panda_link1", "panda_link2")) in disabled_link_pairs()
    assert not mesh.self_collision(READY)
    for pair in mesh.mesh_geom.collisionPairs:
        assert frozenset((names[pair.first], names[pair.second])) not in disabled_link_pairs()
    # the elbow folded flat brings the hand onto link 1: a real self-collision
    assert mesh.self_collision([0.0, 0.0, 0.0, -3.0, 0.0, 0.0, 0.0])
    assert mesh.segment_self_collision_free(READY, READY + 0.1)
    assert not mesh.segment_self_collision_free(READY, [0.0, 0.0, 0.0, -3.0, 0.0, 0.0, 0.0])


# ---- segments -----------------------------------------------------------------------------
def test_segment_check_finds_an_obstacle_between_free_endpoints(mesh, fast):
    q0, q1, mid = READY.copy(), READY.copy(), READY.copy()
    q0[0], q1[0], mid[0] = -1.2, 1.2, 0.0  # sweep the arm across the front
    ball = Shape("sphere", (0.04,), fast.fk(mid)[:3, 3])
    for robot in (fast, mesh):
        assert not robot.in_collision(q0, [ball]) and not robot.in_collision(q1, [ball])
        assert not robot.segment_free(q0, q1, [ball], resolution=0.02)
        assert robot.segment_free(q0, q1, [], resolution=0.02)
    far = Shape("sphere", (0.04,), [-0.6, 0.0, 1.2])
    assert fast.segment_free(q0, q1, [far], margin=0.02)
    assert not fast.segment_free(q0, q1, [far], margin=1.0)  # the margin is honoured
    assert fast.path_free(np.array([q0, READY, q1]), [far], margin=0.02)
    assert not fast.path_free(np.array([q0, READY, q1]), [ball])


def test_segment_resolution_bounds_the_joint_step(fast):
    """A small ball that both endpoints miss is found only when states are dense enough."""
    q0, q1 = READY.copy(), READY.copy()
    q0[0], q1[0] = -0.8, 0.81
    hand = fast.spheres.world_centers(READY[None])[0][fast.spheres.links.index("panda_hand")]
    ball = Shape("sphere", (0.005,), hand)
    assert fast.in_collision(READY, [ball])
    assert not fast.in_collision(q0, [ball]) and not fast.in_collision(q1, [ball])
    assert fast.segment_free(q0, q1, [ball], resolution=2.0)  # the endpoints only
    assert not fast.segment_free(q0, q1, [ball], resolution=0.02)
    assert fast.steps(q0, q1, 0.02) == 81


# ---- benchmark ----------------------------------------------------------------------------
def test_bench_robot_prints_every_row(capsys):
    assert bench_robot.main(["--repeats", "2"]) == 0
    out = capsys.readouterr().out
    for row in ("FK panda_hand_tcp", "IK, warm seed", "clearance, mesh model",
                "segment_free per state"):
        assert row in out


def test_the_exact_bands_fast_side_is_the_full_distance_rule(fast):
    """`band_states` (distances bounded at the margin, cut short at the floor) picks the
    states the full distances pick, and refuses where they refuse: one at or below the
    floor, or more than the budget within the margin."""
    rng = np.random.default_rng(3)
    outcomes = set()
    for _ in range(400):
        obstacles = (Shape("sphere", (rng.uniform(0.03, 0.2),), rng.uniform([-0.6, -0.6, 0.0],
                                                                        [0.8, 0.6, 1.0])),
                     Shape("box", tuple(rng.uniform(0.05, 0.4, 3)),
                           rng.uniform([-0.6, -0.6, 0.0], [0.8, 0.6, 1.0])))
        q0 = rng.uniform(fast.limits.lower, fast.limits.upper)
        Q = q0 + np.linspace(0.0, 1.0, 30)[:, None] * rng.normal(0.0, 0.3, 7)
        margin, floor, budget = rng.choice([0.0, 0.01, 0.05]), -0.005, int(rng.integers(1, 20))
        d = fast.distances(Q, obstacles)
        near = np.flatnonzero(d <= margin)
        refused = bool(np.any(d[near] <= floor)) or len(near) > budget
        got = fast.spheres.band_states(Q, obstacles, margin, floor, budget)
        assert (got is None) == refused
        if got is not None:
            assert got.tolist() == near.tolist()
        outcomes.add("refused" if refused else "near" if len(near) else "clear")
    assert outcomes == {"refused", "near", "clear"}
