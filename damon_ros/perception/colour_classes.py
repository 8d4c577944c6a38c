"""Colour classes of an RGB frame in one compiled pass: OpenCV's 8-bit HSV, bit for bit.

Why not ``cv2.resize`` + ``cv2.cvtColor`` + one ``cv2.inRange`` per range: at 640x480 those
were 0.7 ms of the tracker's 3.5 ms a frame (seven range tests, a resized copy and an HSV
image, each a pass over memory). Here each sampled pixel is read once, converted with the
integer arithmetic of OpenCV's ``RGB2HSV`` (the same division tables and rounding, so every
one of the 2^24 colours gets OpenCV's H, S and V; `test_colour_classes` checks all of them)
and tested against every range, and the per-class masks come out with their pixel counts.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from numba import njit

_SHIFT = 12
_I = np.arange(256, dtype=np.float64)
with np.errstate(divide="ignore"):
    # OpenCV's tables (saturate_cast rounds half to even, as np.rint does); entry 0 is 0
    _SDIV = np.where(_I > 0, np.rint((255 << _SHIFT) / _I), 0).astype(np.int64)
    _HDIV = np.where(_I > 0, np.rint((180 << _SHIFT) / (6.0 * _I)), 0).astype(np.int64)
_HALF = 1 << (_SHIFT - 1)


@njit(cache=True)
def pixel_hsv(r, g, b, s_min, v_min):
    """OpenCV's 8-bit (H, S, V) of one RGB pixel; H = -1 when S < ``s_min`` or
    V < ``v_min`` (grey and dark pixels, the background and the arm, are of no class and
    need no H)."""
    v = max(r, g, b)
    if v < v_min:
        return -1, 0, v
    diff = v - min(r, g, b)
    s = (diff * _SDIV[v] + _HALF) >> _SHIFT
    if s < s_min:
        return -1, s, v
    if v == r:
        h = g - b
    elif v == g:
        h = b - r + 2 * diff
    else:
        h = r - g + 4 * diff
    h = (h * _HDIV[diff] + _HALF) >> _SHIFT
    return (h + 180 if h < 0 else h), s, v


@njit(cache=True)
def in_range(h, s, v, lows, highs, k):
    """Whether (H, S, V) lies in range ``k`` (bounds included, as cv2.inRange)."""
    return (lows[k, 0] <= h <= highs[k, 0] and lows[k, 1] <= s <= highs[k, 1]
            and lows[k, 2] <= v <= highs[k, 2])


@njit(cache=True)
def _classify(rgb, step, lows, highs, owner, classes):
    rows, cols = rgb.shape[0] // step, rgb.shape[1] // step
    masks = np.zeros((classes, rows, cols), np.uint8)
    union = np.zeros((rows, cols), np.uint8)
    counts = np.zeros(classes, np.int64)
    s_min, v_min = lows[:, 1].min(), lows[:, 2].min()
    for i in range(rows):
        for j in range(cols):
            px = rgb[i * step, j * step]
            h, s, v = pixel_hsv(np.int64(px[0]), np.int64(px[1]), np.int64(px[2]), s_min,
                                v_min)
            if h < 0:
                continue
            for k in range(owner.shape[0]):
                c = owner[k]
                if masks[c, i, j] == 0 and in_range(h, s, v, lows, highs, k):
                    masks[c, i, j] = 255
                    union[i, j] = 255
                    counts[c] += 1
    return masks, counts, union


class ColourClasses:
    """The configured HSV ranges, packed once for the compiled pass."""

    def __init__(self, colors: Mapping[str, Sequence[tuple[np.ndarray, np.ndarray]]]) -> None:
        self.names = tuple(colors)
        ranges = [(c, low, high) for c, name in enumerate(self.names)
                  for low, high in colors[name]]
        self.owner = np.array([c for c, _, _ in ranges], np.int64)
        self.lows = np.array([low for _, low, _ in ranges], np.int64).reshape(-1, 3)
        self.highs = np.array([high for _, _, high in ranges], np.int64).reshape(-1, 3)
        for image in frames_of_both_kinds():  # compiled (or loaded) now, not on a frame
            self.masks(image)

    def masks(self, rgb: np.ndarray, step: int = 1
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(masks, counts, union): per class (in ``names`` order) a 0/255 mask of the pixels
        ``(step*i, step*j)`` of ``rgb`` (H x W x 3, uint8, RGB order) and its pixel count;
        the mask of the pixels of any class."""
        return _classify(rgb, int(step), self.lows, self.highs, self.owner, len(self.names))

    def only(self, name: str) -> ColourClasses:
        """The classes reduced to ``name`` (a blob's own colour, for its outline)."""
        out = ColourClasses.__new__(ColourClasses)
        keep = self.owner == self.names.index(name)
        out.names, out.owner = (name,), np.zeros(int(keep.sum()), np.int64)
        out.lows, out.highs = self.lows[keep], self.highs[keep]
        return out


def frames_of_both_kinds() -> tuple[np.ndarray, np.ndarray]:
    """A 1x1 RGB frame, writable and read-only: numba compiles each separately, and a
    frame decoded from a message buffer without a copy is read-only."""
    frozen = np.zeros((1, 1, 3), np.uint8)
    frozen.flags.writeable = False
    return np.zeros((1, 1, 3), np.uint8), frozen


def warm_up() -> None:
    """Compile (or load from the disk cache) the pass: building any classes does it."""
    ColourClasses({"any": [(np.zeros(3, np.uint8), np.full(3, 255, np.uint8))]})
