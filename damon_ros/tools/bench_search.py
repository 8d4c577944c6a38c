"""``damon-ros bench-search``: how long the graph search takes on the shipped graph.

The numbers the re-route budget rests on (issue: whole-graph search ≤ 5 ms, a re-route after
one invalidated edge ≤ 1 ms): the compiled A* over every safe vertex between random safe
vertex pairs; the same search again after one edge of its path is blocked (what each lazy
iteration costs); scipy's compiled Dijkstra over the same graph, as the alternative that
needs no code of ours but has no goal heuristic; and whole routes (`GraphPlanner.plan`) on
the public static scenarios, with their lazy iteration counts.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np


def _ms(fn) -> tuple[float, object]:
    t0 = time.perf_counter()
    out = fn()
    return 1e3 * (time.perf_counter() - t0), out


def _pairs(graph, n: int, rng: np.random.Generator) -> list[tuple[int, int]]:
    safe = np.flatnonzero(graph.safe)
    return [tuple(int(v) for v in rng.choice(safe, 2, replace=False)) for _ in range(n)]


def search_rows(graph, n: int, seed: int) -> list[tuple[str, list[float], str]]:
    """(what, times ms, note) of the raw searches between ``n`` random safe vertex pairs."""
    from scipy.sparse import csgraph

    from damon_ros.planning.graph_search import GraphSearch

    active = graph.safe.copy()
    whole, repaired, dijkstra, lengths = [], [], [], []
    adjacency = graph.adjacency()
    for a, b in _pairs(graph, n, np.random.default_rng(seed)):
        search = GraphSearch(graph.indptr, graph.indices, graph.weights)
        heuristic = np.linalg.norm(graph.q - graph.q[b], axis=1)
        args = (active, heuristic, [(a, 0.0)], {b: 0.0}, math.inf)
        t, path = _ms(lambda args=args, search=search: search.shortest(*args))
        whole.append(t)
        if path is None or len(path) < 5:
            continue
        lengths.append(len(path) - 2)
        middle = len(path) // 2
        search.block(path[middle - 1], path[middle])
        repaired.append(_ms(lambda args=args, search=search: search.shortest(*args))[0])
        dijkstra.append(_ms(lambda a=a: csgraph.dijkstra(adjacency, indices=a, limit=np.inf))[0])
    return [("compiled A*, whole graph", whole,
             f"{graph.n_vertices} vertices, {graph.n_edges} edges; paths median "
             f"{np.median(lengths) if lengths else float('nan'):.0f} vertices"),
            ("compiled A*, again after one path edge blocked", repaired,
             "one lazy iteration"),
            ("scipy csgraph Dijkstra, whole graph", dijkstra, "no heuristic: every vertex")]


def route_rows() -> list[tuple[str, list[float], str]]:
    """Whole static routes (IK excluded) on the public static scenarios."""
    from damon_ros.core.robot import Robot
    from damon_ros.core.scenario import load_public_scenarios
    from damon_ros.learning.bundle import DamonModel
    from damon_ros.planning.graph_planner import GraphPlanner, PlannerConfig
    from damon_ros.simulation.closed_loop import pose_goal

    robot = Robot("fast")
    planner = GraphPlanner(DamonModel.load().graph, robot, robot.limits,
                           PlannerConfig(fallback_budget_s=0.0))
    planner.warm_up()
    times, iterations, solved, total = [], [], 0, 0
    for scenario in load_public_scenarios():
        if scenario.is_dynamic:
            continue
        total += 1
        obstacles = scenario.obstacles_at(0.0)
        result = planner.plan(scenario.start, pose_goal(scenario), obstacles)
        if result.success:
            solved += 1
            times.append(result.timing_ms["search"])
            iterations.append(result.lazy_iterations)
    note = (f"{solved}/{total} public static scenarios by the graph alone; lazy iterations "
            f"median {np.median(iterations) if iterations else float('nan'):.0f}, max "
            f"{max(iterations, default=0)}")
    return [("route with edge checks (graph, no fallback)", times, note)]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="damon-ros bench-search",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=200, help="random vertex pairs")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    if args.pairs < 1:
        parser.error("--pairs must be ≥ 1")
    from damon_ros.learning.bundle import DamonModel

    graph = DamonModel.load().graph
    search_rows(graph, 3, args.seed + 1)  # compile (or load the cached kernel) first
    rows = search_rows(graph, args.pairs, args.seed) + route_rows()
    width = max(len(r[0]) for r in rows)
    print(f"{'search':<{width}}  {'p50 ms':>7}  {'p95 ms':>7}  {'max ms':>7}  note")
    for name, times, note in rows:
        p50, p95, top = (np.percentile(times, [50, 95, 100]) if times else [math.nan] * 3)
        print(f"{name:<{width}}  {p50:>7.3f}  {p95:>7.3f}  {top:>7.3f}  {note}")
    return 0
