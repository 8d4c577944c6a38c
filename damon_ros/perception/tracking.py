"""HSV + depth obstacle tracking: coloured blobs in a RealSense frame -> obstacles in the base.

DAMON's runtime loop sees obstacles through a colour mask and aligned depth, moved into the
robot base frame with the hand-eye calibration. This module runs that perception step, with
no ROS in it (the tracker node is a thin adapter):

1. segmentation (:mod:`damon_ros.perception.segmentation`): coloured regions of the frame;
2. estimation (:mod:`damon_ros.perception.shape_fit`): each region's conservative bounding
   shape in the base frame;
3. tracking (here): per colour class, detections are matched to tracks by gated nearest
   neighbour (optimal assignment) so ids stay stable; velocity is the least-squares slope of
   the recent centres (:mod:`damon_ros.perception.velocity`), zero once a track passes the
   stationarity test (:mod:`damon_ros.perception.stationarity`); tracks unseen for
   ``max_age_s`` are dropped.

The settings of all three are one :class:`~damon_ros.perception.tracker_config.TrackerConfig`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from scipy.optimize import linear_sum_assignment

from damon_ros.core.hull import DOP_DIRECTIONS, MAX_HULL_VERTICES, few_vertices
from damon_ros.core.shapes import Shape
from damon_ros.perception.camera import Camera, to_base_frame
from damon_ros.perception.fusion import fuse
from damon_ros.perception.joint_fit import joint_fit
from damon_ros.perception.segmentation import Segmenter
from damon_ros.perception.shape_fit import blob_points, estimate_shape
from damon_ros.perception.stationarity import Stationarity
from damon_ros.perception.still_blobs import StillBlobs
from damon_ros.perception.tracker_config import TrackerConfig, load_tracker_config
from damon_ros.perception.velocity import VelocityWindow

# --- detection: one frame ---------------------------------------------------------------------


def check_images(camera: Camera, rgb: np.ndarray, depth: np.ndarray) -> None:
    """Refuse frames the tracker cannot interpret, with a message naming the problem."""
    expected = (camera.height, camera.width)
    if not isinstance(rgb, np.ndarray) or rgb.dtype != np.uint8 or rgb.ndim != 3 or (
        rgb.shape[2] != 3
    ):
        raise ValueError(
            "colour image must be a uint8 HxWx3 rgb8 array, got "
            f"{getattr(rgb, 'dtype', type(rgb).__name__)} {getattr(rgb, 'shape', '')}"
        )
    if not isinstance(depth, np.ndarray) or depth.dtype != np.uint16 or depth.ndim != 2:
        raise ValueError(
            "depth image must be a uint16 HxW array in mm (16UC1), got "
            f"{getattr(depth, 'dtype', type(depth).__name__)} {getattr(depth, 'shape', '')}"
        )
    if rgb.shape[:2] != expected or depth.shape != expected:
        raise ValueError(
            f"image sizes colour {rgb.shape[1]}x{rgb.shape[0]} and depth "
            f"{depth.shape[1]}x{depth.shape[0]} must match the camera's "
            f"{camera.width}x{camera.height}"
        )
    if not depth.any():
        raise ValueError("depth image has no valid readings (all zero)")


class Detection(NamedTuple):
    """One obstacle seen in one frame.

    ``partial``: the blob touches the image border or a nearer surface borders it, so part of
    the obstacle may be hidden and the bound is only a bound of what is visible.
    ``seen``: the visible surface alone (base frame; :func:`seen_part`): what the cameras
    saw of the object; the rest of the bound is the hidden extent that no camera saw.
    """

    color: str
    shape: Shape
    round: bool
    partial: bool
    points: int
    area_px: int
    seen: Shape | None = None
    surface: np.ndarray | None = None
    """The visible points themselves (base frame, N x 3): fusion checks every other view's
    bound against them (`fusion.fuse`)."""


def seen_part(points_base: np.ndarray, name: str = "") -> Shape:
    """The visible surface as a point set: the points extreme along 26 directions (its hull
    lies inside the hull of all the points, and is close to it; a few dozen points keep the
    marker small). It tells a refusal caused by what was seen from one caused by the hidden
    extent (:mod:`damon_ros.perception.unseen`); it bounds nothing."""
    points = np.asarray(points_base, dtype=float).reshape(-1, 3)
    scores = DOP_DIRECTIONS @ np.ascontiguousarray(points.T)  # 26 x N: argmax along rows
    chosen = points[np.unique(np.argmax(scores, axis=1))]
    mid = 0.5 * (chosen.min(axis=0) + chosen.max(axis=0))
    return Shape("points", (), mid, points=chosen - mid, name=name)


def _union(parts: Sequence[Shape | None], name: str) -> Shape | None:
    """The seen parts of several views of one object, as one point set."""
    known = [p for p in parts if p is not None]
    if not known:
        return None
    return seen_part(np.vstack([p.position + p.points for p in known]), name)


def detect(camera: Camera, config: TrackerConfig, rgb: np.ndarray, depth: np.ndarray,
           segmenter: Segmenter | None = None, checked: bool = False,
           still: StillBlobs | None = None, stamp: float = 0.0) -> list[Detection]:
    """All obstacles of one frame (no tracking): segment, deproject, bound. ``checked``:
    the caller ran `check_images` already (its all-zero test reads the whole depth image).
    ``still``: this camera's fits of unmoved blobs, reused (:mod:`still_blobs`)."""
    if not checked:
        check_images(camera, rgb, depth)
    segmenter = Segmenter(config) if segmenter is None else segmenter
    still = StillBlobs(0.0) if still is None else still  # (0: keeps no fit)
    still.start_frame(camera)
    found = []
    for blob in segmenter.blobs(rgb, depth):
        kept = still.reuse(blob, stamp)
        if kept is not None:
            found.append(kept)
            continue
        points = blob_points(camera, blob, config)
        if len(points) < config.min_points:
            continue
        estimate = estimate_shape(camera, points, config, name=blob.color,
                                  partial=blob.partial, occluders=blob.occluders)
        surface = to_base_frame(camera, points)
        found.append(Detection(blob.color, estimate.shape, estimate.round, blob.partial,
                               len(points), blob.area_px, seen_part(surface, blob.color),
                               surface))
        still.remember(blob, found[-1], stamp)
    still.end_frame()
    return found


def _same(a: tuple, b: tuple) -> bool:
    """Two fusion inputs ``(detections per view, slack, anchored, cameras)`` are the same
    objects (identity: a kept detection is the very object of the frame it was fitted in)."""
    (views_a, slack_a, anchored_a, cams_a), (views_b, slack_b, anchored_b, cams_b) = a, b
    return (slack_a == slack_b and anchored_a == anchored_b and _identical(cams_a, cams_b)
            and len(views_a) == len(views_b)
            and all(_identical(x, y) for x, y in zip(views_a, views_b, strict=True)))


def _identical(xs: Sequence, ys: Sequence) -> bool:
    return len(xs) == len(ys) and all(x is y for x, y in zip(xs, ys, strict=True))


def _few_vertices(shape: Shape) -> Shape:
    """A point-set bound with at most `hull.MAX_HULL_VERTICES` vertices that contains
    ``shape`` (`hull.few_vertices`); any other shape as it is."""
    if shape.kind != "points" or len(shape.points) <= MAX_HULL_VERTICES:
        return shape
    return Shape("points", (), shape.position, shape.orientation,
                 points=few_vertices(shape.points), name=shape.name)


# --- tracking --------------------------------------------------------------------------------

SAME_INSTANT_S = 1e-3
"""Frames of different cameras this close in time are of one instant (hardware-synchronised
cameras stamp alike to well within it): fused with no motion slack."""


@dataclass(frozen=True, eq=False)
class Track:
    """A tracked obstacle as the planner sees it.

    ``shape`` is the last observed bounding shape (not extrapolated: a consumer that wants a
    prediction uses ``velocity`` and ``last_seen``); ``age`` is seconds since first seen;
    ``hits`` counts the frames it was seen in; ``partial`` is the last detection's flag;
    ``seen`` the last detection's visible surface (`Detection`).
    """

    id: int
    color: str
    shape: Shape
    velocity: np.ndarray
    last_seen: float
    age: float
    hits: int
    partial: bool = False
    seen: Shape | None = None


@dataclass(eq=False)
class _TrackState:
    id: int
    color: str
    shape: Shape
    first_seen: float
    last_seen: float
    motion: VelocityWindow
    stillness: Stationarity
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    hits: int = 0
    partial: bool = False
    seen: Shape | None = None

    def predict(self, stamp: float) -> np.ndarray:
        return self.shape.position + self.velocity * (stamp - self.last_seen)

    def observe(self, detection: Detection, stamp: float) -> None:
        """Take a detection; velocity = least-squares slope of centres over the window.

        With a single centre in the window (a new track, or one unseen for longer than the
        window) the previous velocity is kept; so it is when the view is only what an
        occluder left visible of the object in place (`Stationarity.cut_in_place`): its
        centre is no evidence of motion, and its shape is the last whole one, grown a little
        (`Stationarity.held_bound`).
        """
        shape = _few_vertices(detection.shape)
        self.shape = shape
        self.partial = detection.partial
        self.seen = detection.seen
        self.last_seen = stamp
        self.hits += 1
        if self.stillness.cut_in_place(shape, detection.partial, detection.area_px,
                                       detection.surface):
            self.shape = self.stillness.held_bound(shape)
            return
        was_still = self.stillness.still
        velocity = self.motion.add(stamp, shape.position)
        if velocity is not None:
            self.velocity = self.stillness.update(stamp, shape.position, velocity,
                                                  detection.round)
            if was_still and not self.stillness.still:  # it has just started to move
                since = self.motion.since_rest(self.stillness.anchor,
                                               self.stillness.jitter_m(detection.round))
                if since is not None:
                    self.velocity = since

    def snapshot(self) -> Track:
        return Track(self.id, self.color, self.shape, self.velocity.copy(), self.last_seen,
                     self.last_seen - self.first_seen, self.hits, self.partial, self.seen)


class Tracker:
    """Frames in, tracked obstacles with stable ids and velocities out (base frame)."""

    def __init__(self, camera: Camera, config: TrackerConfig | None = None) -> None:
        self.camera = camera
        self.config = load_tracker_config() if config is None else config
        self.segmenter = Segmenter(self.config)
        self.detections: list[Detection] = []
        self._tracks: list[_TrackState] = []
        self._next_id = 0
        self._last_stamp: float | None = None
        self._views: dict[int, tuple[float, list[Detection]]] = {}  # see `update_camera`
        self._cameras: dict[int, Camera] = {}  # the camera of each view
        self._at_last: set[int] = set()  # the views of the instant tracked last
        self.still: dict[int, StillBlobs] = {}  # each view's unmoved fits (`still_blobs`)
        self._fusion_memo: dict[str, tuple] = {}  # per colour, the last fusion (`_fused`)

    def reset(self) -> None:
        """Forget every track (ids keep counting up, so an old id never means a new thing)."""
        self._tracks = []
        self._last_stamp = None
        self._views = {}
        self._at_last = set()
        self.still = {}
        self._fusion_memo = {}

    def _still(self, view: int) -> StillBlobs:
        if view not in self.still:
            self.still[view] = StillBlobs(self.config.refit_after_s)
        return self.still[view]

    @property
    def tracks(self) -> list[Track]:
        return [t.snapshot() for t in self._tracks]

    def _check_stamp(self, stamp_s: float) -> None:
        if not math.isfinite(stamp_s):
            raise ValueError(f"frame stamp {stamp_s} is not finite")
        last = self._last_stamp
        if last is None:
            return
        if stamp_s < last - self.config.time_jump_s:
            self.reset()  # the clock restarted (simulation reset, bag loop)
        elif stamp_s <= last:
            raise ValueError(f"frame stamp {stamp_s:.6f} s is not newer than the last "
                             f"processed frame {last:.6f} s")

    def update(self, rgb: np.ndarray, depth: np.ndarray, stamp_s: float) -> list[Track]:
        """Process one synchronised frame; return every live track."""
        stamp_s = float(stamp_s)
        check_images(self.camera, rgb, depth)
        self._check_stamp(stamp_s)
        self.detections = detect(self.camera, self.config, rgb, depth, self.segmenter, True,
                                 self._still(0), stamp_s)
        return self._track(stamp_s)

    def update_views(self, cameras: Sequence[Camera], frames: Sequence[tuple[np.ndarray,
                     np.ndarray]], stamp_s: float) -> list[Track]:
        """Process one synchronised frame of each camera (``frames[c]`` = ``(rgb, depth)`` of
        ``cameras[c]``): detections are fused across views (:mod:`fusion`), then tracked."""
        if len(cameras) != len(frames) or not cameras:
            raise ValueError(f"{len(frames)} frames for {len(cameras)} cameras")
        stamp_s = float(stamp_s)
        for camera, (rgb, depth) in zip(cameras, frames, strict=True):
            check_images(camera, rgb, depth)
        self._check_stamp(stamp_s)
        views = [detect(c, self.config, rgb, depth, self.segmenter, True, self._still(v), stamp_s)
                 for v, (c, (rgb, depth)) in enumerate(zip(cameras, frames, strict=True))]
        self.detections = self._fused(views, [0.0] * len(views), anchored=False,
                                      cameras=list(cameras))
        return self._track(stamp_s)

    def update_camera(self, view: int, camera: Camera, rgb: np.ndarray, depth: np.ndarray,
                      stamp_s: float) -> list[Track] | None:
        """One frame of camera ``view`` among several (the tracker node, frames as they come).

        Its detections are fused with each other camera's latest ones that are at most
        ``fusion_window_s`` older, those grown by ``max_speed_mps`` times their age so that
        they still contain the object now (:func:`fusion.fuse`, anchored on this frame:
        an object only another camera sees is tracked from that camera's frames). Cameras
        synchronised in hardware stamp their frames alike: a frame of the instant just
        tracked (within `SAME_INSTANT_S`) that was not part of it is fused with it and
        tracked again at that instant, with no motion slack. Any other frame not newer than
        the last one tracked (frames of different cameras arrive out of order) is not
        tracked but kept for fusing later frames: then None is returned.
        """
        stamp_s = float(stamp_s)
        check_images(camera, rgb, depth)
        last = self._last_stamp
        older = (last is not None and math.isfinite(stamp_s)
                 and last - self.config.time_jump_s <= stamp_s <= last)
        same_instant = older and stamp_s >= last - SAME_INSTANT_S and view not in self._at_last
        if not older:
            self._check_stamp(stamp_s)  # a clock jump resets the tracker and the views
        found = detect(camera, self.config, rgb, depth, self.segmenter, True, self._still(view),
                       stamp_s)
        self._views[view] = (stamp_s, found)
        self._cameras[view] = camera
        if older and not same_instant:
            return None
        now = last if same_instant else stamp_s
        others = [(v, s, d) for v, (s, d) in sorted(self._views.items())
                  if v != view and 0.0 <= now - s <= self.config.fusion_window_s]
        slack = [self.config.max_speed_mps * (now - s)
                 for s in [stamp_s] + [s for _, s, _ in others]]
        self.detections = self._fused([found] + [d for _, _, d in others], slack, anchored=True,
                                      cameras=[camera] + [self._cameras[v] for v, _, _ in others])
        self._at_last = {v for v, (s, _) in self._views.items()
                         if now - SAME_INSTANT_S <= s <= now}
        return self._track(now)

    def _fused(self, views: list[list[Detection]], slack: list[float],
               anchored: bool, cameras: list[Camera]) -> list[Detection]:
        """Per colour class, the detections of several views fused (:func:`fusion.fuse`);
        an object that several cameras saw at one instant gets the one shape fitted to all
        their points instead, where one fits (:func:`joint_fit.joint_fit`)."""
        if len(views) == 1:
            return list(views[0])
        out = []
        memo, self._fusion_memo = self._fusion_memo, {}
        for color in sorted({d.color for view in views for d in view}):
            mine = [[d for d in view if d.color == color] for view in views]
            key = (mine, list(slack), anchored, cameras)
            if color in memo and _same(memo[color][0], key):
                # every view's detections are the very ones fused last (`still_blobs`
                # kept them), at the same slack: the fusion would repeat itself
                self._fusion_memo[color] = memo[color]
                out.extend(memo[color][1])
                continue
            first = len(out)
            per_view = [[(d.shape, d.partial) for d in view] for view in mine]
            seen = [[d.surface for d in view] for view in mine]

            def refit(members, mine=mine, color=color):
                if any(slack[v] != 0.0 for v, _ in members):
                    return None  # frames of different instants: the object moved between
                return joint_fit([(cameras[v], mine[v][i].shape, mine[v][i].surface,
                                   mine[v][i].partial) for v, i in members], self.config, color)

            for shape, partial, members in fuse(per_view, self.config.gate_m, slack, anchored,
                                                seen, self.config.face_tolerance_m, refit):
                parts = [mine[v][i] for v, i in members]
                surfaces = [d.surface for d in parts if d.surface is not None]
                out.append(Detection(color, shape, shape.kind == "sphere", partial,
                                     sum(d.points for d in parts),
                                     sum(d.area_px for d in parts),
                                     _union([d.seen for d in parts], color),
                                     np.vstack(surfaces) if surfaces else None))
            self._fusion_memo[color] = (key, out[first:])
        return out

    def _track(self, stamp_s: float) -> list[Track]:
        for color in {d.color for d in self.detections} | {t.color for t in self._tracks}:
            self._associate(color, [d for d in self.detections if d.color == color], stamp_s)
        self._tracks = [t for t in self._tracks
                        if stamp_s - t.last_seen <= self.config.max_age_s]
        self._last_stamp = stamp_s
        return self.tracks

    def _associate(self, color: str, detections: Sequence[Detection], stamp: float) -> None:
        """Optimal one-to-one matching inside the gate; unmatched detections open tracks."""
        tracks = [t for t in self._tracks if t.color == color]
        matched: set[int] = set()
        if tracks and detections:
            predicted = np.array([t.predict(stamp) for t in tracks])
            centres = np.array([d.shape.position for d in detections])
            cost = np.linalg.norm(predicted[:, None, :] - centres[None, :, :], axis=2)
            rows, cols = linear_sum_assignment(np.where(cost <= self.config.gate_m, cost, 1e6))
            for r, c in zip(rows, cols, strict=True):
                if cost[r, c] <= self.config.gate_m:
                    tracks[r].observe(detections[c], stamp)
                    matched.add(int(c))
        for i, d in enumerate(detections):
            if i not in matched:
                motion = VelocityWindow(self.config.velocity_window_s)
                state = _TrackState(self._next_id, color, d.shape, stamp, stamp, motion,
                                    Stationarity(self.config))
                state.observe(d, stamp)
                self._tracks.append(state)
                self._next_id += 1
