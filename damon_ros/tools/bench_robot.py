"""``damon-ros bench-robot``: median µs per robot-model query, and the fast-model margin.

The table holds the numbers the planner's latency budget is built from: FK, IK, one exact
distance, a batch of fast distances and certified segment checks. ``--margin N`` instead
measures, on N random configurations each with a random obstacle near the arm, how far the
un-inflated sphere model's distance can exceed the exact mesh distance — the measurement
behind :data:`damon_ros.core.collision.FAST_MODEL_MARGIN`.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from dataclasses import dataclass

import coal
import numpy as np
import pinocchio as pin

from damon_ros.core.collision import (
    FAST_MODEL_MARGIN,
    SphereModel,
    panda_inflation,
    surface_points,
)
from damon_ros.core.kinematics import load_arm
from damon_ros.core.limits import READY
from damon_ros.core.robot import Robot
from damon_ros.core.scenario import load_public_scenarios
from damon_ros.core.shapes import Shape


def _median_us(fn: Callable[[], object], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e6 * float(np.median(times))


def _cycle(items: list) -> Callable[[], object]:
    """A function returning the items in turn, so repeated calls do not hit one cached case."""
    state = {"i": -1}

    def nxt():
        state["i"] = (state["i"] + 1) % len(items)
        return items[state["i"]]

    return nxt


def measure(repeats: int = 200, seed: int = 0) -> list[tuple[str, float, str]]:
    """(query, median µs, note) rows."""
    rng = np.random.default_rng(seed)
    mesh, fast = Robot("mesh"), Robot("fast")
    lo, hi = fast.limits.lower, fast.limits.upper
    Q = rng.uniform(lo, hi, (1000, 7))
    free = [q for q in Q[:200] if not mesh.self_collision(q)]
    q_next = _cycle(free)
    sphere = Shape("sphere", (0.05,), [0.5, 0.0, 0.4])
    box = Shape("box", (0.1, 0.3, 0.3), [0.5, 0.2, 0.3], [0, 0, 0.2, 0.98])
    far = Shape("sphere", (0.05,), [-0.6, 0.0, 1.2])
    goals = [(fast.tcp_pose(q), fast.limits.clip(q + rng.normal(scale=0.1, size=7)))
             for q in free[:40]]
    warm, cold = _cycle(goals), _cycle(goals)
    seg_a, seg_b = READY.copy(), READY.copy()
    seg_a[0], seg_b[0] = -0.5, 0.5  # a 1 rad edge: 51 states at 0.02 rad
    seg_states = fast.steps(seg_a, seg_b, 0.02) + 1
    fast.segment_free(seg_a, seg_b, [sphere])  # compile the kernels outside the timing

    def ik_warm():
        (p, o), near = warm()
        return fast.ik(p, o, q_near=near)

    def ik_cold():
        (p, o), _ = cold()
        return fast.ik(p, o, q_near=READY, rng=rng)

    few = max(20, repeats // 5)
    edges = _scenario_edges(fast, rng)
    states = np.mean([fast.steps(a, b, 0.02) + 1 for a, b, _ in edges])
    per_state = _median_us(_cycle_call(fast, edges), repeats) / states
    edge_note = f"0.2–1 rad, {states:.0f} states mean, margin 1 cm"
    return [
        ("FK panda_hand_tcp", _median_us(lambda: fast.fk(q_next()), repeats), "pinocchio"),
        ("IK, warm seed (~0.1 rad away)", _median_us(ik_warm, few), "LM, joint limits"),
        ("IK, cold (ready-pose seed, then random)", _median_us(ik_cold, few), "multi-seed"),
        ("clearance, mesh model, 1 sphere", _median_us(
            lambda: mesh.clearance(q_next(), [sphere]), repeats), "coal GJK, witness points"),
        ("clearance, mesh model, 1 box", _median_us(
            lambda: mesh.clearance(q_next(), [box]), repeats), "coal GJK, witness points"),
        ("clearance, fast model, 1 sphere", _median_us(
            lambda: fast.clearance(q_next(), [sphere]), repeats), "spheres, witness points"),
        ("batch distance, fast, per config (1000 × 2 obst.)", _median_us(
            lambda: fast.distances(Q, [sphere, box]), max(10, repeats // 20)) / len(Q), "numba"),
        ("batch distance, mesh, per config (20 × 1 obst.)", _median_us(
            lambda: mesh.distances(Q[:20], [sphere]), max(5, repeats // 40)) / 20, "coal"),
        ("segment_free per state, 2 obst. near (free)", _median_us(
            lambda: fast.segment_free(seg_a, seg_b, [sphere, box], 0.02), repeats) / seg_states,
         f"{seg_states} states, 1 rad edge"),
        ("segment_free per state, 1 obst. far", _median_us(
            lambda: fast.segment_free(seg_a, seg_b, [far], 0.02), repeats) / seg_states,
         f"{seg_states} states, 1 rad edge"),
        ("segment_free per edge, public scenarios (see note)", _median_us(
            _cycle_call(fast, edges), repeats), f"{per_state:.1f} µs/state; {edge_note}"),
        ("self-collision, mesh model", _median_us(
            lambda: mesh.self_collision(q_next()), repeats), "link boxes, then convex GJK"),
        ("self-collision, meshes alone", _median_us(
            lambda: mesh._mesh_self_collision(q_next()), repeats), "SRDF pairs, convex GJK"),
    ]


def _scenario_edges(robot: Robot, rng: np.random.Generator, per_scenario: int = 20):
    """Planner-like work: random straight edges of 0.2–1 rad (max norm) from random
    configurations, against the obstacles of each public scenario at t = 0."""
    edges = []
    for scenario in load_public_scenarios():
        obstacles = scenario.obstacles_at(0.0)
        for _ in range(per_scenario):
            a = rng.uniform(robot.limits.lower, robot.limits.upper)
            step = rng.normal(size=7)
            step *= rng.uniform(0.2, 1.0) / np.max(np.abs(step))
            edges.append((a, robot.limits.clip(a + step), obstacles))
    return edges


def _cycle_call(robot: Robot, edges: list) -> Callable[[], object]:
    nxt = _cycle(edges)

    def check():
        a, b, obstacles = nxt()
        return robot.segment_free(a, b, obstacles, margin=0.01, resolution=0.02)

    return check


@dataclass(frozen=True)
class ModelExcess:
    """How one sphere model's distance relates to the exact mesh distance."""

    excess_max: float  # max(fast - mesh) over the samples where the meshes are apart
    excess_p99: float
    excess_median: float
    max_when_touching: float  # largest fast distance where the meshes touch the obstacle
    bulge_median: float  # mesh - fast where apart: how much the spheres exceed the meshes
    bulge_p99: float
    bulge_max: float

    @property
    def required(self) -> float:
        """Inflation that makes fast ≤ mesh where apart and fast ≤ 0 where touching."""
        return max(self.excess_max, self.max_when_touching, 0.0)


@dataclass(frozen=True)
class MarginReport:
    samples: int
    touching: int  # samples where the meshes touch or penetrate the obstacle
    models: dict[str, ModelExcess]  # each sphere model, without FAST_MODEL_MARGIN
    by_kind: dict[str, dict[str, ModelExcess]]  # the same per obstacle kind
    self_pairs: int  # link pairs (configuration × SRDF-enabled pair) compared for self-collision
    self_models: dict[str, ModelExcess]  # sphere-pair vs mesh-pair distance


def _random_obstacle(rng: np.random.Generator, anchor: np.ndarray, outward: np.ndarray,
                     spread: float) -> Shape:
    """A sphere, box, cylinder or point set of random size and orientation, its surface
    roughly -5 mm to ``spread`` m out from ``anchor`` along a direction scattered about
    ``outward``."""
    direction = outward + 0.4 * rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    gap = rng.uniform(-0.005, spread)
    kind = int(rng.integers(4))
    if kind == 0:
        radius = rng.uniform(0.01, 0.1)
        return Shape("sphere", (radius,), anchor + direction * (radius + gap))
    if kind == 1:
        size = rng.uniform(0.02, 0.2, 3)
        return Shape("box", tuple(size), anchor + direction * (0.5 * float(np.min(size)) + gap),
                     rng.normal(size=4))
    if kind == 2:
        radius, length = rng.uniform(0.01, 0.08), rng.uniform(0.02, 0.3)
        return Shape("cylinder", (radius, length), anchor + direction * (radius + gap),
                     rng.normal(size=4))
    # a small point set (a depth-camera blob) or a single point, nearest point at ~gap
    n = int(rng.choice([1, 4, 12]))
    pts = rng.normal(scale=rng.uniform(0.005, 0.03), size=(n, 3)) if n > 1 else np.zeros((1, 3))
    pts -= pts[np.argmin(pts @ direction)]  # the point nearest the arm sits at the anchor
    return Shape("points", (), anchor + direction * max(gap, 0.0005), points=pts)


def _anchor(robot: Robot, q: np.ndarray, i: int, points: list[np.ndarray],
            rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A random surface point of mesh ``i`` in configuration q and the outward direction
    from the mesh's centre through it (meshes are convex)."""
    pin.updateGeometryPlacements(robot.model, robot.data, robot.mesh_geom, robot.mesh_data, q)
    pts = points[i]
    m = robot.mesh_data.oMg[i]
    p = m.rotation @ pts[rng.integers(len(pts))] + m.translation
    out = p - (m.rotation @ pts.mean(axis=0) + m.translation)
    return p, out / max(float(np.linalg.norm(out)), 1e-9)


def _excess(fast: np.ndarray, mesh: np.ndarray) -> ModelExcess:
    apart = mesh > 0.0
    e = fast[apart] - mesh[apart]
    touching = fast[~apart]
    return ModelExcess(float(e.max()), float(np.percentile(e, 99)), float(np.median(e)),
                       float(touching.max()) if len(touching) else -np.inf,
                       float(np.median(-e)), float(np.percentile(-e, 99)), float((-e).max()))


def sphere_models() -> dict[str, SphereModel]:
    """The sphere models compared, all without :data:`FAST_MODEL_MARGIN`: the URDF's spheres
    as they are, the old model (grown to contain the meshes) and the fitted set (shipped)."""
    model, geom = load_arm("panda_collision.urdf")
    return {"panda_collision.urdf as is": SphereModel(model, geom, 0.0),
            "old: urdf grown to contain": SphereModel(model, geom, 0.0,
                                                      inflation=panda_inflation()),
            "fitted (config/)": SphereModel.fitted(0.0)}


def measure_margin(samples: int = 10_000, seed: int = 7, spread: float = 0.15,
                   self_samples: int = 2_000) -> MarginReport:
    """Compare sphere models with the meshes on random configurations, each with one random
    obstacle near a random surface point of the arm, and (self-collision) on random
    configurations, pair by pair over the link pairs the SRDF leaves enabled."""
    rng = np.random.default_rng(seed)
    mesh = Robot("mesh")
    models = sphere_models()
    points = [surface_points(o.geometry, 0.02) for o in mesh.mesh_geom.geometryObjects]
    d_mesh = np.empty(samples)
    d_fast = {name: np.empty(samples) for name in models}
    kinds = np.empty(samples, dtype=object)
    for n in range(samples):
        q = rng.uniform(mesh.limits.lower, mesh.limits.upper)
        anchor, outward = _anchor(mesh, q, int(rng.integers(len(points))), points, rng)
        obstacles = [_random_obstacle(rng, anchor, outward, spread)]
        kinds[n] = obstacles[0].kind
        d_mesh[n] = mesh.clearance(q, obstacles).distance
        for name, m in models.items():
            d_fast[name][n] = m.distances(q[None], obstacles)[0]
    by_kind = {k: {name: _excess(d[kinds == k], d_mesh[kinds == k]) for name, d in d_fast.items()}
               for k in ("sphere", "box", "cylinder", "points")}
    pairs, self_models = _self_excess(mesh, models, rng, self_samples)
    return MarginReport(samples, int(np.sum(d_mesh <= 0.0)),
                        {name: _excess(d, d_mesh) for name, d in d_fast.items()}, by_kind,
                        pairs, self_models)


def _self_excess(mesh: Robot, models: dict[str, SphereModel], rng: np.random.Generator,
                 samples: int) -> tuple[int, dict[str, ModelExcess]]:
    """Per joint pair (spheres are fixed to joints, and one sphere may cover two meshes of
    one joint, e.g. link 7 and the hand): the sphere model's distance between the two
    joints' spheres against coal's least distance over the SRDF-enabled mesh pairs between
    them, on random configurations."""
    geom = mesh.mesh_geom
    joint = [o.parentJoint for o in geom.geometryObjects]
    pairs = sorted({tuple(sorted((joint[p.first], joint[p.second])))
                    for p in geom.collisionPairs if joint[p.first] != joint[p.second]})
    req = coal.DistanceRequest()
    req.enable_signed_distance = True
    Q = rng.uniform(mesh.limits.lower, mesh.limits.upper, (samples, 7))
    d_mesh = []
    for q in Q:
        pin.updateGeometryPlacements(mesh.model, mesh.data, geom, mesh.mesh_data, q)
        best = dict.fromkeys(pairs, np.inf)
        for p in geom.collisionPairs:
            jp = tuple(sorted((joint[p.first], joint[p.second])))
            if jp not in best:
                continue
            ma, mb = mesh.mesh_data.oMg[p.first], mesh.mesh_data.oMg[p.second]
            d = coal.distance(geom.geometryObjects[p.first].geometry,
                              coal.Transform3s(ma.rotation, ma.translation),
                              geom.geometryObjects[p.second].geometry,
                              coal.Transform3s(mb.rotation, mb.translation), req,
                              coal.DistanceResult())
            best[jp] = min(best[jp], d)
        d_mesh.append([best[jp] for jp in pairs])
    d_mesh = np.array(d_mesh).ravel()
    out = {}
    for name, m in models.items():
        # in chunks of configurations: the fitted model's joint pairs are up to a few
        # hundred spheres each, and (N, Sa, Sb, 3) at once took 4.5 MB per configuration
        d = np.concatenate([_pair_distances(m, Q[k:k + SELF_CHUNK], pairs)
                            for k in range(0, len(Q), SELF_CHUNK)])
        out[name] = _excess(d.ravel(), d_mesh)
    return len(d_mesh), out


SELF_CHUNK = 64
"""Configurations per batch of the sphere models' self-distances."""


def _pair_distances(m: SphereModel, Q: np.ndarray, pairs) -> np.ndarray:
    """(len(Q), len(pairs)): the least distance between the two joints' spheres of each
    pair in each configuration."""
    C = m.world_centers(Q)  # (N, S, 3)
    cols = []
    for ja, jb in pairs:
        ia, ib = np.flatnonzero(m.joints == ja), np.flatnonzero(m.joints == jb)
        d = (np.linalg.norm(C[:, ia, None] - C[:, None, ib], axis=-1)
             - m.radii[ia][:, None] - m.radii[ib][None])
        cols.append(d.min(axis=(1, 2)))
    return np.stack(cols, axis=1)


def _print_excess(name: str, e: ModelExcess) -> None:
    print(f"  {name:<28} {e.bulge_median * 1e3:>7.1f} {e.bulge_p99 * 1e3:>7.1f} "
          f"{e.bulge_max * 1e3:>7.1f} {e.excess_max * 1e3:>+9.1f} "
          f"{e.max_when_touching * 1e3:>+9.1f}")


def _print_margin(r: MarginReport) -> bool:
    print(f"{r.samples} random configurations, one obstacle each (sphere, box, cylinder, point "
          f"set); the meshes touch it in {r.touching}")
    print("  excess = mesh − fast distance where the meshes are apart (how far the spheres")
    print("  reach beyond the meshes); conservative ⇔ max(fast − mesh) ≤ 0 and fast ≤ 0 where")
    print("  the meshes touch. mm:")
    print(f"  {'sphere model':<28} {'median':>7} {'p99':>7} {'max':>7} {'max f−m':>9} "
          f"{'touching':>9}")
    for name, e in r.models.items():
        _print_excess(name, e)
    for kind, per in r.by_kind.items():
        print(f" {kind} obstacles only:")
        for name, e in per.items():
            _print_excess(name, e)
    print(f" self-collision, {r.self_pairs} (configuration, joint pair) samples, sphere pair − "
          "mesh pair distance:")
    for name, e in r.self_models.items():
        _print_excess(name, e)
    fitted = r.models["fitted (config/)"]
    ok = fitted.required <= 0.0 and r.self_models["fitted (config/)"].required <= 0.0
    print(f"fitted set: fast − mesh ≤ {fitted.excess_max * 1e3:.1f} mm where apart, fast ≤ "
          f"{fitted.max_when_touching * 1e3:+.1f} mm where the meshes touch -> "
          f"{'fast free ⇒ meshes free on every sample' if ok else 'NOT conservative'} "
          f"(FAST_MODEL_MARGIN {FAST_MODEL_MARGIN * 1e3:.1f} mm on top)")
    return ok


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="damon-ros bench-robot",
                                     description="Median µs per robot-model query.")
    parser.add_argument("--repeats", type=int, default=200, help="timed calls per query")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--margin", type=int, default=0, metavar="N",
                        help="instead: measure the fast-model margin on N random samples")
    parser.add_argument("--self-samples", type=int, default=2000, metavar="N",
                        help="with --margin: random configurations for the self-collision check")
    args = parser.parse_args(argv)
    if args.repeats < 1 or args.margin < 0:
        parser.error("--repeats must be ≥ 1 and --margin ≥ 0")
    if args.margin:
        return 0 if _print_margin(measure_margin(args.margin, seed=args.seed or 7,
                                                 self_samples=args.self_samples)) else 1
    rows = measure(args.repeats, args.seed)
    width = max(len(r[0]) for r in rows)
    print(f"{'query':<{width}}  {'median µs':>10}  note")
    for name, us, note in rows:
        print(f"{name:<{width}}  {us:>10.1f}  {note}")
    return 0
