"""The mock arm behaves like a lagging, limited velocity loop; closed loop reaches goals."""

from __future__ import annotations

import math

import numpy as np
import pytest

from damon_ros.control import TrajectoryFollower
from damon_ros.limits import joint_limits
from damon_ros.scenario import load_public_scenarios
from damon_ros.sim import ArmSim
from damon_ros.trajectory import time_parameterize

LIM = joint_limits("panda")
HOME = np.array([0.0, -0.3, 0.0, -2.0, 0.0, 1.8, 0.8])
DT = 1e-3


def drive(sim: ArmSim, command, t0: float, t1: float, dt: float = DT, resend: bool = True):
    """Step the sim from t0 to t1, (re)sending ``command`` each step; (times, q, qd) traces."""
    times, qs, qds = [], [], []
    for k in range(round((t1 - t0) / dt)):
        t = t0 + k * dt
        if resend or k == 0:
            assert sim.command(command, t) is None
        q, qd = sim.step(dt, t + dt)
        times.append(t + dt)
        qs.append(q)
        qds.append(qd)
    return np.array(times), np.array(qs), np.array(qds)


@pytest.mark.parametrize(("kwargs", "words"), [
    ({"q0": np.zeros(6)}, "q0 must be 7 finite"),
    ({"q0": np.full(7, np.nan)}, "q0 must be 7 finite"),
    ({"q0": np.zeros(7)}, "outside the joint limits"),  # joint 4 upper limit is -0.0698
    ({"q0": HOME, "tau": 0.0}, "tau must be a positive"),
    ({"q0": HOME, "command_timeout": -1.0}, "command_timeout must be a positive"),
])
def test_construction_rejects_bad_parameters(kwargs, words):
    with pytest.raises(ValueError, match=words):
        ArmSim(LIM, **kwargs)


def test_first_order_response_to_a_small_step():
    sim = ArmSim(LIM, HOME, tau=0.02)
    cmd = np.full(7, 0.1)
    times, q, qd = drive(sim, cmd, 0.0, 0.1)
    k_tau = int(np.argmin(np.abs(times - 0.02)))
    assert np.allclose(qd[k_tau], 0.1 * (1 - math.exp(-1)), rtol=1e-9)
    assert np.allclose(qd[-1], 0.1 * (1 - math.exp(-5)), rtol=1e-9)
    # Position is the integral of velocity: 0.1 * (t - tau * (1 - exp(-t / tau))).
    assert np.allclose(q[-1] - HOME, 0.1 * (0.1 - 0.02 * (1 - math.exp(-5))), rtol=1e-4)


def test_velocity_and_acceleration_are_clamped():
    sim = ArmSim(LIM, HOME, tau=0.02)
    cmd = np.array([5.0, -5.0, 5.0, 5.0, -5.0, -5.0, 5.0])  # beyond every velocity limit
    _, _, qd = drive(sim, cmd, 0.0, 0.5)
    acc = np.diff(np.vstack((np.zeros(7), qd)), axis=0) / DT
    assert np.all(np.abs(acc) <= LIM.acceleration * (1 + 1e-12))
    assert np.all(np.abs(qd) <= LIM.velocity)
    assert np.allclose(np.abs(qd[-1]), LIM.velocity)


def test_position_limit_stops_the_joint_and_releases_it():
    start = HOME.copy()
    start[0] = LIM.upper[0] - 0.05
    sim = ArmSim(LIM, start)
    cmd = np.zeros(7)
    cmd[0] = 1.0
    _, q, qd = drive(sim, cmd, 0.0, 0.5)
    assert np.all(q[:, 0] <= LIM.upper[0])
    assert q[-1, 0] == LIM.upper[0] and qd[-1, 0] == 0.0
    _, q, qd = drive(sim, -cmd, 0.5, 0.7)
    assert q[-1, 0] < LIM.upper[0] and qd[-1, 0] < 0.0


def test_stale_command_brakes_to_rest_within_limits():
    sim = ArmSim(LIM, HOME, tau=0.02, command_timeout=0.1)
    cmd = np.array([1.0, -1.0, 1.0, 1.0, -1.0, 1.0, 1.0])
    drive(sim, cmd, 0.0, 0.3)
    # One command at 0.3 s and then silence: it is followed until 0.4 s, then dropped.
    _, q, qd = drive(sim, cmd, 0.3, 0.8, resend=False)
    assert np.allclose(qd[90], cmd, atol=1e-6)
    acc = np.diff(qd, axis=0) / DT
    assert np.all(np.abs(acc) <= LIM.acceleration * (1 + 1e-12))
    assert np.all(np.abs(qd[-1]) < 1e-6)
    assert np.allclose(q[-1], sim.step(DT, 0.8 + DT)[0], atol=1e-8)  # at rest


def test_never_commanded_arm_stays_put():
    sim = ArmSim(LIM, HOME)
    for k in range(100):
        q, qd = sim.step(DT, (k + 1) * DT)
    assert np.array_equal(q, HOME) and not qd.any()


def test_bad_commands_are_reported_and_ignored():
    sim = ArmSim(LIM, HOME)
    good = np.full(7, 0.2)
    assert sim.command(good, 0.0) is None
    assert "NaN" in sim.command(np.full(7, np.nan), 0.001)
    assert "7 velocities" in sim.command(np.zeros(3), 0.001)
    assert sim.last_reason and "7 velocities" in sim.last_reason
    for k in range(60):
        sim.step(DT, (k + 1) * DT)
    assert np.all(sim.qd > 0.18)  # still following the last good command
    with pytest.raises(ValueError, match="dt must be a positive"):
        sim.step(0.0, 1.0)
    with pytest.raises(ValueError, match="time must be finite"):
        sim.step(DT, np.nan)


def test_same_commands_give_identical_motion():
    rng = np.random.default_rng(4)
    cmds = rng.uniform(-2.0, 2.0, size=(300, 7))
    runs = []
    for _ in range(2):
        sim = ArmSim(LIM, HOME)
        trace = []
        for k, c in enumerate(cmds):
            sim.command(c, k * DT)
            trace.append(sim.step(DT, (k + 1) * DT)[0])
        runs.append(np.array(trace))
    assert np.array_equal(runs[0], runs[1])


# ----------------------------------------------------------------------------- closed loop

def follow(path: np.ndarray, scale: float = 0.5, settle: float = 0.5):
    """Run follower + sim at 1 kHz along the time-parameterised path; returns traces."""
    traj = time_parameterize(path, LIM, scale, scale, scale)
    sim = ArmSim(LIM, path[0])
    follower = TrajectoryFollower(LIM)
    follower.set_trajectory(traj.times, traj.positions, traj.velocities, traj.accelerations,
                            start_time=0.0)
    q, errors, commands, qds = sim.q, [], [], []
    steps = int(round((traj.duration + settle) / DT))
    for k in range(steps):
        t = k * DT
        u = follower.update(t, q)
        assert sim.command(u, t) is None
        q, qd = sim.step(DT, t + DT)
        assert LIM.within(q)
        errors.append(follower.error)
        commands.append(u)
        qds.append(qd)
    return traj, follower, q, np.array(errors), np.array(commands), np.array(qds), steps * DT


def assert_within_limits(commands: np.ndarray, qds: np.ndarray) -> None:
    """Commands and motion within the velocity/acceleration/jerk limits of the arm."""
    acc = np.diff(np.vstack((np.zeros(7), commands)), axis=0) / DT
    jerk = np.diff(np.vstack((np.zeros(7), acc)), axis=0) / DT
    assert np.all(np.abs(commands) <= LIM.velocity)
    assert np.all(np.abs(acc) <= LIM.acceleration * (1 + 1e-6))
    assert np.all(np.abs(jerk) <= LIM.jerk * (1 + 1e-6) + 1e-6)
    assert np.all(np.abs(qds) <= LIM.velocity)
    assert np.all(np.abs(np.diff(qds, axis=0)) / DT <= LIM.acceleration * (1 + 1e-9))


@pytest.mark.parametrize("name", ["A-001", "C-002", "E-001"])
def test_closed_loop_reaches_a_scenario_goal_tracking_closely(name):
    scenario = load_public_scenarios([name])[0]
    mid = 0.5 * (scenario.start + scenario.goal.joints) + np.array([0.2, 0.1, 0, 0, 0, 0, 0])
    path = np.array([scenario.start, mid, scenario.goal.joints])
    traj, follower, q, errors, commands, qds, t_end = follow(path)
    assert np.max(np.abs(q - path[-1])) < 1e-3
    assert follower.finished(t_end, q, 1e-3)
    assert np.max(np.abs(errors)) < 0.02
    assert_within_limits(commands, qds)


def test_closed_loop_full_speed_move_still_converges_within_limits():
    """At full limits there is no headroom to correct lag, but it converges safely."""
    path = np.array([HOME, HOME + np.array([1.0, 0.5, -1.0, 0.8, 1.0, -0.8, 1.0])])
    _, _, q, errors, commands, qds, _ = follow(path, scale=1.0, settle=1.0)
    assert np.max(np.abs(q - path[-1])) < 1e-3
    assert_within_limits(commands, qds)
