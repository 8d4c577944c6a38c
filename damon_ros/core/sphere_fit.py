"""Fit a tight sphere set to the Panda's collision meshes that still contains them.

The fast model's spheres must contain the meshes ("fast says free ⇒ meshes say free"), and
every millimetre they bulge beyond the meshes closes passages the meshes leave open. The
old model (``panda_collision.urdf`` grown until it contained the meshes) bulged by up to
3 cm. This module fits a new set, per joint, from the meshes themselves:

- **Excess bound.** For a centre ``c`` inside a convex mesh at depth ``h(c)`` (distance to
  the nearest face: exact for an interior point of a convex polytope, ``-max(A c + b)``),
  the ball ``B(c, h)`` lies inside the mesh, so every point of ``B(c, h + δ)`` is within
  ``δ`` of it: a sphere of radius ``h(c) + δ`` bulges at most ``δ`` beyond the mesh, and
  the fast distance to any obstacle is at most ``δ`` above the mesh distance. On a joint
  carrying several meshes (joint 7: link 7, hand, fingers) the depth is the largest over the
  meshes containing ``c``.
- **Exact containment.** Every hull face is cut into small triangles; a sphere contains a
  triangle when it contains its three vertices (a ball is convex). Requiring every small
  triangle inside one sphere covers the whole surface, not just samples of it, so no
  sampling margin is needed. Interior grid points are required too, so a small obstacle
  wholly inside a link is also seen.
- **Fit.** Candidate centres are an interior grid; a candidate covers the elements within
  ``h(c) + δ``. A greedy set cover picks spheres, then each sphere shrinks to the farthest
  element it alone must cover. ``δ`` is the one knob: :func:`fit_panda` sweeps it and the
  count/excess trade-off is measured, not guessed (``damon-ros bench-robot --margin``).

The result is written as JSON (``config/panda_spheres.json``, no pickle) and loaded by
:class:`damon_ros.core.collision.SphereModel`. No rclpy here.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pinocchio as pin

from damon_ros.core.collision import convex_meshes, link_name, local_vertices
from damon_ros.core.kinematics import load_arm
from damon_ros.core.sphere_set import SphereSet


@dataclass
class _Hull:
    vertices: np.ndarray  # in the joint frame
    equations: np.ndarray  # (F, 4) outward unit normals and offsets: inside ⇔ A x + b ≤ 0
    link: str


def _hulls(model: pin.Model, geom: pin.GeometryModel) -> dict[int, list[_Hull]]:
    from scipy.spatial import ConvexHull

    out: dict[int, list[_Hull]] = {}
    for obj in geom.geometryObjects:
        m = obj.placement
        v = local_vertices(obj.geometry) @ m.rotation.T + m.translation
        hull = ConvexHull(v)
        out.setdefault(obj.parentJoint, []).append(
            _Hull(v[hull.vertices], hull.equations, link_name(model, obj)))
    return out


def _depth(hulls: list[_Hull], P: np.ndarray) -> np.ndarray:
    """Largest depth of points (N, 3) inside any of the hulls (negative: outside all)."""
    return np.max([-(P @ h.equations[:, :3].T + h.equations[:, 3]).max(axis=1) for h in hulls],
                  axis=0)


def _triangles(h: _Hull, step: float) -> np.ndarray:
    """The hull's faces cut into triangles (T, 3, 3) with no edge longer than ``step``."""
    from scipy.spatial import ConvexHull

    tris = h.vertices[ConvexHull(h.vertices).simplices]
    k_of = np.maximum(1, np.ceil(np.linalg.norm(tris - np.roll(tris, 1, axis=1), axis=2)
                                 .max(axis=1) / step)).astype(int)
    out = []
    for k in np.unique(k_of):
        # barycentric (i, j) of the sub-triangles' corners: k² of them, up and down
        ij = [((i, j), (i + 1, j), (i, j + 1)) for i in range(k) for j in range(k - i)]
        ij += [((i + 1, j), (i + 1, j + 1), (i, j + 1)) for i in range(k) for j in range(k - i)
               if i + j + 2 <= k]
        w = np.array(ij, dtype=float) / k  # (k², 3, 2)
        t = tris[k_of == k]
        a, b = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
        out.append((t[:, None, None, 0] + w[None, :, :, :1] * a[:, None, None]
                    + w[None, :, :, 1:] * b[:, None, None]).reshape(-1, 3, 3))
    return np.vstack(out)


def _near_surface(h: _Hull, delta: float) -> np.ndarray:
    """Candidate centres close under the surface, where the grid is too coarse: each hull
    face's centroid moved inward by a few multiples of ``delta``, and each vertex moved
    toward the hull's centre."""
    from scipy.spatial import ConvexHull

    hull = ConvexHull(h.vertices)
    cent = h.vertices[hull.simplices].mean(axis=1)
    n = hull.equations[:, :3]
    out = [cent - d * n for d in (0.5 * delta, delta, 2 * delta, 4 * delta)]
    mid = h.vertices.mean(axis=0)
    u = mid - h.vertices
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    out += [h.vertices + t * u for t in (0.5 * delta, delta, 2 * delta, 4 * delta)]
    P = np.vstack(out)
    return P[_depth([h], P) > 0.0]


def _grid(hulls: list[_Hull], spacing: float) -> np.ndarray:
    v = np.vstack([h.vertices for h in hulls])
    axes = [np.arange(lo + 0.5 * spacing, hi, spacing) for lo, hi in zip(v.min(0), v.max(0),
                                                                          strict=True)]
    P = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    return P[_depth(hulls, P) > 0.0]


def fit_joint(hulls: list[_Hull], delta: float, step: float = 0.02,
              center_spacing: float = 0.008, interior_spacing: float = 0.015,
              slack: float = 1e-4) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """Spheres (centres, radii, bulges, links) for the meshes of one joint, each bulging at
    most ``delta`` beyond them, that contain every surface triangle and interior grid point.
    ``slack`` (m) pads every radius against rounding (the JSON keeps 0.1 µm)."""
    # small parts (the fingers' 4 mm pads) get finer triangles and candidate grids
    ext = [np.ptp(h.vertices, axis=0) for h in hulls]
    tris = np.vstack([_triangles(h, min(step, 0.25 * e.max())) for h, e in zip(hulls, ext,
                                                                               strict=True)])
    inner = _grid(hulls, interior_spacing)
    cand = np.unique(np.vstack([_grid([h], min(center_spacing, e.min() / 3.0))
                                for h, e in zip(hulls, ext, strict=True)]
                               + [_near_surface(h, delta) for h in hulls]), axis=0)
    depth = _depth(hulls, cand)
    # need[c, e]: the radius candidate c needs to contain element e
    points = np.vstack([tris.reshape(-1, 3), inner])
    need = np.empty((len(cand), len(tris) + len(inner)), np.float32)
    for a in range(0, len(cand), 512):  # in chunks: candidates × points is large
        d = np.sqrt(np.maximum((cand[a:a + 512] ** 2).sum(1)[:, None] - 2.0 * cand[a:a + 512]
                               @ points.T + (points ** 2).sum(1), 0.0))
        need[a:a + 512, :len(tris)] = d[:, :3 * len(tris)].reshape(-1, len(tris), 3).max(axis=2)
        need[a:a + 512, len(tris):] = d[:, 3 * len(tris):]
    cover = need <= (depth + delta)[:, None]
    # an element no candidate reaches within delta (a sharp corner between grid points)
    # goes to the candidate that reaches it with the least bulge; the bulge is recorded
    lost = np.flatnonzero(~cover.any(axis=0))
    cover[np.argmin(need[:, lost] - depth[:, None], axis=0), lost] = True
    uncovered = np.ones(need.shape[1], bool)
    chosen: list[int] = []
    while uncovered.any():
        gain = cover[:, uncovered].sum(axis=1)
        # most new elements; ties go to the deepest centre (least bulge after shrinking)
        best = int(np.lexsort((-depth, -gain))[0])
        chosen.append(best)
        uncovered &= ~cover[best]
    # shrink: each element goes to the chosen sphere that needs the least radius for it
    sub = need[chosen]
    sub = np.where(cover[chosen], sub, np.inf)
    owner = sub.argmin(axis=0)
    radii = np.array([sub[i, owner == i].max(initial=0.0) for i in range(len(chosen))]) + slack
    keep = radii > slack
    centers, radii = cand[chosen][keep], radii[keep]
    bulge = radii - depth[chosen][keep]
    links = []
    for c in centers:
        d = [-(c @ h.equations[:, :3].T + h.equations[:, 3]).max() for h in hulls]
        links.append(hulls[int(np.argmax(d))].link)
    return centers, radii, bulge, links


def fit_panda(delta: float, **kwargs) -> SphereSet:
    """The Panda's sphere set for one excess bound ``delta`` (m); see :func:`fit_joint`."""
    model, geom = load_arm("panda.urdf")
    meshes = convex_meshes(model, geom)
    joints, centers, radii, bulges, links = [], [], [], [], []
    for j, hulls in sorted(_hulls(model, meshes).items()):
        c, r, b, n = fit_joint(hulls, delta, **kwargs)
        joints += [j] * len(r)
        centers.append(c)
        radii.append(r)
        bulges.append(b)
        links += n
    return SphereSet(np.array(joints, dtype=np.int64), np.vstack(centers), np.concatenate(radii),
                     tuple(links), delta, np.concatenate(bulges))


def main(argv: list[str] | None = None) -> int:
    """``python -m damon_ros.core.sphere_fit [--delta M ...] [--out FILE]``: sweep the
    excess bound, print the sphere count per value, and write the last one's set."""
    import argparse

    p = argparse.ArgumentParser(description=main.__doc__)
    p.add_argument("--delta", type=float, nargs="+", default=[0.007])
    p.add_argument("--out", type=Path)
    args = p.parse_args(argv)
    s = None
    for d in args.delta:
        s = fit_panda(d)
        per = {j: int(np.sum(s.joints == j)) for j in np.unique(s.joints)}
        print(f"delta {d * 1e3:5.1f} mm: {len(s.radii):3d} spheres {per}; bulge median "
              f"{np.median(s.bulge) * 1e3:.1f} mm, max {s.bulge.max() * 1e3:.1f} mm")
    if args.out and s is not None:
        s.save(args.out)
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
