"""A controller + mock_panda closed loop over DDS for the JTC-behaviour tests.

Shared by test_node_controller_jtc.py (an arm that moves) and
test_node_controller_jtc_blocked.py (an arm that never moves); each module runs one loop,
so two 1 kHz loops never run beside each other and the test client records one of them
(with both, the blocked module's three tests took 77 s instead of 3 s under their load).
"""

from __future__ import annotations

import signal
from dataclasses import dataclass

import numpy as np
import rosutil
from diagnostic_msgs.msg import DiagnosticArray
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray
from trajectory_msgs.msg import JointTrajectory

from damon_ros.ros import topics
from damon_ros.ros.launch import read_log

CONFIG = rosutil.ROOT / "config"
NAMES = [f"panda_joint{i}" for i in range(1, 8)]
ACCEPTED, REJECTED = "accepted trajectory", "rejected trajectory"


def trajectory(times, positions, velocities=None, names=NAMES, stamp_ns: int = 0
               ) -> JointTrajectory:
    return rosutil.trajectory_msg(times, positions, velocities, names, stamp_ns)


@dataclass
class Loop:
    ros: rosutil.RosClient
    mock: object
    controller: object
    heartbeat: object
    states: rosutil.Recorder
    commands: rosutil.Recorder
    controller_state: rosutil.Recorder
    pub: object
    commands_before_first_state: int = -1

    def q(self) -> np.ndarray:
        return np.array(self.states.last.position)

    def lines(self, needle: str) -> list[str]:
        return rosutil.log_lines(self.controller, needle)

    def logs(self) -> str:
        return ("\n--- controller ---\n" + read_log(self.controller)[-4000:]
                + "\n--- mock_panda ---\n" + read_log(self.mock)[-2000:])

    def settle(self, timeout_s: float = 4.0) -> bool:
        def still() -> bool:
            recent = self.states.messages[-100:]
            return len(recent) == 100 and max(
                np.max(np.abs(m.velocity)) for m in recent) < 1e-4
        return self.ros.spin_until(still, timeout_s)

    def send(self, msg: JointTrajectory, timeout_s: float = 3.0) -> str:
        """Publish and return the controller's answer: its accepted/rejected line."""
        before = len(self.lines(ACCEPTED)) + len(self.lines(REJECTED))
        self.pub.publish(msg)
        self.ros.spin_until(
            lambda: len(self.lines(ACCEPTED)) + len(self.lines(REJECTED)) > before, timeout_s)
        answers = [line for line in read_log(self.controller).splitlines()
                   if ACCEPTED in line or REJECTED in line]
        assert len(answers) == before + 1, self.logs()  # exactly one answer, none silent
        return answers[-1]

    def now_ns(self) -> int:
        return self.ros.node.get_clock().now().nanoseconds


def start(ros, env, tmp, name: str, controller_params: dict, remaps=None) -> Loop:
    controller = rosutil.start_node("controller", controller_params, env,
                                    tmp / f"{name}_controller.log",
                                    params_file=CONFIG / "controller.yaml")
    loop = Loop(ros, None, controller, rosutil.start_heartbeat(env, tmp / f"{name}_hb.log"),
                ros.record(JointState, topics.JOINT_STATES),
                ros.record(Float64MultiArray, topics.JOINT_COMMANDS),
                ros.record(JointState, topics.CONTROLLER_STATE),
                ros.publisher(JointTrajectory, topics.JOINT_TRAJECTORY))
    assert ros.wait_for_publishers(topics.JOINT_COMMANDS, 1, 60.0), loop.logs()
    ros.spin_for(0.3)
    loop.commands_before_first_state = len(loop.commands)
    loop.mock = rosutil.start_node("mock_panda", None, env, tmp / f"{name}_mock.log",
                                   params_file=CONFIG / "mock_panda.yaml", remaps=remaps)
    assert ros.spin_until(lambda: len(loop.commands) > 10 and len(loop.states) > 10,
                          60.0), loop.logs()
    assert ros.wait_for_subscribers(loop.pub, 1, 10.0), loop.logs()
    # the heartbeat flows (its process starts in seconds on a busy machine; until the
    # controller hears it, every trajectory is refused, as it should be)
    heartbeats = ros.record(DiagnosticArray, topics.PLANNER_STATUS)
    assert ros.spin_until(lambda: len(heartbeats) >= 5, 60.0), loop.logs()
    ros.spin_for(0.3)
    return loop


def stop(loop: Loop | None) -> None:
    if loop is None:
        return
    for proc in (loop.controller, loop.mock, loop.heartbeat):
        if proc is not None:
            rosutil.stop_node(proc, first_signal=signal.SIGTERM)
