"""What every node process applies at start (`damon_ros.ros.environment`)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

RENDER_FRAMES = """
import json, resource, sys
import numpy as np
from damon_ros.ros.environment import keep_freed_memory
from damon_ros.core.scenario import load_public_scenarios
from damon_ros.perception.camera import load_camera
from damon_ros.simulation.renderer import render, scene_at
why = keep_freed_memory() if sys.argv[1] == "keep" else "not asked"
camera, rng = load_camera(), np.random.default_rng(0)
scene = scene_at(load_public_scenarios(["E-002"])[0], 1.0)
for _ in range(3):
    render(camera, scene, 0.002, 0.01, rng)
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(10):
    render(camera, scene, 0.002, 0.01, rng)
faults = (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / 10
print(json.dumps({"why": why, "faults": faults}))
"""


def _render_in_a_process(mode: str, env: dict | None = None) -> dict:
    out = subprocess.run([sys.executable, "-c", RENDER_FRAMES, mode], capture_output=True,
                         text=True, timeout=120, env=env, check=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def test_freed_frame_memory_is_reused_not_faulted_in_again():
    kept = _render_in_a_process("keep")
    assert kept["why"] is None
    assert kept["faults"] < 50, kept  # measured 0 (without: ~1,170 a frame)


def test_malloc_settings_from_the_environment_are_kept():
    env = dict(os.environ, MALLOC_TRIM_THRESHOLD_="131072")
    assert "environment" in _render_in_a_process("keep", env)["why"]


THREADS = """
import cv2
from damon_ros.ros.environment import limit_threads
limit_threads()
print(cv2.getNumThreads())
"""


def _opencv_threads(env: dict) -> int:
    out = subprocess.run([sys.executable, "-c", THREADS], capture_output=True, text=True,
                         timeout=120, env=env, check=True).stdout
    return int(out.strip().splitlines()[-1])


def test_opencv_runs_single_threaded_unless_the_user_says_otherwise():
    from damon_ros.ros.environment import THREAD_VARIABLES

    clean = {k: v for k, v in os.environ.items() if k not in THREAD_VARIABLES}
    assert _opencv_threads(clean) == 1
    assert _opencv_threads(dict(clean, OPENCV_FOR_THREADS_NUM="3")) == 3


FREEZE = """
import gc, json, weakref
from damon_ros.ros.environment import freeze_start_up_heap
start_up = [{"joint": i} for i in range(50_000)]  # a built node's tens of thousands
tracked = len(gc.get_objects())
freeze_start_up_heap()
class Part:
    pass
a, b = Part(), Part()
a.other, b.other = b, a  # a garbage cycle made after the freeze
gone = weakref.ref(a)
del a, b
gc.collect()
print(json.dumps({"tracked": tracked, "walked": len(gc.get_objects()),
                  "frozen": gc.get_freeze_count(), "cycle_freed": gone() is None,
                  "start_up_kept": len(start_up)}))
"""


def test_start_up_heap_is_frozen_and_later_cycles_are_still_collected():
    out = subprocess.run([sys.executable, "-c", FREEZE], capture_output=True, text=True,
                         timeout=120, check=True).stdout
    got = json.loads(out.strip().splitlines()[-1])
    assert got["frozen"] >= got["tracked"] * 0.9, got  # out of every later collection
    assert got["walked"] < got["tracked"] * 0.05, got  # what a full collection still walks
    assert got["cycle_freed"], got  # the collector still works on what came after
    assert got["start_up_kept"] == 50_000
