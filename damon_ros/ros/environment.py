"""The process environment of a damon_ros setup: one DDS domain, localhost discovery, SHM.

Owns every environment variable a damon_ros process is started with: the ROS graph
(`ros_environment`), the extras of a node process started by the demo, the soak run or the
tests (`node_environment`), the UDP-only Fast DDS profile of an in-process observer
(`write_udp_only_profile`, `observer_environment`), and what every node process applies at
start: thread limits (`limit_threads`) and an allocator that keeps freed memory
(`keep_freed_memory`).
"""

from __future__ import annotations

import ctypes
import gc
import os
import sys
import tempfile
from collections.abc import Mapping
from pathlib import Path

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


def node_environment(domain_id: int, log_dir: str | Path | None = None,
                     base: Mapping[str, str] | None = None) -> dict[str, str]:
    """The whole environment of a node process on the private graph of ``domain_id``.

    ``base`` (default: this process's environment) plus `ros_environment`, unbuffered Python
    and uncoloured ROS logs (the output goes to a log file that is read back and searched),
    and ``ROS_LOG_DIR`` at ``log_dir`` (default: the temporary folder) instead of ``~/.ros``.
    """
    env = dict(os.environ if base is None else base)
    env.update(ros_environment(domain_id))
    env.update({
        "PYTHONUNBUFFERED": "1",
        "RCUTILS_COLORIZED_OUTPUT": "0",
        "ROS_LOG_DIR": str(log_dir if log_dir is not None else Path(tempfile.gettempdir())),
    })
    return env


UDP_ONLY_PROFILE = """<?xml version="1.0" encoding="UTF-8" ?>
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <transport_descriptors>
    <transport_descriptor>
      <transport_id>damon_observer_udpv4</transport_id>
      <type>UDPv4</type>
    </transport_descriptor>
  </transport_descriptors>
  <participant profile_name="damon_observer_udp_only" is_default_profile="true">
    <rtps>
      <userTransports><transport_id>damon_observer_udpv4</transport_id></userTransports>
      <useBuiltinTransports>false</useBuiltinTransports>
    </rtps>
  </participant>
</profiles>
"""


def write_udp_only_profile(path: str | Path) -> Path:
    """Write the UDP-only Fast DDS profile of an observer to ``path``; its absolute path.

    Why an observer (the soak monitor, the test client) must not use shared memory: Fast
    DDS guards each shared-memory port with a mutex shared between processes, so a
    CPU-starved normal-priority reader of the real-time nodes' 1 kHz topics can hold one and
    stall them (measured: ~50 ms stalls about once a second; over UDP none). An observer
    must not disturb what it observes. The file is replaced atomically and only when its
    text differs, so concurrent runs sharing one path never read half a file.
    """
    path = Path(path).resolve()
    if not path.is_file() or path.read_text() != UDP_ONLY_PROFILE:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_text(UDP_ONLY_PROFILE)
        tmp.replace(path)
    return path


def observer_environment(domain_id: int, profile_path: str | Path) -> dict[str, str]:
    """`ros_environment` of ``domain_id``, but UDP only (the profile written to
    ``profile_path``, see `write_udp_only_profile`): for a process that watches the nodes."""
    env = ros_environment(domain_id)
    env["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(write_udp_only_profile(profile_path))
    return env


THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS",
                    "OPENCV_FOR_THREADS_NUM")


def limit_threads() -> None:
    """Single-threaded BLAS/OpenMP/OpenCV in this process, unless the user set a thread count.

    Linear-algebra libraries start one worker thread per core that busy-wait for work. In a
    node that runs at SCHED_FIFO next to 1 kHz control loops those spinning threads stall
    everything (measured: a 3 ms plan took 700 ms inside the planner node). Called by
    `node_main` before the node is built: libraries loaded later (torch's OpenMP) read the
    variables, and the BLAS numpy has already loaded is limited through threadpoolctl.
    OpenCV's pool reads its variable at its first parallel call; set directly too when cv2
    is loaded already. Its workers spent 0.7 ms of CPU a frame on the tracker's 320x240
    masks (segmentation 1.7 -> 1.0 ms of process time single-threaded, same result).
    """
    user_set = any(name in os.environ for name in THREAD_VARIABLES)
    for name in THREAD_VARIABLES:
        os.environ.setdefault(name, "1")
    if not user_set:
        from threadpoolctl import threadpool_limits

        threadpool_limits(limits=1)
        cv2 = sys.modules.get("cv2")
        if cv2 is not None:
            cv2.setNumThreads(1)


MALLOC_VARIABLES = ("MALLOC_TRIM_THRESHOLD_", "MALLOC_MMAP_THRESHOLD_", "MALLOC_TOP_PAD_")
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # glibc's mallopt parameter numbers
KEPT_HEAP_BYTES = 256 << 20  # freed heap kept by the process (it stays within its peak)
MMAP_THRESHOLD_BYTES = 32 << 20  # blocks below this come from the heap (glibc's maximum)


def keep_freed_memory() -> str | None:
    """glibc keeps freed memory for reuse instead of handing it back; None, or why not.

    Why: every 640x480 frame (render, publish, segmentation) makes and frees arrays of
    ~1 MB. glibc serves those by mmap, or trims them off its heap when freed, so the next
    frame takes fresh pages: measured on this project's 2-core VM, 1,170 page faults per
    rendered frame, 2.3 ms of an 8.9 ms render, gone with these settings (6.6 ms). Real-time
    practice for ROS 2 control processes is the same (no trimming, no mmap for working
    memory). Left alone when the user set any of `MALLOC_VARIABLES`, or off glibc.
    """
    if any(name in os.environ for name in MALLOC_VARIABLES):
        return "malloc settings from the environment kept"
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return "not glibc: malloc settings unchanged"
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    if not (mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES) == 1
            and mallopt(_M_TRIM_THRESHOLD, KEPT_HEAP_BYTES) == 1):
        return "mallopt refused the settings: malloc settings unchanged"
    return None


def freeze_start_up_heap() -> None:
    """Collect once, then take every object alive after start-up (modules, the model, the
    compiled kernels, the node) out of the cyclic collector's generations (`gc.freeze`).

    Why: a full collection walks every tracked object, and a built node holds 70-95
    thousand of them (rclpy, numpy, scipy, the robot model): measured 10-22 ms a full
    collection in each node's process, 28-53 ms in a bench process. The collector starts
    one whenever enough allocations have survived, wherever that happens: inside a 1 kHz
    tick, a re-route or a frame. After the freeze the same collection walks only what was
    made since (a bench process: 53 -> 16 ms over 48 stress scenes). Frozen objects are
    still freed when their last reference goes; only garbage cycles among them stay,
    and start-up objects live as long as the process anyway.
    """
    gc.collect()
    gc.freeze()
