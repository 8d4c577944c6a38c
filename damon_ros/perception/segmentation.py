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

from damon_ros.perception.colour_classes import ColourClasses
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


def _kernel(size: int) -> np.ndarray | None:
    size = int(size)
    return None if size <= 1 else cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))


_RING = np.ones((3, 3), np.uint8)
OCCLUSION_MARGIN_MM = 30
"""A pixel next to a blob that is this much nearer than the blob belongs to an occluder."""
SEAM_MM = 10
"""A pixel of another colour next to a blob and at most this much farther (5 sigma of the
depth noise) may belong to an object that meets it there and hides part of it."""


def _occluded(inside: np.ndarray, depth: np.ndarray, other: np.ndarray) -> bool:
    """Whether a nearer surface borders the blob, so part of the obstacle may be hidden.

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
    return bool(np.any((d > 0) & (d < near)))


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
        # a pixel between samples lies beyond the outline when some of the grid samples
        # around it (within a step) are not the blob's: count both in a step's square
        grid = ((np.arange(v0, v1) % s == 0)[:, None]
                & (np.arange(u0, u1) % s == 0)[None]).astype(np.uint8)
        samples = np.zeros_like(grid)
        samples[blob.v - v0, blob.u - u0] = 1
        square = np.ones((2 * s - 1, 2 * s - 1), np.float32)
        around = [cv2.filter2D(m, -1, square, borderType=cv2.BORDER_CONSTANT)
                  for m in (grid, samples)]
        beyond = (grid == 0) & (around[1] > 0) & (around[1] < around[0])
        window = (slice(v0, v1), slice(u0, u1))
        colour = self.each[blob.color].masks(rgb[window])[0][0]
        rows, cols = np.nonzero(beyond & (colour > 0) & (depth[window] > 0))
        if not len(rows):
            return blob
        return blob._replace(u=np.concatenate([blob.u, cols + u0]),
                             v=np.concatenate([blob.v, rows + v0]),
                             depth_mm=np.concatenate([blob.depth_mm, depth[window][rows, cols]]),
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
            blobs.append(Blob(
                color=color,
                u=(cols + x0 + wx0) * self.step,
                v=(rows + y0 + wy0) * self.step,
                depth_mm=d[rows, cols],
                area_px=area * self.step**2,
                partial=at_border or _occluded(
                    inside, d, other[y0 + wy0:y0 + wy1, x0 + wx0:x0 + wx1]),
                edge=outline[rows, cols],
            ))
        return blobs
