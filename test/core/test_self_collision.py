"""The link-box screen before the meshes' self-collision query: it never clears a state the
meshes refuse, and it clears most of the states they pass (else it would only cost time)."""

from __future__ import annotations

import numpy as np

from damon_ros.core.collision import local_vertices
from damon_ros.core.limits import READY
from damon_ros.core.self_collision import SelfCollisionScreen, _box


def test_a_links_box_holds_its_mesh(mesh):
    screen = mesh._self_screen
    for o, obj in enumerate(mesh.mesh_geom.geometryObjects):
        v = np.array([obj.placement.act(p) for p in local_vertices(obj.geometry)])
        local = (v - screen.centres[o]) @ screen.axes[o]
        assert np.all(np.abs(local) <= screen.halves[o] + 1e-9)


def test_a_box_fits_the_principal_axes_of_a_turned_cuboid():
    rng = np.random.default_rng(0)
    corners = np.array([[x, y, z] for x in (-0.2, 0.2) for y in (-0.05, 0.05)
                        for z in (-0.01, 0.01)])
    turn = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    centre, axes, halves = _box(corners @ turn.T + [0.3, -0.1, 0.5])
    assert np.allclose(centre, [0.3, -0.1, 0.5])
    assert np.allclose(np.sort(halves), [0.01, 0.05, 0.2])


def test_the_screen_never_clears_a_state_the_meshes_refuse_and_clears_most_they_pass(mesh):
    rng = np.random.default_rng(3)
    Q = np.vstack([rng.uniform(mesh.limits.lower, mesh.limits.upper, (600, 7)),
                   np.clip(READY + rng.normal(0.0, 0.8, (600, 7)), mesh.limits.lower,
                           mesh.limits.upper)])
    clear = mesh._self_screen.clear(Q)
    touching = np.array([mesh._mesh_self_collision(q) for q in Q])
    assert touching.sum() >= 30  # the sample has self-collisions to miss
    assert not np.any(clear & touching)
    assert clear[~touching].mean() >= 0.7
    # the robot's answers are the meshes' answers
    assert all(mesh.self_collision(q) == t for q, t in zip(Q[:200], touching[:200], strict=True))


def test_the_folded_elbow_is_left_to_the_meshes(mesh):
    folded = np.array([0.0, 0.0, 0.0, -3.0, 0.0, 0.0, 0.0])
    assert not mesh._self_screen.clear(folded[None])[0]
    assert mesh._self_screen.clear(READY[None])[0]
    assert SelfCollisionScreen(mesh.model, mesh.mesh_geom).pairs.shape == (
        len(mesh.mesh_geom.collisionPairs), 2)
