"""A box's face planes: points moved onto them along their rays, and the turn they show."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from damon_ros.core import shapes
from damon_ros.core.shapes import Shape
from damon_ros.perception.face_planes import (
    farthest,
    fit_face_planes,
    on_faces,
    settle,
    trusted,
    turn_bounds,
)
from damon_ros.perception.fit_kernels import near_planes
from damon_ros.perception.tight_fit import on_other_faces

EYE = np.array([2.0, 0.3, 0.9])  # a camera in front, to the side and above: three faces
TOL = 0.008


def _seen(turn: Rotation, noise: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Points of the faces of a 12 x 20 x 16 cm box (turned by ``turn``, at the origin of
    the frame) that face `EYE`, every 3 mm, each moved along its ray by Gaussian depth
    noise: (noisy points, true points)."""
    box = Shape("box", (0.12, 0.20, 0.16), np.zeros(3), turn.as_quat())
    points = shapes.surface_samples(box, 0.003)
    local = points @ box.rotation()
    normals = np.where(np.isclose(np.abs(local), 0.5 * np.asarray(box.size)), np.sign(local), 0)
    facing = ((normals @ box.rotation().T) * (EYE - points)).sum(axis=1) > 1e-9
    true = points[facing & (np.abs(normals).sum(axis=1) == 1)]
    rays = (true - EYE) / np.linalg.norm(true - EYE, axis=1)[:, None]
    rng = np.random.default_rng(seed)
    return true + rays * rng.normal(0.0, noise, len(true))[:, None], true


def _planes(points: np.ndarray):
    near_low, near_high = near_planes(np.ascontiguousarray(points), TOL)
    edge = on_other_faces(near_low, near_high)
    visible = np.column_stack([near_low.sum(axis=0) >= 8, near_high.sum(axis=0) >= 8])
    visible &= np.column_stack([EYE < points.min(axis=0), EYE > points.max(axis=0)])
    return fit_face_planes(points, near_low, near_high, edge, visible, TOL), visible


def test_points_met_with_their_face_planes_reach_no_short_of_the_truth_and_not_far_past_it():
    """The bottom of a box nobody sees is bounded by the last samples of the side faces.
    Met with their faces' planes, the samples lie where they are to the planes' error,
    which is allowed for: no side-face sample reaches less far down than its true place,
    and the lowest reaches within a fraction of a millimetre of the lowest true sample. Their
    measured depths (2 mm noise) reached a millimetre and more below that."""
    noisy, true = _seen(Rotation.identity(), 0.002)
    planes, visible = _planes(noisy)
    assert visible[0, 1] and visible[1, 1] and visible[2, 1] and not visible[2, 0]
    everyone = np.ones(len(noisy), dtype=bool)
    reaches = on_faces(settle(planes, EYE, visible, everyone, noisy), noisy, 2, -1)
    assert sorted(f.plane.axis for f in reaches) == [0, 1]  # the top is across the axis
    best = np.full(len(noisy), -np.inf)
    for face in reaches:
        best[face.index] = np.maximum(best[face.index], face.reach)
    side = np.isclose(np.abs(true[:, 0]), 0.06) | np.isclose(np.abs(true[:, 1]), 0.10)
    placed = side & np.isfinite(best)
    assert np.count_nonzero(placed) > 0.95 * np.count_nonzero(side) > 1000
    assert np.all(best[placed] >= -true[placed, 2])
    last = float(np.max(-true[side, 2]))  # the lowest sample (a sample above the edge)
    reach = farthest(reaches, noisy, 2, -1)
    assert 0.0 <= float(np.max(reach)) - last < 0.0005
    assert float(np.max(-noisy[:, 2])) - last > 0.001


def test_the_faces_pooled_show_the_turn_of_a_box_about_each_horizontal_axis():
    """A box turned 1.5 deg about x: the turn bound about x covers it within a degree,
    about y it stays a fraction of a degree; an upright box's bounds are both small (each
    face alone left ~0.3-1 deg)."""
    for turn, about in ((Rotation.from_euler("x", 1.5, degrees=True), 0),
                        (Rotation.from_euler("y", 1.5, degrees=True), 1)):
        noisy, _ = _seen(turn, 0.002, seed=1)
        planes, _ = _planes(noisy)
        bound = np.degrees(turn_bounds(planes, 2.0))
        assert 1.5 <= bound[about] < 2.5
        assert bound[1 - about] < 0.6 and bound[2] == 0.0
    noisy, _ = _seen(Rotation.identity(), 0.002, seed=2)
    bound = np.degrees(turn_bounds(_planes(noisy)[0], 2.0))
    assert np.all(bound < 0.6)


def test_no_face_plane_means_no_turn_bound():
    assert turn_bounds([], 2.0) is None


def test_a_slant_the_face_band_cuts_is_not_taken_as_measured():
    """A frame 3 deg off a 20 cm face: the band of the face tolerance around its robust
    plane holds only part of the face, and the fit to that part reads a flatter slant. Such
    planes are not trusted (`trusted`), so the turn and yaw fall back to their wider bounds;
    in the true frame they are."""
    noisy, _ = _seen(Rotation.from_euler("z", 3.0, degrees=True), 0.002, seed=3)
    assert not trusted(_planes(noisy)[0], TOL)
    noisy, _ = _seen(Rotation.identity(), 0.002, seed=3)
    assert trusted(_planes(noisy)[0], TOL)
