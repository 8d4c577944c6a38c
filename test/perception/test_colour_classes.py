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


def _outline_reference(seg, blob, rgb, depth):
    """The pixels `Segmenter._refined` adds, computed as it was before the compiled pass:
    grid and blob-sample counts by cv2.filter2D, HSV by cv2.cvtColor + cv2.inRange."""
    s = seg.step
    u0, v0 = max(int(blob.u.min()) - s, 0), max(int(blob.v.min()) - s, 0)
    u1, v1 = min(int(blob.u.max()) + s + 1, depth.shape[1]), min(int(blob.v.max()) + s + 1,
                                                                   depth.shape[0])
    grid = ((np.arange(v0, v1) % s == 0)[:, None]
            & (np.arange(u0, u1) % s == 0)[None]).astype(np.uint8)
    samples = np.zeros_like(grid)
    samples[blob.v - v0, blob.u - u0] = 1
    square = np.ones((2 * s - 1, 2 * s - 1), np.float32)
    around = [cv2.filter2D(m, -1, square, borderType=cv2.BORDER_CONSTANT)
              for m in (grid, samples)]
    hsv = cv2.cvtColor(np.ascontiguousarray(rgb[v0:v1, u0:u1]), cv2.COLOR_RGB2HSV)
    colour = np.zeros(grid.shape, np.uint8)
    for low, high in seg.config.colors[blob.color]:
        colour |= cv2.inRange(hsv, low, high)
    rows, cols = np.nonzero((grid == 0) & (around[1] > 0) & (around[1] < around[0])
                            & (colour > 0) & (depth[v0:v1, u0:u1] > 0))
    return rows + v0, cols + u0


def test_blob_outlines_gain_the_full_resolution_pixels_opencv_finds():
    """Rendered frames of the public scenarios: each blob's added outline pixels are those
    of the OpenCV formulation, in the same order."""
    from damon_ros.core.scenario import load_public_scenarios
    from damon_ros.perception.camera import load_cameras
    from damon_ros.perception.segmentation import Segmenter
    from damon_ros.simulation.renderer import (
        load_render_settings,
        render,
        render_settings_kwargs,
        scene_at,
    )

    config = load_tracker_config()
    seg = Segmenter(config)
    camera = load_cameras("camera.yaml")[0]
    rng = np.random.default_rng(3)
    checked = 0
    for scenario in load_public_scenarios(["A-001", "B-001", "C-001", "D-001"]):
        rgb, depth = render(camera, scene_at(scenario, 0.5),
                            **render_settings_kwargs(load_render_settings(), rng))
        for blob in seg.blobs(rgb, depth):
            coarse = (blob.u % seg.step == 0) & (blob.v % seg.step == 0)  # the samples
            rows, cols = _outline_reference(seg, blob._replace(
                u=blob.u[coarse], v=blob.v[coarse]), rgb, depth)
            assert np.array_equal(blob.v[~coarse], rows)
            assert np.array_equal(blob.u[~coarse], cols)
            checked += len(rows)
    assert checked > 100
