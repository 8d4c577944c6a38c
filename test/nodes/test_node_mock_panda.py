"""mock_panda as a real process over real DDS (Fast DDS with the shared-memory profile).

One mock_panda, started from ``config/mock_panda.yaml``, serves the tests of this module in
file order; each test only relies on relative motion, so the order does not matter for
correctness. A second process checks the scenario start state and the contact report,
and the last tests check the shared-memory profile with camera-sized images and the
command line (``--help``, a bad parameter).
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
import yaml
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.serialization import serialize_message
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from damon_ros.core.limits import READY, joint_limits
from damon_ros.core.scenario import load_scenario
from damon_ros.ros import topics
from damon_ros.ros.environment import node_environment
from damon_ros.ros.launch import read_log

CONFIG = rosutil.ROOT / "config" / "mock_panda.yaml"
SCENARIO = Path("/work/shared/scenarios/A-001.yaml")
if not SCENARIO.exists():
    SCENARIO = rosutil.ROOT.parent / "shared" / "scenarios" / "A-001.yaml"
NAMES = [f"panda_joint{i}" for i in range(1, 8)]
LIMITS = joint_limits("panda")
TIMEOUT_S = 0.1  # command_timeout_s of config/mock_panda.yaml


@dataclass
class Graph:
    ros: rosutil.RosClient
    proc: subprocess.Popen
    states: rosutil.Recorder
    commands: object  # the publisher of /damon/joint_commands
    commands_seen: rosutil.Recorder  # every command on /damon/joint_commands, any sender
    domain: int
    first_sent: float = 0.0  # of the last `stream`
    max_gap: float = 0.0

    def q(self) -> np.ndarray:
        return np.array(self.states.last.position)

    def qd(self) -> np.ndarray:
        return np.array(self.states.last.velocity)

    def stream(self, velocity, seconds: float, rate_hz: float = 200.0) -> float:
        """Publish one velocity command at ``rate_hz`` for ``seconds``; time of the last.
        The times of the first and the longest gap between two are kept (`first_sent`,
        `max_gap`): a client stalled by a busy machine leaves gaps the arm stops in."""
        msg = Float64MultiArray(data=[float(v) for v in velocity])
        end = time.monotonic() + seconds
        last = self.first_sent = time.monotonic()
        self.max_gap = 0.0
        while time.monotonic() < end:
            self.commands.publish(msg)
            now = time.monotonic()
            self.max_gap, last = max(self.max_gap, now - last), now
            self.ros.spin_for(1.0 / rate_hz)
        return last

    def settle(self, timeout_s: float = 2.0) -> bool:
        """Wait until the arm has come to rest (velocity below 1e-4 rad/s)."""
        return self.ros.spin_until(
            lambda: self.states.last is not None and np.max(np.abs(self.qd())) < 1e-4,
            timeout_s)


def _failure(proc: subprocess.Popen) -> str:
    return "\n--- mock_panda log ---\n" + read_log(proc)[-4000:]


@pytest.fixture(scope="module")
def graph(tmp_path_factory):
    domain = rosutil.next_domain_id(__file__)
    tmp = tmp_path_factory.mktemp("mock_panda")
    env = node_environment(domain, tmp)
    proc = rosutil.start_node("mock_panda", None, env, tmp / "mock_panda.log",
                              params_file=CONFIG)
    try:
        with rosutil.RosClient(domain) as ros:
            states = ros.record(JointState, topics.JOINT_STATES)
            commands = ros.publisher(Float64MultiArray, topics.JOINT_COMMANDS)
            seen = ros.record(Float64MultiArray, topics.JOINT_COMMANDS)
            assert ros.spin_until(lambda: len(states) > 20, 20.0), _failure(proc)
            assert ros.wait_for_subscribers(commands, 1, 10.0), _failure(proc)
            yield Graph(ros, proc, states, commands, seen, domain)
    finally:
        code, log = rosutil.stop_node(proc, first_signal=signal.SIGINT)
    assert code == 0, log[-4000:]
    assert "loop timing" in log
    assert "limit monitor:" in log  # the totals line (limit_check is on in the config)


def test_publishes_joint_states_at_rate_with_names(graph: Graph):
    graph.states.clear()
    graph.ros.spin_for(1.0)
    msgs = list(graph.states.messages)
    # The test process may not take every message of a 1 kHz stream on a loaded machine, so
    # the rate is judged from the publisher's stamps: consecutive ones are 1 ms apart.
    assert len(msgs) > 200, _failure(graph.proc)
    stamps = np.array([m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec for m in msgs])
    gaps = np.diff(stamps)
    assert np.all(gaps > 0.0)
    assert 0.0008 < np.median(gaps) < 0.00125, f"median period {np.median(gaps)}"
    for m in msgs[:: max(1, len(msgs) // 20)]:
        assert list(m.name) == NAMES
        assert len(m.position) == 7 and len(m.velocity) == 7
        assert m.header.frame_id == ""
    # Nothing commanded yet: the arm rests exactly at the ready pose of the config.
    np.testing.assert_allclose(msgs[-1].position, READY, atol=1e-12)
    np.testing.assert_allclose(msgs[-1].velocity, 0.0, atol=1e-12)


def test_integrates_a_velocity_command(graph: Graph):
    v = np.array([0.2, 0.0, 0.0, 0.0, 0.0, 0.0, -0.1])
    for _ in range(3):
        assert graph.settle()
        q0 = graph.q()
        last = graph.stream(v, 0.5)
        stalled = graph.max_gap
        speeds = np.array([m.velocity for m in graph.states.messages[-50:]])
        graph.stream(np.zeros(7), 0.1)
        assert graph.settle()
        moved = graph.q() - q0
        # commands half the timeout apart: then the arm moved exactly while they came (a
        # client stalled longer on a busy machine let it stop or coast on: again; seen once
        # in a full suite beside two busy loops, 0.377 s of motion for 0.5 s of commands)
        if max(stalled, graph.first_sent - last) < 0.5 * TIMEOUT_S:
            break
    # First-order lag: the rise loses v*tau, the decay gives it back, so q moves v*T.
    np.testing.assert_allclose(moved, v * 0.5, atol=0.015)
    assert np.all(np.abs(moved[1:6]) < 1e-12)
    np.testing.assert_allclose(speeds[-1], v, atol=0.01)


def test_clamps_commands_to_the_velocity_and_acceleration_limits(graph: Graph):
    assert graph.settle()
    start = len(graph.states)
    graph.stream([10.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0], 0.3)
    graph.stream(np.zeros(7), 0.1)
    assert graph.settle()
    msgs = graph.states.messages[start:]
    qd = np.array([m.velocity[0] for m in msgs])
    t = np.array([m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec for m in msgs])
    vmax, amax = LIMITS.velocity[0], LIMITS.acceleration[0]
    assert np.max(np.abs(qd)) <= vmax + 1e-12
    assert np.max(qd) > 0.95 * vmax  # it did run at the limit
    rise = t[np.argmax(qd > 2.0)] - t[np.argmax(qd > 0.01)]
    assert rise >= 0.95 * (2.0 - 0.01) / amax, rise  # no faster than the acceleration limit


def test_reports_limit_violations_and_late_commands(graph: Graph):
    """/damon/sim/limits: a 10 rad/s command is a velocity violation; 200 Hz are late."""
    limits = graph.ros.record(DiagnosticArray, topics.SIM_LIMITS)
    assert graph.ros.spin_until(lambda: len(limits) > 0, 3.0), _failure(graph.proc)
    assert graph.settle()
    graph.stream([10.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0], 0.1)
    graph.stream(np.zeros(7), 0.1)

    def counts() -> dict[str, str]:
        return {kv.key: kv.value for kv in limits.last.status[0].values}

    assert graph.ros.spin_until(lambda: int(counts()["velocity"]) > 0, 3.0), counts()
    status = limits.last.status[0]
    assert status.level == DiagnosticStatus.ERROR and "velocity" in status.message
    values = counts()
    assert int(values["late"]) > 0 and float(values["max_gap_ms"]) > 1.5
    assert int(values["acceleration"]) == 0  # never computed across a gap
    lines = rosutil.log_lines(graph.proc, "first velocity violation")
    assert len(lines) == 1 and "joint 1" in lines[0], lines


def test_stops_when_commands_go_stale(graph: Graph, tmp_path: Path):
    """The command stream comes from a process of its own and stops exactly (SIGSTOP); the
    arm's motion is judged on mock_panda's own publication times of its joint states, so a
    busy test process reading them late does not change what is measured."""
    assert graph.settle()
    stale_lines = len(rosutil.log_lines(graph.proc, "no joint command"))
    env = node_environment(graph.domain, tmp_path)
    commander = rosutil.start_commander(env, tmp_path / "commander.log",
                                        [0.3, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    try:
        assert graph.ros.spin_until(lambda: graph.qd()[0] > 0.29, 20.0), _failure(graph.proc)
        graph.ros.spin_for(0.2)
        commander.send_signal(signal.SIGSTOP)  # the commands stop, exactly
        assert graph.ros.spin_until(lambda: abs(graph.qd()[0]) < 1e-3, 5.0)
        graph.ros.spin_for(0.3)
    finally:
        rosutil.stop_node(commander, first_signal=signal.SIGKILL)
    lines = rosutil.log_lines(graph.proc, "no joint command")
    assert len(lines) == stale_lines + 1, lines  # once per episode
    # When mock_panda's own last command turned stale: the line is logged in that tick. Not
    # the last command this process recorded: a commander frozen mid-send delivers its final
    # messages to one reader and not the other (seen both ways, 20-40 ms apart).
    braking = rosutil.log_time(lines[-1])
    last = braking - TIMEOUT_S  # mock_panda's last command, to within one tick
    states = graph.states.published_after(last - 0.2)
    before = [m.velocity[0] for t, m in states if t < last + 0.6 * TIMEOUT_S]
    # Still moving until the timeout: the last command holds for command_timeout_s ...
    assert len(before) > 50 and min(before) > 0.25, min(before)
    # ... then braking: first-order decay (tau 20 ms) within the acceleration limit.
    stopped = next(t for t, m in states if t > last and abs(m.velocity[0]) < 1e-3)
    assert TIMEOUT_S < stopped - last < TIMEOUT_S + 0.3, stopped - last
    rest = [m.position[0] for t, m in states if t > stopped + 0.05]
    assert len(rest) > 50 and max(rest) - min(rest) < 1e-3  # and it stays at rest


def _bad_burst(graph: Graph) -> None:
    cut = serialize_message(Float64MultiArray(data=[0.5] * 7))[:20]  # bytes of half a message
    for _ in range(5):
        graph.commands.publish(Float64MultiArray(data=[1.0, 2.0, 3.0]))
        graph.commands.publish(Float64MultiArray(data=[float("nan")] * 7))
        graph.commands.publish(Float64MultiArray(data=[float("inf")] + [0.0] * 6))
        graph.commands.publish(cut)


def test_rejects_malformed_commands_and_keeps_running(graph: Graph):
    assert graph.settle()
    before = len(rosutil.log_lines(graph.proc, "rejected joint command"))
    for _ in range(3):
        stale = len(rosutil.log_lines(graph.proc, "no joint command"))
        graph.stream([0.2, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0], 0.2)
        q_before = graph.q()
        _bad_burst(graph)  # shorter than the timeout: the good command stays in force
        graph.ros.spin_for(0.03)
        held = abs(graph.qd()[0] - 0.2) < 0.01
        # stopped, but on the timeout: this client stalled (a loaded machine) between its
        # last good command and the check, which the bad ones do not explain: again
        if held or len(rosutil.log_lines(graph.proc, "no joint command")) == stale:
            break
    assert held, "the last good command should still hold"
    assert graph.q()[0] > q_before[0]
    assert graph.settle(), "a stream of bad commands must end in the timeout stop"
    lines = rosutil.log_lines(graph.proc, "rejected joint command")
    # one line per kind of problem for the whole burst (the repeats are counted)
    assert len(lines) == before + 3, lines
    assert "7 velocities" in lines[-3] and "NaN or inf" in lines[-2], lines
    assert "overruns the 20 bytes" in lines[-1], lines
    assert graph.proc.poll() is None
    count = len(graph.states)
    graph.ros.spin_for(0.2)
    assert len(graph.states) > count + 50  # still publishing


def _contact_scenario(tmp_path: Path) -> tuple[Path, np.ndarray]:
    """A-001 with a second, moving ball that reaches the hand of the start pose at t = 4.5 s
    (the scenario clock starts with the node: the test's client must see clear reports first,
    also when discovery is slow on a busy machine)."""
    from damon_ros.core.robot import Robot

    data = yaml.safe_load(SCENARIO.read_text())
    start = np.array(data["start"]["joints"])
    hand = Robot("mesh").fk(start, "panda_hand")[:3, 3]
    far = hand + np.array([0.0, 0.0, 0.6])
    data["name"] = "contact-test"
    data["obstacles"].append({
        "name": "ball", "shape": "sphere", "size": [0.05], "color": "green",
        "pose": {"position": far.tolist(), "orientation": [0.0, 0.0, 0.0, 1.0]},
        "motion": {"type": "waypoints", "waypoints": [
            [0.0, *far.tolist()], [4.0, *far.tolist()], [4.5, *hand.tolist()]]},
    })
    path = tmp_path / "contact.yaml"
    path.write_text(yaml.safe_dump(data))
    return path, start


def test_scenario_start_and_contact_report(tmp_path: Path):
    path, start = _contact_scenario(tmp_path)
    scenario = load_scenario(path)
    domain = rosutil.next_domain_id(__file__)
    env = node_environment(domain, tmp_path)
    proc = rosutil.start_node("mock_panda", {"scenario": str(path), "contact_check": True,
                                             "contact_rate_hz": 20.0},
                              env, tmp_path / "mock_panda.log", params_file=CONFIG)
    try:
        with rosutil.RosClient(domain) as ros:
            states = ros.record(JointState, topics.JOINT_STATES)
            contact = ros.record(DiagnosticArray, topics.SIM_CONTACT)
            assert ros.spin_until(lambda: len(contact) > 0, 20.0), _failure(proc)
            np.testing.assert_allclose(states.last.position, scenario.start, atol=1e-12)
            first = contact.messages[0].status[0]
            assert first.level == DiagnosticStatus.OK
            values = {kv.key: kv.value for kv in first.values}
            assert float(values["min_clearance_m"]) > 0.05
            assert ros.spin_until(
                lambda: contact.last.status[0].level == DiagnosticStatus.ERROR, 15.0), \
                _failure(proc)
            hit = contact.last.status[0]
            values = {kv.key: kv.value for kv in hit.values}
            assert float(values["min_clearance_m"]) <= 0.0
            assert values["obstacle"] == "ball"
            assert "contact" in hit.message
    finally:
        t0 = time.monotonic()
        code, log = rosutil.stop_node(proc, first_signal=signal.SIGTERM)
    assert code == 0, log[-4000:]
    assert time.monotonic() - t0 < 5.0
    np.testing.assert_allclose(start, scenario.start)


def test_shared_memory_profile_carries_camera_images():
    """Two processes exchange 640x480 rgb8 images through the SHM profile, faster than
    with Fast DDS's defaults (UDP fragments)."""
    domain = rosutil.next_domain_id(__file__)
    rounds = []
    for _ in range(3):
        stats = {shm: rosutil.measure_image_latency(domain, shm_profile=shm, count=30,
                                                    rate_hz=30.0, timeout_s=20.0)
                 for shm in (True, False)}
        assert stats[True]["received"] >= 25, stats
        rounds.append(stats)
        # p90 ~5 ms against ~14 ms on a quiet machine; compared with each other, not with a
        # number, because a loaded machine's scheduling stretches both (CI: 10 ms with SHM).
        # Not the medians: UDP's times are bimodal, a quiet run once had its median at 3.4 ms.
        # A busy neighbour can still stall one SHM round (p90 28 ms against UDP's 19 ms in
        # one fresh-clone run with two busy loops), so a round is repeated, up to three:
        # SHM never faster in any of them fails.
        if stats[True]["p90_ms"] < stats[False]["p90_ms"]:
            return
    raise AssertionError(f"the SHM profile was not faster in any round: {rounds}")


def test_runs_with_its_defaults(tmp_path: Path):
    """No params file at all: the built-in defaults start the node; SIGTERM ends it."""
    rosutil.assert_starts_with_defaults("mock_panda", topics.JOINT_STATES, __file__, tmp_path)


def test_help_and_bad_parameters():
    env = node_environment(rosutil.next_domain_id(__file__))
    rosutil.assert_help_and_bad_parameter(
        "mock_panda", "--help", ("command_timeout_s", "rate_hz"), "limit_profile:=ur5",
        ("limit profile", "ur5"), env)
