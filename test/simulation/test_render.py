"""The mock RealSense renders exact geometry: every hit pixel lies on the shape it shows.

Checked against closed-form silhouettes and depths, against the surface equations of each
shape kind at random poses, and for the file/validation contract the mock camera node uses.
"""

from __future__ import annotations

import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from config_edits import edited_config

from damon_ros.core.resources import config_file
from damon_ros.core.scenario import COLOR_RGB, load_public_scenarios
from damon_ros.core.shapes import Shape, point
from damon_ros.perception.camera import (
    Camera,
    deproject,
    load_camera,
    pose_matrix,
    project,
    to_base_frame,
    to_camera_frame,
)
from damon_ros.simulation.renderer import BACKGROUND_RGB, load_render_settings, render, scene_at

LOOK_DOWN_X = [0.5, -0.5, 0.5, -0.5]
"""Optical frame looking along base +x (z_opt = x, x_opt = -y, y_opt = -z)."""


def _camera(position=(0.0, 0.0, 0.0), orientation=LOOK_DOWN_X, width=640, height=480):
    K = np.array([[615.0, 0.0, 320.0], [0.0, 615.0, 240.0], [0.0, 0.0, 1.0]])
    return Camera(width, height, K, pose_matrix(position, orientation))


def _hit_points(camera: Camera, depth: np.ndarray) -> np.ndarray:
    """Base-frame points of every pixel with a return."""
    v, u = np.nonzero(depth)
    return to_base_frame(camera, deproject(camera, u, v, depth[v, u] * 1e-3))


def _surface_distance(shape: Shape, points: np.ndarray) -> np.ndarray:
    """Unsigned distance of points from the shape's surface (for points near it)."""
    local = (points - shape.position) @ shape.rotation()
    if shape.kind == "sphere":
        return np.abs(np.linalg.norm(local, axis=1) - shape.size[0])
    if shape.kind == "box":
        q = np.abs(local) - 0.5 * np.asarray(shape.size)
        outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
        return np.where(outside > 0, outside, -np.max(q, axis=1))
    r, half = shape.size[0], 0.5 * shape.size[1]
    radial = np.hypot(local[:, 0], local[:, 1])
    dr, dz = radial - r, np.abs(local[:, 2]) - half
    outside = np.hypot(np.maximum(dr, 0), np.maximum(dz, 0))
    return np.where(outside > 0, outside, -np.maximum(dr, dz))


def test_shipped_camera_is_a_d435_colour_stream_looking_at_the_workspace():
    camera = load_camera()
    assert (camera.width, camera.height) == (640, 480)
    assert camera.K[0, 0] == pytest.approx(615.0) and camera.K[1, 1] == pytest.approx(615.0)
    assert camera.frame_id == "camera_color_optical_frame"
    assert camera.base_frame == "panda_link0"
    uv = project(camera, np.array([[0.5, 0.0, 0.4]]))[0]
    assert np.allclose(uv, [320.0, 240.0], atol=1.0)
    # The whole obstacle region of the scenarios is inside the image.
    corners = np.array([[x, y, z] for x in (0.2, 0.8) for y in (-0.8, 0.8) for z in (0.0, 0.9)])
    uv = project(camera, corners)
    assert np.all((uv[:, 0] > 0) & (uv[:, 0] < 639) & (uv[:, 1] > 0) & (uv[:, 1] < 479))
    info = camera.camera_info()
    assert info["distortion_model"] == "plumb_bob" and info["d"] == [0.0] * 5
    assert info["k"] == camera.K.reshape(-1).tolist() and len(info["p"]) == 12


def test_config_lookup_prefers_the_source_checkout():
    path = config_file("camera.yaml")
    assert path == Path(__file__).resolve().parents[2] / "config" / "camera.yaml"
    with pytest.raises(FileNotFoundError, match="no-such.yaml"):
        config_file("no-such.yaml")


def test_render_settings_load_from_the_camera_file():
    settings = load_render_settings()
    assert settings.depth_noise_std_m >= 0.0 and 0.0 <= settings.dropout < 1.0
    assert settings.background_depth_m > 0.0


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda c: c.pop("K"), "missing field 'K'"),
        (lambda c: c.update(K=[1.0, 2.0]), "K must have 9 values"),
        (lambda c: c.update(D=[0.1, 0, 0, 0, 0]), "must be zeros"),
        (lambda c: c["base_T_camera"].update(orientation=[0, 0, 0, 2]), "unit quaternion"),
        (lambda c: c.update(width=0), "must be positive"),
    ],
)
def test_bad_camera_files_are_refused_naming_the_field(tmp_path, edit, message):
    with pytest.raises(ValueError, match=message):
        load_camera(edited_config(tmp_path, "camera.yaml", "camera", edit))


def test_a_missing_camera_file_is_a_value_error(tmp_path):
    with pytest.raises(ValueError, match="cannot be read"):
        load_camera(tmp_path / "absent.yaml")


def test_project_and_deproject_are_inverse():
    camera = load_camera()
    rng = np.random.default_rng(3)
    points = rng.uniform([0.2, -0.6, 0.0], [0.8, 0.6, 0.9], size=(200, 3))
    uv = project(camera, points)
    z = to_camera_frame(camera, points)[:, 2]
    back = to_base_frame(camera, deproject(camera, uv[:, 0], uv[:, 1], z))
    assert np.allclose(back, points, atol=1e-9)
    behind = camera.position + 0.5 * camera.rotation[:, 2] * -1.0
    assert np.all(np.isnan(project(camera, behind[None])))


def test_sphere_on_the_axis_has_the_closed_form_depth_and_silhouette():
    camera = _camera()
    distance, radius = 1.2, 0.1
    ball = Shape("sphere", (radius,), [distance, 0.0, 0.0])
    rgb, depth = render(camera, [(ball, "green")], background_depth_m=0.0)
    assert depth[240, 320] == round((distance - radius) * 1000)
    # Silhouette: a disc of angular radius asin(r / D) about the principal point.
    rho = 615.0 * np.tan(np.arcsin(radius / distance))
    assert (depth > 0).sum() == pytest.approx(np.pi * rho**2, rel=0.02)
    assert tuple(rgb[0, 0]) == BACKGROUND_RGB
    # Lit head-on: the centre pixel shows the full albedo.
    assert np.allclose(rgb[240, 320], COLOR_RGB["green"], atol=1)


def test_rotated_box_silhouette_is_the_hull_of_its_projected_corners():
    camera = _camera()
    box = Shape("box", (0.2, 0.3, 0.15), [1.5, 0.1, -0.05], [0.1, 0.2, 0.3, 0.927])
    _, depth = render(camera, [(box, "red")], background_depth_m=0.0)
    half = 0.5 * np.array(box.size)
    corners = np.array([[a, b, c] for a in (-1, 1) for b in (-1, 1) for c in (-1, 1)]) * half
    uv = project(camera, corners @ box.rotation().T + box.position)
    hull = np.zeros_like(depth, dtype=np.uint8)
    cv2.fillConvexPoly(hull, np.round(cv2.convexHull(uv.astype(np.float32))).astype(np.int32), 1)
    mask = depth > 0
    iou = (mask & (hull > 0)).sum() / (mask | (hull > 0)).sum()
    assert iou > 0.97


def test_cylinder_seen_along_and_across_its_axis():
    camera = _camera()
    radius, length, distance = 0.08, 0.3, 1.5
    upright = Shape("cylinder", (radius, length), [distance, 0.0, 0.0])  # axis = image vertical
    _, depth = render(camera, [(upright, "blue")], background_depth_m=0.0)
    assert depth[240, 320] == round((distance - radius) * 1000)
    rows = np.nonzero(depth[:, 320])[0]
    cols = np.nonzero(depth[240])[0]
    # Image height of the near edge ~ f * L / (D - r); width ~ 2 f r / D.
    assert len(rows) == pytest.approx(615 * length / (distance - radius), abs=3)
    assert len(cols) == pytest.approx(2 * 615 * radius / distance, abs=3)
    turned = [0.0, 0.7071068, 0.0, 0.7071068]  # axis along the view
    facing = Shape("cylinder", (radius, length), [distance, 0.0, 0.0], turned)
    _, depth = render(camera, [(facing, "blue")], background_depth_m=0.0)
    assert depth[240, 320] == round((distance - 0.5 * length) * 1000)  # the cap faces us
    rho = 615 * radius / (distance - 0.5 * length)
    assert (depth > 0).sum() == pytest.approx(np.pi * rho**2, rel=0.03)


@pytest.mark.parametrize("kind", ["sphere", "box", "cylinder"])
def test_every_hit_pixel_lies_on_the_surface_of_a_randomly_posed_shape(kind):
    camera = load_camera()
    rng = np.random.default_rng({"sphere": 0, "box": 1, "cylinder": 2}[kind])
    for _ in range(5):
        size = {"sphere": (rng.uniform(0.03, 0.12),),
                "box": tuple(rng.uniform(0.05, 0.3, 3)),
                "cylinder": (rng.uniform(0.03, 0.1), rng.uniform(0.1, 0.4))}[kind]
        q = rng.normal(size=4)
        centre = rng.uniform([0.3, -0.5, 0.1], [0.8, 0.5, 0.8])
        shape = Shape(kind, size, centre, q / np.linalg.norm(q))
        _, depth = render(camera, [(shape, "yellow")], background_depth_m=0.0)
        points = _hit_points(camera, depth)
        assert len(points) > 100
        # Depth is quantised to 1 mm along z; at grazing incidence that moves a point off the
        # surface by up to ~0.5 mm / cos, so the bound is a little looser than 0.5 mm.
        assert np.percentile(_surface_distance(shape, points), 99) < 0.002
        assert np.max(_surface_distance(shape, points)) < 0.02


def test_the_nearest_surface_wins():
    camera = _camera()
    wall = Shape("box", (0.05, 0.6, 0.6), [2.0, 0.0, 0.0])
    ball = Shape("sphere", (0.1,), [1.0, 0.0, 0.0])
    for order in ([(wall, "red"), (ball, "green")], [(ball, "green"), (wall, "red")]):
        rgb, depth = render(camera, order)
        assert depth[240, 320] == 900 and rgb[240, 320, 1] > rgb[240, 320, 0]
        assert depth[240, 250] == 1975 and rgb[240, 250, 0] > rgb[240, 250, 1]


def test_background_is_grey_at_the_far_wall_or_no_return():
    camera = load_camera()
    rgb, depth = render(camera, [])
    assert np.all(rgb == BACKGROUND_RGB) and np.all(depth == 3500)
    _, depth = render(camera, [], background_depth_m=0.0)
    assert not depth.any()


def test_shapes_off_image_or_behind_the_camera_draw_nothing_and_straddling_ones_draw():
    camera = _camera()
    behind = Shape("sphere", (0.2,), [-1.0, 0.0, 0.0])
    aside = Shape("box", (0.1, 0.1, 0.1), [1.0, 3.0, 0.0])
    _, depth = render(camera, [(behind, "red"), (aside, "red")], background_depth_m=0.0)
    assert not depth.any()
    # A slab overhead from 1 m behind the camera to 1 m in front: its underside is seen
    # by the upward rays only (the corners behind the camera make it cast over the image).
    straddling = Shape("box", (2.0, 2.0, 2.0), [0.0, 0.0, 1.3])
    _, depth = render(camera, [(straddling, "red")], background_depth_m=0.0)
    assert depth[0, 320] == round(0.3 / (240 / 615) * 1000)
    assert depth[240, 320] == 0 and depth[479, 320] == 0


def test_noise_and_dropout_are_seeded_and_have_the_requested_size():
    camera = load_camera()
    scene = scene_at(load_public_scenarios(["D-001"])[0], 0.0)
    a = render(camera, scene, 0.004, 0.05, np.random.default_rng(7))
    b = render(camera, scene, 0.004, 0.05, np.random.default_rng(7))
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    depth = a[1]
    assert (depth == 0).mean() == pytest.approx(0.05, abs=0.005)
    wall = depth[(depth > 3000)].astype(float)  # background pixels that kept their return
    assert np.std(wall - 3500.0) == pytest.approx(4.0, rel=0.05)
    clean_rgb, _ = render(camera, scene)
    assert np.array_equal(clean_rgb, a[0])  # colour is not degraded


@pytest.mark.parametrize(
    ("obstacles", "kwargs", "message"),
    [
        ([(Shape("sphere", (0.1,), [1, 0, 0]), "purple")], {}, "unknown color 'purple'"),
        ([(point([1, 0, 0]), "red")], {}, "cannot render a 'points' shape"),
        ([("sphere", "red")], {}, "is not a Shape"),
        ([Shape("sphere", (0.1,), [1, 0, 0])], {}, "must be a \\(Shape, color\\) pair"),
        ([], {"dropout": 1.5}, "dropout"),
        ([], {"depth_noise_std_m": -1.0}, "depth_noise_std_m"),
        ([], {"depth_noise_std_m": float("nan")}, "depth_noise_std_m"),
        ([], {"background_depth_m": -1.0}, "background_depth_m"),
    ],
)
def test_bad_render_input_is_a_value_error(obstacles, kwargs, message):
    with pytest.raises(ValueError, match=message):
        render(load_camera(), obstacles, **kwargs)


def test_renders_a_three_obstacle_frame_faster_than_the_camera_rate():
    camera = load_camera()
    scene = scene_at(load_public_scenarios(["E-002"])[0], 1.0)
    assert len(scene) == 3
    rng = np.random.default_rng(0)
    render(camera, scene, 0.002, 0.01, rng)
    start = time.process_time()  # CPU time: other processes on the machine do not count
    for _ in range(20):
        render(camera, scene, 0.002, 0.01, rng)
    assert (time.process_time() - start) / 20 < 1.0 / 30.0


def test_consecutive_frames_have_uncorrelated_depth_noise():
    """The noise comes from a pool read at random offsets: pixel by pixel, one frame's
    noise says nothing about the next one's."""
    camera = load_camera()
    rng = np.random.default_rng(3)
    noise = [render(camera, [], 0.004, 0.0, rng)[1].astype(float) - 3500.0 for _ in range(3)]
    for a, b in ((noise[0], noise[1]), (noise[1], noise[2])):
        assert not np.array_equal(a, b)
        assert abs(np.corrcoef(a.ravel(), b.ravel())[0, 1]) < 0.02
