"""The Panda model: FK against Franka's DH table, IK, exact distances, conservative fast model."""

from __future__ import annotations

import math

import numpy as np
import pytest

from damon_ros.limits import joint_limits
from damon_ros.robot import READY, Robot
from damon_ros.shapes import Shape, point

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


@pytest.fixture(scope="module")
def mesh() -> Robot:
    return Robot("mesh")


@pytest.fixture(scope="module")
def fast() -> Robot:
    return Robot("fast")


def _random_free(robot: Robot, rng, n: int) -> list[np.ndarray]:
    out = []
    while len(out) < n:
        q = rng.uniform(robot.limits.lower, robot.limits.upper)
        if not robot.self_collision(q):
            out.append(q)
    return out


def test_limits_profiles():
    panda, fr3 = joint_limits("panda"), joint_limits("fr3", prefix="fr3_")
    assert panda.names[0] == "panda_joint1" and fr3.names[6] == "fr3_joint7"
    assert np.allclose(panda.velocity, [2.175] * 4 + [2.61] * 3)
    assert np.allclose(panda.acceleration, [15, 7.5, 10, 12.5, 15, 20, 20])
    assert np.allclose(panda.jerk, [7500, 3750, 5000, 6250, 7500, 10000, 10000])
    assert not np.allclose(fr3.velocity, panda.velocity)
    with pytest.raises(ValueError, match="unknown limit profile"):
        joint_limits("ur5")


def test_fk_matches_franka_dh_table(mesh):
    rng = np.random.default_rng(0)
    for _ in range(50):
        q = rng.uniform(mesh.limits.lower, mesh.limits.upper)
        T, ref = mesh.fk(q), dh_tcp(q)
        assert np.allclose(T[:3, 3], ref[:3, 3], atol=1e-6)
        assert np.allclose(T[:3, :3], ref[:3, :3], atol=1e-6)


def test_fk_of_other_frames_and_bad_input(mesh):
    assert mesh.fk(READY, "panda_link0")[2, 3] == pytest.approx(0.0)
    with pytest.raises(ValueError, match="unknown frame"):
        mesh.fk(READY, "no_such_frame")
    with pytest.raises(ValueError, match="7 finite"):
        mesh.fk([0.0] * 6)


def test_ik_reaches_99_percent_of_random_reachable_poses(fast):
    rng = np.random.default_rng(1)
    targets = _random_free(fast, rng, 200)
    reached = 0
    for q in targets:
        position, quat = fast.tcp_pose(q)
        seed = fast.limits.clip(q + rng.normal(scale=0.3, size=7))
        result = fast.ik(position, quat, q_near=seed, rng=rng)
        if result.success:
            p, o = fast.tcp_pose(result.q)
            assert np.linalg.norm(p - position) <= 1e-3
            assert 2 * math.acos(min(1.0, abs(float(o @ quat)))) <= 0.01
            assert fast.limits.within(result.q)
            reached += 1
    assert reached >= 198


def test_ik_returns_the_solution_nearest_the_seed(fast):
    position, quat = fast.tcp_pose(READY)
    result = fast.ik(position, quat, q_near=READY)
    assert result.success and np.linalg.norm(result.q - READY) < 1e-3


def test_ik_says_clearly_when_a_pose_is_unreachable(fast):
    result = fast.ik([1.5, 0.0, 0.5], [1.0, 0.0, 0.0, 0.0])
    assert not result.success and "beyond the Panda's reach" in result.reason
    result = fast.ik([0.4, 0.0, 0.4], [0.0, 0.0, 0.0, 2.0])
    assert not result.success and "unit quaternion" in result.reason
    result = fast.ik([0.4, math.nan, 0.4], [1.0, 0.0, 0.0, 0.0])
    assert not result.success and "NaN" in result.reason


def test_ik_respects_minimum_clearance(fast):
    position, quat = fast.tcp_pose(READY)
    block = Shape("sphere", (0.05,), position + np.array([0.0, 0.0, 0.2]))
    result = fast.ik(position, quat, q_near=READY, obstacles=[block], min_clearance=0.05)
    if result.success:
        assert fast.clearance(result.q, [block]).distance >= 0.05
    else:
        assert "collide" in result.reason
    engulf = Shape("sphere", (0.3,), position)
    result = fast.ik(position, quat, q_near=READY, obstacles=[engulf], min_clearance=0.0)
    assert not result.success and "collide" in result.reason


def test_point_and_sphere_distances_agree_analytically(mesh):
    rng = np.random.default_rng(2)
    for q in _random_free(mesh, rng, 5):
        c = mesh.fk(q, "panda_link4")[:3, 3] + rng.normal(scale=0.25, size=3)
        d_point = mesh.clearance(q, [point(c)]).distance
        if d_point < 0.08:
            continue
        d_sphere = mesh.clearance(q, [Shape("sphere", (0.05,), c)])
        assert d_sphere.distance == pytest.approx(d_point - 0.05, abs=1e-4)
        # the witness point lies on the sphere's surface
        assert np.linalg.norm(d_sphere.obstacle_point - c) == pytest.approx(0.05, abs=1e-4)
        gap = np.linalg.norm(d_sphere.robot_point - d_sphere.obstacle_point)
        assert gap == pytest.approx(d_sphere.distance, abs=1e-4)


def test_box_distance_matches_the_face_geometry(mesh):
    q = READY
    tcp = mesh.fk(q)[:3, 3]
    # a wide thin plate below the gripper: the nearest robot point is the lowest mesh point
    plate = Shape("box", (0.25, 0.25, 0.02), [tcp[0], tcp[1], 0.40])
    c = mesh.clearance(q, [plate])
    assert c.obstacle_point[2] == pytest.approx(0.41, abs=1e-4)  # on the top face
    assert c.distance == pytest.approx(c.robot_point[2] - 0.41, abs=1e-4)
    rotated = Shape("box", (0.25, 0.25, 0.02), [tcp[0], tcp[1], 0.40], [0, 0, 0.3826834, 0.9238795])
    assert mesh.clearance(q, [rotated]).distance == pytest.approx(c.distance, abs=1e-4)


def test_batch_equals_single(mesh, fast):
    rng = np.random.default_rng(3)
    Q = np.array(_random_free(mesh, rng, 6))
    obstacles = [Shape("sphere", (0.05,), [0.5, 0.0, 0.5]), Shape("box", (0.1, 0.2, 0.3),
                                                                   [0.4, 0.3, 0.3])]
    for robot in (mesh, fast):
        batch = robot.distances(Q, obstacles)
        single = [robot.clearance(q, obstacles).distance for q in Q]
        assert np.allclose(batch, single, atol=1e-9)


def test_fast_model_is_conservative(mesh, fast):
    """Wherever the meshes are closer than the fast model says, the fast model is wrong in
    the unsafe direction; this must never happen."""
    rng = np.random.default_rng(4)
    links = [f"panda_link{i}" for i in range(1, 8)] + ["panda_hand", "panda_leftfinger"]
    worst = -math.inf
    for q in _random_free(mesh, rng, 400):
        centre = mesh.fk(q, links[rng.integers(len(links))])[:3, 3] + rng.normal(scale=0.08,
                                                                                   size=3)
        if rng.random() < 0.5:
            obstacle = Shape("sphere", (rng.uniform(0.01, 0.08),), centre)
        else:
            obstacle = Shape("box", tuple(rng.uniform(0.02, 0.15, 3)), centre, rng.normal(size=4))
        worst = max(worst, fast.clearance(q, [obstacle]).distance
                    - mesh.clearance(q, [obstacle]).distance)
    assert worst <= 0.0, f"fast model exceeded the mesh distance by {worst:.4f} m"


def test_srdf_disabled_pairs_are_ignored(mesh):
    # adjacent link meshes touch in every pose; the ready pose must not count as self-collision
    assert not mesh.self_collision(READY)
    folded = READY.copy()
    folded[3] = -3.0  # elbow fully folded
    folded[5] = 3.7
    assert isinstance(mesh.self_collision(folded), bool)
    assert len(mesh.mesh_geom.collisionPairs) < 17 * 16 // 2


def test_segment_check_finds_an_obstacle_between_free_endpoints(fast):
    q0 = READY.copy()
    q1 = READY.copy()
    q0[0], q1[0] = -1.2, 1.2  # sweep the arm across the front
    mid = READY.copy()
    mid[0] = 0.0
    ball = Shape("sphere", (0.04,), fast.fk(mid)[:3, 3])
    assert not fast.in_collision(q0, [ball]) and not fast.in_collision(q1, [ball])
    assert not fast.segment_free(q0, q1, [ball], resolution=0.02)
    assert fast.segment_free(q0, q1, [], resolution=0.02)
    far = Shape("sphere", (0.04,), [-0.6, 0.0, 1.2])
    assert fast.segment_free(q0, q1, [far], margin=0.02)
