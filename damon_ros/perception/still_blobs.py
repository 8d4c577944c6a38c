"""Blobs that have not moved since they were fitted keep their fit.

Most of a cell is still: a table, bins, a box waiting to be picked. Fitting a box to its
faces is the dearest step of a frame (~1.3 ms of a 640x480 frame's ~5 ms in the soak), and
a still object's fit changes from frame to frame only by the depth noise. So each camera
keeps, per blob, the detection fitted from it and the depth it was fitted from (the
*anchor*), and a later blob of the same colour reuses that detection when it is the same
view of an object that has not moved:

- its pixel bounding box is the anchor's to a pixel and its partial flag the same (an
  occluder, the image border or a move changes the outline first);
- its depth, pixel by pixel against the anchor's, shows no move: the mean difference of
  the whole blob and of every 16 x 16 pixel cell is within `Z_LIMIT` standard errors of
  zero, the standard error taken from the differences themselves (a noisier camera gets a
  proportionally larger limit, and its fits scatter as much).

Measured on the mock camera (2 mm noise, 1 % dropout) with a 0.13 x 0.15 x 0.23 m box at
2.5 m: a still box stays below 2.5 standard errors; a move of 1 mm along any axis exceeds
4 (0.5 mm sometimes does not), and a surface margin of 1 mm is already in every fit. A
turn of 0.01 rad moves no point by more than 0.8 mm. The comparison is against the anchor,
not the last frame, so a slow creep adds up until it is seen. Every anchor is refitted
after ``refit_after_s`` at the latest, and one not matched in a frame is forgotten.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from damon_ros.perception.camera import Camera
from damon_ros.perception.segmentation import Blob

CELL_PX = 16
"""Side of the cells whose mean depth change is tested (full-resolution pixels): small
enough that a face covering a few percent of the blob has cells of its own."""
Z_LIMIT = 4.0
"""A mean depth change beyond this many standard errors is a move."""
MIN_CELL_POINTS = 8
"""Cells with fewer points (outline, dropout) are left to the whole-blob test."""


@dataclass
class _Anchor:
    color: str
    box: tuple[int, int, int, int]  # u0, v0, u1, v1 (inclusive)
    partial: bool
    depth: np.ndarray  # the anchor's depth (mm) over its box; 0 where it had none
    detection: Any
    stamp: float


def _box(blob: Blob) -> tuple[int, int, int, int]:
    return int(blob.u.min()), int(blob.v.min()), int(blob.u.max()), int(blob.v.max())


def unmoved(anchor_depth: np.ndarray, box: tuple[int, int, int, int], blob: Blob) -> bool:
    """Whether ``blob``'s depth matches the anchor's (``anchor_depth`` over ``box``) within
    `Z_LIMIT` standard errors, over the whole blob and in each cell."""
    u0, v0, u1, v1 = box
    inside = (blob.u >= u0) & (blob.u <= u1) & (blob.v >= v0) & (blob.v <= v1)
    rows, cols = blob.v[inside] - v0, blob.u[inside] - u0
    ref = anchor_depth[rows, cols]
    both = ref > 0
    if both.sum() < MIN_CELL_POINTS:
        return False
    dz = blob.depth_mm[inside][both].astype(float) - ref[both]
    sigma = max(1.4826 * float(np.median(np.abs(dz - np.median(dz)))), 1.0)  # mm: depth is
    # rounded to a millimetre, so no camera's differences are tighter than that
    if abs(dz.mean()) > Z_LIMIT * sigma / np.sqrt(dz.size):
        return False
    per_row = (u1 - u0) // CELL_PX + 1
    cell = (rows[both] // CELL_PX) * per_row + cols[both] // CELL_PX
    count = np.bincount(cell)
    total = np.bincount(cell, dz)
    full = count >= MIN_CELL_POINTS
    return bool(np.all(np.abs(total[full]) <= Z_LIMIT * sigma * np.sqrt(count[full])))


class StillBlobs:
    """One camera's anchors (see the module): `reuse` before fitting a blob, `remember`
    after, `end_frame` once a frame's blobs are all done."""

    def __init__(self, refit_after_s: float) -> None:
        self.refit_after_s = float(refit_after_s)
        self._anchors: list[_Anchor] = []
        self._kept: list[_Anchor] = []
        self._camera: tuple[np.ndarray, np.ndarray] | None = None
        self.reused = 0
        self.fitted = 0

    def start_frame(self, camera: Camera) -> None:
        """A new frame of ``camera``: anchors of another calibration are forgotten."""
        key = (np.asarray(camera.K), np.asarray(camera.base_T_camera))
        if self._camera is None or not all(np.array_equal(a, b)
                                           for a, b in zip(key, self._camera, strict=True)):
            self._anchors = []
        self._camera = key
        self._kept = []

    def reuse(self, blob: Blob, stamp: float) -> Any | None:
        """The detection of an anchor that ``blob`` shows unmoved, or None (fit it)."""
        if self.refit_after_s <= 0.0:
            return None
        box = _box(blob)
        for anchor in self._anchors:
            if (anchor.color != blob.color or anchor.partial != blob.partial
                    or max(abs(a - b) for a, b in zip(anchor.box, box, strict=True)) > 1
                    or not 0.0 <= stamp - anchor.stamp <= self.refit_after_s):
                continue
            if unmoved(anchor.depth, anchor.box, blob):
                self._anchors.remove(anchor)
                self._kept.append(anchor)
                self.reused += 1
                return anchor.detection
        return None

    def remember(self, blob: Blob, detection: Any, stamp: float) -> None:
        """``detection`` was fitted to ``blob`` now: it becomes an anchor."""
        self.fitted += 1
        if self.refit_after_s <= 0.0:
            return
        u0, v0, u1, v1 = box = _box(blob)
        depth = np.zeros((v1 - v0 + 1, u1 - u0 + 1), np.float32)
        depth[blob.v - v0, blob.u - u0] = blob.depth_mm
        self._kept.append(_Anchor(blob.color, box, blob.partial, depth, detection, stamp))

    def end_frame(self) -> None:
        """Anchors not seen in this frame are forgotten."""
        self._anchors, self._kept = self._kept, []
