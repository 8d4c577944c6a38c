"""The tracker's settings (``config/tracker.yaml``): one validated, frozen record.

Every stage of the perception pipeline (segmentation, shape estimation, tracking) reads its
parameters from one :class:`TrackerConfig`, so the file is parsed and checked once, here,
and a bad value is refused naming its field before any frame is processed.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from damon_ros.core.resources import config_file, read_yaml_section

SHAPE_MODES = ("sphere", "box", "auto")
THICKNESS_CLASSES = ("box", "blob")
"""Shape classes with a prior on their hidden depth (``max_thickness_m``)."""

_LOWER_BOUNDS: tuple[tuple[tuple[str, ...], str, Callable[[Any], bool]], ...] = (
    (("downsample", "min_points", "max_points"), ">= 1", lambda v: int(v) < 1),
    (("open_kernel_px", "close_kernel_px", "min_area_px", "inflation_m", "sphere_rms_floor_m",
      "min_depth_m", "surface_margin_m", "static_speed_mps"), ">= 0", lambda v: v < 0),
    (("max_depth_m", "mad_k", "mad_floor_m", "sphere_rms_ratio", "sphere_width_ratio",
      "gate_m", "max_age_s", "velocity_window_s", "time_jump_s", "face_tolerance_m",
      "static_hold_s", "moving_speed_mps", "moving_shift_m", "moving_shift_round_m",
      "max_speed_mps"), "> 0",
     lambda v: not v > 0),
    (("fusion_window_s", "refit_after_s"), ">= 0", lambda v: v < 0),
)
"""``(fields, bound, violates)``: the numeric fields in the order they are checked, the bound
named in the error, and the test of a value that breaks it."""


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
    sphere_rms_floor_m: float = 0.003
    sphere_width_ratio: float = 0.25
    gate_m: float = 0.15
    max_age_s: float = 0.5
    velocity_window_s: float = 0.3
    time_jump_s: float = 1.0
    max_thickness_m: dict[str, float] = field(default_factory=lambda: {"box": 0.15,
                                                                       "blob": 0.25})
    face_tolerance_m: float = 0.008
    surface_margin_m: float = 0.001
    static_speed_mps: float = 0.03
    static_hold_s: float = 0.25
    moving_speed_mps: float = 0.08
    moving_shift_m: float = 0.02
    moving_shift_round_m: float = 0.007
    fusion_window_s: float = 0.05
    max_speed_mps: float = 1.0
    refit_after_s: float = 1.0

    def __post_init__(self) -> None:
        if not self.colors:
            raise ValueError("tracker colors: at least one colour class is needed")
        if self.shape not in SHAPE_MODES:
            raise ValueError(f"tracker shape {self.shape!r} must be one of {SHAPE_MODES}")
        for names, bound, violates in _LOWER_BOUNDS:
            for name in names:
                value = getattr(self, name)
                if violates(value):
                    raise ValueError(f"tracker {name} {value} must be {bound}")
        thickness = self.max_thickness_m
        if not isinstance(thickness, dict) or set(thickness) != set(THICKNESS_CLASSES) or any(
                isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0
                for v in thickness.values()):
            raise ValueError(f"tracker max_thickness_m {thickness!r} must map each of "
                             f"{THICKNESS_CLASSES} to a positive depth in metres")
        if self.static_speed_mps >= self.moving_speed_mps:
            raise ValueError(f"tracker static_speed_mps {self.static_speed_mps} must be below "
                             f"moving_speed_mps {self.moving_speed_mps} (hysteresis)")
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
