"""tracker: the HSV + depth obstacle tracker, a thin ROS adapter over
`damon_ros.perception.tracking`.

Colour (``rgb8``/``bgr8``) and aligned depth (``16UC1``/``mono16``/``32FC1``) images in,
paired by stamp (`FrameSynchronizer`), tracked (`Tracker.update_camera`), and published as one
``visualization_msgs/MarkerArray`` per frame on ``/damon/obstacles`` in the robot base frame:
one marker per track (shape, pose, scale; ns = colour class, id = track id, stable while the
track lives; ``lifetime`` = the tracker's ``max_age_s`` so that a consumer forgets an
obstacle the tracker stopped publishing) and a DELETE marker when a track is dropped. The
stamp of every marker is the stamp of the image it was seen in.

Several cameras: ``cameras`` lists each camera's topic prefix (``<prefix>/color/image_raw``,
...) and ``camera_configs`` its camera file (hand-eye pose) in the same order. Each frame pair
of one camera is fused with the other cameras' latest frames (`Tracker.update_camera`: an
older frame's bound is grown by how far an obstacle can have moved since) into one obstacle
per object, whose hidden extent is what no camera sees; one camera is the default.

Intrinsics come from camera_info (frames are dropped, with one log line, until it arrives);
the extrinsic is the hand-eye calibration ``base_T_camera`` of the camera file, which also
names the base frame (the same for every camera). A bad image (unsupported encoding, size
unlike camera_info, short data, all-zero depth) is dropped with one log line per kind of
problem, repeated at most every ``warn_every_s`` with a count; the node keeps
running. Stamps that jump back by more than the tracker's ``time_jump_s`` (a simulator
reset, a bag loop) restart pairing and tracking instead.

Scheduling: ``realtime_priority`` (default 10) runs the node SCHED_FIFO, above the mock
camera (5) and below the 1 kHz control nodes (20). Measured on the loaded 2-core machine
(load ~5), it takes the stamp -> publication latency from p50 11 / p95 20 ms to p50 7 / p95
8 ms; the tracking itself takes ~2.5 ms of it, the rest is moving two images through DDS.

The work per frame is serial (pair, track, publish), so one executor thread serves every
callback: no locks, and no second Python thread competing for the GIL with the tracking.
Latency (image stamp -> marker publication) is logged per frame at debug level and summed up
every ``stats_period_s`` and at shutdown.
"""

from __future__ import annotations

import math
import sys
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from builtin_interfaces.msg import Time
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, Image
from visualization_msgs.msg import MarkerArray

from damon_ros.perception import fit_kernels
from damon_ros.perception.camera import Camera, load_camera
from damon_ros.perception.tracker_config import load_tracker_config
from damon_ros.perception.tracking import Track, Tracker
from damon_ros.ros import topics
from damon_ros.ros.cdr import marker_array_bytes
from damon_ros.ros.images import (
    COLOR_ENCODINGS,
    DEPTH_ENCODINGS,
    FrameSynchronizer,
    decode_color,
    decode_depth,
)
from damon_ros.ros.markers import (
    SEEN_SUFFIX,
    MarkerRecord,
    class_rgba,
    delete_record,
    shape_record,
)
from damon_ros.ros.node_loop import use_realtime_priority
from damon_ros.ros.node_main import node_main
from damon_ros.ros.parameters import Param, declare_all
from damon_ros.ros.problems import ProblemLog
from damon_ros.ros.stamps import clock_seconds, stamp_seconds

NAME = "tracker"
LATENCY_HISTORY = 3000

PARAMETERS = (
    Param("tracker_config", "", "tracker settings (HSV classes, shape model, tracking); "
                                "'' = config/tracker.yaml"),
    Param("cameras", (topics.CAMERA_PREFIX,),
          "topic prefix of each camera (<prefix>/color/image_raw, ...); fused into one world"),
    Param("camera_configs", ("",),
          "camera file of each camera in `cameras` (base_T_camera, base frame), a path or a "
          "shipped name (camera_side.yaml); '' = config/camera.yaml (intrinsics: camera_info)"),
    Param("sync_tolerance_s", 0.005,
          "colour and depth frames pair when their stamps differ by <= this", 0.0, 1.0),
    Param("queue_size", 10, "unmatched frames held per stream while waiting for the other",
          1, 1000),
    Param("marker_lifetime_s", 0.0, "marker lifetime (s); 0: the tracker's max_age_s",
          0.0, 3600.0),
    Param("publish_partial", True,
          "also publish obstacles seen only in part (image border, occluder)"),
    Param("stats_period_s", 10.0,
          "log frame rate and latency every this many seconds; 0: at shutdown", 0.0, 3600.0),
    Param("warn_every_s", 10.0,
          "a repeated problem (bad image, ...) is logged at most this often", 0.0, 3600.0),
    Param("realtime_priority", 10,
          "SCHED_FIFO priority of the node's threads, 0: normal scheduling", 0, 99),
)


# --- pure helpers (tested without ROS) --------------------------------------------------------


def camera_from_info(msg: CameraInfo, calibration: Camera) -> Camera:
    """The camera the tracker deprojects with: camera_info's K and size, the file's pose."""
    k = np.asarray(msg.k, dtype=float)
    try:
        return Camera(width=int(msg.width), height=int(msg.height), K=k.reshape(3, 3),
                      base_T_camera=calibration.base_T_camera, fps=calibration.fps,
                      frame_id=msg.header.frame_id or calibration.frame_id,
                      base_frame=calibration.base_frame)
    except ValueError as exc:
        raise ValueError(f"camera_info unusable: {exc}") from exc


def decode_image(msg: Image, camera: Camera, depth: bool) -> np.ndarray:
    """A colour (rgb8) or depth (uint16 mm) array, checked against camera_info's size."""
    what = "depth" if depth else "colour"
    encodings = DEPTH_ENCODINGS if depth else COLOR_ENCODINGS
    if msg.encoding not in encodings:
        raise ValueError(f"{what} image encoding {msg.encoding!r} is not supported; expected "
                         f"one of {encodings}")
    if (msg.width, msg.height) != (camera.width, camera.height):
        raise ValueError(f"{what} image is {msg.width}x{msg.height} but camera_info says "
                         f"{camera.width}x{camera.height}")
    if depth:
        return decode_depth(msg.encoding, msg.height, msg.width, msg.step, msg.data,
                            bool(msg.is_bigendian))
    return decode_color(msg.encoding, msg.height, msg.width, msg.step, msg.data)


def obstacle_markers(tracks: Sequence[Track], previous: set[tuple[str, int]], frame_id: str,
                     stamp: Time, lifetime_s: float, publish_partial: bool
                     ) -> tuple[list[MarkerRecord], set[tuple[str, int]]]:
    """One ADD marker per (published) track, a DELETE for each one no longer published,
    as records for `cdr.marker_array_bytes`.

    A track's visible surface goes beside it as ``(color + SEEN_SUFFIX, id)`` (see
    :mod:`damon_ros.ros.markers`): what the cameras saw, the rest being its hidden extent.
    Returns the markers and the keys they show, which are ``previous`` for the next frame.
    """
    out = []
    shown = set()
    for track in tracks:
        if track.partial and not publish_partial:
            continue
        out.append(shape_record(track.shape, track.color, track.id, frame_id, stamp,
                                lifetime_s, class_rgba(track.color)))
        shown.add((track.color, track.id))
        if track.seen is not None:
            out.append(shape_record(track.seen, track.color + SEEN_SUFFIX, track.id, frame_id,
                                    stamp, lifetime_s, class_rgba(track.color, 1.0)))
            shown.add((track.color + SEEN_SUFFIX, track.id))
    for ns, id in sorted(previous - shown):
        out.append(delete_record(ns, id, frame_id, stamp))
    return out, shown


@dataclass(eq=False)
class CameraView:
    """One camera of the tracker: its topics' prefix, calibration, pairing and intrinsics."""

    prefix: str
    calibration: Camera
    sync: FrameSynchronizer
    camera: Camera | None = None  # from the first usable camera_info
    info_key: tuple | None = None
    waiting_logged: bool = False


def camera_views(prefixes: Sequence[str], configs: Sequence[str], sync_tolerance_s: float,
                 queue_size: int) -> list[CameraView]:
    """The cameras of the parameters ``cameras`` and ``camera_configs`` (same length, one
    base frame, distinct prefixes), refused with a reason otherwise."""
    prefixes, configs = list(prefixes), list(configs)
    if not prefixes or len(prefixes) != len(configs):
        raise ValueError(f"parameters cameras ({len(prefixes)}) and camera_configs "
                         f"({len(configs)}) must list the same, non-zero number of cameras")
    if len(set(prefixes)) != len(prefixes):
        raise ValueError(f"parameter cameras {prefixes} names a camera twice")
    for prefix in prefixes:
        topics.camera_topics(prefix)  # refuses an empty one
    views = [CameraView(p, load_camera(c or None), FrameSynchronizer(sync_tolerance_s,
                                                                      queue_size))
             for p, c in zip(prefixes, configs, strict=True)]
    frames = {v.calibration.base_frame for v in views}
    if len(frames) > 1:
        raise ValueError(f"camera_configs give different base frames {sorted(frames)}; the "
                         "tracker publishes in one")
    return views


@dataclass
class LatencyStats:
    """Stamp -> publication latencies, processing times and the CPU time the processing took
    of recent frames (seconds), and how much of that CPU time was tracking (the rest builds
    and publishes the markers). Processing well above its CPU time means the node waited for
    a core (a busy machine), not that tracking grew slower."""

    latency: deque
    processing: deque
    cpu: deque
    tracking: deque
    frames: int = 0

    @classmethod
    def empty(cls) -> LatencyStats:
        return cls(*(deque(maxlen=LATENCY_HISTORY) for _ in range(4)))

    def add(self, latency_s: float, processing_s: float, cpu_s: float,
            tracking_cpu_s: float) -> None:
        self.latency.append(latency_s)
        self.processing.append(processing_s)
        self.cpu.append(cpu_s)
        self.tracking.append(tracking_cpu_s)
        self.frames += 1

    def summary(self) -> str:
        if not self.latency:
            return "no frames tracked yet"
        lat = 1e3 * np.asarray(self.latency)
        proc = 1e3 * np.asarray(self.processing)
        return (f"latency stamp->publish p50 {np.median(lat):.2f} ms, p95 "
                f"{np.percentile(lat, 95):.2f} ms, p99 {np.percentile(lat, 99):.2f} ms, max "
                f"{lat.max():.2f} ms; processing p50 "
                f"{np.median(proc):.2f} ms, its CPU time p50 {1e3 * np.median(self.cpu):.2f} ms "
                f"(tracking p50 {1e3 * np.median(self.tracking):.2f} ms) (last {lat.size} "
                "frames)")


# --- the node ---------------------------------------------------------------------------------


class TrackerNode(Node):
    """Camera topics in, `Tracker.update` per synchronised pair, obstacle markers out."""

    def __init__(self) -> None:
        super().__init__(NAME)
        p = declare_all(self, PARAMETERS)
        self.config = load_tracker_config(p["tracker_config"] or None)
        self.views = camera_views(p["cameras"], p["camera_configs"], p["sync_tolerance_s"],
                                  p["queue_size"])
        self.base_frame = self.views[0].calibration.base_frame
        self.lifetime_s = p["marker_lifetime_s"] or self.config.max_age_s
        self.publish_partial = p["publish_partial"]
        self.problems = ProblemLog(self.get_logger().warning, p["warn_every_s"])
        self.stats = LatencyStats.empty()
        self.tracker = Tracker(self.views[0].calibration, self.config)
        fit_kernels.warm_up()  # before the first frame, not during it
        self.late_frames = 0  # frames older than one of another camera already tracked
        self._newest_stamp = -math.inf
        self._shown: set[tuple[str, int]] = set()
        self._pub = self.create_publisher(MarkerArray, topics.OBSTACLES, 10)
        qos = qos_profile_sensor_data
        for i, view in enumerate(self.views):
            color, depth, info = topics.camera_topics(view.prefix)
            self.create_subscription(CameraInfo, info, lambda m, i=i: self._on_info(i, m), qos)
            self.create_subscription(Image, color, lambda m, i=i: self._on_image(i, m, False),
                                     qos)
            self.create_subscription(Image, depth, lambda m, i=i: self._on_image(i, m, True),
                                     qos)
        if p["stats_period_s"] > 0.0:
            self._stats_started = time.monotonic()
            self._stats_frames = 0
            self.create_timer(p["stats_period_s"], self._log_stats)
        use_realtime_priority(self, p["realtime_priority"])
        self.get_logger().info(
            f"tracking {sorted(self.config.colors)} as {self.config.shape}s in "
            f"{self.base_frame} on {topics.OBSTACLES} from {len(self.views)} camera(s) "
            f"{[v.prefix for v in self.views]}, marker lifetime {self.lifetime_s:g} s")

    # -- callbacks

    def _on_info(self, i: int, msg: CameraInfo) -> None:
        view = self.views[i]
        key = (msg.width, msg.height, tuple(msg.k), msg.header.frame_id)
        if key == view.info_key:
            return
        calibration = view.calibration
        try:
            camera = camera_from_info(msg, calibration)
        except ValueError as exc:
            self.problems.report(f"{view.prefix}: {exc}")
            return
        view.info_key = key
        if any(msg.d):
            self.problems.report(f"{view.prefix}: camera_info has distortion {list(msg.d)}; the "
                                 "tracker assumes a rectified image and ignores it")
        if camera.frame_id != calibration.frame_id:
            self.problems.report(f"{view.prefix}: camera_info frame {camera.frame_id!r} differs "
                                 f"from the calibrated {calibration.frame_id!r}; using the "
                                 "calibration's base_T_camera")
        view.camera = camera  # tracks live in the base frame: they stay valid
        K = camera.K
        self.get_logger().info(f"{view.prefix} camera_info: {camera.width}x{camera.height}, fx "
                               f"{K[0, 0]:g} fy {K[1, 1]:g} cx {K[0, 2]:g} cy {K[1, 2]:g}")

    def _on_image(self, i: int, msg: Image, depth: bool) -> None:
        view = self.views[i]
        if view.camera is None:
            if not view.waiting_logged:
                view.waiting_logged = True
                info = topics.camera_topics(view.prefix)[2]
                self.get_logger().warning(f"no camera_info on {info} yet: dropping frames until "
                                          "it arrives")
            return
        stamp = stamp_seconds(msg.header.stamp)
        self._check_clock(stamp)
        try:
            image = decode_image(msg, view.camera, depth)
            add = view.sync.add_depth if depth else view.sync.add_color
            pairs = add(stamp, (image, msg.header.stamp))
        except ValueError as exc:
            self.problems.report(f"dropped a frame: {exc}")
            return
        for pair in pairs:
            self._track(i, pair.color, pair.depth)

    def _check_clock(self, stamp: float) -> None:
        """Restart pairing when stamps jump back (simulation reset, bag loop).

        `FrameSynchronizer` drops every frame older than its last pair, which after such a
        jump would be every frame from then on; `Tracker` resets itself on the same test.
        """
        if stamp < self._newest_stamp - self.config.time_jump_s:
            self.get_logger().info(f"image stamps jumped back by {self._newest_stamp - stamp:.3f}"
                                   " s: restarting colour/depth pairing")
            for view in self.views:
                view.sync = FrameSynchronizer(view.sync.tolerance_s, view.sync.queue_size)
            self._newest_stamp = stamp
        self._newest_stamp = max(self._newest_stamp, stamp)

    def _track(self, i: int, color: tuple[np.ndarray, Time],
               depth: tuple[np.ndarray, Time]) -> None:
        started, cpu_started = time.perf_counter(), time.thread_time()
        rgb, stamp = color
        try:
            tracks = self.tracker.update_camera(i, self.views[i].camera, rgb, depth[0],
                                                stamp_seconds(stamp))
        except ValueError as exc:
            self.problems.report(f"dropped a frame: {exc}")
            return
        if tracks is None:  # older than another camera's frame: kept for fusion only
            self.late_frames += 1
            return
        tracked_cpu = time.thread_time()
        markers, self._shown = obstacle_markers(tracks, self._shown, self.base_frame, stamp,
                                                self.lifetime_s, self.publish_partial)
        self._pub.publish(marker_array_bytes(markers))
        latency = clock_seconds(self) - stamp_seconds(stamp)
        self.stats.add(latency, time.perf_counter() - started,
                       time.thread_time() - cpu_started, tracked_cpu - cpu_started)
        self.get_logger().debug(f"{len(tracks)} tracks, latency {latency * 1e3:.2f} ms")

    def _log_stats(self) -> None:
        now = time.monotonic()
        fps = (self.stats.frames - self._stats_frames) / max(now - self._stats_started, 1e-9)
        self._stats_started, self._stats_frames = now, self.stats.frames
        dropped = sum(v.sync.dropped for v in self.views)
        late = f", {self.late_frames} late frames fused only" if len(self.views) > 1 else ""
        self.get_logger().info(f"{fps:.1f} frames/s tracked; {self.stats.summary()}; "
                               f"{dropped} unpaired frames dropped so far{late}; "
                               f"{self._kept_fits()}")

    def _kept_fits(self) -> str:
        """How many blobs kept their fit (`still_blobs`): a still scene should be most."""
        kept = sum(s.reused for s in self.tracker.still.values())
        fitted = sum(s.fitted for s in self.tracker.still.values())
        return f"{kept} of {kept + fitted} blobs kept an unmoved fit"

    def on_shutdown(self) -> None:
        """Called by `run_single_threaded`: the run's statistics in one line."""
        self.get_logger().info(f"{self.stats.frames} frames tracked; {self.stats.summary()}; "
                               f"{self._kept_fits()}")


CONFIG_FILE = "config/tracker_node.yaml"
"""The node's parameters file: config/tracker.yaml holds the tracking settings themselves."""
EXTRA_HELP = "The tracking settings themselves: config/tracker.yaml (parameter tracker_config)."


def main(args: Sequence[str] | None = None) -> int:
    """Console entry point (``--help``, one-line errors): see `node_main`."""
    return node_main(NAME, __doc__.split("\n\n")[0], PARAMETERS, TrackerNode, args,
                     extra_help=EXTRA_HELP, config_file=CONFIG_FILE)


if __name__ == "__main__":
    sys.exit(main())

