"""The HSV + depth tracker recovers rendered obstacles, bounds them safely and tracks them.

Frames come from the mock RealSense (damon_ros.simulation.renderer), so
ground truth is exact: sphere
centres must be recovered within 1 cm, every bound must contain the true obstacle, ids
must persist and velocities match the scenario's motion.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import pytest
from config_edits import edited_config

from damon_ros.core.scenario import COLOR_RGB, load_public_scenarios
from damon_ros.core.shapes import Shape, contains
from damon_ros.perception.camera import Camera, load_camera, pose_matrix
from damon_ros.perception.shape_fit import fit_sphere
from damon_ros.perception.tracker_config import load_tracker_config
from damon_ros.perception.tracking import Tracker, check_images, detect
from damon_ros.simulation.renderer import AMBIENT, render, scene_at

CAMERA = load_camera()
CONFIG = load_tracker_config()


def _samples(shape: Shape, n: int = 400) -> np.ndarray:
    """Points covering a shape's boundary (corners and rims included)."""
    rng = np.random.default_rng(0)
    if shape.kind == "sphere":
        d = rng.normal(size=(n, 3))
        local = shape.size[0] * d / np.linalg.norm(d, axis=1, keepdims=True)
    elif shape.kind == "box":
        local = 0.5 * np.asarray(shape.size) * np.array(
            [[a, b, c] for a in (-1, 1) for b in (-1, 1) for c in (-1, 1)]
        )
    else:
        r, half = shape.size[0], 0.5 * shape.size[1]
        angle = np.linspace(0.0, 2 * np.pi, 64, endpoint=False)
        ring = np.column_stack([r * np.cos(angle), r * np.sin(angle), np.zeros(64)])
        local = np.vstack([ring + [0, 0, half], ring - [0, 0, half]])
    return local @ shape.rotation().T + shape.position


def _contains(bound: Shape, true: Shape) -> bool:
    points = _samples(true)
    if bound.kind in ("points", "cylinder"):
        return bool(np.all(contains(bound, points, 1e-9)))
    if bound.kind == "sphere":
        return bool(np.all(np.linalg.norm(points - bound.position, axis=1) <= bound.size[0]))
    local = (points - bound.position) @ bound.rotation()
    return bool(np.all(np.abs(local) <= 0.5 * np.asarray(bound.size)))


def _match(detections, shape: Shape, color: str):
    same = [d for d in detections if d.color == color]
    assert same, f"no {color} detection"
    return min(same, key=lambda d: np.linalg.norm(d.shape.position - shape.position))


# --- configuration -------------------------------------------------------------------------


def test_shipped_config_loads_with_red_wrapping_around_hue_zero():
    assert set(CONFIG.colors) == {"red", "green", "blue", "yellow"}
    assert len(CONFIG.colors["red"]) == 2
    assert CONFIG.shape == "auto" and 0.0 < CONFIG.inflation_m <= 0.02
    assert set(CONFIG.max_thickness_m) == {"box", "blob"}


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda t: t["colors"]["red"].__setitem__(0, [[0, 100, 45], [200, 255, 255]]),
         "colors.red\\[0\\].*H is 0..179"),
        (lambda t: t["colors"].__setitem__("green", [[1, 2, 3]]), "colors.green\\[0\\] must be"),
        (lambda t: t.update(shape="cone"), "shape 'cone'"),
        (lambda t: t.update(gate_m=0.0), "gate_m"),
        (lambda t: t.update(bogus=1), "unknown keys \\['bogus'\\]"),
        (lambda t: t.pop("colors"), "colors must map"),
    ],
)
def test_bad_tracker_files_are_refused_naming_the_field(tmp_path, edit, message):
    with pytest.raises(ValueError, match=message):
        load_tracker_config(edited_config(tmp_path, "tracker.yaml", "tracker", edit))


def test_shaded_obstacle_colours_stay_in_their_class_and_grey_in_none():
    import cv2

    for name, rgb in COLOR_RGB.items():
        for light in np.linspace(AMBIENT, 1.0, 8):
            pixel = np.clip(np.asarray(rgb) * light + 0.5, 0, 255).astype(np.uint8)
            hsv = cv2.cvtColor(pixel.reshape(1, 1, 3), cv2.COLOR_RGB2HSV)
            hits = [c for c, ranges in CONFIG.colors.items()
                    if any(cv2.inRange(hsv, lo, hi)[0, 0] for lo, hi in ranges)]
            assert hits == [name], (name, light, hsv)
    for grey in ((128, 128, 128), (255, 255, 255), (40, 40, 40), (150, 140, 135)):
        hsv = cv2.cvtColor(np.array(grey, np.uint8).reshape(1, 1, 3), cv2.COLOR_RGB2HSV)
        assert not any(cv2.inRange(hsv, lo, hi)[0, 0]
                       for ranges in CONFIG.colors.values() for lo, hi in ranges)


# --- image validation --------------------------------------------------------------------


def test_bad_frames_are_refused_with_a_clear_message():
    rgb, depth = render(CAMERA, [])
    check_images(CAMERA, rgb, depth)
    with pytest.raises(ValueError, match="uint8 HxWx3"):
        check_images(CAMERA, rgb.astype(np.float32), depth)
    with pytest.raises(ValueError, match="uint8 HxWx3"):
        check_images(CAMERA, rgb[..., 0], depth)
    with pytest.raises(ValueError, match="uint16 HxW"):
        check_images(CAMERA, rgb, depth.astype(np.float32))
    with pytest.raises(ValueError, match="must match the camera's 640x480"):
        check_images(CAMERA, rgb[:240], depth[:240])
    with pytest.raises(ValueError, match="all zero"):
        check_images(CAMERA, rgb, np.zeros_like(depth))
    tracker = Tracker(CAMERA, CONFIG)
    with pytest.raises(ValueError, match="all zero"):
        tracker.update(rgb, np.zeros_like(depth), 0.0)
    assert tracker.update(rgb, depth, 0.1) == []  # it keeps working afterwards


# --- detection -----------------------------------------------------------------------------


def test_sphere_fit_recovers_a_cap_exactly_and_refuses_a_plane():
    rng = np.random.default_rng(1)
    d = rng.normal(size=(300, 3))
    d[:, 2] = -np.abs(d[:, 2])  # the half facing a camera at the origin
    centre = np.array([0.1, -0.2, 1.0])
    points = centre + 0.07 * d / np.linalg.norm(d, axis=1, keepdims=True)
    c, r, rms = fit_sphere(points)
    assert np.allclose(c, centre, atol=1e-9) and r == pytest.approx(0.07) and rms < 1e-9
    with pytest.raises(ValueError, match="at least 4 points"):
        fit_sphere(points[:3])
    plane = np.column_stack([rng.uniform(size=(50, 2)), np.ones(50)])
    with pytest.raises(ValueError, match="coplanar"):
        fit_sphere(plane)


@pytest.mark.parametrize("noise", [0.0, 0.003])
def test_sphere_at_one_metre_is_recovered_within_a_centimetre_and_contained(noise):
    camera = Camera(640, 480, CAMERA.K, pose_matrix([0, 0, 0], [0.5, -0.5, 0.5, -0.5]))
    rng = np.random.default_rng(11)
    for _ in range(8):
        true = Shape("sphere", (rng.uniform(0.03, 0.1),),
                     [rng.uniform(0.9, 1.1), rng.uniform(-0.3, 0.3), rng.uniform(-0.2, 0.2)])
        rgb, depth = render(camera, [(true, "blue")], noise, 0.02, rng)
        (found,) = detect(camera, CONFIG, rgb, depth)
        assert found.color == "blue" and found.round and found.shape.kind == "sphere"
        assert np.linalg.norm(found.shape.position - true.position) < 0.01
        assert _contains(found.shape, true)
        radius = found.shape.size[0]
        # the margin is the fit's residuals (mm depth quantisation alone: under a mm)
        assert true.size[0] < radius < true.size[0] + 3.0 * noise + 0.003  # nothing bloats it


@pytest.mark.parametrize("noise", [0.0, 0.002])
def test_scenario_d001_each_obstacle_recovered_by_colour_with_no_false_positives(noise):
    scenario = load_public_scenarios(["D-001"])[0]
    rng = np.random.default_rng(5)
    for t in (0.0, 3.0, 5.0, 8.0):
        scene = scene_at(scenario, t)
        rgb, depth = render(CAMERA, scene, noise, 0.01 if noise else 0.0, rng)
        found = detect(CAMERA, CONFIG, rgb, depth)
        assert sorted(d.color for d in found) == sorted(c for _, c in scene)
        for shape, color in scene:
            d = _match(found, shape, color)
            if shape.kind == "sphere":
                assert d.round
                assert np.linalg.norm(d.shape.position - shape.position) < 0.01
            else:
                assert not d.round  # a box face does not pass for a ball
            assert _contains(d.shape, shape), (t, color)


@pytest.mark.parametrize("mode", ["sphere", "box", "auto"])
def test_every_public_obstacle_is_bounded_unless_flagged_partial(mode):
    config = dataclasses.replace(CONFIG, shape=mode)
    partial = 0
    for scenario in load_public_scenarios():
        for t in (0.0, 4.0):
            scene = scene_at(scenario, t)
            rgb, depth = render(CAMERA, scene, 0.002, 0.01, np.random.default_rng(2))
            found = detect(CAMERA, config, rgb, depth)
            assert len(found) == len(scene), scenario.name
            for shape, color in scene:
                d = _match(found, shape, color)
                expected = "sphere" if mode == "sphere" or (mode == "auto" and d.round) else "box"
                if mode == "auto" and not d.round and not d.partial:
                    # boxes fit their faces, cylinders (tilted too) their side's arc
                    expected = shape.kind if shape.kind in ("box", "cylinder") else "points"
                assert d.shape.kind == expected, (scenario.name, shape.kind)
                if shape.kind == "sphere":
                    assert np.linalg.norm(d.shape.position - shape.position) < 0.01
                if d.partial:
                    partial += 1
                    continue
                assert _contains(d.shape, shape), (scenario.name, t, color, mode)
    # E-001/E-002's low yellow box stands behind the red one: seen in part, and flagged;
    # C-001/C-002's ball is sunk into the box's top: at the seam either may hide the other.
    assert 4 <= partial <= 16


def test_an_occluded_blob_is_flagged_and_a_free_one_is_not():
    scenario = load_public_scenarios(["E-002"])[0]
    rgb, depth = render(CAMERA, scene_at(scenario, 0.0))
    flags = {d.color: d.partial for d in detect(CAMERA, CONFIG, rgb, depth)}
    assert flags == {"red": False, "yellow": True, "green": False}
    alone = [(s, c) for s, c in scene_at(scenario, 0.0) if c == "yellow"]
    rgb, depth = render(CAMERA, alone)
    (d,) = detect(CAMERA, CONFIG, rgb, depth)
    assert not d.partial and _contains(d.shape, alone[0][0])


def test_empty_and_grey_scenes_give_no_detections():
    rng = np.random.default_rng(4)
    rgb, depth = render(CAMERA, [], 0.005, 0.05, rng)
    assert detect(CAMERA, CONFIG, rgb, depth) == []
    # A white and a grey box (the robot's own colours) are not obstacles of any class.
    rgb[100:200, 100:200] = 250
    rgb[300:350, 300:400] = (90, 92, 95)
    tracker = Tracker(CAMERA, CONFIG)
    for i in range(5):
        assert tracker.update(rgb, depth, 0.1 * i) == []


def test_speckle_below_the_minimum_area_is_ignored():
    rgb, depth = render(CAMERA, [])
    rng = np.random.default_rng(6)
    rows, cols = rng.integers(0, 480, 300), rng.integers(0, 640, 300)
    rgb[rows, cols] = COLOR_RGB["red"]
    assert detect(CAMERA, CONFIG, rgb, depth) == []


# --- tracking ------------------------------------------------------------------------------


def _run(scenario, times, tracker, noise=0.002, seed=0):
    rng = np.random.default_rng(seed)
    out = []
    for t in times:
        rgb, depth = render(CAMERA, scene_at(scenario, t), noise, 0.01, rng)
        out.append(tracker.update(rgb, depth, t))
    return out


def test_moving_sphere_keeps_its_id_and_its_velocity_is_measured():
    scenario = load_public_scenarios(["D-001"])[0]
    ball = next(o for o in scenario.obstacles if o.is_dynamic)
    times = 2.5 + np.arange(45) / 30.0
    history = _run(scenario, times, Tracker(CAMERA, CONFIG))
    ids = {tr.id for tracks in history for tr in tracks if tr.color == "green"}
    assert len(ids) == 1
    for t, tracks in zip(times[10:], history[10:], strict=True):
        green = next(tr for tr in tracks if tr.color == "green")
        red = next(tr for tr in tracks if tr.color == "red")
        truth = ball.velocity_at(t)
        assert np.linalg.norm(green.velocity - truth) < 0.2 * np.linalg.norm(truth)
        assert np.linalg.norm(green.shape.position - ball.position_at(t)) < 0.01
        assert np.linalg.norm(red.velocity) < 0.02  # the static box
        assert green.last_seen == t and green.hits >= 11
    assert history[-1][0].age == pytest.approx(times[-1] - times[0])


def test_tracks_are_dropped_after_max_age_and_return_with_a_new_id():
    ball = Shape("sphere", (0.06,), [0.5, 0.0, 0.4])
    tracker = Tracker(CAMERA, CONFIG)
    full, empty = render(CAMERA, [(ball, "yellow")]), render(CAMERA, [])
    (first,) = tracker.update(*full, 0.0)
    assert tracker.update(*empty, CONFIG.max_age_s - 0.1)[0].id == first.id  # still held
    assert tracker.update(*empty, CONFIG.max_age_s + 0.1) == []
    (again,) = tracker.update(*full, CONFIG.max_age_s + 0.2)
    assert again.id != first.id and again.hits == 1


def test_a_detection_outside_the_gate_opens_a_new_track():
    tracker = Tracker(CAMERA, CONFIG)
    here = Shape("sphere", (0.05,), [0.5, -0.2, 0.4])
    there = here.moved_to(here.position + [0.0, CONFIG.gate_m + 0.05, 0.0])
    (first,) = tracker.update(*render(CAMERA, [(here, "blue")]), 0.0)
    tracks = tracker.update(*render(CAMERA, [(there, "blue")]), 0.033)
    assert len(tracks) == 2  # the old one is kept (unseen) until max_age_s
    new = next(tr for tr in tracks if tr.id != first.id)
    old = next(tr for tr in tracks if tr.id == first.id)
    assert np.linalg.norm(new.shape.position - there.position) < 0.01
    assert old.last_seen == 0.0 and np.all(old.velocity == 0.0)


def test_two_same_colour_spheres_crossing_in_depth_keep_their_ids():
    tracker = Tracker(CAMERA, CONFIG)
    ids = None
    for i in range(30):
        t = i / 30.0
        a = Shape("sphere", (0.05,), [0.5, -0.3 + 0.3 * t, 0.3])
        b = Shape("sphere", (0.05,), [0.5, 0.3 - 0.3 * t, 0.6])
        tracks = tracker.update(*render(CAMERA, [(a, "red"), (b, "red")]), t)
        by_height = sorted(tracks, key=lambda tr: tr.shape.position[2])
        assert len(by_height) == 2
        now = [tr.id for tr in by_height]
        ids = now if ids is None else ids
        assert now == ids


def test_stamps_must_increase_and_a_clock_restart_resets():
    ball = Shape("sphere", (0.06,), [0.5, 0.0, 0.4])
    frame = render(CAMERA, [(ball, "green")])
    tracker = Tracker(CAMERA, CONFIG)
    (first,) = tracker.update(*frame, 10.0)
    with pytest.raises(ValueError, match="not newer"):
        tracker.update(*frame, 10.0)
    with pytest.raises(ValueError, match="not finite"):
        tracker.update(*frame, float("nan"))
    (restarted,) = tracker.update(*frame, 0.0)  # 10 s back: a new clock, not a stale frame
    assert restarted.id != first.id and restarted.hits == 1


def test_tracker_processes_three_obstacle_frames_far_faster_than_the_camera():
    scenario = load_public_scenarios(["E-002"])[0]
    rng = np.random.default_rng(0)
    frames = [render(CAMERA, scene_at(scenario, 1.0 + i / 30), 0.002, 0.01, rng)
              for i in range(20)]
    tracker = Tracker(CAMERA, CONFIG)
    tracker.update(*frames[0], 0.0)
    # CPU time, not wall time: other work on a busy machine does not count against it
    # (measured ~3 ms a frame on a quiet machine)
    start = time.process_time()
    for i, frame in enumerate(frames[1:], start=1):
        tracks = tracker.update(*frame, i / 30)
    per_frame = (time.process_time() - start) / (len(frames) - 1)
    assert len(tracks) == 3
    assert per_frame < 1.0 / 60.0  # keeps up with a 30 fps camera twice over


@pytest.mark.parametrize("seed", range(4))
def test_a_ball_that_starts_fast_is_reported_near_its_speed_within_a_tenth_of_a_second(seed):
    """The 0.3 s window's slope still holds the samples at rest just after a start (half the
    speed or less); the short slope of the last 0.1 s is taken instead. A still ball's jitter
    never passes for a start, nor does a steady mover's noise change its speed."""
    from damon_ros.perception.velocity import VelocityWindow

    rng = np.random.default_rng(seed)
    start, speed = VelocityWindow(CONFIG.velocity_window_s), 1.3
    still, steady = VelocityWindow(CONFIG.velocity_window_s), VelocityWindow(0.3)
    for i in range(30):
        t = i / 30
        noise = rng.normal(0.0, 0.003, 3)
        moved = start.add(t, np.array([max(0.0, speed * (t - 0.5)), 0.0, 0.0]) + noise)
        rest = still.add(t, noise)
        cruise = steady.add(t, np.array([0.4 * t, 0.0, 0.0]) + noise)
        if t >= 0.6:  # 0.1 s after the start
            assert moved[0] > 0.8 * speed, (t, moved)
        if t >= 0.2:  # (two or three samples of noise alone make any slope)
            assert np.linalg.norm(rest) < 0.1
        if cruise is not None and t >= 0.2:
            assert abs(cruise[0] - 0.4) < 0.1


@pytest.mark.parametrize(("speed", "after_frame"), [(0.19, 0.0), (0.31, 0.55), (0.19, 0.7)])
def test_a_ball_that_starts_slowly_is_reported_at_its_speed_once_it_moves(speed, after_frame):
    """A ball at rest starts at 0.19-0.31 m/s (below the short slope's onset test: 2 cm in
    0.1 s), on a frame or ``after_frame`` of a frame period after one. It is seen to move
    within 1.5 cm, and its velocity then comes from the samples since it was last at rest,
    not from a window that still holds it at rest (which reported 0.07-0.13 m/s for 0.1 s,
    2 cm late, and a stop certified against that was hit: generated G scene G-s2402-045,
    one camera). A start between frames leaves the first frame a few mm out: that frame is
    no longer at rest (a ball's jitter is a quarter of its 7 mm shift, not of a box's 2 cm,
    which took it for rest and the speed for 1.45 times the truth), and the motion is taken
    to begin where the moved frames' line leaves the rest place (from the last frame at rest
    it was two thirds of the speed: G-s2607-030, one camera, a diving ball hit the arm)."""
    import yaml

    from damon_ros.core.resources import public_scenarios_dir
    from damon_ros.core.scenario import parse_scenario

    data = yaml.safe_load((public_scenarios_dir() / "D-001.yaml").read_text())
    start, direction = np.array([0.55, 0.2, 0.6]), np.array([-0.3, -0.7, -0.6])
    direction /= np.linalg.norm(direction)
    begin = 1.0 + after_frame / 30.0
    end = start + direction * speed * 2.0
    data["obstacles"] = [{"name": "ball", "shape": "sphere", "size": [0.06], "color": "yellow",
                          "pose": {"position": start.tolist(), "orientation": [0, 0, 0, 1]},
                          "motion": {"type": "waypoints",
                                     "waypoints": [[0.0, *start], [begin, *start],
                                                   [begin + 2.0, *end.tolist()]]}}]
    scenario = parse_scenario(data, "slow-start")
    times = np.arange(45) / 30.0
    history = _run(scenario, times, Tracker(CAMERA, CONFIG))
    reported = [(t, np.linalg.norm(tracks[0].velocity)) for t, tracks in zip(times, history,
                                                                            strict=True)]
    assert all(v < 0.01 for t, v in reported if t < begin)  # at rest, then seen to move ...
    moving = [(t, v) for t, v in reported if t >= begin and v > 0.01]
    # ... within a frame of leaving its anchor by moving_shift_round_m (a fitted ball's
    # centre), not by a box's moving_shift_m (2 cm: 0.1 s at 0.19 m/s)
    assert moving and moving[0][0] <= begin + CONFIG.moving_shift_round_m / speed + 1 / 30, \
        moving
    assert all(abs(v - speed) < 0.25 * speed for _, v in moving), moving
