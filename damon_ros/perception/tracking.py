"""HSV + depth obstacle tracking: coloured blobs in a RealSense frame -> obstacles in the base.

DAMON's runtime loop sees obstacles through a colour mask and aligned depth, moved into the
robot base frame with the hand-eye calibration. This module is that perception step, with
no ROS in it (the tracker node is a thin adapter):

1. segmentation: RGB -> HSV, one range set per colour class, opening/closing, connected
   components, a minimum area;
2. estimation: each blob's depth pixels are deprojected with K, depth outliers are dropped
   by a median/MAD test, and a *conservative* bounding shape is estimated in the base frame;
   a round blob gets a least-squares sphere (the visible cap fixes the centre), any other a
   bound that assumes the hidden depth is at most the largest visible width; everything is
   inflated by a margin, because the planner certifies paths against these shapes;
3. tracking: per colour class, detections are matched to tracks by gated nearest neighbour
   (optimal assignment) so ids stay stable; velocity is the least-squares slope of the
   recent centres; tracks unseen for ``max_age_s`` are dropped.

``FrameSynchronizer`` pairs colour and depth frames by stamp (message_filters' approximate
policy, which is not installable here).
"""

from __future__ import annotations

import bisect
import math
import os
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, NamedTuple

import cv2
import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial.transform import Rotation

from damon_ros.core.resources import config_file, read_yaml_section
from damon_ros.core.shapes import Shape
from damon_ros.perception.camera import Camera

SHAPE_MODES = ("sphere", "box", "auto")
COLOR_ENCODINGS = ("rgb8", "bgr8")
DEPTH_ENCODINGS = ("16UC1", "mono16", "32FC1")
MAD_TO_SIGMA = 1.4826
"""MAD of a normal distribution times this is its standard deviation."""


# --- configuration ---------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class TrackerConfig:
    """Tracker parameters (``config/tracker.yaml``); see that file for what each one does.

    ``colors`` maps a class name to a tuple of ``(low, high)`` HSV ranges (uint8 arrays).
    """

    colors: dict[str, tuple[tuple[np.ndarray, np.ndarray], ...]]
    downsample: int = 2
    open_kernel_px: int = 3
    close_kernel_px: int = 3
    min_area_px: int = 80
    min_points: int = 12
    max_points: int = 1500
    min_depth_m: float = 0.15
    max_depth_m: float = 6.0
    mad_k: float = 3.5
    mad_floor_m: float = 0.03
    shape: str = "sphere"
    inflation_m: float = 0.015
    sphere_rms_ratio: float = 0.03
    sphere_rms_floor_m: float = 0.006
    sphere_width_ratio: float = 0.25
    gate_m: float = 0.15
    max_age_s: float = 0.5
    velocity_window_s: float = 0.3
    time_jump_s: float = 1.0

    def __post_init__(self) -> None:
        if not self.colors:
            raise ValueError("tracker colors: at least one colour class is needed")
        if self.shape not in SHAPE_MODES:
            raise ValueError(f"tracker shape {self.shape!r} must be one of {SHAPE_MODES}")
        for name in ("downsample", "min_points", "max_points"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"tracker {name} {getattr(self, name)} must be >= 1")
        for name in ("open_kernel_px", "close_kernel_px", "min_area_px", "inflation_m",
                     "sphere_rms_floor_m", "min_depth_m"):
            if getattr(self, name) < 0:
                raise ValueError(f"tracker {name} {getattr(self, name)} must be >= 0")
        for name in ("max_depth_m", "mad_k", "mad_floor_m", "sphere_rms_ratio",
                     "sphere_width_ratio", "gate_m", "max_age_s", "velocity_window_s",
                     "time_jump_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"tracker {name} {getattr(self, name)} must be > 0")
        if self.min_depth_m >= self.max_depth_m:
            raise ValueError(
                f"tracker min_depth_m {self.min_depth_m} must be below max_depth_m "
                f"{self.max_depth_m}"
            )


def _hsv_ranges(name: str, value: Any) -> tuple[tuple[np.ndarray, np.ndarray], ...]:
    """Validate one class's ``[[low], [high]]`` list: H in 0..179, S and V in 0..255."""
    if not isinstance(value, list) or not value:
        raise ValueError(f"colors.{name} must be a non-empty list of [[h, s, v], [h, s, v]]")
    ranges = []
    for i, pair in enumerate(value):
        arr = np.asarray(pair, dtype=float)
        if arr.shape != (2, 3):
            raise ValueError(f"colors.{name}[{i}] must be [[h, s, v], [h, s, v]]")
        if np.any(arr < 0) or np.any(arr[:, 0] > 179) or np.any(arr[:, 1:] > 255):
            raise ValueError(f"colors.{name}[{i}] {arr.tolist()}: H is 0..179, S and V 0..255")
        if np.any(arr[0] > arr[1]):
            raise ValueError(f"colors.{name}[{i}] {arr.tolist()}: low must not exceed high")
        ranges.append((arr[0].astype(np.uint8), arr[1].astype(np.uint8)))
    return tuple(ranges)


def tracker_config_from_dict(data: dict, source: str = "<tracker>") -> TrackerConfig:
    """Build a :class:`TrackerConfig` from the ``tracker:`` mapping, naming any bad field."""
    known = {f.name for f in fields(TrackerConfig)}
    unknown = sorted(set(data) - known)
    try:
        if unknown:
            raise ValueError(f"unknown keys {unknown}")
        colors = data.get("colors")
        if not isinstance(colors, dict):
            raise ValueError("colors must map class names to HSV ranges")
        kwargs = {k: v for k, v in data.items() if k != "colors"}
        return TrackerConfig(
            colors={str(k): _hsv_ranges(str(k), v) for k, v in colors.items()}, **kwargs
        )
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{source}: tracker: {exc}") from exc


def load_tracker_config(path: str | os.PathLike | None = None) -> TrackerConfig:
    """The tracker configuration of ``path``, or of the shipped ``config/tracker.yaml``."""
    path = config_file("tracker.yaml") if path is None else Path(path)
    return tracker_config_from_dict(read_yaml_section(path, "tracker"), str(path))


# --- images: decoding and validation -----------------------------------------------------------


def _buffer(data: Any, height: int, step: int, what: str) -> np.ndarray:
    if height <= 0 or step <= 0:
        raise ValueError(f"{what} image has height {height} and step {step}; both must be > 0")
    buf = np.frombuffer(data, dtype=np.uint8)
    if buf.size < height * step:
        raise ValueError(
            f"{what} image holds {buf.size} bytes, less than height*step = {height * step}"
        )
    return buf[: height * step].reshape(height, step)


def decode_color(encoding: str, height: int, width: int, step: int, data: Any) -> np.ndarray:
    """A sensor_msgs/Image's fields as an ``rgb8`` array (H, W, 3); ``bgr8`` is converted."""
    if encoding not in COLOR_ENCODINGS:
        raise ValueError(f"colour image encoding {encoding!r} is not supported; "
                         f"expected one of {COLOR_ENCODINGS}")
    if step < 3 * width:
        raise ValueError(f"colour image step {step} is less than 3 * width = {3 * width}")
    rows = _buffer(data, height, step, "colour")
    image = rows[:, : 3 * width].reshape(height, width, 3)
    if encoding == "bgr8":
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    return np.ascontiguousarray(image)


def decode_depth(
    encoding: str, height: int, width: int, step: int, data: Any, is_bigendian: bool = False
) -> np.ndarray:
    """A depth sensor_msgs/Image as uint16 millimetres (0 = no return).

    ``16UC1``/``mono16`` are RealSense's millimetres; ``32FC1`` (metres, NaN = no return) is
    converted so that one code path serves both drivers.
    """
    if encoding not in DEPTH_ENCODINGS:
        raise ValueError(f"depth image encoding {encoding!r} is not supported; "
                         f"expected one of {DEPTH_ENCODINGS}")
    size = 4 if encoding == "32FC1" else 2
    if step < size * width:
        raise ValueError(f"depth image step {step} is less than {size} * width = {size * width}")
    rows = _buffer(data, height, step, "depth")[:, : size * width]
    order = ">" if is_bigendian else "<"
    if size == 2:
        return np.ascontiguousarray(rows).view(f"{order}u2").astype(np.uint16)
    metres = np.ascontiguousarray(rows).view(f"{order}f4").astype(np.float64)
    metres[~np.isfinite(metres) | (metres < 0.0)] = 0.0
    return np.clip(metres * 1000.0 + 0.5, 0, 65535).astype(np.uint16)


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


# --- segmentation ----------------------------------------------------------------------------


class Blob(NamedTuple):
    """One connected region of a colour class: full-resolution pixel coordinates and depth."""

    color: str
    u: np.ndarray
    v: np.ndarray
    depth_mm: np.ndarray
    area_px: int
    partial: bool


def _kernel(size: int) -> np.ndarray | None:
    size = int(size)
    return None if size <= 1 else cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))


_RING = np.ones((3, 3), np.uint8)
OCCLUSION_MARGIN_MM = 30
"""A pixel next to a blob that is this much nearer than the blob belongs to an occluder."""


def _occluded(inside: np.ndarray, depth: np.ndarray) -> bool:
    """Whether a nearer surface borders the blob, so part of the obstacle may be hidden.

    ``inside`` and ``depth`` cover the blob's bounding box grown by one pixel.
    """
    blob_depth = np.where(inside, depth, 0).astype(np.uint16)
    neighbour = cv2.dilate(blob_depth, _RING).astype(np.int32)
    ring = cv2.dilate(inside.view(np.uint8), _RING).astype(bool) & ~inside
    d = depth[ring].astype(np.int32)
    return bool(np.any((d > 0) & (d < neighbour[ring] - OCCLUSION_MARGIN_MM)))


def _class_mask(hsv: np.ndarray, ranges) -> np.ndarray:
    mask = cv2.inRange(hsv, ranges[0][0], ranges[0][1])
    for low, high in ranges[1:]:
        mask |= cv2.inRange(hsv, low, high)
    return mask


class Segmenter:
    """HSV class masks -> cleaned connected components, only inside each class's bounding box.

    Most of a frame is background; restricting morphology and labelling to the rectangle
    around a class's pixels is what keeps a frame at a fraction of a millisecond.
    """

    def __init__(self, config: TrackerConfig) -> None:
        self.config = config
        self.step = int(config.downsample)
        self.open = _kernel(config.open_kernel_px)
        self.close = _kernel(config.close_kernel_px)
        self.min_area = max(1, int(math.ceil(config.min_area_px / self.step**2)))
        self.pad = max(int(config.open_kernel_px), int(config.close_kernel_px), 1)

    def blobs(self, rgb: np.ndarray, depth: np.ndarray) -> list[Blob]:
        s = self.step
        # Nearest-neighbour resize by an integer factor keeps pixels (s*i, s*j), as the depth
        # slice below does, and is several times faster than copying a strided view.
        small = rgb if s == 1 else cv2.resize(
            rgb, (rgb.shape[1] // s, rgb.shape[0] // s), interpolation=cv2.INTER_NEAREST
        )
        depth_small = depth[::s, ::s]
        hsv = cv2.cvtColor(small, cv2.COLOR_RGB2HSV)
        found: list[Blob] = []
        for color, ranges in self.config.colors.items():
            mask = _class_mask(hsv, ranges)
            if cv2.countNonZero(mask) < self.min_area:
                continue
            found.extend(self._components(color, mask, depth_small))
        return found

    def _roi(self, mask: np.ndarray) -> tuple[int, int, int, int]:
        x, y, w, h = cv2.boundingRect(mask)
        p = self.pad
        x0, y0 = max(x - p, 0), max(y - p, 0)
        return x0, y0, min(x + w + p, mask.shape[1]), min(y + h + p, mask.shape[0])

    def _components(self, color: str, mask: np.ndarray, depth: np.ndarray) -> list[Blob]:
        x0, y0, x1, y1 = self._roi(mask)
        raw = mask[y0:y1, x0:x1]
        clean = raw
        if self.open is not None:
            clean = cv2.morphologyEx(clean, cv2.MORPH_OPEN, self.open)
        if self.close is not None:
            clean = cv2.morphologyEx(clean, cv2.MORPH_CLOSE, self.close)
        count, labels, stats, _ = cv2.connectedComponentsWithStats(clean, connectivity=8)
        height, width = mask.shape
        blobs = []
        for k in range(1, count):
            bx, by, bw, bh, area = (int(a) for a in stats[k])
            if area < self.min_area:
                continue
            # The bounding box grown by one pixel (the ROI's padding leaves room for it).
            wx0, wy0 = max(bx - 1, 0), max(by - 1, 0)
            wx1, wy1 = min(bx + bw + 1, x1 - x0), min(by + bh + 1, y1 - y0)
            window = (slice(wy0, wy1), slice(wx0, wx1))
            # Closing may bridge into background: only truly coloured pixels carry depth.
            inside = (labels[window] == k) & (raw[window] > 0)
            d = depth[y0 + wy0:y0 + wy1, x0 + wx0:x0 + wx1]
            at_border = (x0 + bx == 0 or y0 + by == 0 or x0 + bx + bw == width
                         or y0 + by + bh == height)
            rows, cols = np.nonzero(inside & (d > 0))
            blobs.append(Blob(
                color=color,
                u=(cols + x0 + wx0) * self.step,
                v=(rows + y0 + wy0) * self.step,
                depth_mm=d[rows, cols],
                area_px=area * self.step**2,
                partial=at_border or _occluded(inside, d),
            ))
        return blobs


# --- estimation ------------------------------------------------------------------------------


def blob_points(camera: Camera, blob: Blob, config: TrackerConfig) -> np.ndarray:
    """Optical-frame points of a blob: in range, thinned to ``max_points``, MAD-filtered."""
    z = blob.depth_mm.astype(np.float64) * 1e-3
    keep = (z >= config.min_depth_m) & (z <= config.max_depth_m)
    u, v, z = blob.u[keep], blob.v[keep], z[keep]
    if z.size > config.max_points:
        stride = int(math.ceil(z.size / config.max_points))
        u, v, z = u[::stride], v[::stride], z[::stride]
    if z.size == 0:
        return np.empty((0, 3))
    median = float(np.median(z))
    mad = float(np.median(np.abs(z - median)))
    inlier = np.abs(z - median) <= max(config.mad_k * MAD_TO_SIGMA * mad, config.mad_floor_m)
    fx, fy, cx, cy = camera.K[0, 0], camera.K[1, 1], camera.K[0, 2], camera.K[1, 2]
    z = z[inlier]
    return np.stack([(u[inlier] - cx) / fx * z, (v[inlier] - cy) / fy * z, z], axis=1)


def fit_sphere(points: np.ndarray, iterations: int = 2) -> tuple[np.ndarray, float, float]:
    """Least-squares sphere ``(centre, radius, rms residual)`` through points (N >= 4).

    An algebraic fit (linear in centre and ``r^2 - |c|^2``) starts Gauss-Newton on the
    geometric distance; the visible cap of a sphere seen from outside is close to a
    hemisphere, which constrains the centre well in all three directions. The 4x4 normal
    equations are solved directly: the points are centred, so they are well conditioned.
    Arrays are kept 3xN (rows contiguous) because that is what makes the reductions fast.
    """
    p = np.asarray(points, dtype=float).reshape(-1, 3)
    if len(p) < 4:
        raise ValueError(f"a sphere fit needs at least 4 points, got {len(p)}")
    q = np.ascontiguousarray(p.T)
    mean = q.mean(axis=1)
    q -= mean[:, None]
    A = np.empty((4, q.shape[1]))  # the transposed design matrix
    A[:3] = 2.0 * q
    A[3] = 1.0
    sol = _solve_normal(A, (q * q).sum(axis=0))
    if sol is None:
        raise ValueError("a sphere fit needs points that are not coplanar")
    centre = sol[:3]
    radius = math.sqrt(max(sol[3] + centre @ centre, 1e-12))
    for _ in range(iterations):
        diff = q - centre[:, None]
        dist = np.maximum(np.sqrt((diff * diff).sum(axis=0)), 1e-12)
        A[:3] = diff / dist
        step = _solve_normal(A, dist - radius)  # residual r_i = dist_i - radius
        if step is None:
            break
        centre, radius = centre + step[:3], radius + step[3]
    diff = q - centre[:, None]
    residual = np.sqrt((diff * diff).sum(axis=0)) - radius
    rms = math.sqrt(float(residual @ residual) / len(residual))
    return centre + mean, float(abs(radius)), rms


def _solve_normal(At: np.ndarray, b: np.ndarray) -> np.ndarray | None:
    """Least squares ``A x ~ b`` (given ``A`` transposed) by the normal equations."""
    try:
        return np.linalg.solve(At @ At.T, At @ b)
    except np.linalg.LinAlgError:
        return None


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product of two 3-vectors (np.cross costs microseconds of dispatch per call)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2],
                     a[0] * b[1] - a[1] * b[0]])


def view_basis(camera: Camera, direction: np.ndarray) -> np.ndarray:
    """Optical-frame axes (columns) ``[side, down, view]`` of a frame looking along ``direction``.

    ``side`` is horizontal in the base frame, so boxes built in this frame stand upright.
    """
    view = direction / math.sqrt(direction @ direction)
    side = _cross(camera.rotation[2], view)  # base z ("up") expressed in the optical frame
    norm = math.sqrt(side @ side)
    if norm < 1e-6:  # looking straight up or down
        side = np.array([1.0, 0.0, 0.0]) - view[0] * view
        norm = math.sqrt(side @ side)
    side = side / norm
    return np.column_stack([side, _cross(view, side), view])


class Estimate(NamedTuple):
    """A detection's bounding shape in the base frame, and whether it was fitted as round."""

    shape: Shape
    round: bool


FIT_POINTS = 300
"""The sphere fit uses at most about this many points: a cap of a few hundred pixels fixes the
centre far below a millimetre, and big blobs (near boxes) would otherwise dominate the cost."""


def _is_round(config: TrackerConfig, radius: float, rms: float, width: float,
              centre_depth: float, surface_depth: float) -> bool:
    """A sphere fit describes the blob: small residual, radius ~ half width, centre behind."""
    return (
        rms <= config.sphere_rms_ratio * radius + config.sphere_rms_floor_m
        and abs(radius - 0.5 * width) <= config.sphere_width_ratio * 0.5 * width
        and centre_depth > surface_depth
    )


def _round_fit(points: np.ndarray, local: np.ndarray, basis: np.ndarray, width: float,
               config: TrackerConfig) -> tuple[np.ndarray, float] | None:
    """Centre and radius (reaching every point) of the blob's sphere, or None if not round.

    ``points`` are N x 3 in the optical frame, ``local`` the same as 3 x N view coordinates.
    """
    if len(points) < 4:
        return None
    stride = max(1, len(points) // FIT_POINTS)
    try:
        centre, radius, rms = fit_sphere(points[::stride])
    except ValueError:
        return None
    if not _is_round(config, radius, rms, width, float(centre @ basis[:, 2]),
                     float(local[2].mean())):
        return None
    return centre, max(radius, _reach(local, basis.T @ centre))


def _reach(local: np.ndarray, centre: np.ndarray) -> float:
    """Largest distance from ``centre`` to the 3 x N points ``local``."""
    diff = local - centre[:, None]
    return math.sqrt(float(np.max((diff * diff).sum(axis=0))))


def estimate_shape(camera: Camera, points: np.ndarray, config: TrackerConfig,
                   name: str = "") -> Estimate:
    """Conservative bounding shape (base frame) of an obstacle seen as optical-frame points.

    Round blobs: the fitted sphere, radius ``max(fit, farthest point) + inflation``. Others:
    each visible point is extended along its ray by the largest visible width (the hidden
    depth of a compact obstacle is at most that), and the bound covers both ends: a sphere
    about the middle of that cloud, or the box of it in the view-aligned frame.
    """
    points_t = points.T
    basis = view_basis(camera, points_t.mean(axis=1))
    local = basis.T @ points_t  # 3 x N [side, down, view] coordinates
    low, high = local.min(axis=1), local.max(axis=1)
    width = float(max(high[0] - low[0], high[1] - low[1]))
    inflate = config.inflation_m
    R, t = camera.rotation, camera.position
    fit = _round_fit(points, local, basis, width, config)
    if fit is not None:
        centre, radius = R @ fit[0] + t, fit[1] + inflate
        if config.shape == "box":
            return Estimate(Shape("box", (2 * radius,) * 3, centre, name=name), True)
        return Estimate(Shape("sphere", (radius,), centre, name=name), True)
    ranges = np.sqrt((points_t * points_t).sum(axis=0))
    far = local * (1.0 + width / ranges)  # each point pushed back along its ray by width
    low = np.minimum(low, far.min(axis=1))
    high = np.maximum(high, far.max(axis=1))
    mid = 0.5 * (low + high)
    centre = R @ (basis @ mid) + t
    if config.shape == "sphere":
        radius = max(_reach(local, mid), _reach(far, mid)) + inflate
        return Estimate(Shape("sphere", (radius,), centre, name=name), False)
    orientation = Rotation.from_matrix(R @ basis).as_quat()
    size = tuple(high - low + 2.0 * inflate)
    return Estimate(Shape("box", size, centre, orientation, name=name), False)


class Detection(NamedTuple):
    """One obstacle seen in one frame.

    ``partial``: the blob touches the image border or a nearer surface borders it, so part of
    the obstacle may be hidden and the bound is only a bound of what is visible.
    """

    color: str
    shape: Shape
    round: bool
    partial: bool
    points: int
    area_px: int


def detect(camera: Camera, config: TrackerConfig, rgb: np.ndarray, depth: np.ndarray,
           segmenter: Segmenter | None = None) -> list[Detection]:
    """All obstacles of one frame (no tracking): segment, deproject, bound."""
    check_images(camera, rgb, depth)
    segmenter = Segmenter(config) if segmenter is None else segmenter
    found = []
    for blob in segmenter.blobs(rgb, depth):
        points = blob_points(camera, blob, config)
        if len(points) < config.min_points:
            continue
        estimate = estimate_shape(camera, points, config, name=blob.color)
        found.append(Detection(blob.color, estimate.shape, estimate.round, blob.partial,
                               len(points), blob.area_px))
    return found


# --- tracking --------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Track:
    """A tracked obstacle as the planner sees it.

    ``shape`` is the last observed bounding shape (not extrapolated: a consumer that wants a
    prediction uses ``velocity`` and ``last_seen``); ``age`` is seconds since first seen;
    ``hits`` counts the frames it was seen in; ``partial`` is the last detection's flag.
    """

    id: int
    color: str
    shape: Shape
    velocity: np.ndarray
    last_seen: float
    age: float
    hits: int
    partial: bool = False


@dataclass(eq=False)
class _TrackState:
    id: int
    color: str
    shape: Shape
    first_seen: float
    last_seen: float
    history: deque = field(default_factory=deque)
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    hits: int = 0
    partial: bool = False

    def predict(self, stamp: float) -> np.ndarray:
        return self.shape.position + self.velocity * (stamp - self.last_seen)

    def observe(self, detection: Detection, stamp: float, window_s: float) -> None:
        """Take a detection; velocity = least-squares slope of centres over the window."""
        shape = detection.shape
        self.shape = shape
        self.partial = detection.partial
        self.last_seen = stamp
        self.hits += 1
        self.history.append((stamp, shape.position))
        while self.history and self.history[0][0] < stamp - window_s:
            self.history.popleft()
        if len(self.history) < 2:
            return
        t = np.array([h[0] for h in self.history])
        p = np.array([h[1] for h in self.history])
        dt = t - t.mean()
        self.velocity = (dt @ (p - p.mean(axis=0))) / float(dt @ dt)

    def snapshot(self) -> Track:
        return Track(self.id, self.color, self.shape, self.velocity.copy(), self.last_seen,
                     self.last_seen - self.first_seen, self.hits, self.partial)


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

    def reset(self) -> None:
        """Forget every track (ids keep counting up, so an old id never means a new thing)."""
        self._tracks = []
        self._last_stamp = None

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
        self.detections = detect(self.camera, self.config, rgb, depth, self.segmenter)
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
                    tracks[r].observe(detections[c], stamp, self.config.velocity_window_s)
                    matched.add(int(c))
        for i, d in enumerate(detections):
            if i not in matched:
                state = _TrackState(self._next_id, color, d.shape, stamp, stamp)
                state.observe(d, stamp, self.config.velocity_window_s)
                self._tracks.append(state)
                self._next_id += 1


# --- colour/depth synchronisation -----------------------------------------------------------


class FramePair(NamedTuple):
    """A colour frame and the depth frame taken with it."""

    stamp: float
    color: Any
    depth: Any


class FrameSynchronizer:
    """Pairs colour and depth frames whose stamps differ by at most ``tolerance_s``.

    A frame is matched with the closest-stamped frame of the other stream inside the
    tolerance. Pairs come out with increasing stamps: once a pair is out, frames older than it
    can no longer be used by a tracker and are dropped, as are late arrivals older than it.
    Each queue holds at most ``queue_size`` unmatched frames (oldest dropped first).
    """

    def __init__(self, tolerance_s: float = 0.005, queue_size: int = 10) -> None:
        if not tolerance_s >= 0.0 or not math.isfinite(tolerance_s):
            raise ValueError(f"tolerance_s {tolerance_s} must be a finite number >= 0")
        if int(queue_size) < 1:
            raise ValueError(f"queue_size {queue_size} must be >= 1")
        self.tolerance_s = float(tolerance_s)
        self.queue_size = int(queue_size)
        self._queues: dict[str, list[tuple[float, Any]]] = {"color": [], "depth": []}
        self._last = {"color": -math.inf, "depth": -math.inf}
        self.dropped = 0

    def add_color(self, stamp: float, msg: Any) -> list[FramePair]:
        return self._add("color", "depth", float(stamp), msg)

    def add_depth(self, stamp: float, msg: Any) -> list[FramePair]:
        return self._add("depth", "color", float(stamp), msg)

    def pending(self) -> tuple[int, int]:
        """Unmatched frames held: ``(colour, depth)``."""
        return len(self._queues["color"]), len(self._queues["depth"])

    def _add(self, mine: str, other: str, stamp: float, msg: Any) -> list[FramePair]:
        if not math.isfinite(stamp):
            raise ValueError(f"{mine} frame stamp {stamp} is not finite")
        if stamp <= self._last[mine]:
            self.dropped += 1  # older than a pair already emitted
            return []
        candidates = self._queues[other]
        best = min(range(len(candidates)), key=lambda i: abs(candidates[i][0] - stamp),
                   default=None)
        if best is None or abs(candidates[best][0] - stamp) > self.tolerance_s:
            self._insert(mine, stamp, msg)
            return []
        other_stamp, other_msg = candidates.pop(best)
        self._last[mine], self._last[other] = stamp, other_stamp
        self._prune(mine)
        self._prune(other)
        color, depth = (msg, other_msg) if mine == "color" else (other_msg, msg)
        return [FramePair(stamp if mine == "color" else other_stamp, color, depth)]

    def _insert(self, side: str, stamp: float, msg: Any) -> None:
        queue = self._queues[side]
        keys = [s for s, _ in queue]
        queue.insert(bisect.bisect_right(keys, stamp), (stamp, msg))
        while len(queue) > self.queue_size:
            queue.pop(0)
            self.dropped += 1

    def _prune(self, side: str) -> None:
        """Drop frames at or before the last pair's stamp on this stream."""
        queue = self._queues[side]
        keep = [item for item in queue if item[0] > self._last[side]]
        self.dropped += len(queue) - len(keep)
        self._queues[side] = keep
