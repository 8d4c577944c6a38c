"""The compiled colour pass gives exactly what OpenCV's HSV conversion and range tests give."""

from __future__ import annotations

import cv2
import numpy as np

from damon_ros.perception.colour_classes import ColourClasses
from damon_ros.perception.tracker_config import load_tracker_config


def _every_colour() -> np.ndarray:
    x = np.arange(1 << 24, dtype=np.uint32)
    return np.stack([(x >> 16) & 255, (x >> 8) & 255, x & 255], -1).astype(
        np.uint8).reshape(4096, 4096, 3)


def test_every_colour_is_classed_as_opencv_classes_it():
    """All 2^24 RGB colours against cv2.cvtColor(RGB2HSV) + cv2.inRange with the shipped
    ranges (red wraps around H = 0): the same pixels in every class, none missed or added."""
    colors = load_tracker_config().colors
    image = _every_colour()
    hsv = cv2.cvtColor(image, cv2.COLOR_RGB2HSV)
    masks, counts, union = ColourClasses(colors).masks(image)
    expected_union = np.zeros(hsv.shape[:2], np.uint8)
    for k, (name, ranges) in enumerate(colors.items()):
        expected = np.zeros(hsv.shape[:2], np.uint8)
        for low, high in ranges:
            expected |= cv2.inRange(hsv, low, high)
        assert np.array_equal(masks[k], expected), name
        assert counts[k] == np.count_nonzero(expected) > 0
        expected_union |= expected
    assert np.array_equal(union, expected_union)


def test_a_step_samples_the_pixels_the_depth_slice_keeps():
    """With a step of 2 the masks cover pixels (2i, 2j), as ``depth[::2, ::2]`` does."""
    low, high = np.array([0, 100, 45], np.uint8), np.array([10, 255, 255], np.uint8)
    rgb = np.zeros((6, 8, 3), np.uint8)
    rgb[2, 4] = (255, 0, 0)  # sampled: (1, 2)
    rgb[3, 5] = (255, 0, 0)  # between samples: not seen
    masks, counts, _ = ColourClasses({"red": [(low, high)]}).masks(rgb, 2)
    assert masks.shape == (1, 3, 4) and counts[0] == 1
    assert masks[0, 1, 2] == 255
