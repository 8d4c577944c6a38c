"""Collection on a real two-node Ray cluster on this machine writes the same chunk files as
a local run.

The cluster is two ``ray start --block`` processes (a head and a second node joining it) on
127.0.0.1, each in a session of its own, so the fixture stops exactly the processes it
started (SIGTERM to their process groups, then SIGKILL) whatever the test did — and never
another developer's Ray. Every wait is bounded.
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from damon_ros.learning.collect import collect
from damon_ros.learning.dataset import chunk_path, chunk_ranges, read_sidecar
from damon_ros.learning.engines import LocalEngine, Work

pytest.importorskip("ray")

ROOT = Path(__file__).resolve().parents[2]
RAY = str(Path(sys.executable).with_name("ray"))
START_S = 150.0  # bound on one node coming up (~5 s on a quiet machine)
N, CHUNK, SEED = 600, 200, 4


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _start_node(args: list[str], log: Path, env: dict) -> subprocess.Popen:
    with open(log, "w") as out:
        return subprocess.Popen(
            [RAY, "start", "--block", "--node-ip-address=127.0.0.1", "--num-cpus=1",
             "--disable-usage-stats", "--object-store-memory=80000000",
             f"--dashboard-agent-listen-port={_free_port()}",
             f"--metrics-export-port={_free_port()}", *args],
            stdout=out, stderr=subprocess.STDOUT, env=env, start_new_session=True)


def _wait_started(proc: subprocess.Popen, log: Path) -> None:
    deadline = time.monotonic() + START_S
    while time.monotonic() < deadline:
        if "Ray runtime started" in log.read_text(errors="replace"):
            return
        if proc.poll() is not None:
            break
        time.sleep(0.5)
    raise RuntimeError(f"ray start did not come up:\n{log.read_text(errors='replace')[-3000:]}")


def _stop(procs: list[subprocess.Popen]) -> None:
    for proc in procs:
        try:
            os.killpg(proc.pid, signal.SIGTERM)
        except ProcessLookupError:
            pass
    # `ray start --block` took 30 s to end on SIGTERM: after 5 s in all, each node's
    # process group (every process of that node) is killed
    deadline = time.monotonic() + 5.0
    for proc in procs:
        try:
            proc.wait(max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(10)


@pytest.fixture(scope="module")
def cluster():
    """Address of a head plus one more node, both on 127.0.0.1 with one CPU each."""
    temp = Path(tempfile.mkdtemp(prefix="ray", dir="/tmp"))  # short: Ray's socket paths
    # a home of its own: Ray keeps an auth token in ~/.ray once it has run here (a local
    # instance writes one), and a node joining with it was refused ("InvalidAuthToken")
    home, saved_home = temp / "home", os.environ.get("HOME")
    home.mkdir()
    os.environ["HOME"] = str(home)  # the driver (this process) connects from it too
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p),
        RAY_agent_register_timeout_ms="300000", RAY_DASHBOARD_STARTUP_TIMEOUT_S="300")
    port = _free_port()
    address = f"127.0.0.1:{port}"
    procs: list[subprocess.Popen] = []
    try:
        procs.append(_start_node(["--head", f"--port={port}", "--include-dashboard=false",
                                  f"--temp-dir={temp / 't'}"], temp / "head.log", env))
        _wait_started(procs[-1], temp / "head.log")
        procs.append(_start_node([f"--address={address}"], temp / "node.log", env))
        _wait_started(procs[-1], temp / "node.log")
        yield address
    finally:
        _stop(procs)
        if saved_home is None:
            os.environ.pop("HOME", None)
        else:
            os.environ["HOME"] = saved_home
        shutil.rmtree(temp, ignore_errors=True)


def test_two_node_cluster_writes_the_local_runs_chunks(cluster, tmp_path):
    import ray

    ray.init(address=cluster, _node_ip_address="127.0.0.1", logging_level="ERROR",
             log_to_driver=False)
    try:
        alive = [n for n in ray.nodes() if n["Alive"]]
        assert len(alive) == 2 and ray.cluster_resources()["CPU"] == 2
        # the engine joins the driver's connection and leaves it open
        on_ray = collect(N, SEED, tmp_path / "ray", chunk_size=CHUNK, progress=False,
                         engine="ray", address=cluster)
    finally:
        ray.shutdown()
    local = collect(N, SEED, tmp_path / "local", workers=1, chunk_size=CHUNK, progress=False)
    assert [c["sha256"] for c in on_ray["chunks"]] == [c["sha256"] for c in local["chunks"]]
    assert len(on_ray["chunks"]) == 3 and on_ray["timing"]["engine"] == "ray"
    # a partly lost run: only the missing chunk is made again, on the cluster
    chunk_path(tmp_path / "ray", 1).unlink()
    again = collect(N, SEED, tmp_path / "ray", chunk_size=CHUNK, progress=False,
                    engine="ray", address=cluster)
    assert again["timing"]["samples_this_run"] == CHUNK
    assert read_sidecar(tmp_path / "ray")["chunks"] == local["chunks"]


# ---- without a cluster ----------------------------------------------------------------
def _square_setup(offset: int) -> int:
    return offset


def _square(offset: int, job: int) -> int:
    if job < 0:
        raise ValueError("negative job")
    return job * job + offset


def test_local_engine_yields_every_result_and_raises_a_jobs_error():
    assert sorted(LocalEngine(2).map(Work(_square_setup, (1,), _square), range(5))) == \
        [1, 2, 5, 10, 17]
    assert list(LocalEngine(1).map(Work(_square_setup, (0,), _square), [])) == []
    with pytest.raises(ValueError, match="negative"):
        list(LocalEngine(2).map(Work(_square_setup, (0,), _square), [1, -1]))


def test_engine_options_are_checked(tmp_path):
    with pytest.raises(ValueError, match="engine"):
        collect(10, 0, tmp_path, workers=1, progress=False, engine="spark")
    with pytest.raises(ValueError, match="address"):
        collect(10, 0, tmp_path, workers=1, progress=False, address="127.0.0.1:1")
    assert chunk_ranges(10, 5000) == [(0, 10)]
