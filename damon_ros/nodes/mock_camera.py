"""mock_camera: the RealSense stand-in, a thin ROS adapter over `damon_ros.simulation.renderer`.

Renders the obstacles of a scenario file, at scenario time, seen from the calibrated camera
pose (``config/camera.yaml``), and publishes what a D435 driver would: colour (``rgb8``),
depth aligned to colour (``16UC1``, mm, 0 = no return) and the colour camera_info, all three
with the same stamp; plus the ground truth on ``/damon/sim/obstacles`` (MarkerArray in the
base frame, ns = colour, id = obstacle index, text = obstacle name) for evaluation.

Timing: frames come from a timer at ``fps``. A frame is stamped at the instant it is
published, and the scene is rendered *for that instant*: the node predicts how long
rendering takes (the 90th percentile of recent frames plus a margin), renders the scene at
tick + prediction, and if rendering finished early waits for the stamp before publishing.
So the picture is exactly the scene at its stamp and no stamp lies in the future; the stamp
-> obstacle latency measured downstream is transport + tracking, as with a camera whose
exposure took no time. Scenario time is ``(ROS time - scenario_start_time_s) * time_scale``
(start = this node's start when 0), the same convention as mock_panda;
``scenario_start_time_s`` may be set while the node runs (the demo starts the scenario clock
when it publishes the goal).

Scheduling: ``realtime_priority`` (default 5) runs the node SCHED_FIFO, below the tracker
(10) and far below the 1 kHz control nodes (20), so that on a loaded machine frames still
leave on time without ever delaying the control loops.

QoS: the three camera topics use ``qos_profile_sensor_data`` (best effort, keep last 5),
what the tracker subscribes with: an image that is late is useless, and a best-effort
writer never makes the render loop wait for a slow reader. A reliable subscriber (rviz's
default) must select best effort to receive them.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time
from collections import deque
from collections.abc import Sequence

import numpy as np
import yaml
from builtin_interfaces.msg import Time
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, Image
from visualization_msgs.msg import MarkerArray

from damon_ros.core.scenario import Scenario, load_scenario
from damon_ros.perception.camera import Camera, camera_file, load_camera
from damon_ros.ros import topics
from damon_ros.ros.cdr import image_bytes, marker_array_bytes
from damon_ros.ros.markers import class_rgba, shape_record
from damon_ros.ros.node_loop import use_realtime_priority
from damon_ros.ros.node_main import node_main
from damon_ros.ros.parameters import Param, accept_at_run_time, declare_all
from damon_ros.ros.stamps import clock_seconds, to_stamp
from damon_ros.simulation.renderer import (
    RenderSettings,
    load_render_settings,
    render,
    render_settings_kwargs,
    scene_at,
)

NAME = "mock_camera"
WARN_EVERY_S = 5.0
RENDER_MARGIN_S = 0.001
"""Added to the predicted render time, so that the stamp is rarely passed before publishing."""

PARAMETERS = (
    Param("scenario", "", "scenario file whose obstacles are rendered (required)"),
    Param("fps", 30.0, "frames per second", 0.1, 240.0),
    Param("camera_config", "",
          "camera file (intrinsics, base_T_camera, mock_render), a path or a shipped name "
          "(camera_side.yaml); '' = shipped camera.yaml"),
    Param("camera_prefix", topics.CAMERA_PREFIX,
          "topic prefix of this camera (<prefix>/color/image_raw, ...): one per camera"),
    Param("depth_noise_std_m", -1.0,
          "depth noise std (m); < 0: the camera file's mock_render value"),
    Param("dropout", -1.0, "fraction of depth pixels with no return; < 0: the camera file's value"),
    Param("background_depth_m", -1.0,
          "depth of the grey backdrop (m), 0 = no return; < 0: file's value"),
    Param("seed", -1, "noise seed; < 0: the camera file's value"),
    Param("time_scale", 1.0, "scenario seconds per ROS second", 0.0, 100.0),
    Param("scenario_start_time_s", 0.0, "ROS time (s) of scenario time 0; 0: this node's start"),
    Param("publish_ground_truth", True,
          f"publish the scenario's obstacles on {topics.SIM_OBSTACLES}"),
    Param("publish_images", True, "render and publish the camera images (false: ground truth "
                                  "only, for runs without perception)"),
    Param("truth_lifetime_frames", 3.0, "lifetime of a ground-truth marker, in frames",
          0.0, 1000.0),
    Param("sync_stamps", False, "hardware-synchronised cameras (RealSense inter_cam_sync_mode): "
          "frames at the multiples of 1/fps in ROS time, so that cameras with the same fps "
          "take theirs at the same instants and the tracker fuses them with no motion slack"),
    Param("realtime_priority", 5,
          "SCHED_FIFO priority of the node's threads, 0: normal scheduling", 0, 99),
)


def render_settings(camera_config: str, overrides: dict[str, float]) -> RenderSettings:
    """The ``mock_render`` section of the camera file (or the shipped one), then overrides.

    A real calibration file has no ``mock_render`` section; the shipped settings serve then.
    Overrides with a negative value mean "keep the file's value".
    """
    path = camera_file(camera_config) if camera_config else None
    has_section = path is not None and isinstance(
        data := yaml.safe_load(path.read_text(encoding="utf-8")), dict) and "mock_render" in data
    settings = load_render_settings(path if has_section else None)
    chosen = {k: v for k, v in overrides.items() if v >= 0}
    if "seed" in chosen:
        chosen["seed"] = int(chosen["seed"])
    settings = dataclasses.replace(settings, **chosen)
    if not 0.0 <= settings.dropout < 1.0:
        raise ValueError(f"dropout {settings.dropout} must be in [0, 1)")
    return settings


def camera_info_message(camera: Camera, stamp) -> CameraInfo:
    info = camera.camera_info()
    msg = CameraInfo(width=info["width"], height=info["height"],
                     distortion_model=info["distortion_model"], d=info["d"], k=info["k"],
                     r=info["r"], p=info["p"])
    msg.header.stamp = stamp
    msg.header.frame_id = camera.frame_id
    return msg


class MockCamera(Node):
    """Parameters in, `render` per timer tick, camera topics (and ground truth) out."""

    def __init__(self) -> None:
        super().__init__(NAME)
        p = declare_all(self, PARAMETERS)
        if not p["scenario"]:
            raise ValueError("parameter scenario is required: the scenario file to render")
        self.scenario: Scenario = load_scenario(p["scenario"])
        self.camera = load_camera(p["camera_config"] or None)
        overrides = {k: p[k] for k in ("depth_noise_std_m", "dropout", "background_depth_m",
                                       "seed")}
        self.settings = render_settings(p["camera_config"], overrides)
        self._rng = np.random.default_rng(self.settings.seed)
        # One throw-away frame (own noise generator) so that bad settings fail here, with a
        # one-line error, instead of inside the timer.
        render(self.camera, scene_at(self.scenario, 0.0),
               **render_settings_kwargs(self.settings, np.random.default_rng(0)))
        self.publish_images = p["publish_images"]
        self.period = 1.0 / p["fps"]
        self.time_scale = p["time_scale"]
        self.truth_lifetime_s = p["truth_lifetime_frames"] * self.period
        self._render_s: deque[float] = deque([0.5 * self.period], maxlen=30)
        self._publish_s: deque[float] = deque(maxlen=3000)  # publishing a frame's messages
        self._frames = 0
        self._overruns = 0
        color, depth, info = topics.camera_topics(p["camera_prefix"])
        self._pub_color = self.create_publisher(Image, color, qos_profile_sensor_data)
        self._pub_depth = self.create_publisher(Image, depth, qos_profile_sensor_data)
        self._pub_info = self.create_publisher(CameraInfo, info, qos_profile_sensor_data)
        self._pub_truth = (self.create_publisher(MarkerArray, topics.SIM_OBSTACLES, 10)
                           if p["publish_ground_truth"] else None)
        self.start_time = float(p["scenario_start_time_s"] or clock_seconds(self))
        accept_at_run_time(self, {"scenario_start_time_s": self._set_scenario_start})
        self.sync_stamps = p["sync_stamps"]
        if self.sync_stamps:  # tick half a period before each instant of the shared grid
            now = clock_seconds(self)
            time.sleep((0.5 * self.period - now) % self.period)
        self.create_timer(self.period, self._frame)
        use_realtime_priority(self, p["realtime_priority"])
        s = self.settings
        self.get_logger().info(
            f"scenario {self.scenario.name} ({len(self.scenario.obstacles)} obstacles) on "
            f"{color}, "
            f"{self.camera.width}x{self.camera.height} at {p['fps']:g} fps, depth noise "
            f"{s.depth_noise_std_m:g} m, dropout {s.dropout:g}, seed {s.seed}, scenario t=0 at "
            f"{self.start_time:.3f} s, time scale {self.time_scale:g}")

    def _set_scenario_start(self, value: float) -> None:
        """Scenario time 0 moved while running: the demo starts the clock with the goal,
        once every node is up, instead of guessing how long start-up takes."""
        self.start_time = float(value or clock_seconds(self))
        self.get_logger().info(f"scenario t=0 now at {self.start_time:.3f} s")

    def scenario_time(self, ros_time: float) -> float:
        return (ros_time - self.start_time) * self.time_scale

    def _frame(self) -> None:
        tick = clock_seconds(self)
        predicted = float(np.percentile(self._render_s, 90)) + RENDER_MARGIN_S
        stamp_s = tick + min(predicted, self.period)
        if self.sync_stamps:  # the next instant of the grid, waited for below
            stamp_s = math.ceil(stamp_s / self.period - 1e-9) * self.period
        scene = scene_at(self.scenario, self.scenario_time(stamp_s))
        stamp = to_stamp(stamp_s)
        if self.publish_images:
            rgb, depth = render(self.camera, scene, **render_settings_kwargs(self.settings,
                                                                              self._rng))
            messages = self._messages(rgb, depth, scene, stamp)
        else:
            messages = self._messages(None, None, scene, stamp)
        ready = clock_seconds(self)
        self._render_s.append(ready - tick)
        if ready < stamp_s:
            time.sleep(stamp_s - ready)  # never publish a stamp from the future
        published = clock_seconds(self)
        for publisher, msg in messages:
            publisher.publish(msg)
        self._frames += 1
        done = clock_seconds(self)
        self._publish_s.append(done - published)
        if done - tick > self.period:
            self._overruns += 1
            self.get_logger().warning(
                f"a frame took {(done - tick) * 1e3:.1f} ms (render {(ready - tick) * 1e3:.1f}, "
                f"publish {(done - published) * 1e3:.1f}), longer than the "
                f"{self.period * 1e3:.1f} ms period: publishing below the requested fps "
                f"({self._overruns} so far)", throttle_duration_sec=WARN_EVERY_S)

    def _messages(self, rgb: np.ndarray | None, depth: np.ndarray | None, scene,
                  stamp: Time) -> list:
        """The frame's messages, every one stamped ``stamp``, all but the camera info
        serialised already (`cdr.image_bytes`, `cdr.marker_array_bytes`): the pixels are
        copied once, before the stamp's instant, and publishing only hands bytes over."""
        frame = self.camera.frame_id
        at = (stamp.sec, stamp.nanosec)
        messages = [] if rgb is None else [
            (self._pub_color, image_bytes(rgb, "rgb8", at, frame)),
            (self._pub_depth, image_bytes(depth, "16UC1", at, frame)),
            (self._pub_info, camera_info_message(self.camera, stamp))]
        if self._pub_truth is not None:
            messages.append((self._pub_truth, marker_array_bytes([
                shape_record(shape, color, i, self.camera.base_frame, stamp,
                             self.truth_lifetime_s, class_rgba(color, 0.4))
                for i, (shape, color) in enumerate(scene)])))
        return messages

    def on_shutdown(self) -> None:
        """Called by `run_single_threaded`: one line of frame statistics."""
        ms = 1e3 * np.asarray(self._render_s)
        pub = 1e3 * np.asarray(self._publish_s) if self._publish_s else np.full(1, np.nan)
        self.get_logger().info(
            f"{self._frames} frames published, render p50 {np.median(ms):.1f} ms (last "
            f"{ms.size}), publish p50 {np.median(pub):.2f} ms p95 {np.percentile(pub, 95):.2f} "
            f"ms (last {len(self._publish_s)}), {self._overruns} frames over the period")


def main(args: Sequence[str] | None = None) -> int:
    """Console entry point (``--help``, one-line errors): see `node_main`."""
    return node_main(NAME, __doc__.split("\n\n")[0], PARAMETERS, MockCamera, args)


if __name__ == "__main__":
    sys.exit(main())
