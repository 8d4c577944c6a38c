"""The process environment of a damon_ros setup: one DDS domain, localhost discovery, SHM.

Also the thread limits every node process applies at start (see `limit_threads`).
"""

from __future__ import annotations

import os

from damon_ros.core.resources import config_dir

SHM_PROFILE = "fastdds_shm.xml"


def ros_environment(domain_id: int) -> dict[str, str]:
    """Environment variables that put a process on a private, local, shared-memory ROS graph.

    The demo and the tests start several node processes; giving them one ``ROS_DOMAIN_ID``,
    discovery limited to this machine and Fast DDS with the shared-memory profile keeps
    concurrent runs apart and moves 640x480 images in ~3 ms instead of ~13 ms. Merge the
    result into ``os.environ`` (or a copy of it) before starting a process or calling
    ``rclpy.init``: the RMW reads these once per process.
    """
    if isinstance(domain_id, bool) or not isinstance(domain_id, int) or not 0 <= domain_id <= 101:
        raise ValueError(f"domain_id must be an integer in 0..101, got {domain_id!r}")
    profile = config_dir() / SHM_PROFILE
    if not profile.is_file():
        raise ValueError(f"Fast DDS profile {profile} is missing")
    return {
        "ROS_DOMAIN_ID": str(domain_id),
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp",
        "FASTRTPS_DEFAULT_PROFILES_FILE": str(profile),
    }


THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def limit_threads() -> None:
    """Single-threaded BLAS/OpenMP in this process, unless the user set a thread count.

    Linear-algebra libraries start one worker thread per core that busy-wait for work. In a
    node that runs at SCHED_FIFO next to 1 kHz control loops those spinning threads stall
    everything (measured: a 3 ms plan took 700 ms inside the planner node). Called by
    `node_main` before the node is built: libraries loaded later (torch's OpenMP) read the
    variables, and the BLAS numpy has already loaded is limited through threadpoolctl.
    """
    user_set = any(name in os.environ for name in THREAD_VARIABLES)
    for name in THREAD_VARIABLES:
        os.environ.setdefault(name, "1")
    if not user_set:
        from threadpoolctl import threadpool_limits

        threadpool_limits(limits=1)
