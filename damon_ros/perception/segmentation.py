"""Colour segmentation: an RGB frame and its depth -> one :class:`Blob` per coloured region.

The first step of perception: RGB -> HSV, one range set per colour class, opening/closing,
connected components, a minimum area. A blob also says whether it may be cut off (it
touches the image border, or a nearer surface borders it), because a bound of what is
visible is then only a bound of part of the obstacle.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import cv2
import numpy as np
from numba import njit

from damon_ros.perception.colour_classes import (
    ColourClasses,
    frames_of_both_kinds,
    in_range,
    pixel_hsv,
)
from damon_ros.perception.tracker_config import TrackerConfig


class Blob(NamedTuple):
    """One connected region of a colour class: full-resolution pixel coordinates and depth."""

    color: str
    u: np.ndarray
    v: np.ndarray
    depth_mm: np.ndarray
    area_px: int
    partial: bool
    edge: np.ndarray | None = None
    """Per pixel: on the blob's outline. Thinning keeps these, because a shape's extent is
    set by its outline and a bound is only as tight as the outline is sampled."""
    occluders: np.ndarray | None = None
    """(K, 2) full-resolution ``(u, v)`` of the pixels next to the blob that belong to a
    nearer surface or another object (`_occluders`): where its silhouette may be cut."""


def _kernel(size: int) -> np.ndarray | None:
    size = int(size)
    return None if size <= 1 else cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))


_RING = np.ones((3, 3), np.uint8)
OCCLUSION_MARGIN_MM = 30
"""A pixel next to a blob that is this much nearer than the blob belongs to an occluder."""
SEAM_MM = 10
"""A pixel of another colour next to a blob and at most this much farther (5 sigma of the
depth noise) may belong to an object that meets it there and hides part of it."""


def _occluders(inside: np.ndarray, depth: np.ndarray, other: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """Rows and columns of the pixels next to the blob where a nearer surface borders it,
    so part of the obstacle may be hidden there.

    ``inside``, ``depth`` and ``other`` (pixels of the other colour classes) cover the blob's
    bounding box grown by one pixel. Another object's pixels that are not clearly behind
    the blob (`SEAM_MM`) count as nearer too: where two objects meet (one resting on or
    pushed into the other) the depth runs on across the seam, and either may hide part of
    the other (a ball sunk into a pole hid its far end from the side camera, unflagged).
    """
    blob_depth = np.where(inside, depth, 0).astype(np.uint16)
    neighbour = cv2.dilate(blob_depth, _RING).astype(np.int32)
    ring = cv2.dilate(inside.view(np.uint8), _RING).astype(bool) & ~inside
    d = depth[ring].astype(np.int32)
    near = neighbour[ring] + np.where(other[ring], SEAM_MM, -OCCLUSION_MARGIN_MM)
    rows, cols = np.nonzero(ring)
    hit = (d > 0) & (d < near)
    return rows[hit], cols[hit]


@njit(cache=True)
def _beyond_outline(rgb, depth, u, v, edge, u0, v0, u1, v1, step, lows, highs):
    """Rows and columns (row-major) of the pixels of the window [v0, v1) x [u0, u1) that lie
    between grid samples (every ``step``-th row and column), have a blob sample (``u``,
    ``v``) and a grid sample that is not the blob's within ``step - 1`` pixels in both
    axes (grid samples outside the window do not count), are of the blob's colour
    (``lows``/``highs``) and have depth. Such a pixel's blob sample is on the outline
    (``edge``: the other sample is its neighbour), so only the outline's surroundings are
    visited."""
    h, w = v1 - v0, u1 - u0
    mine = np.zeros((h, w), np.bool_)
    near = np.zeros((h, w), np.bool_)
    r = step - 1
    for k in range(u.shape[0]):
        mine[v[k] - v0, u[k] - u0] = True
        if edge[k]:
            near[max(v[k] - v0 - r, 0):v[k] - v0 + r + 1,
                 max(u[k] - u0 - r, 0):u[k] - u0 + r + 1] = True
    s_min, v_min = lows[:, 1].min(), lows[:, 2].min()
    rows, cols = [], []
    for y in range(v0, v1):
        for x in range(u0, u1):
            if not near[y - v0, x - u0] or (y % step == 0 and x % step == 0) or \
                    depth[y, x] == 0:
                continue
            grid = blob = 0
            for gy in range(max(y - r, v0), min(y + step, v1)):
                if gy % step:
                    continue
                for gx in range(max(x - r, u0), min(x + step, u1)):
                    if gx % step == 0:
                        grid += 1
                        blob += mine[gy - v0, gx - u0]
            if blob == 0 or blob == grid:
                continue
            px = rgb[y, x]
            hh, ss, vv = pixel_hsv(np.int64(px[0]), np.int64(px[1]), np.int64(px[2]), s_min,
                                   v_min)
            if hh < 0:
                continue
            for k in range(lows.shape[0]):
                if in_range(hh, ss, vv, lows, highs, k):
                    rows.append(y)
                    cols.append(x)
                    break
    return np.array(rows, np.int64), np.array(cols, np.int64)


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
        self.classes = ColourClasses(config.colors)
        self.each = {name: self.classes.only(name) for name in self.classes.names}
        none = np.zeros(0, np.int64)  # compiled (or loaded) now, not on the first blob
        for image in frames_of_both_kinds():
            _beyond_outline(image, np.zeros((1, 1), np.uint16), none, none,
                            np.zeros(0, np.bool_), 0, 0, 1, 1, max(self.step, 1),
                            self.classes.lows, self.classes.highs)

    def blobs(self, rgb: np.ndarray, depth: np.ndarray) -> list[Blob]:
        s = self.step
        # the pixels (s*i, s*j) of the colour frame, as the depth slice keeps them
        masks, counts, coloured = self.classes.masks(rgb, s)
        depth_small = depth[:masks.shape[1] * s:s, :masks.shape[2] * s:s]
        found: list[Blob] = []
        for color, mask, count in zip(self.classes.names, masks, counts, strict=True):
            if count < self.min_area:
                continue
            for blob in self._components(color, mask, depth_small, (coloured > mask)):
                found.append(self._refined(blob, rgb, depth))
        return found

    def _refined(self, blob: Blob, rgb: np.ndarray, depth: np.ndarray) -> Blob:
        """The blob with the full-resolution pixels between its outline samples and the next
        samples out that are of its colour and have depth: its silhouette is then known to a
        pixel, not to a downsampled step (`tight_fit.spacing_m`), which halves the margins
        that the edges of a bound get."""
        s = self.step
        if s == 1 or blob.edge is None or not blob.edge.any():
            return blob
        u0, v0 = max(int(blob.u.min()) - s, 0), max(int(blob.v.min()) - s, 0)
        u1 = min(int(blob.u.max()) + s + 1, depth.shape[1])
        v1 = min(int(blob.v.max()) + s + 1, depth.shape[0])
        own = self.each[blob.color]
        rows, cols = _beyond_outline(rgb, depth, blob.u, blob.v, blob.edge, u0, v0, u1, v1, s,
                                     own.lows, own.highs)
        if not len(rows):
            return blob
        return blob._replace(u=np.concatenate([blob.u, cols]),
                             v=np.concatenate([blob.v, rows]),
                             depth_mm=np.concatenate([blob.depth_mm, depth[rows, cols]]),
                             edge=np.concatenate([blob.edge, np.ones(len(rows), bool)]))

    def _roi(self, mask: np.ndarray) -> tuple[int, int, int, int]:
        x, y, w, h = cv2.boundingRect(mask)
        p = self.pad
        x0, y0 = max(x - p, 0), max(y - p, 0)
        return x0, y0, min(x + w + p, mask.shape[1]), min(y + h + p, mask.shape[0])

    def _components(self, color: str, mask: np.ndarray, depth: np.ndarray,
                    other: np.ndarray) -> list[Blob]:
        """Cleaned connected components of one class's ``mask``; ``other``: the pixels of
        the other classes (the occlusion test)."""
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
            valid = inside & (d > 0)
            rows, cols = np.nonzero(valid)
            outline = valid & ~cv2.erode(valid.view(np.uint8), _RING,
                                         borderType=cv2.BORDER_CONSTANT, borderValue=0).astype(bool)
            occ_rows, occ_cols = _occluders(inside, d,
                                            other[y0 + wy0:y0 + wy1, x0 + wx0:x0 + wx1])
            blobs.append(Blob(
                color=color,
                u=(cols + x0 + wx0) * self.step,
                v=(rows + y0 + wy0) * self.step,
                depth_mm=d[rows, cols],
                area_px=area * self.step**2,
                partial=at_border or occ_rows.size > 0,
                edge=outline[rows, cols],
                occluders=np.column_stack([(occ_cols + x0 + wx0) * self.step,
                                           (occ_rows + y0 + wy0) * self.step]),
            ))
        return blobs
