"""``damon-ros analyze``: module 3 of the paper as a tool — the runtime model and the N sweep.

For each graph size N it builds the graph from the same data and VAE and runs generated
tasks (``damon-ros scenarios``' families, a seed of their own) in closed loop on an engine
(local processes or Ray). Two disjoint task sets are used:

- **fit tasks** fit what the model needs from the scenes the planner meets: the GMR
  p(d ≤ λ | z) on every planned waypoint (its clearance to the obstacles as they move until
  the arm has passed it, :func:`runtime_model.threat_distances`), and the runtime model's
  κ, t_0, c_r (:class:`runtime_model.RuntimeModel`), with t_p measured per size;
- **validation tasks** (≥ 100 per size by default) are predicted from their first planned
  route *before* they run, then run: T and the re-route probability, predicted vs measured,
  and the expected calibration error of p(collision) on their waypoints (held-out vertices).

N* is picked twice — by the lowest predicted T and by the lowest measured T (at the best
measured success). Tables are printed; the paper's plots are written as PNG files.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from damon_ros.learning.graph import GraphBuildConfig

THREAT_CLIP_M = 0.15
THREAT_FLOOR_M = 0.001
STEP_S = 0.25  # s of planned motion between the steps of a route
GMR_COMPONENTS = (1, 2, 4, 8)  # chosen by held-out log-loss on the fit tasks


# ---- one task, on a worker ----------------------------------------------------------
def _task_run(state, job: dict) -> dict:
    """Plan the task's first route (the prediction's input), then run it in closed loop."""
    from damon_ros.core.scenario import load_scenario
    from damon_ros.learning.runtime_model import threat_distances
    from damon_ros.planning.reactive import RuntimeConfig
    from damon_ros.simulation.closed_loop import pose_goal

    scenario = load_scenario(job["scenario"])
    record = state.run(job["graph"], scenario, job["seed"])
    out = {k: job[k] for k in ("size", "split", "scenario")}
    out.update(success=bool(record.success), T=record.total_time_s, replans=record.replans,
               plan_s=record.planning_time_s, planned=False)
    scene, fast = scenario.obstacles_at(0.0), state.fast
    # the prediction's own plan: not timed, so not warmed up again
    first = state.planner(job["graph"], warm=False).plan(scenario.start, pose_goal(scenario),
                                                         scene)
    if not first.success or first.trajectory is None:
        return out
    steps, passed = _route_steps(first.trajectory, record.planning_time_s)
    points = [fast.clearance(q, scene).obstacle_point if scene else np.zeros(3) for q in steps]
    threat = threat_distances(lambda Q, t: fast.distances(Q, scenario.obstacles_at(t)),
                              steps, passed, RuntimeConfig().prediction_horizon_s)
    out.update(planned=True, duration=float(first.trajectory.times[-1]),
               rows=[[*q, *p, 0.0] for q, p in zip(steps.tolist(), points, strict=True)],
               threat=threat.tolist())
    return out


def _route_steps(trajectory, start_s: float) -> tuple[np.ndarray, np.ndarray]:
    """The route's steps: its configurations every STEP_S of planned motion after the start
    (a shortcut route has only a few waypoints, and an obstacle can cross between them),
    with the times the arm passes them (the first plan starts after ``start_s``)."""
    times = np.append(np.arange(STEP_S, trajectory.duration, STEP_S), trajectory.duration)
    return np.array([trajectory.sample(float(t))[0] for t in times]), start_s + times


# ---- the driver ---------------------------------------------------------------------
def generate_tasks(out: Path, families: str, count: int, seed: int) -> list[Path]:
    """``count`` generated task files spread over ``families`` (kept if already there)."""
    from damon_ros.core.robot import Robot
    from damon_ros.simulation.scenario_generation import ScenarioGenerator, write_scenarios

    return write_scenarios(ScenarioGenerator(Robot("mesh")), out, families, count, seed)[0]


def run_tasks(engine, graphs: dict[int, str], fit: list[Path], validate: list[Path],
              seed: int, progress: bool) -> list[dict]:
    """Every task at every size on ``engine``; results in arrival order."""
    from tqdm import tqdm

    from damon_ros.learning.engines import Work
    from damon_ros.simulation.graph_tasks import setup

    jobs = [{"size": n, "graph": graphs[n], "split": split, "scenario": str(f), "seed": seed}
            for n in graphs for split, files in (("fit", fit), ("validate", validate))
            for f in files]
    work = Work(setup, (), _task_run)
    return list(tqdm(engine.map(work, jobs), total=len(jobs), desc="closed-loop tasks",
                     unit="task", disable=not progress))


def _split_fit(fit: list[dict], seed: int) -> tuple[list[dict], list[dict]]:
    order = np.random.default_rng(seed).permutation(len(fit))
    half = len(fit) // 2
    return [fit[i] for i in order[:half]], [fit[i] for i in order[half:]]


def _stack(tasks: list[dict], codec) -> tuple[np.ndarray, np.ndarray]:
    z = codec.encode(np.concatenate([np.array(r["rows"]) for r in tasks]))
    return z, np.concatenate([r["threat"] for r in tasks])


def threat_feature(d: np.ndarray) -> np.ndarray:
    """What the GMR models: log clearance, clipped to [THREAT_FLOOR_M, THREAT_CLIP_M]. Routes
    are certified at λ, so their steps crowd just above it (5th percentile 16 mm for
    λ = 10 mm); in metres a Gaussian mixture smears that crowd across λ and predicted
    P(d ≤ λ) ≈ 0.05 where 0.003 happened; in log space the crowd is resolved. Beyond the
    clip only "far" matters."""
    return np.log(np.clip(d, THREAT_FLOOR_M, THREAT_CLIP_M))


def fit_gmr(fit: list[dict], codec, margin: float, seed: int):
    """The GMR of :func:`threat_feature` given z on the fit tasks' steps (evaluated at
    log λ), its component count chosen by the log-loss of the event d ≤ λ on half of the
    fit tasks held out from a fit on the other half."""
    from damon_ros.learning.gmr import CollisionGMR
    from damon_ros.learning.runtime_model import log_loss

    a, b = _split_fit(fit, seed)
    za, da = _stack(a, codec)
    zb, db = _stack(b, codec)
    level = float(np.log(margin))
    scores = {k: log_loss(CollisionGMR.fit(za, threat_feature(da), k, level, seed)
                          .collision_probability(zb), db <= margin)
              for k in GMR_COMPONENTS if k <= len(za) // 10}
    best = min(scores, key=scores.get) if scores else 1
    z, d = _stack(fit, codec)
    return CollisionGMR.fit(z, threat_feature(d), best, level, seed), best


def fit_models(results: list[dict], codec, margin: float, seed: int):
    """(GMR, its component count, route calibration, runtime model, t_p per size), all from
    the fit tasks."""
    from damon_ros.learning.runtime_model import (
        RouteCalibration,
        RuntimeModel,
        expected_reroutes,
        route_risk,
    )

    fit = [r for r in results if r["split"] == "fit" and r["planned"]]
    if len(fit) < 4:
        raise ValueError(f"only {len(fit)} fit tasks could be planned: too few to fit on")
    gmr, components = fit_gmr(fit, codec, margin, seed)
    for r in fit:
        r["risk"] = route_risk(gmr.collision_probability(codec.encode(np.array(r["rows"]))))
    calibration = RouteCalibration.fit([r["risk"] for r in fit], [r["replans"] > 0 for r in fit])
    t_plan = {n: float(np.mean([r["plan_s"] for r in results
                                if r["split"] == "fit" and r["size"] == n]))
              for n in {r["size"] for r in results}}
    ok = [r for r in fit if r["success"]]
    model = RuntimeModel.fit([t_plan[r["size"]] for r in ok], [r["duration"] for r in ok],
                             [expected_reroutes(calibration(r["risk"])) for r in ok],
                             [r["T"] for r in ok])
    return gmr, components, calibration, model, t_plan


def sweep_rows(results: list[dict], codec, gmr, calibration, model,
               t_plan: dict[int, float], graph_stats: dict[int, dict], margin: float):
    """Per size: measured vs predicted on the validation tasks; and the calibration error
    of p(collision) on all their steps (held-out vertices)."""
    from damon_ros.learning.gmr import reliability
    from damon_ros.learning.runtime_model import expected_reroutes, route_risk

    rows, p_all, hit_all = [], [], []
    for n in sorted(t_plan):
        tasks = [r for r in results if r["split"] == "validate" and r["size"] == n]
        planned = [r for r in tasks if r["planned"]]
        for r in planned:
            p = gmr.collision_probability(codec.encode(np.array(r["rows"])))
            r["reroute_p"] = calibration(route_risk(p))
            p_all.append(p)
            hit_all.append(np.array(r["threat"]) <= margin)
        done = [r for r in planned if r["success"]]
        t_pred = [model.predict(t_plan[n], r["duration"], expected_reroutes(r["reroute_p"]))
                  for r in done]
        rows.append({
            "N": n, **graph_stats[n], "tasks": len(tasks),
            "success": float(np.mean([r["success"] for r in tasks])) if tasks else math.nan,
            "reroute_measured": _mean([r["replans"] > 0 for r in planned]),
            "reroute_predicted": _mean([r["reroute_p"] for r in planned]),
            "T_measured": _mean([r["T"] for r in done]),
            "T_predicted": _mean(t_pred),
            "t_plan_ms": 1e3 * t_plan[n],
            "plan_ms_median": float(np.median([1e3 * r["plan_s"] for r in tasks])),
        })
    p_all = np.concatenate(p_all) if p_all else np.zeros(0)
    hit_all = np.concatenate(hit_all) if hit_all else np.zeros(0, bool)
    error = reliability(p_all, hit_all)[1] if len(p_all) else math.nan
    return rows, error, (p_all, hit_all)


def _mean(values) -> float:
    return float(np.mean(values)) if len(values) else math.nan


def print_table(rows: list[dict]) -> None:
    header = ("N", "vertices", "tasks", "success", "reroute meas.", "reroute pred.",
              "T meas. (s)", "T pred. (s)", "T error", "plan ms p50")
    print(" | ".join(header))
    for r in rows:
        err = abs(r["T_predicted"] - r["T_measured"]) / r["T_measured"]
        print(" | ".join([f"{r['N']}", f"{r['vertices']}", f"{r['tasks']}",
                          f"{100 * r['success']:.0f} %",
                          f"{r['reroute_measured']:.3f}", f"{r['reroute_predicted']:.3f}",
                          f"{r['T_measured']:.2f}", f"{r['T_predicted']:.2f}",
                          f"{100 * err:.1f} %", f"{r['plan_ms_median']:.1f}"]))


def plots(out: Path, codec, data, rows: list[dict], graph, calibration) -> list[Path]:
    """The paper's figures, from this project's own data; ``calibration`` is the
    (prediction, outcome) pairs of the reliability curve."""
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
        axes[0].set_ylim(0.0, 1.0)
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

    table, error = reliability(*calibration)
    fig, ax = plt.subplots(figsize=(5, 5))
    ax.plot([0, 1], [0, 1], "k:", label="perfect")
    ax.plot(table[:, 0], table[:, 1], "o-", label=f"GMR (calibration error {error:.3f})")
    ax.set(xlabel="predicted P(d ≤ λ | z)", ylabel="observed frequency",
           title="Reliability of p(collision), held-out task waypoints")
    ax.legend()
    files.append(out / "reliability.png")
    fig.savefig(files[-1], dpi=120)
    plt.close(fig)
    return files


def _sample_calibration(data, codec, gmr, margin: float) -> float:
    """The shipped GMR (fitted on graph vertices against point obstacles) judged on 20,000
    collection samples: how well it describes the data it was built from."""
    from damon_ros.learning.gmr import reliability
    from damon_ros.learning.vae_training import rows_from

    rng = np.random.default_rng(1)
    idx = rng.choice(len(data["q"]), size=min(20000, len(data["q"])), replace=False)
    z = codec.encode(rows_from({k: v[idx] for k, v in data.items()}))
    return reliability(gmr.collision_probability(z), data["distance"][idx] <= margin)[1]


def _parser() -> argparse.ArgumentParser:
    from damon_ros.learning.engines import ENGINES
    from damon_ros.simulation.scenario_generation import FAMILIES

    parser = argparse.ArgumentParser(prog="damon-ros analyze",
                                     description="GMR runtime model and the graph-size sweep.")
    parser.add_argument("--data", required=True, help="directory written by damon-ros collect")
    parser.add_argument("--model", default=None, help="model directory (default: shipped)")
    parser.add_argument("--sizes", default="5000,10000,20000,40000",
                        help="comma-separated graph sizes N to sweep")
    parser.add_argument("--tasks", type=int, default=105,
                        help="validation tasks per size (generated, spread over --families)")
    parser.add_argument("--fit-tasks", type=int, default=49,
                        help="fit tasks per size (another seed: never a validation task)")
    parser.add_argument("--families", default="".join(FAMILIES), help="task families")
    parser.add_argument("--task-seed", type=int, default=16,
                        help="validation tasks' seed (fit tasks use seed + 1000)")
    parser.add_argument("--grid", type=int, default=GraphBuildConfig.grid_size)
    parser.add_argument("--out", default="analysis",
                        help="folder for plots, results.json and the task files")
    parser.add_argument("--engine", choices=ENGINES, default="local")
    parser.add_argument("--address", default=None, help="with --engine ray: the cluster")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quiet", action="store_true")
    return parser


def main(argv: list[str] | None = None) -> int:
    from damon_ros.learning.bundle import DamonModel, ModelError
    from damon_ros.learning.dataset import load_dataset
    from damon_ros.learning.engines import EngineError, make_engine
    from damon_ros.learning.graph_builder import build_model_graph
    from damon_ros.planning.graph_planner import PlannerConfig

    args = _parser().parse_args(argv)
    t0, progress = time.perf_counter(), not args.quiet
    try:
        sizes = [int(s) for s in args.sizes.split(",") if s.strip()]
        if not sizes or min(sizes) < 1 or args.tasks < 1 or args.fit_tasks < 3:
            raise ValueError("need sizes >= 1, --tasks >= 1 and --fit-tasks >= 3")
        model = DamonModel.load(args.model)
        data, data_meta = load_dataset(args.data)
        engine = make_engine(args.engine, args.workers, args.address)
    except (ModelError, ValueError) as exc:
        print(f"damon-ros analyze: {exc}", file=sys.stderr)
        return 2
    out = Path(args.out).resolve()
    fit = generate_tasks(out / "tasks" / "fit", args.families, args.fit_tasks,
                         args.task_seed + 1000)
    validate = generate_tasks(out / "tasks" / "validate", args.families, args.tasks,
                              args.task_seed)
    # the event a re-route answers: an obstacle closer than the planner certifies routes
    # (on the same fast model), which only a moving obstacle can bring about
    margin = PlannerConfig().margin
    # graphs and task files are written under --out, and jobs name them: on a cluster of
    # several machines --out must be a folder every node sees (a shared file system)
    graphs, stats = {}, {}
    (out / "graphs").mkdir(parents=True, exist_ok=True)
    for n in sizes:
        config = GraphBuildConfig(n_vertices=n, grid_size=args.grid, seed=args.seed)
        graph, built = build_model_graph(data, data_meta, model.vae, config, args.workers,
                                         progress)
        graphs[n] = str(out / "graphs" / f"graph_{n}.npz")
        graph.save(graphs[n])
        stats[n] = {"vertices": graph.n_vertices, "edges": graph.n_edges,
                    "largest_component_share": built["largest_component_share"]}
    try:
        results = run_tasks(engine, graphs, fit, validate, args.seed, progress)
    except EngineError as exc:
        print(f"damon-ros analyze: {exc}", file=sys.stderr)
        return 1
    with (out / "tasks.jsonl").open("w") as f:  # every run, for a second look
        f.writelines(json.dumps(r) + "\n" for r in results)
    try:
        gmr, components, route, runtime, t_plan = fit_models(results, model.vae, margin,
                                                             args.seed)
    except ValueError as exc:
        print(f"damon-ros analyze: {exc}", file=sys.stderr)
        return 1
    rows, ece, calibration = sweep_rows(results, model.vae, gmr, route, runtime, t_plan,
                                        stats, margin)
    files = plots(out, model.vae, data, rows, model.graph, calibration)
    by_measured = _n_star(rows, "T_measured", by_success=True)
    by_model = _n_star(rows, "T_predicted", by_success=False)
    by_measured_t = _n_star(rows, "T_measured", by_success=False)
    summary = {
        "sweep": rows, "n_star": by_measured, "n_star_predicted": by_model,
        "n_star_measured_T": by_measured_t,
        "calibration_error": ece,
        "calibration_error_samples": _sample_calibration(data, model.vae, model.gmr,
                                                         model.margin),
        "runtime_model": {"kappa": runtime.kappa, "t0_s": runtime.t0,
                          "c_reroute_s": runtime.c_reroute, "t_plan_s": t_plan,
                          "margin_m": margin, "gmr_components": components,
                          "gmr_models": f"log clearance clipped to [{THREAT_FLOOR_M}, "
                                        f"{THREAT_CLIP_M}] m, given z",
                          "route_calibration": {"a": route.a, "b": route.b},
                          "step_s": STEP_S},
        "tasks": {"families": args.families, "validate": len(validate), "fit": len(fit),
                  "task_seed": args.task_seed, "fit_seed": args.task_seed + 1000},
    }
    (out / "results.json").write_text(json.dumps(summary, indent=1) + "\n")
    print_table(rows)
    print(f"runtime model: T = t_p (1 + E) + {runtime.kappa:.3f} D + {runtime.t0:.3f} s "
          f"+ {runtime.c_reroute:.3f} s E  (fitted on {len(fit)} tasks per size)")
    print(f"p(collision) calibration error on held-out task waypoints: {ece:.3f} "
          f"(shipped GMR on collection samples: {summary['calibration_error_samples']:.3f})")
    print(f"N* = {by_model} by the model's T, {by_measured_t} by measured T, {by_measured} "
          "by measured T among the sizes with the best measured success")
    print(f"plots: {', '.join(str(f) for f in files)} ({time.perf_counter() - t0:.0f} s)")
    return 0


def _n_star(rows: list[dict], key: str, by_success: bool) -> int | None:
    """The size with the lowest ``key``; with ``by_success`` only among the sizes with the
    best success (a size that fails tasks is not made attractive by those it finished)."""
    top = max((r["success"] for r in rows), default=0.0)
    pool = [r for r in rows if math.isfinite(r[key]) and (not by_success or r["success"] == top)]
    return min(pool, key=lambda r: r[key])["N"] if pool else None
