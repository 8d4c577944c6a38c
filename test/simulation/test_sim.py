"""The mock arm behaves like a lagging, limited velocity loop; closed loop reaches goals."""

from __future__ import annotations

import math

import numpy as np
import pytest

from damon_ros.core.limits import joint_limits
from damon_ros.core.scenario import load_public_scenarios
from damon_ros.planning.follower import TrajectoryFollower
from damon_ros.planning.trajectory import time_parameterize
from damon_ros.simulation.mock_arm import LATE, LIMIT_KINDS, ArmSim, LimitMonitor

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

def follow(path: np.ndarray, scale: float = 0.5, settle: float = 0.5,
           monitor: LimitMonitor | None = None):
    """Run follower + sim at 1 kHz along the time-parameterised path; returns traces."""
    traj = time_parameterize(path, LIM, scale, scale, scale)
    sim = ArmSim(LIM, path[0], monitor=monitor)
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


# ----------------------------------------------------------------------------- limit monitor

def test_limit_monitor_counts_nothing_in_a_shaped_command_stream():
    """The controller's own output at full limits, 1 kHz, closed loop: zero counts."""
    monitor = LimitMonitor(LIM, DT)
    path = np.array([HOME, HOME + np.array([1.0, 0.5, -1.0, 0.8, 1.0, -0.8, 1.0])])
    *_, steps = follow(path, scale=1.0, settle=0.5, monitor=monitor)
    assert monitor.commands == round(steps / DT)
    assert monitor.counts == dict.fromkeys((*LIMIT_KINDS, LATE), 0), monitor.summary()
    assert monitor.peak["acceleration"] > 0.9  # it did run close to the limits
    assert not monitor.take_reports()


def test_limit_monitor_counts_a_step_beyond_the_acceleration_limit():
    monitor = LimitMonitor(LIM, DT)
    step = np.zeros(7)
    step[1] = 1.1 * LIM.acceleration[1] * DT  # 10 % more than one period allows
    for k, u in enumerate((np.zeros(7), np.zeros(7), step, step)):
        monitor.command(u, k * DT)
    assert monitor.counts["acceleration"] == 1
    assert monitor.counts["jerk"] == 2  # into the step and out of it
    assert monitor.counts["velocity"] == monitor.counts[LATE] == 0
    reports = monitor.take_reports()
    assert any("acceleration" in r and "joint 2" in r and "1.1000 x" in r for r in reports)
    assert monitor.take_reports() == []  # each kind is handed out once
    monitor.command(np.zeros(7), 4 * DT)
    assert monitor.counts["acceleration"] == 2 and monitor.take_reports() == []
    assert "2 acceleration" in monitor.summary()


def test_limit_monitor_counts_velocity_and_position_limits():
    monitor = LimitMonitor(LIM, DT)
    monitor.command(np.r_[1.01 * LIM.velocity[0], np.zeros(6)], 0.0)
    assert monitor.counts["velocity"] == 1
    start = HOME.copy()
    start[0] = LIM.upper[0] - 0.01
    sim = ArmSim(LIM, start, monitor=LimitMonitor(LIM, DT))
    cmd = np.r_[1.0, np.zeros(6)]
    drive(sim, cmd, 0.0, 0.2)  # runs into the upper limit and stays there
    assert sim.monitor.counts["position"] == 1  # one entry, however long it stays
    drive(sim, -cmd, 0.2, 0.3)
    drive(sim, cmd, 0.3, 0.6)
    assert sim.monitor.counts["position"] == 2
    assert "joint 1 reached its position limit" in sim.monitor.take_reports()[0]


def test_limit_monitor_skips_a_gap_and_counts_it_as_late():
    """A late message is not a controller violation: no acceleration across the gap."""
    monitor = LimitMonitor(LIM, DT)
    far = np.r_[0.5, np.zeros(6)]  # 0.5 rad/s in one step would be 500 rad/s^2
    monitor.command(np.zeros(7), 0.0)
    monitor.command(np.zeros(7), 1.4 * DT)  # within 1.5 periods: checked
    monitor.command(far, 3.0 * DT)  # 1.6 periods later: late
    monitor.command(far, 4.0 * DT)
    assert monitor.counts[LATE] == 1
    assert monitor.violations == 0, monitor.summary()
    assert abs(monitor.max_gap - 1.6 * DT) < 1e-12


def test_limit_monitor_sees_a_late_send_hidden_by_a_stalled_receiver():
    """Sent 5 periods apart (a late controller tick) but taken 0.1 ms apart: late, not a
    500 rad/s^2 acceleration; on-time sends that arrive together are still checked."""
    monitor = LimitMonitor(LIM, DT)
    far = np.r_[0.5, np.zeros(6)]
    monitor.command(np.zeros(7), 10.0, sent=100.0)
    monitor.command(far, 10.0001, sent=100.005)
    assert monitor.counts[LATE] == 1 and monitor.violations == 0
    monitor.command(np.zeros(7), 10.0002, sent=100.006)  # catches up on the stall: skipped
    assert monitor.counts[LATE] == 1 and monitor.violations == 0
    monitor.command(far, 10.0003, sent=100.007)
    assert monitor.counts[LATE] == 1 and monitor.counts["acceleration"] == 1
    assert monitor.jitter["acceleration"] == 0  # 500 rad/s^2 at any spacing


def test_limit_monitor_tells_tick_jitter_from_a_shaping_error():
    """A step shaped for a 1.25 ms tick: within the limit at the sender's spacing, beyond
    it at the robot's 1 ms cycle; counted, and counted as jitter."""
    monitor = LimitMonitor(LIM, DT)
    step = np.r_[1.2 * LIM.acceleration[0] * DT, np.zeros(6)]
    monitor.command(np.zeros(7), 0.0, sent=50.0)
    monitor.command(step, 1.25 * DT, sent=50.0 + 1.25 * DT)
    assert monitor.counts["acceleration"] == 1 and monitor.jitter["acceleration"] == 1
    monitor.command(2 * step, 2.25 * DT, sent=50.0 + 2.25 * DT)  # 1 ms: shaping error
    assert monitor.counts["acceleration"] == 2 and monitor.jitter["acceleration"] == 1
    assert "within the limits at the sender's own tick spacing: 1 acceleration" in \
        monitor.summary()


def test_nan_commands_never_reach_the_limit_monitor():
    sim = ArmSim(LIM, HOME, monitor=LimitMonitor(LIM, DT))
    assert sim.command(np.zeros(7), 0.0) is None
    assert "NaN" in sim.command(np.full(7, np.nan), DT)
    assert "7 velocities" in sim.command(np.zeros(3), 2 * DT)
    assert sim.monitor.commands == 1 and sim.monitor.violations == 0
    with pytest.raises(ValueError, match="finite"):
        sim.monitor.command(np.r_[np.inf, np.zeros(6)], 3 * DT)
    with pytest.raises(ValueError, match="period must be a positive"):
        LimitMonitor(LIM, 0.0)
