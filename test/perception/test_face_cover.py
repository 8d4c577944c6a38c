"""Whether a box's face is whole: the share of its image no sample covers."""

from __future__ import annotations

import numpy as np

from damon_ros.perception.camera import load_camera, project
from damon_ros.perception.face_cover import HOLE_SHARE, face_corners, uncovered_share

CAMERA = load_camera()


def _face_samples(width: float, height: float, keep=None) -> np.ndarray:
    """Where the camera's pixels (every second row and column, as the tracker samples) see
    a face 1.7 m in front of it, square to its view: base-frame points on a plane ``width``
    x ``height`` m, and only those ``keep(a, b)`` (face coordinates from its corner) allows."""
    centre = CAMERA.position + 1.7 * CAMERA.rotation[:, 2]
    right, down = CAMERA.rotation[:, 0], CAMERA.rotation[:, 1]
    step = 2.0 * 1.7 / CAMERA.K[0, 0]
    a, b = np.meshgrid(np.arange(0.0, width, step), np.arange(0.0, height, step))
    a, b = a.ravel(), b.ravel()
    if keep is not None:
        mask = keep(a, b)
        a, b = a[mask], b[mask]
    corner = centre - 0.5 * width * right - 0.5 * height * down
    return corner + a[:, None] * right + b[:, None] * down


def _share(points: np.ndarray) -> float:
    local = points @ CAMERA.rotation  # camera axes as the face's frame: the face is across z
    corners = face_corners(local, 2) @ CAMERA.rotation.T
    return uncovered_share(CAMERA, points, corners)


def test_a_whole_face_is_covered():
    points = _face_samples(0.12, 0.09)
    assert np.isfinite(project(CAMERA, points)).all()
    assert _share(points) < 0.01


def test_a_face_with_a_gap_across_it_is_not():
    """A palm and fingers with a thumb 3 cm beside them: the strip between is uncovered."""
    points = _face_samples(0.12, 0.17, lambda a, b: (a < 0.09) | (np.abs(b - 0.085) < 0.011))
    assert _share(points) > 2 * HOLE_SHARE


def test_too_little_to_judge_is_no_gap():
    points = _face_samples(0.012, 0.012)
    assert _share(points) == 0.0
