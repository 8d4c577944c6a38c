"""The fast model's point sets are their convex hulls, exactly (compared with coal)."""

from __future__ import annotations

import coal
import numpy as np
import pytest

from damon_ros.core import sphere_kernels
from damon_ros.core.collision import obstacle_geometry, signed_distance
from damon_ros.core.hull import MAX_HULL_VERTICES, few_vertices, hull_faces, hull_signed_many
from damon_ros.core.shapes import Shape


def _coal_signed(p: np.ndarray, shape: Shape) -> float:
    """coal's signed distance from point p to the obstacle (a tiny probe sphere)."""
    geom, tf = obstacle_geometry(shape)
    request = coal.DistanceRequest()
    request.enable_signed_distance = True
    probe = 1e-6
    return coal.distance(coal.Sphere(probe), coal.Transform3s(np.eye(3), p), geom, tf, request,
                         coal.DistanceResult()) + probe


@pytest.mark.parametrize("n", [1, 2, 3, 4, 12, 60])
def test_hull_distance_equals_coal_inside_and_outside(n):
    rng = np.random.default_rng(n)
    points = rng.normal(scale=0.03, size=(n, 3))
    if n == 3:  # flat on purpose
        points[:, 2] = 0.0
    shape = Shape("points", (), np.array([0.4, -0.1, 0.3]), points=points)
    world = shape.position + points
    queries = np.vstack([world.mean(axis=0) + rng.normal(scale=0.01, size=(20, 3)),
                         world.mean(axis=0) + rng.normal(scale=0.1, size=(40, 3))])
    ours = signed_distance(queries, shape)
    theirs = np.array([_coal_signed(q, shape) for q in queries])
    outside = theirs > 1e-6
    assert outside.sum() > 20
    assert np.allclose(ours[outside], theirs[outside], atol=2e-6)
    # inside (only a solid hull has an inside): both negative, depth to the nearest face
    assert np.all(ours[~outside] <= 1e-6)


def test_kernel_is_the_hull_not_its_bounding_sphere():
    """A point above a flat blob (a tracked surface patch): the kernel's distance is the
    hull's, where the blob's bounding sphere is centimetres closer."""
    rng = np.random.default_rng(3)
    points = rng.normal(scale=(0.04, 0.04, 0.002), size=(12, 3))
    shape = Shape("points", (), np.zeros(3), points=points)
    kind, pos, rot, params, hull = sphere_kernels.pack_obstacles((shape,))
    p = points.mean(axis=0) + np.array([0.0, 0.0, 0.05])
    exact = float(hull_signed_many(p[:, None].copy(), hull_faces(points))[0])
    tight = sphere_kernels._signed_tight(p[0], p[1], p[2], kind, pos, rot, params, hull, 0)
    bound = sphere_kernels._signed(p[0], p[1], p[2], kind, pos, rot, params, hull, 0)
    assert tight == pytest.approx(exact, abs=1e-12)
    assert tight == pytest.approx(_coal_signed(p, shape), abs=2e-6)
    assert bound < tight - 0.01  # the bound tests stay conservative


@pytest.mark.parametrize("n", [20, 150, 2000])
def test_few_vertices_contain_the_hull_with_at_most_the_cap(n):
    """A point set's stand-in keeps every point of it inside its hull, with no more than
    `MAX_HULL_VERTICES` vertices (the points themselves when they are that few), and is not
    much larger (a 26-DOP of an ellipsoid: 1.3 times its volume)."""
    from scipy.spatial import ConvexHull

    rng = np.random.default_rng(n)
    d = rng.normal(size=(n, 3))
    points = d / np.linalg.norm(d, axis=1, keepdims=True) * [0.1, 0.05, 0.2] + [0.4, 0.1, 0.3]
    few = few_vertices(points)
    if n <= MAX_HULL_VERTICES:
        assert few is points or np.array_equal(few, points)
        return
    assert len(few) <= MAX_HULL_VERTICES
    hull = ConvexHull(few)
    values = points @ hull.equations[:, :3].T + hull.equations[:, 3]
    assert np.all(values <= 1e-12)
    assert hull.volume < 1.4 * ConvexHull(points).volume
