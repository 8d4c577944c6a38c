"""A blob that has not moved keeps its fit; a move of a couple of millimetres anywhere, a new
calibration or the age limit makes the tracker fit it again."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from damon_ros.core.shapes import Shape
from damon_ros.perception.camera import load_camera
from damon_ros.perception.segmentation import Blob
from damon_ros.perception.still_blobs import CELL_PX, StillBlobs, unmoved
from damon_ros.perception.tracker_config import load_tracker_config
from damon_ros.perception.tracking import Tracker
from damon_ros.simulation.renderer import render

CAMERA = load_camera()
CONFIG = load_tracker_config()
YAW = 0.2
BOX = Shape("box", (0.13, 0.15, 0.22), [0.56, -0.05, 0.38],
            [0.0, 0.0, np.sin(YAW / 2), np.cos(YAW / 2)])


def _frame(box: Shape, rng, camera=CAMERA):
    return render(camera, [(box, "red")], 0.002, 0.01, rng)


def _inside(bound: Shape, box: Shape) -> bool:
    corners = 0.5 * np.array(box.size) * np.array(
        [[a, b, c] for a in (-1, 1) for b in (-1, 1) for c in (-1, 1)])
    points = corners @ box.rotation().T + box.position
    local = (points - bound.position) @ bound.rotation()
    return bool(np.all(np.abs(local) <= 0.5 * np.asarray(bound.size) + 1e-9))


@pytest.mark.parametrize("seed", [0, 1])
def test_a_still_box_keeps_its_fit_and_a_moved_one_is_fitted_again(seed):
    rng = np.random.default_rng(seed)
    tracker = Tracker(CAMERA, CONFIG)
    for i in range(10):
        (track,) = tracker.update(*_frame(BOX, rng), i / 30)
    still = tracker.still[0]
    assert still.reused >= 7 and still.fitted + still.reused == 10
    assert _inside(track.shape, BOX) and np.all(track.velocity == 0.0)
    t = 10 / 30
    for axis in range(3):
        moved = BOX.moved_to(BOX.position + 0.002 * np.eye(3)[axis])
        fitted = still.fitted
        t += 1 / 30
        (track,) = tracker.update(*_frame(moved, rng), t)
        assert still.fitted == fitted + 1, f"a 2 mm move along axis {axis} kept the old fit"
        assert _inside(track.shape, moved)
        tracker = Tracker(CAMERA, CONFIG)  # the next axis starts from the box in place
        tracker.update(*_frame(BOX, rng), t)
        still = tracker.still[0]


def test_fits_are_renewed_after_refit_after_s_and_never_kept_when_it_is_zero():
    rng = np.random.default_rng(2)
    frames = [_frame(BOX, rng) for _ in range(3)]
    tracker = Tracker(CAMERA, CONFIG)
    age = CONFIG.refit_after_s
    for stamp in (0.0, 0.5 * age, 1.2 * age):  # the third frame's anchor is too old
        tracker.update(*frames[0], stamp)
    assert (tracker.still[0].fitted, tracker.still[0].reused) == (2, 1)
    never = Tracker(CAMERA, dataclasses.replace(CONFIG, refit_after_s=0.0))
    for i, frame in enumerate(frames):
        never.update(*frame, i / 30)
    assert (never.still[0].fitted, never.still[0].reused) == (3, 0)


def test_a_new_calibration_forgets_the_fits():
    rng = np.random.default_rng(3)
    tracker = Tracker(CAMERA, CONFIG)
    moved_camera = dataclasses.replace(CAMERA, base_T_camera=CAMERA.base_T_camera.copy())
    moved_camera.base_T_camera[0, 3] += 0.001
    frame = _frame(BOX, rng)
    tracker.update_camera(0, CAMERA, *frame, 0.0)
    tracker.update_camera(0, moved_camera, *frame, 1 / 30)
    assert (tracker.still[0].fitted, tracker.still[0].reused) == (2, 0)


def test_a_change_in_one_cell_is_a_move():
    """Depth noise of 2 mm over a 64 x 64 pixel patch; a 2 mm step in one 16 x 16 cell (a
    small face that moved) is seen although the whole patch's mean barely changes."""
    rng = np.random.default_rng(4)
    v, u = np.mgrid[0:64, 0:64]
    u, v = u.ravel(), v.ravel()
    anchor = np.round(1000 + rng.normal(0.0, 2.0, (64, 64))).astype(np.float32)

    def blob(step_mm: float) -> Blob:
        depth = np.round(1000 + rng.normal(0.0, 2.0, u.size))
        depth[(u < CELL_PX) & (v < CELL_PX)] += step_mm
        return Blob("red", u, v, depth.astype(np.uint16), u.size, False)

    box = (0, 0, 63, 63)
    assert unmoved(anchor, box, blob(0.0))
    assert not unmoved(anchor, box, blob(2.0))


def test_only_a_blob_of_the_same_colour_and_outline_is_matched():
    rng = np.random.default_rng(5)
    v, u = np.mgrid[10:40, 20:60]
    u, v = u.ravel(), v.ravel()
    depth = np.round(1500 + rng.normal(0.0, 2.0, u.size)).astype(np.uint16)
    blob = Blob("red", u, v, depth, u.size, False)
    still = StillBlobs(1.0)
    still.start_frame(CAMERA)
    still.remember(blob, "the fit", 0.0)
    still.end_frame()
    still.start_frame(CAMERA)
    assert still.reuse(blob._replace(color="blue"), 0.1) is None
    assert still.reuse(blob._replace(u=blob.u + 2), 0.1) is None
    assert still.reuse(blob._replace(partial=True), 0.1) is None
    assert still.reuse(blob, 0.1) == "the fit"
    assert still.reuse(blob, 0.1) is None  # one anchor serves one blob a frame


def test_two_cameras_fuse_a_still_box_once_and_a_moved_one_again(monkeypatch):
    """Kept detections in every view are the very objects fused last: the fusion (and its
    joint fit) is not repeated; a move in one view fuses again."""
    from damon_ros.perception import tracking

    side = load_camera("camera_side.yaml")
    fits = []
    joint_fit = tracking.joint_fit
    monkeypatch.setattr(tracking, "joint_fit", lambda *a: fits.append(1) or joint_fit(*a))
    rng = np.random.default_rng(6)
    tracker = Tracker(CAMERA, CONFIG)
    shapes = []
    for i in range(6):
        frames = [_frame(BOX, rng, camera) for camera in (CAMERA, side)]
        (track,) = tracker.update_views([CAMERA, side], frames, i / 30)
        shapes.append(track.shape)
    reused = min(tracker.still[v].reused for v in (0, 1))
    assert reused >= 3 and len(fits) <= 6 - reused
    assert _inside(shapes[-1], BOX)
    moved = BOX.moved_to(BOX.position + [0.0, 0.003, 0.0])
    before = len(fits)
    frames = [_frame(moved, rng, camera) for camera in (CAMERA, side)]
    (track,) = tracker.update_views([CAMERA, side], frames, 6 / 30)
    assert len(fits) == before + 1 and _inside(track.shape, moved)
