"""``damon-ros analyze``: module 3 of the paper as a tool — GMR runtime model and the N sweep.

For each graph size N it builds the graph from the same data and VAE, runs every given
scenario in closed loop, and compares what happened with what the GMR predicts:

- rerouting probability: measured = share of route steps (initial plan + re-routes) that
  had to be re-routed; predicted = 1 − Π(1 − p_i) over the waypoints of the initial route,
  p_i = P(d ≤ λ | z_i) from the GMR at each waypoint's latent point;
- task time T: measured = simulated total time; predicted = Σ t_p/(1 − p_i) + t_r,i with
  t_p the measured mean planning time at that N and t_r,i each segment's motion time.

N* is the N with the lowest mean measured T. Tables are printed; the paper's plots are
written as PNG files (latent manifold coloured by flag, graph with a routed path, rerouting
probability and T against N predicted vs measured, reliability curve of p(collision)).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from damon_ros.learning.graph import GraphBuildConfig


def _route_prediction(model_gmr, codec, robot, result, scene_now, t_plan: float):
    """(predicted rerouting probability, predicted T) of a planned route."""
    from damon_ros.learning.gmr import predicted_runtime

    path = result.path
    rows = []
    for q in path:
        c = robot.clearance(q, scene_now) if scene_now else None
        point = c.obstacle_point if c is not None else np.zeros(3)
        rows.append(np.concatenate([q, point, [0.0]]))
    p = model_gmr.collision_probability(codec.encode(np.array(rows)))
    seg_times = np.diff([0.0] + _segment_ends(result.trajectory, path))
    p_steps = p[1:] if len(p) > 1 else p
    return 1.0 - float(np.prod(1.0 - p_steps)), predicted_runtime(p_steps, t_plan, seg_times)


def _segment_ends(trajectory, path: np.ndarray) -> list[float]:
    """Times at which the trajectory passes each waypoint after the first."""
    ends = []
    for q in path[1:]:
        d = np.max(np.abs(trajectory.positions - q), axis=1)
        ends.append(float(trajectory.times[int(np.argmin(d))]))
    return ends


def sweep(data, data_meta, codec, gmr_components: int, margin: float, sizes: list[int],
          scenarios, grid: int, workers: int, seed: int, progress: bool) -> list[dict]:
    from damon_ros.core.robot import Robot
    from damon_ros.learning.gmr import CollisionGMR
    from damon_ros.learning.graph_builder import build_model_graph
    from damon_ros.planning.graph_planner import GraphPlanner
    from damon_ros.planning.reactive import ReactivePlanner
    from damon_ros.simulation.closed_loop import SimConfig, run_scenario

    fast, mesh = Robot("fast"), Robot("mesh")
    rows = []
    for n in sizes:
        config = GraphBuildConfig(n_vertices=n, grid_size=grid, seed=seed)
        graph, stats = build_model_graph(data, data_meta, codec, config, workers, progress)
        keep = graph.distance > -0.5
        gmr = CollisionGMR.fit(graph.z[keep], graph.distance[keep], gmr_components, margin, seed)
        measured_t, predicted_t, measured_r, predicted_r, plan_ms, success = [], [], [], [], [], []
        for scenario in scenarios:
            planner = GraphPlanner(graph, fast, fast.limits)
            planner.warm_up()
            runtime = ReactivePlanner(planner)
            record = run_scenario(scenario, runtime, "damon", mesh, fast, SimConfig(seed=seed))
            success.append(record.success)
            plan_ms.append(record.planning_time_s * 1e3)
            steps = 1 + record.replans
            measured_r.append(record.replans / steps)
            if record.success:
                measured_t.append(record.total_time_s)
            first = GraphPlanner(graph, fast, fast.limits).plan(
                scenario.start, _goal(scenario), scenario.obstacles_at(0.0))
            if first.success:
                r, t = _route_prediction(gmr, codec, fast, first, scenario.obstacles_at(0.0),
                                         record.planning_time_s)
                predicted_r.append(r)
                predicted_t.append(t)
        rows.append({
            "N": n, "vertices": graph.n_vertices, "edges": graph.n_edges,
            "success": float(np.mean(success)),
            "reroute_measured": float(np.mean(measured_r)),
            "reroute_predicted": float(np.mean(predicted_r)) if predicted_r else float("nan"),
            "T_measured": float(np.mean(measured_t)) if measured_t else float("nan"),
            "T_predicted": float(np.mean(predicted_t)) if predicted_t else float("nan"),
            "plan_ms_median": float(np.median(plan_ms)),
            "largest_component_share": stats["largest_component_share"],
        })
        if progress:
            print(json.dumps(rows[-1]), file=sys.stderr)
    return rows


def _goal(scenario):
    from damon_ros.planning.graph_planner import PoseGoal

    g = scenario.goal
    return PoseGoal(g.position, g.orientation, g.position_tolerance, g.orientation_tolerance)


def print_table(rows: list[dict]) -> None:
    header = ("N", "vertices", "success", "reroute meas.", "reroute pred.", "T meas. (s)",
              "T pred. (s)", "plan ms p50")
    print(" | ".join(header))
    for r in rows:
        print(" | ".join([f"{r['N']}", f"{r['vertices']}", f"{100 * r['success']:.0f} %",
                          f"{r['reroute_measured']:.3f}", f"{r['reroute_predicted']:.3f}",
                          f"{r['T_measured']:.2f}", f"{r['T_predicted']:.2f}",
                          f"{r['plan_ms_median']:.1f}"]))


def plots(out: Path, codec, data, rows: list[dict], graph, gmr, margin: float) -> list[Path]:
    """The paper's figures, from this project's own data."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from damon_ros.learning.gmr import reliability
    from damon_ros.learning.vae_training import rows_from

    out.mkdir(parents=True, exist_ok=True)
    files = []
    rng = np.random.default_rng(0)
    idx = rng.choice(len(data["q"]), size=min(20000, len(data["q"])), replace=False)
    x = rows_from({k: v[idx] for k, v in data.items()})
    z = codec.encode(x)
    fig, ax = plt.subplots(figsize=(6, 5))
    flag = x[:, 10] > 0.5
    ax.scatter(z[~flag, 0], z[~flag, 1], s=1, c="tab:blue", label="collision-free")
    ax.scatter(z[flag, 0], z[flag, 1], s=1, c="tab:red", label="collision")
    ax.set(xlabel="z1", ylabel="z2", title="Latent manifold coloured by collision flag")
    ax.legend(markerscale=8)
    files.append(out / "latent_manifold.png")
    fig.savefig(files[-1], dpi=120)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(6, 5))
    safe = graph.safe
    ax.scatter(graph.z[safe, 0], graph.z[safe, 1], s=1, c="0.7", label="safe vertices")
    ax.scatter(graph.z[~safe, 0], graph.z[~safe, 1], s=1, c="tab:red", label="colliding")
    from scipy.sparse.csgraph import dijkstra

    source = int(np.flatnonzero(safe)[0])
    dist, pred = dijkstra(graph.adjacency(), indices=source, return_predecessors=True)
    target = int(np.argmax(np.where(np.isfinite(dist), dist, -1)))
    route = [target]
    while route[-1] != source and pred[route[-1]] >= 0:
        route.append(int(pred[route[-1]]))
    ax.plot(graph.z[route, 0], graph.z[route, 1], "g-", lw=1.5, label="Dijkstra route")
    ax.set(xlabel="z1", ylabel="z2", title="Latent graph with a routed path")
    ax.legend(markerscale=8)
    files.append(out / "graph_route.png")
    fig.savefig(files[-1], dpi=120)
    plt.close(fig)

    if rows:
        n = [r["N"] for r in rows]
        fig, axes = plt.subplots(1, 2, figsize=(10, 4))
        axes[0].plot(n, [r["reroute_measured"] for r in rows], "o-", label="measured")
        axes[0].plot(n, [r["reroute_predicted"] for r in rows], "s--", label="predicted (GMR)")
        axes[0].set(xscale="log", xlabel="graph size N", ylabel="rerouting probability")
        axes[1].plot(n, [r["T_measured"] for r in rows], "o-", label="measured")
        axes[1].plot(n, [r["T_predicted"] for r in rows], "s--", label="predicted (GMR)")
        axes[1].set(xscale="log", xlabel="graph size N", ylabel="task time T (s)")
        for a in axes:
            a.legend()
        files.append(out / "sweep.png")
        fig.tight_layout()
        fig.savefig(files[-1], dpi=120)
        plt.close(fig)

    p = gmr.collision_probability(z)
    near = data["distance"][idx] <= margin
    table, error = reliability(p, near)
    print(f"p(collision) calibration on {len(p)} samples: mean |predicted - observed| per "
          f"bin {error:.3f}")
    fig, ax = plt.subplots(figsize=(5, 5))
    ax.plot([0, 1], [0, 1], "k:", label="perfect")
    ax.plot(table[:, 0], table[:, 1], "o-", label=f"GMR (mean abs. error {error:.3f})")
    ax.set(xlabel="predicted P(d ≤ λ | z)", ylabel="observed frequency",
           title="Reliability of p(collision)")
    ax.legend()
    files.append(out / "reliability.png")
    fig.savefig(files[-1], dpi=120)
    plt.close(fig)
    return files


def main(argv: list[str] | None = None) -> int:
    from damon_ros.core.resources import public_scenarios_dir
    from damon_ros.core.scenario import ScenarioError, load_scenario, scenario_files
    from damon_ros.learning.bundle import DamonModel, ModelError
    from damon_ros.learning.dataset import load_dataset

    parser = argparse.ArgumentParser(prog="damon-ros analyze",
                                     description="GMR runtime model and the graph-size sweep.")
    parser.add_argument("--data", required=True, help="directory written by damon-ros collect")
    parser.add_argument("--model", default=None, help="model directory (default: shipped)")
    parser.add_argument("--sizes", default="2000,5000,10000,20000",
                        help="comma-separated graph sizes N to sweep ('' = no sweep)")
    parser.add_argument("--scenarios", nargs="*", default=None,
                        help="scenario files or folders (default: the public scenarios)")
    parser.add_argument("--grid", type=int, default=GraphBuildConfig.grid_size)
    parser.add_argument("--out", default="analysis", help="folder for plots and results.json")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quiet", action="store_true")
    args = parser.parse_args(argv)
    try:
        model = DamonModel.load(args.model)
        data, data_meta = load_dataset(args.data)
        scenarios = [load_scenario(f) for f in scenario_files(
            args.scenarios or [public_scenarios_dir()])]
    except (ModelError, ValueError, ScenarioError) as exc:
        print(f"damon-ros analyze: {exc}", file=sys.stderr)
        return 2
    sizes = [int(s) for s in args.sizes.split(",") if s.strip()]
    t0 = time.perf_counter()
    components = int(model.meta.get("gmr", {}).get("components", 8))
    rows = sweep(data, data_meta, model.vae, components, model.margin, sizes, scenarios,
                 args.grid, args.workers, args.seed, not args.quiet) if sizes else []
    out = Path(args.out)
    files = plots(out, model.vae, data, rows, model.graph, model.gmr, model.margin)
    # N*: the lowest mean measured T among the sizes with the best success rate (a size that
    # fails runs is not made attractive by the T of the runs it did finish)
    top = max((r["success"] for r in rows), default=0.0)
    best = min((r for r in rows if r["success"] == top and np.isfinite(r["T_measured"])),
               key=lambda r: r["T_measured"], default=None)
    (out / "results.json").write_text(json.dumps({"sweep": rows, "n_star": best and best["N"]},
                                                 indent=1) + "\n")
    if rows:
        print_table(rows)
        print(f"N* = {best['N'] if best else 'none'} (lowest mean measured T at the best "
              "success rate)")
    print(f"plots: {', '.join(str(f) for f in files)} ({time.perf_counter() - t0:.0f} s)")
    return 0
