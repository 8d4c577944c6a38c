"""controller as a real process over real DDS, closed loop with mock_panda.

One controller and one mock_panda, both started from their ``config/*.yaml`` (the controller
with the planner heartbeat watchdog on, fed by a fake planner process), serve the
tests of this module. The fixture first starts the controller alone and checks that it
commands nothing before the first joint state, and at the end checks that SIGINT/SIGTERM
end both nodes with exit code 0. Stale joint states are made exact by freezing mock_panda
with SIGSTOP: the last joint state it published is then known from its stamp.
"""

from __future__ import annotations

import signal
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import rosutil
from diagnostic_msgs.msg import DiagnosticArray
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray
from trajectory_msgs.msg import JointTrajectory

from damon_ros.core.limits import joint_limits
from damon_ros.ros import topics
from damon_ros.ros.environment import node_environment
from damon_ros.ros.launch import read_log

CONFIG = rosutil.ROOT / "config"
NAMES = [f"panda_joint{i}" for i in range(1, 8)]
LIMITS = joint_limits("panda")
JS_TIMEOUT_S = 0.1  # joint_state_timeout_s of config/controller.yaml
HEARTBEAT_S = 0.5  # planner_heartbeat_timeout_s given to the controller
TOLERANCE = 2e-3  # rad, goal tolerance of the closed loop


def trajectory(times, positions, velocities=None, names=NAMES) -> JointTrajectory:
    """A JointTrajectory with a zero stamp (start on arrival), points in ``names`` order."""
    return rosutil.trajectory_msg(times, positions, velocities, names)


def _log(proc: subprocess.Popen, name: str) -> str:
    return f"\n--- {name} log ---\n" + read_log(proc)[-4000:]


@dataclass(repr=False)  # recorders of ~1e5 messages: pytest printed them for minutes
class Arm:
    ros: rosutil.RosClient
    mock: subprocess.Popen
    controller: subprocess.Popen
    states: rosutil.Recorder
    commands: rosutil.Recorder
    controller_state: rosutil.Recorder
    trajectories: object
    planner: subprocess.Popen | None = None  # /damon/planner_status at 20 Hz
    heartbeats: rosutil.Recorder | None = None
    commands_before_first_state: int = -1

    def q(self) -> np.ndarray:
        return np.array(self.states.last.position)

    def settle(self, timeout_s: float = 10.0) -> bool:
        """Still for the last 100 states (0.1 s): one slow state may be the turning point
        of the overshoot when the arm brakes and comes back to the hold position. The bound
        is for a starved test client (CI: the controller logged the hold reached within
        0.04 s, the client had not seen 100 still states within 3 s); an arm that never
        stops fails it all the same."""
        def still() -> bool:
            recent = self.states.messages[-100:]
            return len(recent) == 100 and max(
                np.max(np.abs(m.velocity)) for m in recent) < 1e-4

        return self.ros.spin_until(still, timeout_s)

    def first_command_below(self, t: float, speed: float) -> float | None:
        """When the controller published its first command with all |u| <= ``speed`` after
        system time ``t`` (publisher clock, so this process's own delays do not count)."""
        for source, msg in self.commands.published_after(t):
            if np.max(np.abs(msg.data)) <= speed:
                return source
        return None

    def stale_count(self) -> int:
        return len(rosutil.log_lines(self.controller, "joint states stale"))

    def logs(self) -> str:
        return _log(self.controller, "controller") + _log(self.mock, "mock_panda")


def _start_arm(ros: rosutil.RosClient, env: dict, tmp: Path) -> Arm:
    controller = rosutil.start_node("controller",
                                    {"planner_heartbeat_timeout_s": HEARTBEAT_S}, env,
                                    tmp / "controller.log", params_file=CONFIG / "controller.yaml")
    arm = Arm(ros, None, controller,
              ros.record(JointState, topics.JOINT_STATES),
              ros.record(Float64MultiArray, topics.JOINT_COMMANDS),
              ros.record(JointState, topics.CONTROLLER_STATE),
              ros.publisher(JointTrajectory, topics.JOINT_TRAJECTORY))
    arm.planner = rosutil.start_heartbeat(env, tmp / "planner.log")
    arm.heartbeats = ros.record(DiagnosticArray, topics.PLANNER_STATUS)
    # The controller alone: its command publisher is up, yet it commands nothing.
    ros.wait_for_publishers(topics.JOINT_COMMANDS, 1, 20.0)
    ros.spin_for(0.3)
    arm.commands_before_first_state = len(arm.commands)
    arm.mock = rosutil.start_node("mock_panda", None, env, tmp / "mock_panda.log",
                                  params_file=CONFIG / "mock_panda.yaml")
    return arm


@pytest.fixture(scope="module")
def arm(tmp_path_factory):
    domain = rosutil.next_domain_id(__file__)
    tmp = tmp_path_factory.mktemp("closed_loop")
    env = node_environment(domain, tmp)
    procs = []
    try:
        with rosutil.RosClient(domain) as ros:
            arm = _start_arm(ros, env, tmp)
            procs = [arm.controller, arm.mock, arm.planner]
            assert ros.spin_until(lambda: len(arm.commands) > 10 and len(arm.states) > 10,
                                  20.0), arm.logs()
            assert ros.wait_for_subscribers(arm.trajectories, 1, 10.0), arm.logs()
            yield arm
    finally:
        t0 = time.monotonic()
        results = [rosutil.stop_node(p, first_signal=sig) for p, sig in
                   zip(procs, (signal.SIGTERM, signal.SIGINT, signal.SIGINT), strict=False)]
        stop_s = time.monotonic() - t0
    for code, log in results[:2]:
        assert code == 0, log[-4000:]
        assert "loop timing" in log
    assert stop_s < 5.0


def test_nothing_is_commanded_before_the_first_joint_state(arm: Arm):
    assert arm.commands_before_first_state == 0


def _send_and_reach(arm: Arm, q0: np.ndarray, goal: np.ndarray) -> float | None:
    """Send a two-point trajectory q0 -> goal (1.5 s); when the mock reached the goal, or None.

    The time is the mock's own publication time of the first joint state within TOLERANCE,
    measured from the moment the trajectory was sent.
    """
    mid = 0.5 * (q0 + goal)
    # Joints listed in another order than the controller's: reordering by name is accepted.
    order = [6, 0, 3, 1, 5, 2, 4]
    rows = np.array([mid, goal])[:, order]
    velocities = np.array([0.5 * (goal - q0) / 0.75, np.zeros(7)])[:, order]
    msg = trajectory([0.75, 1.5], rows, velocities, names=[NAMES[j] for j in order])
    sent = time.time()
    arm.trajectories.publish(msg)

    def reached() -> float | None:
        for source, state in arm.states.published_after(sent):
            if np.max(np.abs(np.array(state.position) - goal)) < TOLERANCE:
                return source - sent
        return None

    arm.ros.spin_until(lambda: reached() is not None, 6.0)
    return reached()


def test_follows_a_trajectory_to_the_goal_and_holds(arm: Arm):
    assert arm.settle()
    q0 = arm.q()
    goal = q0 + np.array([0.3, -0.2, 0.25, 0.3, -0.3, 0.2, 0.4])
    start = len(arm.commands)
    for _ in range(2):
        stale = arm.stale_count()
        reached = _send_and_reach(arm, arm.q(), goal)
        # Only a logged stale-joint-state abort (a stall of this shared machine, which the
        # controller must answer by stopping) excuses a miss, and only once.
        if reached is not None or arm.stale_count() == stale:
            break
        assert arm.settle()
    assert reached is not None, arm.logs()
    # follows the timing, not just the end point (not before the end; the late bound
    # leaves room for a busy test client that sees the states late: 2.7 s seen once)
    assert 1.3 < reached < 4.0, reached
    arm.ros.spin_for(0.5)
    assert np.max(np.abs(arm.q() - goal)) < TOLERANCE  # holds
    # The trajectory ends 1.5 s after it was sent; "reached" (within TOLERANCE) may come
    # before that, and a busy test process may still be reading older states: wait for the
    # controller to report the end, then check it exactly.
    assert arm.ros.spin_until(lambda: np.allclose(arm.controller_state.last.position, goal,
                                                  atol=1e-9, rtol=0.0), 3.0)
    held = arm.controller_state.last
    assert list(held.name) == NAMES
    np.testing.assert_allclose(held.position, goal, atol=1e-9)  # desired = goal
    np.testing.assert_allclose(held.velocity, 0.0, atol=1e-9)
    assert np.max(np.abs(held.effort)) < TOLERANCE  # error
    u = np.array([c.data for c in arm.commands.messages[start:]])
    assert u.shape[1] == 7
    assert np.all(np.abs(u) <= LIMITS.velocity + 1e-9)
    assert np.max(np.abs(u)) > 0.2  # it did move by commanding velocities
    assert "accepted trajectory" in read_log(arm.controller)


EXPECTED = {"unknown joint": "panda_joint8", "duplicate joint": "repeat",
            "times": "strictly increasing", "nan": "NaN", "limits": "outside",
            "velocity": "rad/s", "short point": "every point needs 7 positions",
            "ended": "ends in the past"}


@pytest.mark.parametrize("case", list(EXPECTED))
def test_rejects_a_malformed_trajectory_and_stays_still(arm: Arm, case: str):
    assert arm.settle()
    q0 = arm.q()
    target = q0 + 0.2
    times, rows, names = [0.5, 1.0], np.array([q0 + 0.1, target]), list(NAMES)
    velocities = None
    if case == "unknown joint":
        names[6] = "panda_joint8"
    elif case == "duplicate joint":
        names[6] = names[0]
    elif case == "times":
        times = [1.0, 1.0]
    elif case == "nan":
        rows[1, 3] = np.nan
    elif case == "limits":
        rows[1, 3] = LIMITS.upper[3] + 0.5
    elif case == "velocity":
        velocities = np.zeros((2, 7))
        velocities[0, 2] = 1.5 * LIMITS.velocity[2]
    msg = trajectory(times, rows, velocities, names=names)
    if case == "short point":
        msg.points[1].positions = msg.points[1].positions[:6]
    elif case == "ended":  # stamped to start 10 s ago: it would have ended 9 s ago
        stamp = arm.ros.node.get_clock().now().nanoseconds - 10_000_000_000
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
    before = len(rosutil.log_lines(arm.controller, "rejected trajectory"))
    arm.trajectories.publish(msg)
    arm.ros.spin_until(
        lambda: len(rosutil.log_lines(arm.controller, "rejected trajectory")) > before, 3.0)
    arm.ros.spin_for(0.3)
    lines = rosutil.log_lines(arm.controller, "rejected trajectory")
    assert len(lines) == before + 1, arm.logs()
    assert np.max(np.abs(arm.q() - q0)) < 1e-4  # the arm did not move
    assert np.max(np.abs(arm.commands.last.data)) < 1e-3
    assert EXPECTED[case] in lines[-1], lines[-1]


def _hold_here(arm: Arm) -> JointTrajectory:
    """The stop every JTC-semantics controller executes: one point at the current position."""
    return trajectory([0.0], [arm.q()], [np.zeros(7)])


def _under_way(arm: Arm) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(start, direction, goal) of a slow move of joint 1, once the arm is under way.

    Under way within 2 s, then slowly on for 58 s (15 mrad/s): a busy test process reads
    states late, and its stop must still land well before the end (in CI a 3 s trajectory
    had ended before the stop arrived; here the hold came 15 s after the empty one)."""
    assert arm.settle()
    q0 = arm.q()
    step = np.array([1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    goal = q0 + 0.8 * step
    arm.trajectories.publish(trajectory([2.0, 60.0], [q0 + 0.1 * step, goal],
                                        [0.015 * step, np.zeros(7)]))
    assert arm.ros.spin_until(lambda: arm.q()[0] > q0[0] + 0.02, 5.0), arm.logs()
    return q0, step, goal


def test_empty_trajectory_is_refused_and_a_hold_trajectory_stops(arm: Arm):
    """JTC semantics: an empty trajectory is rejected with a line and the motion goes on;
    a one-point trajectory at the current position stops the arm and holds it."""
    q0, step, goal = _under_way(arm)
    before = len(rosutil.log_lines(arm.controller, "rejected trajectory of 0 points"))
    arm.trajectories.publish(JointTrajectory(joint_names=NAMES))  # no points: refused
    assert arm.ros.spin_until(lambda: len(rosutil.log_lines(
        arm.controller, "rejected trajectory of 0 points")) > before, 5.0), arm.logs()
    moving = arm.q()[0]
    assert arm.ros.spin_until(lambda: arm.q()[0] > moving + 0.01, 5.0)  # still going
    arm.trajectories.publish(_hold_here(arm))
    assert arm.settle(), arm.logs()
    q_stop = arm.q()
    assert q0[0] + 0.02 < q_stop[0] < goal[0] - 0.2  # stopped on the way
    arm.ros.spin_for(0.5)
    assert np.max(np.abs(arm.q() - q_stop)) < 2e-3  # and holds there


def test_a_trajectory_that_cannot_be_followed_from_here_stops_the_arm(arm: Arm):
    """Well formed but not followable from the arm's state (0.3 rad in 50 ms): refused
    with a line, and unlike the JTC the arm brakes and holds instead of going on with the
    old motion, for the refused one may have been a stop (a soak arm went on)."""
    q0, step, goal = _under_way(arm)
    before = len(rosutil.log_lines(arm.controller, "braking to a stop"))
    arm.trajectories.publish(trajectory([0.05], [arm.q() - 0.3 * step], [np.zeros(7)]))
    assert arm.ros.spin_until(lambda: len(rosutil.log_lines(
        arm.controller, "braking to a stop")) > before, 5.0), arm.logs()
    assert arm.settle(), arm.logs()
    q_stop = arm.q()
    assert q0[0] + 0.02 < q_stop[0] < goal[0] - 0.2  # stopped on the way, not jumped back
    arm.ros.spin_for(0.5)
    assert np.max(np.abs(arm.q() - q_stop)) < 2e-3  # and holds there


def _last_before_silence(ros: rosutil.RosClient, recorder: rosutil.Recorder,
                         quiet_s: float = 0.3, timeout_s: float = 10.0) -> float:
    """Publication time of the last message of a stream that has stopped.

    This process may take messages late; only once nothing new came for ``quiet_s`` is the
    last one recorded the last one sent.
    """
    seen = [len(recorder), time.monotonic()]

    def quiet() -> bool:
        if len(recorder) != seen[0]:
            seen[:] = [len(recorder), time.monotonic()]
        return time.monotonic() - seen[1] > quiet_s

    assert ros.spin_until(quiet, timeout_s), "the stream did not stop"
    return recorder.sources[-1]


def _silence_the_planner(arm: Arm, goal: np.ndarray) -> float:
    """Start a move to ``goal``, stop the planner's heartbeat; when the arm was stopped.

    The time runs from the planner's last heartbeat to the controller's first command
    below 0.01 rad/s, both publication times.
    """
    arm.trajectories.publish(trajectory([2.0], [goal], [np.zeros(7)]))
    # Under way, well above the speed the hold is detected by, before the planner falls
    # silent: a fixed wait here let a late trajectory start look like a hold at once.
    assert arm.ros.spin_until(
        lambda: np.max(np.abs(arm.commands.last.data)) > 0.05, 5.0), arm.logs()
    arm.planner.send_signal(signal.SIGSTOP)  # the planner falls silent, exactly
    try:
        silent = _last_before_silence(arm.ros, arm.heartbeats)
        # Holding is position control: the command settles near zero, not exactly at it.
        assert arm.ros.spin_until(lambda: arm.first_command_below(silent, 0.01), 5.0), \
            arm.logs()
        stopped = arm.first_command_below(silent, 0.01) - silent
        assert arm.settle()
    finally:
        arm.planner.send_signal(signal.SIGCONT)
    n = len(arm.heartbeats)
    assert arm.ros.spin_until(lambda: len(arm.heartbeats) > n + 2, 5.0)
    return stopped


def test_silent_planner_holds_the_arm(arm: Arm):
    assert arm.settle()
    for _ in range(2):  # a logged stale-joint-state stop spoils one attempt (see above)
        stale = arm.stale_count()
        lines = len(rosutil.log_lines(arm.controller, f"no {topics.PLANNER_STATUS}"))
        goal = arm.q() + np.array([0.3, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
        stopped = _silence_the_planner(arm, goal)
        if arm.stale_count() == stale:
            break
        arm.trajectories.publish(_hold_here(arm))
        assert arm.settle()
    print(f"\nsilent planner: holding {1e3 * stopped:.1f} ms after its last heartbeat "
          f"(timeout {1e3 * HEARTBEAT_S:.0f} ms)")
    # Never before the timeout; after it, within a delay a loaded 2-core machine keeps to
    # (the quiet figure, ~0.5 s, is printed above; CI once saw 2.5 s while the
    # controller's executor still carried the 1 kHz joint states).
    assert HEARTBEAT_S - 0.005 < stopped < HEARTBEAT_S + 1.0, stopped
    assert arm.q()[0] < goal[0] - 0.05  # it never got there
    np.testing.assert_allclose(arm.controller_state.last.velocity, 0.0)  # holding
    assert len(rosutil.log_lines(arm.controller, f"no {topics.PLANNER_STATUS}")) == lines + 1


def _braking_start(commands: rosutil.Recorder, zero: float) -> float:
    """Publication time of the first command of the monotone ramp that ends at ``zero``.

    With frozen joint states the tracking error only grows, so the command grows until the
    controller declares the states stale; from then on it falls monotonically to zero.
    """
    sources = np.array(commands.sources)
    u = np.array([np.max(np.abs(m.data)) for m in commands.messages])
    k = int(np.searchsorted(sources, zero))
    while k > 0 and u[k - 1] >= u[k]:
        k -= 1
    return float(sources[k])


def test_stale_joint_states_brake_the_commands_to_zero(arm: Arm):
    assert arm.settle()
    q0 = arm.q()
    lines = len(rosutil.log_lines(arm.controller, "joint states stale"))
    arm.trajectories.publish(trajectory([2.0], [q0 + np.array([0.3, 0, 0, 0, 0, 0, 0])],
                                        [np.zeros(7)]))
    arm.ros.spin_for(0.5)  # accelerating along the quintic
    arm.mock.send_signal(signal.SIGSTOP)  # joint states stop, exactly
    try:
        last_state = _last_before_silence(arm.ros, arm.states)
        assert arm.ros.spin_until(lambda: arm.first_command_below(last_state, 0.0), 5.0)
        zero = arm.first_command_below(last_state, 0.0)
        braking = _braking_start(arm.commands, zero) - last_state
        to_zero = zero - last_state
    finally:
        arm.mock.send_signal(signal.SIGCONT)
    print(f"\nstale joint states: braking after {1e3 * braking:.1f} ms, zero command after "
          f"{1e3 * to_zero:.1f} ms (timeout {1e3 * JS_TIMEOUT_S:.0f} ms)")
    # Braking starts once the states are JS_TIMEOUT_S old (+ one tick + DDS + wake-up: ~5 ms
    # on a quiet machine, printed above); the ramp to zero keeps to the acceleration and jerk
    # limits: ~25 ms from this speed. The upper bound leaves room for a busy machine.
    assert JS_TIMEOUT_S - 0.002 < braking < JS_TIMEOUT_S + 0.05, braking
    assert braking < to_zero < braking + 0.05, to_zero
    assert len(rosutil.log_lines(arm.controller, "joint states stale")) == lines + 1
    assert arm.ros.spin_until(
        lambda: "joint states are back" in read_log(arm.controller), 3.0)
    assert arm.settle()
    q_hold = arm.q()
    arm.ros.spin_for(0.3)
    assert np.max(np.abs(arm.q() - q_hold)) < 1e-3  # holds where it is, no lurch


def test_runs_with_its_defaults(tmp_path: Path):
    """No params file at all: the built-in defaults start the node; SIGTERM ends it."""
    rosutil.assert_starts_with_defaults("controller", topics.JOINT_COMMANDS, __file__, tmp_path)


def test_help_and_bad_parameters(tmp_path: Path):
    env = node_environment(rosutil.next_domain_id(__file__), tmp_path)
    rosutil.assert_help_and_bad_parameter(
        "controller", "-h", ("joint_state_timeout_s", "i_clamp"), "interpolation:=bspline",
        ("interpolation", "bspline"), env)
