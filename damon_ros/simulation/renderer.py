"""The mock RealSense: analytic ray casting of obstacle shapes into rgb8 + 16UC1 images.

The mock camera node, the closed-loop benchmark and the tracker tests all need images that
look like what a D435 publishes (colour plus depth aligned to colour, in millimetres, 0 = no
return) for a known scene, so that the tracker is exercised on pixels, not on ground truth.
Rays are cast exactly against spheres, boxes and finite cylinders in each shape's own frame;
each shape only touches the pixels of its projected bounding rectangle, which keeps a
640x480 frame with a few obstacles at hundreds of frames per second on one core.

Conventions: the camera frame is ``camera_color_optical_frame`` (z forward, x right, y down);
a pixel's integer coordinates are its centre (OpenCV/ROS); depth is the z coordinate in the
optical frame (what RealSense publishes), not the range along the ray. Because every ray is
written as ``[x, y, 1]`` in the optical frame, the ray parameter of a hit is its depth.

The background is a grey backdrop (RGB 128, 128, 128: saturation 0, so no HSV colour class
matches it) at a constant depth ``background_depth_m`` (default 3.5 m, a far wall behind the
robot); ``background_depth_m=0`` renders it as "no return" instead. The robot is not drawn.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from damon_ros.core.resources import config_file, read_yaml_section
from damon_ros.core.scenario import COLOR_RGB, COLORS, Scenario
from damon_ros.core.shapes import Shape
from damon_ros.perception.camera import Camera, project, to_camera_frame

BACKGROUND_RGB = (128, 128, 128)
AMBIENT = 0.35
"""Share of the albedo seen on a surface at grazing incidence; the rest is Lambertian with a
light at the camera (a headlight), so every visible surface is lit."""

MAX_DEPTH_MM = 65535
NEAR_M = 0.01
"""Corners closer than this to the camera plane make a shape's projection unbounded; such a
shape is then ray-cast over the whole image."""














@dataclass(frozen=True)
class RenderSettings:
    """How the mock camera degrades its images (the ``mock_render:`` section)."""

    depth_noise_std_m: float = 0.0
    dropout: float = 0.0
    background_depth_m: float = 3.5
    seed: int = 0


def load_render_settings(path: str | os.PathLike | None = None) -> RenderSettings:
    """The ``mock_render:`` section of ``path`` or of the shipped camera file."""
    path = config_file("camera.yaml") if path is None else Path(path)
    data = read_yaml_section(path, "mock_render")
    unknown = set(data) - set(RenderSettings.__dataclass_fields__)
    if unknown:
        raise ValueError(f"{path}: mock_render: unknown keys {sorted(unknown)}")
    return RenderSettings(**data)


# --- projection helpers (shared with the tracker) -----------------------------------------










# --- ray casting -----------------------------------------------------------------------------


def _local_corners(shape: Shape) -> np.ndarray:
    """Corners of a box around the shape, in its own frame."""
    if shape.kind == "box":
        half = 0.5 * np.asarray(shape.size)
    elif shape.kind == "sphere":
        half = np.full(3, shape.size[0])
    elif shape.kind == "cylinder":
        half = np.array([shape.size[0], shape.size[0], 0.5 * shape.size[1]])
    else:
        raise ValueError(f"cannot render a {shape.kind!r} shape; expected box, sphere or cylinder")
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    return signs * half


def _pixel_rect(camera: Camera, shape: Shape) -> tuple[int, int, int, int] | None:
    """Rows and columns ``(r0, r1, c0, c1)`` the shape can cover, or None when off-image."""
    corners = _local_corners(shape) @ shape.rotation().T + shape.position
    p = to_camera_frame(camera, corners)
    if np.all(p[:, 2] <= NEAR_M):
        return None
    if np.any(p[:, 2] <= NEAR_M):
        return 0, camera.height, 0, camera.width
    uv = project(camera, corners)
    c0 = max(int(np.floor(uv[:, 0].min())), 0)
    c1 = min(int(np.ceil(uv[:, 0].max())) + 1, camera.width)
    r0 = max(int(np.floor(uv[:, 1].min())), 0)
    r1 = min(int(np.ceil(uv[:, 1].max())) + 1, camera.height)
    if c0 >= c1 or r0 >= r1:
        return None
    return r0, r1, c0, c1


def _first_root(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Smaller root of ``a t^2 + 2 b t + c = 0`` where real and positive ``a``; else inf."""
    disc = b * b - a * c
    hit = (disc >= 0.0) & (a > 1e-12)
    t = np.full(a.shape, np.inf)
    t[hit] = (-b[hit] - np.sqrt(disc[hit])) / a[hit]
    return t


def _hit_sphere(o: np.ndarray, d: list[np.ndarray], size) -> tuple[np.ndarray, list]:
    r = size[0]
    a = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
    b = o[0] * d[0] + o[1] * d[1] + o[2] * d[2]
    t = _first_root(a, b, np.full(a.shape, float(o @ o - r * r)))
    t = np.where(t > 0.0, t, np.inf)
    t_hit = np.where(np.isfinite(t), t, 0.0)  # missed rays: any finite normal will do
    normal = [(o[i] + t_hit * d[i]) / r for i in range(3)]
    return t, normal


def _hit_box(o: np.ndarray, d: list[np.ndarray], size) -> tuple[np.ndarray, list]:
    """Slab test: the ray is inside the box between the last entry and the first exit."""
    half = 0.5 * np.asarray(size)
    near = []
    far = []
    for i in range(3):
        di = np.where(np.abs(d[i]) < 1e-12, 1e-12, d[i])
        t1 = (-half[i] - o[i]) / di
        t2 = (half[i] - o[i]) / di
        near.append(np.minimum(t1, t2))
        far.append(np.maximum(t1, t2))
    near_stack = np.stack(near)
    t_in = near_stack.max(axis=0)
    t_out = np.minimum(np.minimum(far[0], far[1]), far[2])
    t = np.where((t_out >= t_in) & (t_in > 0.0), t_in, np.inf)
    axis = near_stack.argmax(axis=0)
    normal = [np.where(axis == i, -np.sign(d[i]), 0.0) for i in range(3)]
    return t, normal


def _hit_cylinder(o: np.ndarray, d: list[np.ndarray], size) -> tuple[np.ndarray, list]:
    """Finite cylinder along local z: the side (infinite cylinder clipped) or the near cap."""
    r, half = size[0], 0.5 * size[1]
    a = d[0] * d[0] + d[1] * d[1]
    b = o[0] * d[0] + o[1] * d[1]
    t_side = _first_root(a, b, np.full(a.shape, float(o[0] ** 2 + o[1] ** 2 - r * r)))
    z_side = o[2] + np.where(np.isfinite(t_side), t_side, 0.0) * d[2]
    t_side = np.where((np.abs(z_side) <= half) & (t_side > 0.0), t_side, np.inf)
    dz = np.where(np.abs(d[2]) < 1e-12, 1e-12, d[2])
    cap_z = np.where(dz > 0.0, -half, half)  # the cap facing the ray
    t_cap = (cap_z - o[2]) / dz
    x = o[0] + t_cap * d[0]
    y = o[1] + t_cap * d[1]
    t_cap = np.where((x * x + y * y <= r * r) & (t_cap > 0.0), t_cap, np.inf)
    t = np.minimum(t_side, t_cap)
    side = t_side <= t_cap
    t_hit = np.where(np.isfinite(t), t, 0.0)
    normal = [
        np.where(side, (o[0] + t_hit * d[0]) / r, 0.0),
        np.where(side, (o[1] + t_hit * d[1]) / r, 0.0),
        np.where(side, 0.0, np.sign(cap_z)),
    ]
    return t, normal


_HITS = {"sphere": _hit_sphere, "box": _hit_box, "cylinder": _hit_cylinder}


def _cast(camera: Camera, shape: Shape, rect: tuple[int, int, int, int]):
    """Depth (inf where missed) and Lambertian intensity of one shape over a pixel rectangle."""
    r0, r1, c0, c1 = rect
    R = shape.rotation()
    M = R.T @ camera.rotation  # optical-frame ray -> shape-frame ray
    o = R.T @ (camera.position - shape.position)
    xs = camera.ray_x[c0:c1][None, :]
    ys = camera.ray_y[r0:r1][:, None]
    d = [M[i, 0] * xs + M[i, 1] * ys + M[i, 2] for i in range(3)]
    t, normal = _HITS[shape.kind](o, d, shape.size)
    length = np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
    cosine = -(normal[0] * d[0] + normal[1] * d[1] + normal[2] * d[2]) / length
    intensity = AMBIENT + (1.0 - AMBIENT) * np.clip(cosine, 0.0, 1.0)
    return t, intensity


def _check_obstacles(obstacles: Sequence[tuple[Shape, str]]) -> None:
    for i, item in enumerate(obstacles):
        if not isinstance(item, (tuple, list)) or len(item) != 2:
            raise ValueError(f"obstacles[{i}] must be a (Shape, color) pair")
        shape, color = item
        if not isinstance(shape, Shape):
            raise ValueError(f"obstacles[{i}]: {type(shape).__name__} is not a Shape")
        if color not in COLOR_RGB:
            raise ValueError(f"obstacles[{i}]: unknown color {color!r}; expected one of {COLORS}")
        _local_corners(shape)


_NOISE_POOL_SIZE = 1 << 21  # 2 Mi standard normal values (8 MB): 6 full 640x480 frames


@functools.lru_cache(maxsize=1)
def _noise_pool() -> np.ndarray:
    """Standard normal float32 values drawn once (fixed seed), read at a random offset.

    Why: drawing 307,200 normals per 640x480 frame took ~5 ms, a third of a frame's render
    time, on the 2-core machine the whole cell shares. A window at a fresh random offset,
    with a random sign, is still independent from pixel to pixel within a frame; between
    frames a pixel reads another pool value (values reappear, shifted to other pixels),
    and the caller's seeded ``rng`` still fixes every frame.
    """
    return np.random.default_rng(20261201).standard_normal(_NOISE_POOL_SIZE, dtype=np.float32)


def _degrade(depth_m: np.ndarray, noise_std: float, dropout: float, rng) -> np.ndarray:
    """Gaussian depth noise on every return, then random pixels with no return."""
    if not noise_std >= 0.0 or not np.isfinite(noise_std) or not 0.0 <= dropout < 1.0:
        raise ValueError(
            f"depth_noise_std_m {noise_std} must be >= 0 and dropout {dropout} in [0, 1)"
        )
    if noise_std == 0.0 and dropout == 0.0:
        return depth_m
    rng = np.random.default_rng() if rng is None else rng
    valid = depth_m > 0.0
    n = int(valid.sum())
    if noise_std > 0.0 and n:
        pool = _noise_pool()
        if n > pool.size:  # larger than any camera here: draw afresh
            noise = rng.standard_normal(n, dtype=np.float32)
        else:
            start = int(rng.integers(0, pool.size - n + 1))
            noise = pool[start:start + n] * np.float32(rng.choice((-1.0, 1.0)))
        depth_m[valid] += np.float32(noise_std) * noise
    if dropout > 0.0:  # each pixel with probability `dropout`: a binomial count of them
        np.put(depth_m, rng.choice(depth_m.size, rng.binomial(depth_m.size, dropout),
                                   replace=False), 0.0)
    return depth_m


@functools.lru_cache(maxsize=4)
def _background(height: int, width: int) -> np.ndarray:
    """The empty colour image, copied per frame (filling it from a tuple took 2.4 ms)."""
    return np.tile(np.array(BACKGROUND_RGB, dtype=np.uint8), (height, width, 1))


def render(
    camera: Camera,
    obstacles: Sequence[tuple[Shape, str]],
    depth_noise_std_m: float = 0.0,
    dropout: float = 0.0,
    rng: np.random.Generator | None = None,
    background_depth_m: float = 3.5,
) -> tuple[np.ndarray, np.ndarray]:
    """Render coloured obstacles: ``(rgb uint8 HxWx3, depth uint16 HxW in mm, 0 = no return)``.

    The nearest surface wins per pixel. Noise and dropout only touch depth (the colour stream
    of a D435 is far cleaner than its depth); pass a seeded ``rng`` for reproducible frames.
    """
    _check_obstacles(obstacles)
    if not 0.0 <= background_depth_m * 1000.0 <= MAX_DEPTH_MM:  # NaN fails too
        raise ValueError(f"background_depth_m {background_depth_m} must be in [0, 65.535]")
    H, W = camera.height, camera.width
    rgb = _background(H, W).copy()
    depth = np.full((H, W), np.inf if background_depth_m == 0.0 else background_depth_m,
                    dtype=np.float32)
    for shape, color in obstacles:
        rect = _pixel_rect(camera, shape)
        if rect is None:
            continue
        t, intensity = _cast(camera, shape, rect)
        r0, r1, c0, c1 = rect
        window = depth[r0:r1, c0:c1]
        nearer = t < window
        window[nearer] = t[nearer]
        shade = intensity[nearer][:, None] * np.asarray(COLOR_RGB[color], dtype=float)
        rgb[r0:r1, c0:c1][nearer] = np.clip(shade + 0.5, 0, 255).astype(np.uint8)
    depth[~np.isfinite(depth)] = 0.0
    depth = _degrade(depth, float(depth_noise_std_m), float(dropout), rng)
    depth *= np.float32(1000.0)  # to mm, rounded, within uint16 (np.clip took 2 ms here)
    depth += np.float32(0.5)
    np.minimum(depth, np.float32(MAX_DEPTH_MM), out=depth)
    np.maximum(depth, np.float32(0.0), out=depth)
    return rgb, depth.astype(np.uint16)


def scene_at(scenario: Scenario, t: float) -> list[tuple[Shape, str]]:
    """The scenario's obstacles at time ``t`` as ``(shape, color)`` pairs for :func:`render`;
    a compound obstacle contributes each of its parts, all in its colour."""
    return [(p, o.color) for o in scenario.obstacles for p in o.parts_at(t)]


def render_settings_kwargs(settings: RenderSettings, rng: np.random.Generator) -> dict:
    """Keyword arguments of :func:`render` for a settings section and a noise generator."""
    return {
        "depth_noise_std_m": settings.depth_noise_std_m,
        "dropout": settings.dropout,
        "background_depth_m": settings.background_depth_m,
        "rng": rng,
    }
