"""FR3's position-dependent velocity limits (libfranka's rate_limiting.h) as one model,
and the three places that must keep to it: time parameterisation, the controller's
command shaping and mock_panda's limit monitor."""

from __future__ import annotations

import math

import numpy as np
import pytest

from damon_ros.core.limits import READY, joint_limits
from damon_ros.planning.follower import TrajectoryFollower
from damon_ros.planning.trajectory import time_parameterize
from damon_ros.simulation.mock_arm import ArmSim, LimitMonitor

FR3 = joint_limits("fr3")
PANDA = joint_limits("panda")
# libfranka 0.13 (2023) include/franka/rate_limiting.h, kJointVelocityLimitsParams and
# kMaxJointVelocity for the FR3: (vmax, c, k, p_up, p_lo) per joint.
LIBFRANKA = [
    (2.62, 0.30, 12.0, 2.7501, -2.7501),
    (2.62, 0.20, 5.17, 1.7918, -1.7918),
    (2.62, 0.20, 7.00, 2.9065, -2.9065),
    (2.62, 0.30, 8.00, -0.1458, -3.0481),
    (5.26, 0.35, 34.0, 2.8101, -2.8101),
    (4.18, 0.35, 11.0, 4.5205, 0.54092),
    (5.26, 0.35, 34.0, 3.0196, -3.0196),
]
TOL = 1e-3  # kLimitEps + kTolNumberPacketsLost (0 on the FR3) * ...


def libfranka_bounds(j: int, q: float) -> tuple[float, float]:
    """The formula, written out once more for one joint and one position."""
    vmax, c, k, p_up, p_lo = LIBFRANKA[j]
    upper = min(vmax, max(0.0, -c + math.sqrt(max(0.0, k * (p_up - q))))) - TOL
    lower = max(-vmax, min(0.0, c - math.sqrt(max(0.0, k * (q - p_lo))))) + TOL
    return lower, upper


@pytest.mark.parametrize("j", range(7))
def test_fr3_bounds_match_libfranka_per_joint(j):
    lo, hi = FR3.lower[j], FR3.upper[j]
    positions = [lo, lo + 1e-4, lo + 0.005, lo + 0.02, lo + 0.1, 0.5 * (lo + hi),
                 hi - 0.1, hi - 0.02, hi - 0.005, hi - 1e-4, hi]
    for x in positions:
        q = 0.5 * (FR3.lower + FR3.upper)
        q[j] = x
        lower, upper = FR3.velocity_bounds(q)
        want = libfranka_bounds(j, x)
        assert lower[j] == pytest.approx(want[0], abs=1e-12), (j, x)
        assert upper[j] == pytest.approx(want[1], abs=1e-12), (j, x)
    # mid-range it is the constant maximum less the tolerance; near a limit it falls
    mid = FR3.velocity_bounds(0.5 * (FR3.lower + FR3.upper))
    assert mid[1][j] == pytest.approx(LIBFRANKA[j][0] - TOL)
    q = 0.5 * (FR3.lower + FR3.upper)
    q[j] = hi - 0.02
    assert FR3.velocity_bounds(q)[1][j] < 0.6  # toward the upper limit: slow
    assert FR3.velocity_bounds(q)[0][j] == pytest.approx(-LIBFRANKA[j][0] + TOL)  # away: fast


def test_hand_computed_values():
    """Joint 2 at 1.7 rad: -0.2 + sqrt(5.17 * 0.0918) - 1e-3 = 0.4879 rad/s (by hand)."""
    q = READY.copy()
    q[1] = 1.7
    assert FR3.velocity_bounds(q)[1][1] == pytest.approx(0.48789, abs=1e-4)
    q[1] = -1.7
    assert FR3.velocity_bounds(q)[0][1] == pytest.approx(-0.48789, abs=1e-4)


def test_panda_bounds_are_its_constants_and_scaling_scales_both():
    for q in (READY, PANDA.lower, PANDA.upper):
        lower, upper = PANDA.velocity_bounds(q)
        assert np.array_equal(upper, PANDA.velocity) and np.array_equal(lower, -PANDA.velocity)
    q = READY.copy()
    q[1] = 1.7
    full, half = FR3.velocity_bounds(q), FR3.scaled(velocity=0.5).velocity_bounds(q)
    assert np.allclose(half[0], 0.5 * full[0]) and np.allclose(half[1], 0.5 * full[1])
    many = np.tile(q, (5, 1))
    assert FR3.velocity_bounds(many)[1].shape == (5, 7)


@pytest.mark.parametrize("j", range(7))
def test_time_parameterisation_keeps_below_the_bound_toward_each_limit(j):
    lim = FR3.scaled(0.9)
    for target in (FR3.upper[j] - 0.02, FR3.lower[j] + 0.02):
        a = 0.5 * (FR3.lower + FR3.upper)
        a[j] = 0.5 * (FR3.lower[j] + FR3.upper[j])
        b = a.copy()
        b[j] = target
        traj = time_parameterize([a, b, a], FR3, 0.9, 0.5, 0.5, dt=0.001)
        assert np.max(lim.velocity_excess(traj.positions, traj.velocities)) == 0.0
        assert np.max(np.abs(traj.velocities[:, j])) > 0.5  # and still moves fast mid-range


def test_the_constant_limits_would_have_broken_the_bound():
    """The test above can fail: timed with the constant maxima, joint 2 is 0.5+ rad/s over."""
    import dataclasses
    a = READY.copy()
    a[1] = 0.0
    b = a.copy()
    b[1] = FR3.upper[1] - 0.02
    constant = dataclasses.replace(FR3, curve=None)
    traj = time_parameterize([a, b], constant, 0.9, 0.5, 0.5, dt=0.001)
    assert np.max(FR3.scaled(0.9).velocity_excess(traj.positions, traj.velocities)) > 0.3


@pytest.mark.parametrize("j", range(7))
def test_controller_commands_stay_within_the_bound_when_driven_at_a_limit(j):
    """A desired trajectory that ends beyond joint j's limit: the follower's commands
    toward the limit stay inside libfranka's bound at every step (the monitor counts)."""
    rate = 1000.0
    monitor = LimitMonitor(FR3, 1.0 / rate)
    q0 = READY.copy()
    q0[3] = -1.5
    q0[5] = 2.0
    arm = ArmSim(FR3, q0, monitor=monitor)
    follower = TrajectoryFollower(FR3, rate_hz=rate)
    goal = q0.copy()
    goal[j] = FR3.upper[j] - 0.011  # the shaper stops at the 10 mrad margin
    follower.set_trajectory([0.0, 1.5], [q0, goal])
    t = 0.0
    for _ in range(4000):
        u = follower.update(t, arm.q)
        arm.command(u, t)
        t += 1.0 / rate
        arm.step(1.0 / rate, t)
    assert arm.q[j] > FR3.upper[j] - 0.05  # it got close to the limit
    assert monitor.counts["velocity"] == 0, monitor.first


def test_monitor_counts_a_command_above_the_position_dependent_bound():
    monitor = LimitMonitor(FR3, 0.001)
    q = READY.copy()
    q[1] = 1.7
    u = np.zeros(7)
    u[1] = 0.6  # below vmax 2.62, above the 0.488 bound at 1.7 rad
    monitor.command(u, 0.0)
    assert monitor.counts["velocity"] == 0  # without q only the constant is known
    monitor.command(u, 0.001, q=q)
    assert monitor.counts["velocity"] == 1
    assert "position-dependent" in monitor.first["velocity"]
    u[1] = -0.6  # away from the limit: fine
    monitor.command(u, 0.002, q=q)
    assert monitor.counts["velocity"] == 1
