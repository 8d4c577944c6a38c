"""``damon-ros ablation``: what the learned manifold contributes, on the same vertices.

The shipped graph's vertices are rewired three ways — (a) latent kNN within each obstacle
node's subgraph only (the paper), (b) joint-space kNN only (a plain roadmap over the same
configurations), (c) both (shipped) — each pruned of self-colliding edges like the
shipped one, and each runs the same scenarios in closed loop (public and freshly
generated). The table goes to stdout and, with ``--page``, into docs/BENCHMARKS.md between
``<!-- ablation -->`` markers (the rest of the page is left as it is).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from damon_ros.tools.report import write_marked

VARIANTS = {
    "latent kNN only (paper)": {"k_joint": 0},
    "joint-space kNN only (roadmap)": {"k_latent": 0},
    "both (shipped)": {},
}
GRAPH_ONLY = {"fallback_budget_s": 0.0}
"""The planner's RRT-Connect fallback is off here: the question is what each graph finds."""


def rewired(graph, config, workers: int, progress: bool):
    """A copy of ``graph`` with its edges rebuilt under ``config`` and pruned."""
    from damon_ros.learning.graph import LatentGraph, wire_edges
    from damon_ros.learning.graph_builder import prune_self_colliding_edges

    indptr, indices, weights = wire_edges(graph.z, graph.q, graph.node, graph.safe,
                                          len(graph.nodes), config)
    copy = LatentGraph(z=graph.z, q=graph.q, node=graph.node, distance=graph.distance,
                       safe=graph.safe, nodes=graph.nodes, indptr=indptr, indices=indices,
                       weights=weights, origin=graph.origin)
    prune_self_colliding_edges(copy, workers, progress)
    return copy


def table(records: list[dict], stats: dict[str, dict]) -> list[str]:
    lines = ["| edges | set | runs | success | contacts | plan ms p50 | re-plan ms p50 | "
             "T p50 (s) | path p50 (rad) | graph edges | largest component |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for variant in VARIANTS:
        for subset in ("public", "generated"):
            rs = [r for r in records if r["variant"] == variant and r["set"] == subset]
            if not rs:
                continue
            ok = [r for r in rs if r["success"]]
            replan = [x for r in rs for x in r["replan_latency_ms"]]
            lines.append(
                f"| {variant} | {subset} | {len(rs)} | {100 * len(ok) / len(rs):.1f} % | "
                f"{sum(bool(r['collided']) for r in rs)} | "
                f"{_median([1e3 * r['planning_time_s'] for r in rs])} | {_median(replan)} | "
                f"{_median([r['total_time_s'] for r in ok])} | "
                f"{_median([r['path_length_rad'] for r in ok])} | "
                f"{stats[variant]['edges']:,} | "
                f"{100 * stats[variant]['largest_component_share']:.1f} % |")
    return lines


def vae_study(data_dir: str, sizes: list[int], rows: int, epochs: int, seed: int,
              progress: bool) -> list[dict]:
    """The shipped architecture and loss at several latent sizes, same rows and seed:
    held-out reconstruction per input group and how well z alone separates the flag."""
    from damon_ros.learning.vae import Architecture
    from damon_ros.learning.vae_training import load_training_rows, train_vae

    x, _ = load_training_rows(data_dir, rows, seed)
    out = []
    for k in sizes:
        _, metrics = train_vae(x, epochs, seed=seed, architecture=Architecture(latent=k),
                               threads=1, progress=progress)
        out.append({"latent": k, **{m: metrics[m] for m in (
            "joint_rmse_rad", "point_rmse_m", "flag_accuracy", "latent_auc_knn",
            "latent_auc_poly3", "train_seconds", "train_rows")}})
    return out


def vae_table(rows: list[dict], epochs: int) -> list[str]:
    lines = [f"| latent size | joint RMSE (rad) | obstacle point RMSE (m) | flag accuracy | "
             f"flag AUC from z (kNN) | flag AUC from z (cubic) | train rows, {epochs} epochs |",
             "|---|---|---|---|---|---|---|"]
    lines += [f"| {r['latent']} | {r['joint_rmse_rad']:.3f} | {r['point_rmse_m']:.3f} | "
              f"{r['flag_accuracy']:.3f} | {r['latent_auc_knn']:.3f} | "
              f"{r['latent_auc_poly3']:.3f} | {r['train_rows']:,} |" for r in rows]
    return lines


def _median(values) -> str:
    values = [v for v in values if v is not None and np.isfinite(v)]
    return f"{np.median(values):.2f}" if values else "–"


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="damon-ros ablation", description=__doc__.split(
        "\n")[0].split(": ", 1)[1])
    parser.add_argument("--model", default=None, help="model directory (default: shipped)")
    parser.add_argument("--scenarios", nargs="*", default=None,
                        help="public scenario files or folders (default: the public set)")
    parser.add_argument("--generated", type=int, default=10,
                        help="freshly generated scenarios per family (0 = none)")
    parser.add_argument("--generated-seed", type=int, default=21)
    parser.add_argument("--out", default="ablation.jsonl", help="JSON lines, one per run")
    parser.add_argument("--page", default=None, help="markdown page to put the table in")
    parser.add_argument("--vae-data", default=None,
                        help="a collected data set: also train the VAE at --latent-sizes")
    parser.add_argument("--latent-sizes", default="2,3,4")
    parser.add_argument("--vae-rows", type=int, default=200000)
    parser.add_argument("--vae-epochs", type=int, default=4)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quiet", action="store_true")
    return parser


def main(argv: list[str] | None = None) -> int:
    from tqdm import tqdm

    from damon_ros.core.resources import public_scenarios_dir
    from damon_ros.core.robot import Robot
    from damon_ros.core.scenario import ScenarioError, load_scenario, scenario_files
    from damon_ros.learning.bundle import DamonModel, ModelError
    from damon_ros.learning.engines import LocalEngine, Work
    from damon_ros.learning.graph import GraphBuildConfig
    from damon_ros.simulation.graph_tasks import run_job, setup
    from damon_ros.simulation.scenario_generation import ScenarioGenerator, write_scenarios

    args = _parser().parse_args(argv)
    t0, progress = time.perf_counter(), not args.quiet
    try:
        model = DamonModel.load(args.model)
        public = scenario_files(args.scenarios or [public_scenarios_dir()])
        for f in public:
            load_scenario(f)
        engine = LocalEngine(args.workers)
    except (ModelError, ScenarioError, ValueError) as exc:
        print(f"damon-ros ablation: {exc}", file=sys.stderr)
        return 2
    shipped = GraphBuildConfig(**model.meta.get("graph_config", {}))
    with tempfile.TemporaryDirectory(prefix="damon_ablation_") as tmp:
        generated = write_scenarios(ScenarioGenerator(Robot("mesh")), Path(tmp) / "generated",
                                    "ABCDEFG", 7 * args.generated, args.generated_seed)[0] \
            if args.generated else []
        graphs, stats, jobs = {}, {}, []
        for i, (variant, change) in enumerate(VARIANTS.items()):
            graph = rewired(model.graph, dataclasses.replace(shipped, **change), args.workers,
                            progress)
            graphs[variant] = str(Path(tmp) / f"graph_{i}.npz")
            graph.save(graphs[variant])
            stats[variant] = {"edges": graph.n_edges, **graph.connectivity()}
            jobs += [{"variant": variant, "set": subset, "graph": graphs[variant],
                      "scenario": str(f), "seed": args.seed, "planner": GRAPH_ONLY}
                     for subset, files in (("public", public), ("generated", generated))
                     for f in files]
        results = list(tqdm(engine.map(Work(setup, (), run_job), jobs), total=len(jobs),
                            unit="run", desc="closed-loop runs", disable=not progress))
    with open(args.out, "w") as f:
        f.writelines(json.dumps({k: v for k, v in r.items() if k != "graph"}) + "\n"
                     for r in results)
    command = "damon-ros ablation " + " ".join(argv if argv is not None else sys.argv[2:])
    lines = ["## What the learned manifold contributes (same vertices, three edge rules)", "",
             f"`{command}`", "", *table(results, stats), "",
             f"{model.graph.n_vertices:,} vertices of the shipped model; each variant pruned "
             "of self-colliding edges; the graph alone (the RRT-Connect fallback off); "
             "closed loop, ideal perception; public scenarios and "
             f"{len(generated)} generated ones (seed {args.generated_seed})."]
    if args.vae_data:
        sizes = [int(k) for k in args.latent_sizes.split(",") if k.strip()]
        study = vae_study(args.vae_data, sizes, args.vae_rows, args.vae_epochs, args.seed,
                          progress)
        lines += ["", "### The VAE at other latent sizes (same rows, loss and seed)", "",
                  *vae_table(study, args.vae_epochs), "",
                  "Held-out rows; the flag AUCs ask how well a classifier on z alone (k = 25 "
                  "nearest latent neighbours, or a cubic logistic boundary) tells colliding "
                  "from free samples — what a latent kNN graph relies on."]
    print("\n".join(lines))
    if args.page:
        write_marked(Path(args.page), "ablation", lines)
        print(f"table written to {args.page}")
    print(f"{len(results)} runs in {time.perf_counter() - t0:.0f} s; runs in {args.out}")
    return 0
