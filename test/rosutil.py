"""Harness for tests that run damon_ros nodes over real DDS.

Every ROS test imports this module, so that all of them isolate, start, wait and clean up the
same way:

- **Isolation.** `next_domain_id` hands each test its own ``ROS_DOMAIN_ID`` in 1..100: a
  counter per test file, starting from a base derived (CRC-32) from the file's name and this
  pytest process's id. Fast DDS on Linux allows domains 0..101 (higher ones run out of UDP
  ports); 0 is left alone because that is where anybody's unconfigured ROS tools live. The
  process id is mixed in because several pytest runs may share this machine at once; with
  ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` nothing from another host can interfere.
- **Environment.** `damon_ros.ros.environment.node_environment`: the caller's environment
  plus the private graph (domain, localhost discovery, Fast DDS with the shared-memory
  profile), unbuffered Python, uncoloured logs, and a ROS log directory under the test's
  temporary folder instead of ``~/.ros``.
- **Processes.** `start_node` and `stop_node` are those of `damon_ros.ros.launch` (stdout
  and stderr in a log file, `damon_ros.ros.launch.read_log` shows it when an assertion
  fails; SIGINT, then SIGTERM, then SIGKILL, each wait bounded), run from this checkout's
  root and returning the log with the exit code. `assert_starts_with_defaults` and
  `assert_help_and_bad_parameter` are the start-up checks every node's tests make.
- **In-process client.** `RosClient` (a context manager) owns an ``rclpy.Context``, a node
  and a single-threaded executor; `RosClient.spin_until` always returns within its timeout.
  It records topics with publisher timestamps and reaches the nodes over UDP only, so
  that a slow test process can not stall them through shared memory (see `RosClient`).

Measurements: ``python test/rosutil.py image-latency`` (a 640x480 rgb8 image between two
processes, with and without the shared-memory profile) and ``python test/rosutil.py
loop-timing --seconds 15 [--priority 0]`` (the 1 kHz loop periods of mock_panda and
controller running closed loop).
"""

from __future__ import annotations

import argparse
import bisect
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
import zlib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import QoSProfile
from rclpy.signals import SignalHandlerOptions

from damon_ros.ros import launch, topics
from damon_ros.ros.environment import node_environment, observer_environment
from damon_ros.ros.launch import read_log
from damon_ros.ros.rate_loop import set_realtime_priority

ROOT = Path(__file__).resolve().parents[1]

DOMAIN_LOW, DOMAIN_HIGH = 1, 100
_domain_counters: dict[str, int] = {}


def next_domain_id(test_file: str) -> int:
    """A fresh ``ROS_DOMAIN_ID`` in 1..100 for the next test of ``test_file`` (see module doc)."""
    stem = Path(test_file).stem
    span = DOMAIN_HIGH - DOMAIN_LOW + 1
    base = zlib.crc32(f"{stem}:{os.getpid()}".encode()) % span
    k = _domain_counters.get(stem, 0)
    _domain_counters[stem] = k + 1
    return DOMAIN_LOW + (base + k) % span


def start_node(module: str, params: Mapping[str, object] | None, env: Mapping[str, str],
               log_path: Path, params_file: Path | None = None,
               remaps: Mapping[str, str] | None = None) -> subprocess.Popen:
    """`damon_ros.ros.launch.start_node`, run from this checkout's root.

    ``python -m`` then imports the damon_ros of this checkout, the one the tests import,
    even where another copy of the package is installed.
    """
    return launch.start_node(module, params, env, log_path, remaps=remaps,
                             params_file=params_file, cwd=ROOT)


def stop_node(proc: subprocess.Popen, timeout: float = 5.0,
              first_signal: int = signal.SIGINT) -> tuple[int, str]:
    """`damon_ros.ros.launch.stop_node`, then the node's log: (exit code, log text).

    Every test that stops a node asserts on both, and shows the log when the code is wrong.
    """
    code = launch.stop_node(proc, timeout=timeout, first_signal=first_signal)
    return code, read_log(proc)


def log_lines(proc: subprocess.Popen, needle: str) -> list[str]:
    """Lines of the node's log that contain ``needle``."""
    return [line for line in read_log(proc).splitlines() if needle in line]


@dataclass
class Recorder:
    """Messages of one subscription with their arrival and publication times.

    ``times``: arrival in this process (``time.monotonic()``), late whenever this process is
    slow. ``sources``: when the publisher wrote the message (DDS source timestamp, system
    clock, s), which does not depend on this process at all: latencies between two nodes
    are measured on it. ``sequence``: the publisher's sequence numbers, to spot lost ones.
    """

    messages: list = field(default_factory=list)
    times: list[float] = field(default_factory=list)
    sources: list[float] = field(default_factory=list)
    sequence: list[int] = field(default_factory=list)

    def __call__(self, msg, info) -> None:
        self.times.append(time.monotonic())
        self.sources.append(info["source_timestamp"] * 1e-9)
        self.sequence.append(info["publication_sequence_number"] or 0)
        self.messages.append(msg)

    def __len__(self) -> int:
        return len(self.messages)

    @property
    def last(self):
        return self.messages[-1] if self.messages else None

    def clear(self) -> None:
        for column in (self.messages, self.times, self.sources, self.sequence):
            column.clear()

    def since(self, t: float) -> list:
        """Messages that arrived after monotonic time ``t`` (a bisection)."""
        return self.messages[bisect.bisect_right(self.times, t):]

    def published_after(self, t: float) -> list[tuple[float, object]]:
        """(source time, message) pairs published after system time ``t`` (a bisection)."""
        k = bisect.bisect_right(self.sources, t)
        return list(zip(self.sources[k:], self.messages[k:], strict=True))


def client_profile_path() -> Path:
    """Where the test processes keep their UDP-only Fast DDS profile (see `RosClient`)."""
    return Path(tempfile.gettempdir()) / f"damon_test_client_{os.getuid()}.xml"


class RosClient:
    """An in-process ROS participant for a test: own context, node and executor.

    Use as ``with RosClient(domain_id) as ros: ...``; leaving the block destroys the node
    and shuts the context down, even when the test failed.

    ``realtime_priority`` > 0 runs this process with SCHED_FIFO while the block lasts
    (normal scheduling again after it; nothing happens where that is not permitted). Use it
    sparingly: beside the real-time 1 kHz nodes, a real-time test process taking their 2 kHz
    of messages pushed this 2-core machine into the kernel's RT throttling, which stopped
    every RT thread, the nodes' included, for up to 300 ms.

    The client itself talks to the nodes over UDP only (`observer_environment`), while the nodes
    use the shared-memory profile among themselves. Fast DDS guards its shared-memory ports
    with mutexes shared between processes, so a CPU-starved normal-priority reader holding
    one stalls a real-time writer: measured here, with a shared-memory client on a loaded
    2-core machine, mock_panda and controller stalled ~50 ms about once a second (stale
    joint states); with a UDP-only client, in the same conditions, they did not. An
    observer must not disturb what it observes. Python may still take messages late, so
    timing is judged on `Recorder.sources` (publisher clocks), and recorders keep a deep
    history.
    """

    def __init__(self, domain_id: int, name: str = "test_client", realtime_priority: int = 0):
        self.domain_id = domain_id
        self.name = name
        self.realtime_priority = realtime_priority
        self.context: Context | None = None
        self.node = None
        self.recording_node = None
        self._recorded: list[tuple[object, Recorder]] = []
        self.executor: SingleThreadedExecutor | None = None

    def __enter__(self) -> RosClient:
        # The RMW reads these once per process; the domain itself is passed explicitly.
        for key, value in observer_environment(self.domain_id, client_profile_path()).items():
            if key != "ROS_DOMAIN_ID":
                os.environ[key] = value
        self.context = Context()
        # No rclpy signal handlers: Ctrl-C and pytest-timeout must keep working as usual.
        rclpy.init(context=self.context, domain_id=self.domain_id,
                   signal_handler_options=SignalHandlerOptions.NO)
        try:
            self.node = rclpy.create_node(self.name, context=self.context)
            self.recording_node = rclpy.create_node(f"{self.name}_recorder",
                                                    context=self.context)
            self.executor = SingleThreadedExecutor(context=self.context)
            self.executor.add_node(self.node)
            if self.realtime_priority > 0:
                set_realtime_priority(self.realtime_priority)
        except Exception:
            self.close()
            raise
        return self

    def __exit__(self, *_exc) -> None:
        self.close()

    def close(self) -> None:
        if self.realtime_priority > 0:
            set_realtime_priority(0)
        if self.executor is not None:
            self.executor.shutdown(timeout_sec=1.0)
            self.executor = None
        self._recorded.clear()
        for node in (self.node, self.recording_node):
            if node is not None:
                node.destroy_node()
        self.node = self.recording_node = None
        if self.context is not None:
            rclpy.try_shutdown(context=self.context)
            self.context = None

    def record(self, msg_type, topic: str, qos: QoSProfile | int = 2000) -> Recorder:
        """Record a topic into a `Recorder`, filled whenever this client spins.

        Recorded subscriptions live on a second node that no executor waits on; `spin_until`
        takes their messages directly (as ``rclpy.wait_for_message`` does). Measured here, an
        executor callback costs ~390 us per message and a direct take ~140 us: with two 1 kHz
        topics the executor alone would need most of a loaded core and fall seconds behind.
        The deep default history keeps every message while the test is busy elsewhere.
        """
        recorder = Recorder()
        sub = self.recording_node.create_subscription(msg_type, topic, recorder, qos)
        self._recorded.append((sub, recorder))
        return recorder

    def _take_recorded(self) -> None:
        for sub, recorder in self._recorded:
            with sub.handle:
                while (taken := sub.handle.take_message(sub.msg_type, sub.raw)) is not None:
                    recorder(*taken)

    def publisher(self, msg_type, topic: str, qos: QoSProfile | int = 10):
        return self.node.create_publisher(msg_type, topic, qos)

    def spin_until(self, predicate: Callable[[], bool], timeout_s: float) -> bool:
        """Spin until ``predicate()`` is true; False once ``timeout_s`` has passed.

        Each round takes the recorded messages, checks the predicate, then serves timers and
        other callbacks for at most 2 ms, so the call returns within the timeout plus one
        round.
        """
        deadline = time.monotonic() + timeout_s
        while True:
            self._take_recorded()
            if predicate():
                return True
            remaining = deadline - time.monotonic()
            if remaining <= 0.0:
                return False
            self.executor.spin_once(timeout_sec=min(remaining, 0.002))

    def spin_for(self, seconds: float) -> None:
        self.spin_until(lambda: False, seconds)

    def wait_for_subscribers(self, publisher, count: int = 1, timeout_s: float = 10.0) -> bool:
        """Discovery is asynchronous: wait until ``count`` readers matched ``publisher``."""
        return self.spin_until(lambda: publisher.get_subscription_count() >= count, timeout_s)

    def wait_for_publishers(self, topic: str, count: int = 1, timeout_s: float = 10.0) -> bool:
        return self.spin_until(lambda: self.node.count_publishers(topic) >= count, timeout_s)


# ------------------------------------------------------------------ start-up checks

def assert_starts_with_defaults(module: str, topic: str, test_file: str, tmp_path: Path) -> None:
    """No params file at all: the built-in defaults start ``module``, it publishes ``topic``,
    and SIGTERM ends it with exit code 0 and no warning or error in its log (a refused
    real-time priority aside: unprivileged machines refuse SCHED_FIFO)."""
    domain = next_domain_id(test_file)
    proc = start_node(module, None, node_environment(domain, tmp_path),
                      tmp_path / f"{module}.log")
    try:
        with RosClient(domain) as ros:
            assert ros.wait_for_publishers(topic, 1, 20.0), read_log(proc)
    finally:
        code, log = stop_node(proc, first_signal=signal.SIGTERM)
    assert code == 0, log[-4000:]
    problems = [line for line in log.splitlines()
                if ("WARN" in line or "ERROR" in line) and "SCHED_FIFO" not in line]
    assert not problems, log[-4000:]


def assert_help_and_bad_parameter(module: str, help_flag: str, help_words: Sequence[str],
                                  bad_parameter: str, error_words: Sequence[str],
                                  env: Mapping[str, str]) -> None:
    """``help_flag`` prints the parameters (``help_words`` among them) and exits 0;
    ``-p bad_parameter`` exits 2 with ``error_words`` on stderr and no traceback."""
    cmd = [sys.executable, "-m", f"damon_ros.nodes.{module}"]
    out = subprocess.run([*cmd, help_flag], capture_output=True, text=True, timeout=30)
    assert out.returncode == 0, out.stderr[-2000:]
    assert all(word in out.stdout for word in help_words), out.stdout[-2000:]
    out = subprocess.run([*cmd, "--ros-args", "-p", bad_parameter], capture_output=True,
                         text=True, timeout=30, env=dict(env))
    assert out.returncode == 2, out.stderr[-2000:]
    assert all(word in out.stderr for word in error_words), out.stderr[-2000:]
    assert "Traceback" not in out.stderr, out.stderr[-2000:]


# ------------------------------------------------------------------ image transport latency

IMAGE_TOPIC = "/damon_test/image"


def _image_publisher(domain_id: int, count: int, rate_hz: float) -> int:
    """Child process: publish ``count`` 640x480 rgb8 images stamped just before publishing."""
    import numpy as np
    from sensor_msgs.msg import Image

    rclpy.init(domain_id=domain_id)
    node = rclpy.create_node("image_latency_pub")
    pub = node.create_publisher(Image, IMAGE_TOPIC, 5)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    deadline = time.monotonic() + 15.0
    while pub.get_subscription_count() < 1 and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.05)
    pixels = np.random.default_rng(0).integers(0, 256, (480, 640, 3), dtype=np.uint8)
    msg = Image(height=480, width=640, encoding="rgb8", step=640 * 3)
    msg.data = pixels.tobytes()
    for _ in range(count):
        now = time.time_ns()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(now, 1_000_000_000)
        pub.publish(msg)
        executor.spin_once(timeout_sec=1.0 / rate_hz)
    executor.spin_once(timeout_sec=0.5)  # let the reliable writer finish the last sample
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


def _image_subscriber(domain_id: int, count: int, timeout_s: float) -> int:
    """Child process: receive images and print their latencies (ms) as one JSON line."""
    from sensor_msgs.msg import Image

    rclpy.init(domain_id=domain_id)
    node = rclpy.create_node("image_latency_sub")
    latencies: list[float] = []

    def on_image(msg: Image) -> None:
        sent = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        latencies.append((time.time_ns() - sent) * 1e-6)

    node.create_subscription(Image, IMAGE_TOPIC, on_image, 5)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    deadline = time.monotonic() + timeout_s
    while len(latencies) < count and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.05)
    print(json.dumps(latencies), flush=True)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


def measure_image_latency(domain_id: int, shm_profile: bool, count: int = 60,
                          rate_hz: float = 20.0, timeout_s: float = 30.0) -> dict[str, float]:
    """One-way latency of 640x480 rgb8 images between two processes (median/p90/max, ms).

    Both ends are child processes because Fast DDS reads its profile once per process.
    ``shm_profile`` False runs them with Fast DDS's built-in transports instead.
    """
    env = node_environment(domain_id)
    if not shm_profile:
        env.pop("FASTRTPS_DEFAULT_PROFILES_FILE")
    me = [sys.executable, str(Path(__file__).resolve())]
    common = ["--domain", str(domain_id), "--count", str(count)]
    sub = subprocess.Popen(me + ["_image_sub", *common, "--timeout", str(timeout_s)], env=env,
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    pub = subprocess.Popen(me + ["_image_pub", *common, "--rate", str(rate_hz)], env=env,
                           stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        out, err = sub.communicate(timeout=timeout_s + 10.0)
    finally:
        for proc in (sub, pub):
            if proc.poll() is None:
                proc.kill()
            proc.wait(timeout=5.0)
    if sub.returncode != 0 or not out.strip():
        raise RuntimeError(f"image subscriber failed ({sub.returncode}): {err[-2000:]}")
    import numpy as np

    ms = np.array(json.loads(out.strip().splitlines()[-1]))[5:]  # skip the discovery warm-up
    if ms.size == 0:
        return {"received": 0}
    return {"received": int(ms.size + 5), "median_ms": float(np.median(ms)),
            "p90_ms": float(np.percentile(ms, 90)), "max_ms": float(ms.max())}


# ------------------------------------------------------------------ 1 kHz loop timing

def measure_loop_timing(domain_id: int, seconds: float,
                        params: Mapping[str, object] | None = None) -> dict[str, str]:
    """Run mock_panda and controller closed loop for ``seconds``; their loop-timing lines.

    Both start from their ``config/*.yaml`` (plus ``params`` for both); the lines are what
    each node logs at shutdown (`damon_ros.ros.rate_loop.FixedRateLoop.summary`).
    """
    with tempfile.TemporaryDirectory() as tmp:
        env = node_environment(domain_id, Path(tmp))
        procs = {name: start_node(name, params, env, Path(tmp) / f"{name}.log",
                                  params_file=ROOT / "config" / f"{name}.yaml")
                 for name in ("mock_panda", "controller")}
        time.sleep(seconds + 3.0)  # start-up (imports, discovery) is not in the loop timing
        logs = {name: stop_node(proc)[1] for name, proc in procs.items()}
    return {name: next((line for line in log.splitlines() if "loop timing" in line), log[-500:])
            for name, log in logs.items()}


# ------------------------------------------------------------------ fake planner heartbeat

def start_heartbeat(env: Mapping[str, str], log_path: Path, rate_hz: float = 20.0,
                    topic: str = topics.PLANNER_STATUS) -> subprocess.Popen:
    """A process that publishes an OK ``DiagnosticArray`` on ``topic`` at ``rate_hz``.

    A process of its own, not a timer of the test client: a small process wakes on time on
    a loaded machine, a busy test process may not. SIGSTOP / SIGCONT make it fall silent
    and resume exactly; stop it with `stop_node`.
    """
    cmd = [sys.executable, str(Path(__file__).resolve()), "_heartbeat", "--rate", str(rate_hz),
           "--topic", topic]
    return launch.start_process(cmd, env, log_path)


def _heartbeat(rate_hz: float, topic: str) -> int:
    """Child process: the fake planner's status messages until SIGINT/SIGTERM."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
    from rclpy.executors import ExternalShutdownException

    launch.exit_with_parent()
    rclpy.init()
    node = rclpy.create_node("fake_planner")
    pub = node.create_publisher(DiagnosticArray, topic, 10)
    msg = DiagnosticArray(status=[DiagnosticStatus(name="fake planner", message="alive")])
    node.create_timer(1.0 / rate_hz, lambda: pub.publish(msg))
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


def _main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python test/rosutil.py",
                                     description="ROS test harness utilities.")
    parser.add_argument("mode", choices=("image-latency", "loop-timing", "_image_pub",
                                         "_image_sub", "_heartbeat"))
    parser.add_argument("--seconds", type=float, default=15.0)
    parser.add_argument("--priority", type=int, default=None,
                        help="loop-timing: realtime_priority of both nodes (default: YAML)")
    parser.add_argument("--topic", default=topics.PLANNER_STATUS)
    parser.add_argument("--domain", type=int, default=57)
    parser.add_argument("--count", type=int, default=100)
    parser.add_argument("--rate", type=float, default=20.0)
    parser.add_argument("--timeout", type=float, default=30.0)
    args = parser.parse_args(argv)
    if args.mode == "_image_pub":
        return _image_publisher(args.domain, args.count, args.rate)
    if args.mode == "_image_sub":
        return _image_subscriber(args.domain, args.count, args.timeout)
    if args.mode == "_heartbeat":
        return _heartbeat(args.rate, args.topic)
    if args.mode == "loop-timing":
        params = None if args.priority is None else {"realtime_priority": args.priority}
        for name, line in measure_loop_timing(args.domain, args.seconds, params).items():
            print(f"{name}: {line}")
        return 0
    for shm in (False, True):
        stats = measure_image_latency(args.domain, shm, args.count, args.rate, args.timeout)
        label = "shared-memory profile" if shm else "Fast DDS defaults    "
        print(f"640x480 rgb8, {label}: " + ", ".join(
            f"{k} {v:.2f}" if isinstance(v, float) else f"{k} {v}" for k, v in stats.items()))
    return 0


if __name__ == "__main__":
    sys.exit(_main())
