"""The PID trajectory follower: JTC rejection rules, semantics, and commands within limits."""

from __future__ import annotations

import re

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from damon_ros.core.limits import POSITION_LIMIT_MARGIN, joint_limits
from damon_ros.planning.follower import (
    CommandShaper,
    PIDGains,
    Tolerances,
    TrajectoryFollower,
    reorder_points,
    validate_trajectory,
)
from damon_ros.planning.trajectory import interpolate, time_parameterize

LIM = joint_limits("panda")
NAMES = list(LIM.names)
HOME = np.array([0.0, -0.3, 0.0, -2.0, 0.0, 1.8, 0.8])
DT = 1e-3


class LimitWatch:
    """Checks each command against the limits as a fixed-cycle arm sees the stream: one
    command per cycle ``dt0``, whatever interval the controller's tick really took (``dt``
    is accepted for the callers' convenience and ignored: that is the point)."""

    def __init__(self, lim=LIM, dt0: float = DT):
        self.lim, self.u, self.a, self.dt0 = lim, np.zeros(7), np.zeros(7), dt0

    def check(self, u: np.ndarray, dt: float) -> None:
        a = (u - self.u) / self.dt0
        jerk = (a - self.a) / self.dt0
        assert np.all(np.isfinite(u)), u
        assert np.all(np.abs(u) <= self.lim.velocity * (1 + 1e-9)), u
        assert np.all(np.abs(a) <= self.lim.acceleration * (1 + 1e-6) + 1e-9), a
        assert np.all(np.abs(jerk) <= self.lim.jerk * (1 + 1e-6) + 1e-6), jerk
        self.u, self.a = u, a


def run(follower, t0, t1, q_of_t, watch=None, dt=DT):
    """Run the follower from t0 to t1 with measurements q_of_t(t); returns the commands."""
    out = []
    for t in np.arange(t0, t1, dt):
        u = follower.update(float(t), q_of_t(t))
        if watch:
            watch.check(u, dt)
        out.append(u)
    return np.array(out)


# ----------------------------------------------------------------------------- gains

def test_gains_default_per_joint_and_broadcast_scalars():
    g = PIDGains()
    assert g.p.shape == (7,) and np.all(g.ff_velocity_scale == 1.0)
    g = PIDGains(p=12.0, i=0.0, d=0.0, i_clamp=0.0, ff_velocity_scale=0.9)
    assert np.array_equal(g.p, np.full(7, 12.0))
    assert PIDGains.uniform(3, p=5.0).p.shape == (3,)


@pytest.mark.parametrize(("kwargs", "words"), [
    ({"p": -1.0}, "gain p must be finite and >= 0"),
    ({"i": [1.0, 2.0]}, "gain i must be a scalar or 7 values"),
    ({"d": np.nan}, "gain d must be finite"),
])
def test_gains_reject_bad_values(kwargs, words):
    with pytest.raises(ValueError, match=words):
        PIDGains(**kwargs)


# ----------------------------------------------------------------------------- validation

def points(n=3, names=NAMES):
    """A valid little trajectory in the given joint order."""
    pos = np.array([HOME + 0.05 * k for k in range(n)])
    order = [NAMES.index(name) for name in names]
    return [0.1 * (k + 1) for k in range(n)], pos[:, order].tolist(), [[0.0] * 7] * n


def test_valid_and_reordered_trajectories_are_accepted_and_mapped_by_name():
    times, pos, vel = points()
    assert validate_trajectory(NAMES, NAMES, times, pos, vel, None, LIM) is None
    shuffled = [NAMES[k] for k in (3, 0, 6, 1, 5, 2, 4)]
    times, pos_s, vel_s = points(names=shuffled)
    assert validate_trajectory(shuffled, NAMES, times, pos_s, vel_s, None, LIM) is None
    t, p, v, a = reorder_points(shuffled, NAMES, times, pos_s, vel_s, None)
    assert np.array_equal(p, np.array(pos)) and a is None and v.shape == (3, 7)
    # Empty: refused, as the JTC refuses it (a stop is a one-point hold trajectory).
    assert "no points" in validate_trajectory(NAMES, NAMES, [], [], [], [], LIM)


def mutate(field, value):
    times, pos, vel = points()
    args = {"joint_names": NAMES, "times": times, "positions": pos, "velocities": vel,
            "accelerations": None}
    args[field] = value(args[field]) if callable(value) else value
    return args


@pytest.mark.parametrize(("args", "words"), [
    (mutate("joint_names", NAMES[:6] + ["elbow"]), "unknown joints \\['elbow'\\]"),
    (mutate("joint_names", NAMES[:6] + [NAMES[0]]), "repeat"),
    (mutate("times", [0.1, 0.3, 0.3]), "not strictly increasing at point 2"),
    (mutate("times", [-0.1, 0.3, 0.4]), "must not be negative"),
    (mutate("times", [0.1, np.nan, 0.4]), "time_from_start holds NaN"),
    (mutate("positions", lambda p: [p[0], p[1][:6], p[2]]), "every point needs 7 positions"),
    (mutate("positions", lambda p: p[:2]), "positions has 2 points"),
    (mutate("positions", lambda p: [p[0], [np.inf] + p[1][1:], p[2]]), "positions hold NaN"),
    (mutate("positions", lambda p: [p[0], p[1][:3] + [0.5] + p[1][4:], p[2]]),
     "point 1 puts panda_joint4 at 0.5000 rad, outside"),
    (mutate("velocities", [[0.0] * 7, [0.0, 0.0, 3.0, 0, 0, 0, 0], [0.0] * 7]),
     "point 1 asks panda_joint3 for 3.0000 rad/s"),
    (mutate("velocities", [[0.0] * 7, [], [0.0] * 7]), "velocities must be empty or hold 7"),
    (mutate("velocities", [[np.nan] * 7] * 3), "velocities hold NaN"),
    (mutate("velocities", None) | {"accelerations": [[0.0] * 7] * 3}, "without velocities"),
])
def test_bad_trajectories_are_rejected_with_a_reason(args, words):
    reason = validate_trajectory(expected_names=NAMES, limits=LIM, **args)
    assert reason is not None and "\n" not in reason
    assert re.search(words, reason), reason
    if "outside" in words or "rad/s" in words:
        return  # structurally fine: reorder_points maps it, set_trajectory rejects it
    with pytest.raises(ValueError):
        reorder_points(args["joint_names"], NAMES, args["times"], args["positions"],
                       args["velocities"], args["accelerations"])


def test_missing_joint_and_past_trajectory_are_rejected():
    times, pos, vel = points()
    reason = validate_trajectory(NAMES[:6], NAMES, times, [p[:6] for p in pos],
                                 [v[:6] for v in vel], None, LIM)
    assert reason.startswith("missing joints ['panda_joint7']")
    reason = validate_trajectory(NAMES, NAMES, times, pos, vel, None, LIM,
                                 start_time=10.0, now=11.0)
    assert reason.startswith("trajectory ends in the past")
    assert validate_trajectory(NAMES, NAMES, times, pos, vel, None, LIM,
                               start_time=10.0, now=10.2) is None


# ----------------------------------------------------------------------------- semantics

def test_holds_the_first_measurement_without_a_trajectory():
    f = TrajectoryFollower(LIM)
    u = run(f, 0.0, 0.2, lambda t: HOME)
    assert np.all(u == 0.0)
    assert np.array_equal(f.desired[0], HOME) and f.finished(0.2, HOME)


def test_desired_state_is_the_jtc_spline_and_starts_from_the_current_state():
    f = TrajectoryFollower(LIM)
    f.update(0.0, HOME)
    times = np.array([0.5, 1.0])
    pos = np.array([HOME + 0.1, HOME + 0.2])
    vel = np.array([np.full(7, 0.2), np.zeros(7)])
    f.set_trajectory(times, pos, vel, None, start_time=0.0)
    f.update(0.001, HOME)
    # First point after time 0: the spline starts from where the arm is.
    anchor = ([0.0, 0.5, 1.0], [HOME, pos[0], pos[1]], [np.zeros(7), vel[0], vel[1]])
    assert np.allclose(f.desired[0], interpolate(*anchor, None, 0.001)[0])
    for t in (0.25, 0.7):
        f.update(t, HOME)
        assert np.allclose(f.desired[0], interpolate(*anchor, None, t)[0])
        assert np.allclose(f.desired[1], interpolate(*anchor, None, t)[1])
    assert np.allclose(f.error, f.desired[0] - HOME)


def test_new_trajectory_replaces_and_empty_one_holds_position():
    f = TrajectoryFollower(LIM)
    f.update(0.0, HOME)
    f.set_trajectory([0.0, 1.0], [HOME, HOME + 0.3], start_time=0.0)
    f.update(0.5, HOME)
    f.set_trajectory([0.0, 1.0], [HOME, HOME - 0.3], start_time=0.5)
    f.update(1.0, HOME)
    assert np.allclose(f.desired[0], HOME - 0.15)
    here = HOME - 0.1
    f.set_trajectory([], [])
    assert not f.active
    u = run(f, 1.001, 1.5, lambda t: here)
    assert np.array_equal(f.desired[0], here)
    assert np.all(u[-1] == 0.0) and f.finished(1.5, here)


def test_start_stamp_in_the_future_and_finished():
    f = TrajectoryFollower(LIM)
    traj = time_parameterize(np.array([HOME, HOME + 0.2]), LIM, 0.5, 0.5, 0.5)
    f.set_trajectory(traj.times, traj.positions, traj.velocities, traj.accelerations,
                     start_time=1.0)
    run(f, 0.0, 0.9, lambda t: HOME)
    assert np.allclose(f.desired[0], HOME) and f.active
    assert not f.finished(0.9, HOME)
    end = 1.0 + traj.duration
    assert not f.finished(end - 0.01, HOME + 0.2)
    assert f.finished(end, HOME + 0.2) and not f.finished(end, HOME + 0.19)


def test_set_trajectory_rejects_bad_input():
    f = TrajectoryFollower(LIM)
    with pytest.raises(ValueError, match="outside"):
        f.set_trajectory([0.0, 1.0], [HOME, HOME + 5.0])
    with pytest.raises(ValueError, match="6 joints"):
        f.set_trajectory([0.0, 1.0], np.zeros((2, 6)))
    with pytest.raises(ValueError, match="NaN"):
        f.set_trajectory([0.0, 1.0], [HOME, HOME * np.nan])
    with pytest.raises(ValueError, match="start_time"):
        f.set_trajectory([0.0, 1.0], [HOME, HOME], start_time=np.inf)
    with pytest.raises(ValueError, match="hold position"):
        f.hold(np.zeros(3))
    with pytest.raises(ValueError, match="controller time"):
        f.update(np.nan, HOME)
    with pytest.raises(ValueError, match="measured positions must be 7"):
        f.update(0.0, np.zeros(6))
    with pytest.raises(ValueError, match="interpolation"):
        TrajectoryFollower(LIM, interpolation="bezier")
    with pytest.raises(ValueError, match="rate_hz"):
        TrajectoryFollower(LIM, rate_hz=0.0)


def test_nan_measurement_aborts_and_brakes_within_limits():
    f = TrajectoryFollower(LIM)
    watch = LimitWatch()
    f.update(0.0, HOME)
    f.set_trajectory([0.0, 0.5], [HOME, HOME + 0.5], start_time=0.0)
    run(f, 0.001, 0.2, lambda t: HOME, watch)
    moving = np.abs(f.command).max()
    assert moving > 1.0
    bad = HOME.copy()
    bad[2] = np.nan
    u = run(f, 0.2, 0.7, lambda t: bad, watch)
    assert "NaN" in f.last_fault and not f.active
    # Brakes at once (the acceleration may need a step or two to turn: jerk limit).
    assert np.all(np.abs(u).max(axis=0) <= np.abs(u[0]) + LIM.acceleration * DT)
    assert np.all(u[-1] == 0.0)
    assert np.all(np.isnan(f.error))
    run(f, 0.7, 0.8, lambda t: HOME, watch)
    assert np.array_equal(f.desired[0], HOME)  # holds the last good measurement


def test_step_error_ramps_up_within_acceleration_and_jerk_limits():
    f = TrajectoryFollower(LIM)
    watch = LimitWatch()
    f.hold(HOME + np.array([1.0, -1.0, 1.0, 0.5, -1.0, 1.0, -1.0]))
    u = run(f, 0.0, 0.6, lambda t: HOME, watch)
    assert np.allclose(np.abs(u[-1]), LIM.velocity)  # saturated at the velocity limit


def test_integral_is_clamped_and_does_not_wind_up_while_saturated():
    def blocked_arm(i_clamp):
        """I-only controller, arm blocked: +1 rad error for 3 s, then -1 rad."""
        gains = PIDGains(p=0.0, i=10.0, d=0.0, i_clamp=i_clamp, ff_velocity_scale=0.0)
        f = TrajectoryFollower(LIM, gains)
        f.hold(HOME + 1.0)
        first = run(f, 0.0, 3.0, lambda t: HOME)
        f.hold(HOME - 1.0)
        return first, run(f, 3.0, 3.6, lambda t: HOME)

    saturated, recovery = blocked_arm(i_clamp=5.0)
    assert np.allclose(saturated[-1], LIM.velocity)  # the I term alone saturates the output
    assert np.all(recovery[-1] < 0.0)
    # Without anti-windup the integral would sit at the clamp, so a looser clamp would
    # delay the recovery; with it, the integral stopped at the velocity limit either way.
    assert np.array_equal(blocked_arm(i_clamp=50.0)[1], recovery)
    # A clamp below the velocity limit caps the I term's share of the output.
    assert np.allclose(blocked_arm(i_clamp=0.5)[0][-1], 0.5)


def test_never_commands_past_a_position_limit():
    """Hold a target beyond the upper limits: an ideal arm stops `POSITION_LIMIT_MARGIN`
    inside them, never on or past them."""
    f = TrajectoryFollower(LIM)
    q = HOME.copy()
    watch = LimitWatch()
    for k in range(3000):
        if k == 0:
            f.hold(LIM.upper + 0.5)
        u = f.update(k * DT, q)
        watch.check(u, DT)
        q = q + u * DT
        assert np.all(q <= LIM.upper - POSITION_LIMIT_MARGIN + 1e-4), q - LIM.upper
    assert np.allclose(q, LIM.upper - POSITION_LIMIT_MARGIN, atol=2e-3)
    q = LIM.lower.copy()
    f = TrajectoryFollower(LIM)
    f.hold(LIM.lower - 1.0)
    assert np.all(run(f, 0.0, 0.1, lambda t: q) >= 0.0)


def test_shaper_reaches_a_target_without_overshoot():
    shaper = CommandShaper(LIM)
    u, a = np.zeros(7), np.zeros(7)
    target = np.array([1.0, -0.5, 0.001, 2.0, -2.6, 0.0, 0.3])
    trace = []
    for _ in range(400):
        u, a = shaper.shape(target, u, a, DT)
        trace.append(u)
    trace = np.array(trace)
    assert np.allclose(u, target, atol=1e-12)
    assert np.all(np.abs(trace) <= np.abs(target) + 1e-12)  # monotone, no overshoot


# ----------------------------------------------------------------------------- properties

finite_q = st.lists(st.floats(-10.0, 10.0), min_size=7, max_size=7)
wild_q = st.lists(st.one_of(st.floats(allow_nan=True, allow_infinity=True),
                            st.floats(-1e6, 1e6)), min_size=7, max_size=7)
event = st.one_of(
    st.tuples(st.just("measure"), st.one_of(finite_q, wild_q), st.integers(1, 60)),
    st.tuples(st.just("trajectory"), st.integers(0, 2**31 - 1), st.integers(1, 60)),
    st.tuples(st.just("hold"), finite_q, st.integers(1, 60)),
    st.tuples(st.just("empty"), st.just(None), st.integers(1, 60)),
    st.tuples(st.just("glitch"), st.integers(0, 6), st.integers(1, 5)),
)


def random_points(seed: int):
    """A random acceptable JointTrajectory: times, positions, maybe velocities/accelerations."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 5))
    times = np.cumsum(rng.uniform(0.01, 0.5, n)) - (0.0 if rng.random() < 0.5 else 0.01)
    pos = rng.uniform(LIM.lower, LIM.upper, (n, 7))
    vel = rng.uniform(-LIM.velocity, LIM.velocity, (n, 7)) if rng.random() < 0.7 else None
    acc = rng.normal(0.0, 50.0, (n, 7)) if vel is not None and rng.random() < 0.5 else None
    return np.maximum(times, 0.0), pos, vel, acc


@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # absurd inputs overflow on purpose
@settings(max_examples=120, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow])
@given(rate=st.sampled_from([100.0, 500.0, 1000.0]), jitter=st.sampled_from([0.0, 0.3]),
       events=st.lists(event, min_size=1, max_size=8), seed=st.integers(0, 1000))
def test_commands_stay_finite_and_within_limits_whatever_comes_in(rate, jitter, events, seed):
    rng = np.random.default_rng(seed)
    f = TrajectoryFollower(LIM, rate_hz=rate)
    watch = LimitWatch(dt0=1.0 / rate)
    t, q = 0.0, HOME.copy()
    for kind, value, steps in events:
        if kind == "trajectory":
            times, pos, vel, acc = random_points(value)
            try:  # most random ones cannot be followed within the limits: refused
                f.set_trajectory(times, pos, vel, acc, start_time=None if value % 2 else t)
            except ValueError as exc:
                assert "limits" in str(exc), exc
        elif kind == "hold":
            f.hold(value)
        elif kind == "empty":
            f.set_trajectory([], [])
        elif kind == "glitch":  # a few NaN readings of one joint, then the same arm again
            good, q = q, q.copy()
            q[value] = np.nan
        else:
            q = np.array(value, dtype=float)
        for _ in range(steps):
            dt = (1.0 + jitter * rng.uniform(-1.0, 1.0)) / rate
            t += dt
            u = f.update(t, q)
            watch.check(u, dt)
            if np.all(np.isfinite(q)):
                q = q + u * dt  # the arm moves as commanded between measurements
        if kind == "glitch":
            q = good


# ----------------------------------------------------------------------------- JTC semantics

def test_nonzero_final_velocity_is_refused_unless_allowed():
    times, pos, vel = points()
    vel = [list(v) for v in vel]
    vel[-1][2] = 0.1
    reason = validate_trajectory(NAMES, NAMES, times, pos, vel, None, LIM)
    assert "panda_joint3" in reason and "allow_nonzero_velocity_at_trajectory_end" in reason
    assert validate_trajectory(NAMES, NAMES, times, pos, vel, None, LIM,
                               allow_nonzero_end_velocity=True) is None


def test_partial_joints_are_refused_unless_allowed_and_then_hold_their_position():
    names = [NAMES[4], NAMES[1]]
    times, pos = [0.5], [[0.3, -0.2]]
    assert "allow_partial_joints_goal" in validate_trajectory(names, NAMES, times, pos, None,
                                                              None, LIM)
    assert validate_trajectory(names, NAMES, times, pos, None, None, LIM,
                               allow_partial=True) is None
    _, p, v, _ = reorder_points(names, NAMES, times, pos, [[0.0, 0.0]], None, fill=HOME)
    expected = HOME.copy()
    expected[[4, 1]] = [0.3, -0.2]
    assert np.array_equal(p[0], expected) and np.array_equal(v, np.zeros((1, 7)))


def test_future_stamp_is_approached_from_the_current_state_not_waited_for():
    f = TrajectoryFollower(LIM)
    f.update(0.0, HOME)
    goal = HOME + 0.1
    f.set_trajectory([0.0], [goal], [np.zeros(7)], None, start_time=1.0)  # reach it at t=1
    f.update(0.5, HOME)
    assert np.all((f.desired[0] > HOME + 0.01) & (f.desired[0] < goal - 0.01))
    f.update(1.0, HOME)
    assert np.allclose(f.desired[0], goal)


def test_a_trajectory_too_fast_to_follow_is_refused_not_clipped():
    f = TrajectoryFollower(LIM)
    f.update(0.0, HOME)
    f.hold(HOME)
    with pytest.raises(ValueError, match="cannot be followed within the limits"):
        f.set_trajectory([0.05], [HOME + 0.3], [np.zeros(7)])  # ~9 rad/s
    assert not f.active  # what ran (a hold) goes on


def _track(f, q0, t_end, block=False):
    """Follow with an arm that moves as commanded (or not at all); the events."""
    q = q0.copy()
    for t in np.arange(0.001, t_end, DT):
        u = f.update(float(t), q)
        if not block:
            q = q + u * DT
    return q, f.take_events()


def test_path_tolerance_aborts_and_holds_the_measured_position():
    tol = Tolerances(np.full(7, 0.01), np.zeros(7))
    f = TrajectoryFollower(LIM, tolerances=tol)
    f.update(0.0, HOME)
    f.set_trajectory([1.0], [HOME + 0.3], [np.zeros(7)])
    q, events = _track(f, HOME, 0.5, block=True)  # a blocked arm falls behind
    assert [level for level, _ in events] == ["error"]
    assert "path tolerance violated" in events[0][1] and "constraints.panda_joint1" in events[0][1]
    assert not f.active and np.array_equal(f.desired[0], HOME)


def test_goal_time_aborts_when_the_goal_is_not_reached_and_reports_a_reached_one():
    tol = Tolerances(np.zeros(7), np.full(7, 1e-3), goal_time=0.2)
    f = TrajectoryFollower(LIM, tolerances=tol)
    f.update(0.0, HOME)
    f.set_trajectory([0.3], [HOME + 0.01], [np.zeros(7)])
    _, events = _track(f, HOME, 0.8, block=True)
    assert len(events) == 1 and "goal not reached within constraints.goal_time" in events[0][1]
    f = TrajectoryFollower(LIM, tolerances=tol)
    f.update(0.0, HOME)
    f.set_trajectory([0.3], [HOME + 0.01], [np.zeros(7)])
    _, events = _track(f, HOME, 0.8)
    assert len(events) == 1 and events[0][1].startswith("goal reached"), events


@pytest.mark.parametrize("delay_ticks", [0, 2, 6])
def test_a_plain_move_on_a_lagging_arm_settles_without_overshoot(delay_ticks):
    """The mock arm's 20 ms actuator lag plus a loop delay: the goal is approached from one
    side (before the velocity lead, 1.3-1.5 mrad past it)."""
    from collections import deque

    from damon_ros.simulation.mock_arm import ArmSim

    f = TrajectoryFollower(LIM)
    sim = ArmSim(LIM, HOME)
    goal = HOME + np.array([0.3, 0, 0, 0, 0, 0, 0])
    measured = deque([HOME] * (delay_ticks + 1))
    f.update(0.0, HOME)
    f.set_trajectory([0.75, 1.5], [0.5 * (HOME + goal), goal],
                     [0.5 * (goal - HOME) / 0.75, np.zeros(7)])
    past = []
    for k in range(1, 3500):
        sim.command(f.update(k * DT, measured.popleft()), k * DT)
        q, _ = sim.step(DT, (k + 1) * DT)
        measured.append(q)
        past.append(q[0] - goal[0])
    past = np.array(past)
    assert past.max() < 5e-5, past.max()  # never more than 0.05 mrad beyond the goal
    assert abs(past[-1]) < 1e-4


def test_a_stop_that_cannot_be_interpolated_onto_is_joined_not_refused():
    """A brake planned from a state measured while the arm accelerated: its first point lies
    mrad from the arm, yet bending the arm's velocity onto it in 5 ms asks ~37 rad/s². It is
    joined (the note says so) and the commands stay within the limits; a jump of 0.3 rad in
    50 ms stays refused (test above)."""
    from damon_ros.planning.trajectory import stop_trajectory

    f = TrajectoryFollower(LIM)
    u = np.array([0.3, 0.2, 0.1, 0.3, 0.1, 0.2, 0.3])
    f.update(0.0, HOME)
    stop = stop_trajectory(HOME, 0.8 * u, LIM, coast_s=0.03)
    plan = f.prepare(stop.times[1:], stop.positions[1:], stop.velocities[1:],
                     stop.accelerations[1:], start_time=-0.005, state=(0.0, HOME, u))
    assert plan.note.startswith("joined at its first point"), plan.note
    f.start(plan)
    q, previous = HOME.copy(), f.update(0.0, HOME)
    for k in range(1, 600):  # the arm moves as commanded; the commands keep the limits
        q = q + previous * 1e-3
        command = f.update(k * 1e-3, q)
        assert np.all(np.abs(command) <= LIM.velocity + 1e-9)
        assert np.all(np.abs(command - previous) <= LIM.acceleration * 1e-3 * (1 + 1e-6))
        previous = command
    assert np.max(np.abs(previous)) < 1e-3  # settling at the brake's end
    assert np.max(np.abs(q - stop.positions[-1])) < 5e-3


def _stop_as_sent(q: np.ndarray, qd: np.ndarray, age_s: float):
    """A stop as the planner node sends it (`nodes.planner._publish_stop`): the planner's
    brake from the state measured ``age_s`` ago, held 1 s past now, without its first
    sample (time 0, the measured state), stamped with the measurement time; the arrays the
    controller validates, in its joint order."""
    from damon_ros.planning.graph_planner import BRAKE_LATENCY_S
    from damon_ros.planning.trajectory import held_until, stop_trajectory

    stop = held_until(stop_trajectory(q, qd, LIM, coast_s=BRAKE_LATENCY_S, dt=0.01),
                      age_s + 1.0)
    velocities, accelerations = stop.velocities[1:].copy(), stop.accelerations[1:].copy()
    velocities[-1] = accelerations[-1] = 0.0  # `_exactly_at_rest`
    return stop.times[1:], stop.positions[1:], velocities, accelerations


@pytest.mark.parametrize("age_ms", [0.5, 2.0, 5.0, 8.0, 30.0])
def test_a_stop_from_full_speed_near_a_joint_limit_is_accepted_and_keeps_the_limits(age_ms):
    """The soak's refused stop: joint 7 at its velocity limit 0.3 rad before its position
    limit, the stop measured ``age_ms`` before it reaches the controller, whose arm is
    where its (slightly different) command took it. At 2.61 rad/s the brake's first point
    (10 ms) lies up to 26 mrad ahead of the arm, beyond the join distance, yet only
    because the arm is moving there: the controller takes it (before: "asks panda_joint7
    for velocity 2.659"), and every command it then gives keeps the limits."""
    from damon_ros.planning.follower import validate_trajectory

    q0 = HOME.copy()
    q0[6] = LIM.upper[6] - 0.3
    qd = np.array([0.3, -0.2, 0.1, 0.3, -0.1, 0.2, LIM.velocity[6]])
    u = qd * np.array([1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 0.995])  # the command trails a bit
    age = 1e-3 * age_ms
    q_now = q0 + u * age + 2e-4
    times, positions, velocities, accelerations = _stop_as_sent(q0, qd, age)
    names = list(LIM.names)
    assert validate_trajectory(names, names, times, positions, velocities, accelerations,
                               LIM) is None
    f = TrajectoryFollower(LIM)
    plan = f.prepare(times, positions, velocities, accelerations, start_time=10.0 - age,
                     state=(10.0, q_now, u))
    f.start(plan)
    q, previous = q_now.copy(), f.update(10.0, q_now)
    for k in range(1, 1500):  # the arm moves as commanded; the commands keep the limits
        command = f.update(10.0 + k * 1e-3, q)
        assert np.all(np.abs(command) <= LIM.velocity + 1e-9)
        assert np.all(np.abs(command - previous) <= LIM.acceleration * 1e-3 * (1 + 1e-6))
        q, previous = q + command * 1e-3, command
    assert np.max(np.abs(previous)) < 1e-3  # stopped
    assert np.all(q <= LIM.upper) and np.max(np.abs(q - positions[-1])) < 5e-3


def test_brake_from_full_speed_stops_within_the_limits_and_holds():
    """`TrajectoryFollower.brake` (what the controller does with a trajectory it cannot
    follow from here): the command falls to zero within the acceleration and jerk limits
    and the arm then holds where it stopped."""
    f = TrajectoryFollower(LIM)
    f.update(0.0, HOME)
    f.set_trajectory([2.0], [HOME + np.array([0, 0, 0, 0, 0, 0, 2.0])], [np.zeros(7)])
    q, previous = HOME.copy(), f.update(0.0, HOME)
    for k in range(1, 800):  # under way, fast
        q = q + previous * 1e-3
        previous = f.update(k * 1e-3, q)
    assert previous[6] > 1.0
    f.brake()
    assert f.finished(0.8, q) is False
    a_prev = np.zeros(7)
    for k in range(800, 2500):
        q = q + previous * 1e-3
        command = f.update(k * 1e-3, q)
        a = (command - previous) / 1e-3
        assert np.all(np.abs(command) <= np.abs(previous) + 1e-9)  # only ever slower
        assert np.all(np.abs(a) <= LIM.acceleration * (1 + 1e-6))
        assert np.all(np.abs(a - a_prev) <= LIM.jerk * 1e-3 * (1 + 1e-6) + 1e-9)
        previous, a_prev = command, a
    assert np.max(np.abs(previous)) < 1e-3 and not f.active
    assert f.finished(2.5, q)  # holding where it stopped
