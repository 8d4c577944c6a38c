"""Time parameterisation stays on the certified lines within the limits; splines are exact."""

from __future__ import annotations

import numpy as np
import pytest

from damon_ros.core.limits import joint_limits
from damon_ros.planning.trajectory import (
    Spline,
    Trajectory,
    interpolate,
    stop_trajectory,
    swerve_trajectory,
    time_grid,
    time_parameterize,
)

LIM = joint_limits("panda")
ON_LINE = 1e-6


def random_path(rng: np.random.Generator, n: int, lim=LIM) -> np.ndarray:
    """Waypoints inside the limits, with some short hops and a repeated point mixed in."""
    margin = 0.05 * (lim.upper - lim.lower)
    pts = rng.uniform(lim.lower + margin, lim.upper - margin, size=(n, 7))
    if n > 2:
        pts[1] = pts[0] + rng.normal(0.0, 1e-3, 7)  # a short hop
        pts[2] = pts[1]  # a repeated waypoint
    return pts


def path_progress(path: np.ndarray, q: np.ndarray) -> list[tuple[int, float, float]]:
    """(segment, fraction, distance) of q against each non-degenerate segment of the path."""
    out = []
    for i, (a, b) in enumerate(zip(path[:-1], path[1:], strict=True)):
        d = b - a
        nn = float(d @ d)
        if nn == 0.0:
            continue
        lam = float(np.clip((q - a) @ d / nn, 0.0, 1.0))
        out.append((i, lam, float(np.linalg.norm(q - (a + lam * d)))))
    return out


def assert_follows_path(path: np.ndarray, positions: np.ndarray) -> None:
    """Every point lies on the path, and the points advance along it in order.

    Being close to *some* segment is not enough (a corner cut stays close to both lines);
    the position along the path, (segment index, fraction), must never go back.
    """
    where = (0, 0.0)
    for q in positions:
        candidates = [
            (i, lam) for i, lam, dist in path_progress(path, q)
            if dist < ON_LINE and (i, lam) >= (where[0], where[1] - 1e-9)
        ]
        assert candidates, f"sample {q} is off the path or went backwards from {where}"
        where = min(candidates)


def check_limits(traj: Trajectory, lim) -> None:
    assert np.all(np.abs(traj.velocities) <= lim.velocity * (1 + 1e-9) + 1e-12)
    assert np.all(np.abs(traj.accelerations) <= lim.acceleration * (1 + 1e-6) + 1e-9)
    jerk = np.diff(traj.accelerations, axis=0) / np.diff(traj.times)[:, None]
    assert np.all(np.abs(jerk) <= lim.jerk * (1 + 1e-3) + 1e-6)


@pytest.mark.parametrize("seed", range(12))
def test_random_paths_stay_on_segments_and_within_limits(seed):
    rng = np.random.default_rng(seed)
    path = random_path(rng, int(rng.integers(2, 6)))
    scales = (1.0, 1.0, 1.0) if seed % 2 == 0 else (0.4, 0.3, 0.2)
    traj = time_parameterize(path, LIM, *scales, dt=0.01)
    assert_follows_path(path, traj.positions)
    check_limits(traj, LIM.scaled(*scales))
    assert np.array_equal(traj.positions[-1], path[-1])
    assert np.allclose(traj.positions[0], path[0], atol=1e-12)
    assert np.all(traj.velocities[[0, -1]] == 0.0)
    assert np.all(traj.accelerations[[0, -1]] == 0.0)
    # Between the samples, the quintic used by the controller stays on the lines too.
    mid = (traj.times[:-1] + traj.times[1:]) / 2
    assert_follows_path(path, np.array([traj.sample(t)[0] for t in mid]))


def test_samples_are_consistent_derivatives_of_each_other():
    """Velocities and accelerations are the derivatives of the sampled positions."""
    path = random_path(np.random.default_rng(11), 4)
    dt = 1e-4
    traj = time_parameterize(path, LIM, 0.7, 0.6, 0.5, dt=dt)
    inner = np.abs(np.diff(traj.times) - dt) < 1e-12  # uniform gaps (not next to knots)
    ok = inner[:-1] & inner[1:]
    qd_fd = (traj.positions[2:] - traj.positions[:-2]) / (2 * dt)
    qdd_fd = (traj.velocities[2:] - traj.velocities[:-2]) / (2 * dt)
    assert np.max(np.abs(qd_fd - traj.velocities[1:-1])[ok]) < 1e-4
    assert np.max(np.abs(qdd_fd - traj.accelerations[1:-1])[ok]) < 0.5  # jerk switches


def test_arm_rests_at_every_waypoint():
    path = random_path(np.random.default_rng(3), 4)
    path = np.delete(path, 2, axis=0)  # no repeats: every waypoint is a corner
    traj = time_parameterize(path, LIM, dt=0.01)
    for wp in path:
        k = int(np.argmin(np.linalg.norm(traj.positions - wp, axis=1)))
        assert np.linalg.norm(traj.positions[k] - wp) < 1e-9
        assert np.max(np.abs(traj.velocities[k])) < 1e-9


def test_single_joint_duration_matches_closed_form():
    """Long move, one joint: T = D/v + v/a + a/j when v and a limits are both reached."""
    q0 = np.array([0.0, 0.0, 0.0, -1.5, 0.0, 1.5, 0.0])
    q1 = q0.copy()
    q1[0] = 2.5
    traj = time_parameterize(np.array([q0, q1]), LIM)
    v, a, j = LIM.velocity[0], LIM.acceleration[0], LIM.jerk[0]
    assert traj.duration == pytest.approx(2.5 / v + v / a + a / j, rel=1e-9)


def test_slowest_joint_sets_the_pace_and_all_joints_share_the_profile():
    q0 = np.array([0.0, 0.0, 0.0, -1.5, 0.0, 1.5, 0.0])
    q1 = q0 + np.array([1.0, 0.5, 0.0, 0.0, 0.0, 0.0, -0.2])
    traj = time_parameterize(np.array([q0, q1]), LIM)
    frac = (traj.positions - q0) / (q1 - q0 + (q1 == q0))
    assert np.allclose(frac[:, 0], frac[:, 1], atol=1e-12)
    assert np.allclose(frac[:, 0], frac[:, 6], atol=1e-12)
    assert np.all(traj.positions[:, [2, 3, 4, 5]] == q0[[2, 3, 4, 5]])
    # Joint 2 has the tightest acceleration (7.5) and jerk; joint 1 the velocity bound.
    assert np.max(np.abs(traj.accelerations[:, 1])) == pytest.approx(7.5, rel=1e-6)


def test_single_waypoint_and_repeats_give_a_standing_trajectory():
    q0 = np.array([0.0, 0.0, 0.0, -1.5, 0.0, 1.5, 0.0])
    for path in (q0[None], np.array([q0, q0, q0])):
        traj = time_parameterize(path, LIM)
        assert traj.duration == 0.0
        assert traj.positions.shape == (1, 7)
        assert np.array_equal(traj.positions[0], q0)


@pytest.mark.parametrize(
    ("path", "kwargs", "words"),
    [
        (np.zeros((2, 6)), {}, "path must have shape"),
        (np.full((2, 7), np.nan), {}, "NaN"),
        (np.zeros((0, 7)), {}, "at least one waypoint"),
        (np.array([[0.0, 0, 0, -1.5, 0, 1.5, 0], [3.5, 0, 0, -1.5, 0, 1.5, 0]]), {}, "outside"),
        (np.array([[0.0, 0, 0, -1.5, 0, 1.5, 0]] * 2), {"velocity_scale": 0.0}, "velocity_scale"),
        (np.array([[0.0, 0, 0, -1.5, 0, 1.5, 0]] * 2), {"jerk_scale": 1.5}, "jerk_scale"),
        (np.array([[0.0, 0, 0, -1.5, 0, 1.5, 0]] * 2), {"dt": -0.01}, "dt"),
    ],
)
def test_bad_input_is_rejected(path, kwargs, words):
    with pytest.raises(ValueError, match=words):
        time_parameterize(path, LIM, **kwargs)


def test_fr3_profile_and_dt_are_respected():
    lim = joint_limits("fr3")
    path = random_path(np.random.default_rng(7), 3, lim)
    traj = time_parameterize(path, lim, dt=0.002)
    check_limits(traj, lim)
    assert_follows_path(path, traj.positions)
    assert np.max(np.diff(traj.times)) <= 0.002 + 1e-12


def straight_trajectory() -> Trajectory:
    q0 = np.array([0.0, 0.0, 0.0, -1.5, 0.0, 1.5, 0.0])
    return time_parameterize(np.array([q0, q0 + 0.3]), LIM, dt=0.01)


def test_sample_clamps_and_resample_preserves_the_motion():
    traj = straight_trajectory()
    q, qd, qdd = traj.sample(-1.0)
    assert np.array_equal(q, traj.positions[0]) and not qd.any() and not qdd.any()
    q, qd, qdd = traj.sample(traj.duration + 5.0)
    assert np.array_equal(q, traj.positions[-1]) and not qd.any() and not qdd.any()
    fine = traj.resample(0.001)
    assert fine.duration == traj.duration
    assert np.max(np.diff(fine.times)) <= 0.001 + 1e-12
    for k in range(0, fine.times.size, 37):
        assert np.allclose(fine.positions[k], traj.sample(fine.times[k])[0])
    # Sampled knots reproduce exactly.
    assert np.allclose(traj.sample(traj.times[5])[0], traj.positions[5], atol=1e-15)


@pytest.mark.parametrize(
    ("change", "words"),
    [
        ({"times": np.array([0.1, 0.2])}, "start at 0"),
        ({"times": np.array([0.0, 0.0])}, "strictly increasing"),
        ({"times": np.array([0.0, np.inf])}, "NaN or inf"),
        ({"positions": np.zeros((3, 7))}, "positions must have shape"),
        ({"velocities": np.full((2, 7), np.nan)}, "velocities holds NaN"),
        ({"accelerations": np.zeros((2, 6))}, "accelerations must have shape"),
    ],
)
def test_trajectory_validation(change, words):
    fields = {"times": np.array([0.0, 1.0]), "positions": np.zeros((2, 7)),
              "velocities": np.zeros((2, 7)), "accelerations": np.zeros((2, 7))}
    fields.update(change)
    with pytest.raises(ValueError, match=words):
        Trajectory(**fields)


def test_time_grid_keeps_the_end_without_tiny_gaps():
    assert np.allclose(time_grid(0.1, 0.03), [0.0, 0.03, 0.06, 0.09, 0.1])
    assert np.allclose(time_grid(0.09000001, 0.03), [0.0, 0.03, 0.06, 0.09000001])
    assert np.array_equal(time_grid(0.0, 0.01), [0.0])
    assert np.array_equal(time_grid(1e-8, 0.01), [0.0, 1e-8])


def test_tiny_moves_still_start_at_zero_and_end_on_the_goal():
    q0 = np.array([0.0, 0.0, 0.0, -1.5, 0.0, 1.5, 0.0])
    for step in (2e-9, 1e-7, 1e-4):
        path = np.array([q0, q0 + step, q0 + 2 * step, q0 + 0.2])
        traj = time_parameterize(path, LIM, dt=0.01)
        assert traj.times[0] == 0.0 and np.array_equal(traj.positions[-1], path[-1])
        assert_follows_path(path, traj.positions)
        check_limits(traj, LIM)


def poly(coeffs, t):
    """Value, first and second derivative of a polynomial given lowest order first."""
    p = np.polynomial.Polynomial(coeffs)
    return p(t), p.deriv(1)(t), p.deriv(2)(t)


@pytest.mark.parametrize(("degree", "method", "given"), [
    (5, "quintic", "va"), (3, "cubic", "va"), (3, "quintic", "v"), (1, "quintic", ""),
])
def test_splines_reproduce_polynomials_of_their_order(degree, method, given):
    rng = np.random.default_rng(degree)
    coeffs = rng.normal(size=(7, degree + 1))
    times = np.array([0.0, 0.4, 1.1, 1.5])
    vals = np.array([[poly(c, t) for c in coeffs] for t in times])  # (4, 7, 3)
    vel = vals[:, :, 1] if "v" in given else None
    acc = vals[:, :, 2] if "a" in given else None
    spline = Spline(times, vals[:, :, 0], vel, acc, method)
    assert spline.order == degree
    for t in (0.0, 0.2, 0.4, 0.77, 1.3, 1.5):
        q, qd, qdd = spline.evaluate(t)
        expected = np.array([poly(c, t) for c in coeffs])
        assert np.allclose(q, expected[:, 0], atol=1e-9)
        if degree > 1:
            assert np.allclose(qd, expected[:, 1], atol=1e-8)
            assert np.allclose(qdd, expected[:, 2], atol=1e-6)
        assert np.allclose(interpolate(times, vals[:, :, 0], vel, acc, t, method)[0], q)


def test_interpolate_holds_the_ends_and_handles_one_point():
    times = np.array([0.5, 1.0])
    pos = np.array([[0.0] * 7, [1.0] * 7])
    vel = np.array([[0.0] * 7, [0.5] * 7])
    q, qd, _ = interpolate(times, pos, vel, None, 0.0)
    assert np.array_equal(q, pos[0]) and not qd.any()
    q, qd, _ = interpolate(times, pos, vel, None, 1.0)
    assert np.array_equal(q, pos[1]) and np.array_equal(qd, vel[1])
    q, qd, _ = interpolate(times, pos, vel, None, 9.0)
    assert np.array_equal(q, pos[1]) and not qd.any()
    q, _, _ = interpolate([0.0], pos[:1], None, None, 3.0)
    assert np.array_equal(q, pos[0])
    q, qd, _ = interpolate(times, pos, None, None, 0.75)
    assert np.allclose(q, 0.5) and np.allclose(qd, 2.0)


@pytest.mark.parametrize(("args", "words"), [
    (([0.0, 1.0], np.zeros((2, 7)), None, None, 0.5, "spline"), "interpolation method"),
    (([0.0, 1.0], np.zeros((3, 7)), None, None, 0.5), "positions must have shape"),
    (([1.0, 0.0], np.zeros((2, 7)), None, None, 0.5), "strictly increasing"),
    (([0.0, 1.0], np.zeros((2, 7)), np.zeros((2, 6)), None, 0.5), "velocities"),
])
def test_interpolate_rejects_bad_points(args, words):
    with pytest.raises(ValueError, match=words):
        interpolate(*args)


@pytest.mark.parametrize("seed", range(4))
def test_a_swerve_follows_the_stop_then_turns_to_rest_at_its_target_within_limits(seed):
    """`swerve_trajectory`: the stop's samples up to the branch, then a continuous motion
    (velocities the derivative of positions) to rest at the target, inside every limit."""
    rng = np.random.default_rng(seed)
    mid = 0.5 * (LIM.lower + LIM.upper)
    q = mid + rng.uniform(-0.5, 0.5, 7)
    qd = rng.uniform(-0.6, 0.6, 7) * LIM.velocity
    target = q + rng.uniform(-0.3, 0.3, 7)
    stop = stop_trajectory(q, qd, LIM, coast_s=0.03, dt=0.01)
    tr = swerve_trajectory(stop, 0.06, target, LIM, dt=0.01)
    assert tr is not None
    k = int(np.searchsorted(stop.times, 0.06 - 1e-9))
    assert np.array_equal(tr.positions[:k + 1], stop.positions[:k + 1])
    assert np.allclose(tr.positions[-1], target) and not tr.velocities[-1].any()
    assert np.all(np.abs(tr.velocities) <= LIM.velocity + 1e-9)
    assert np.all(np.abs(tr.accelerations) <= LIM.acceleration + 1e-6)
    mid_v = 0.5 * (tr.velocities[1:] + tr.velocities[:-1])
    assert np.allclose(np.diff(tr.positions, axis=0), mid_v * np.diff(tr.times)[:, None],
                       atol=2e-3)


def test_a_swerve_that_would_overshoot_a_position_limit_is_refused():
    """Heading fast into joint 1's upper limit, a turn back to a state below it would pass
    the limit on the way: no swerve (the caller keeps its other escapes)."""
    q = 0.5 * (LIM.lower + LIM.upper)
    q[0] = LIM.upper[0] - 0.05
    qd = np.zeros(7)
    qd[0] = LIM.velocity[0]
    stop = stop_trajectory(q, qd, LIM, coast_s=0.03, dt=0.01)
    assert swerve_trajectory(stop, 0.06, q - 0.2, LIM, dt=0.01) is None
