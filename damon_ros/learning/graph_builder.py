"""Collected data + trained VAE → the latent graph and the GMR (``damon-ros build-graph``).

Completes a model directory written by ``damon-ros train``: builds the two-layer graph at
the requested density N, removes graph edges along which the exact meshes self-collide
(checked once here, so the planner only checks obstacles on graph edges at run time), fits
the Gaussian-mixture regression of clearance over (z, d) of the vertices, and records
everything with hashes in ``meta.json``.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import time
from pathlib import Path

import numpy as np

from damon_ros.learning.graph import GraphBuildConfig, LatentGraph, build_graph

SELF_CHECK_RESOLUTION = 0.1  # rad between mesh self-collision checks along graph edges
_WORKER: dict = {}


def _mesh():
    if "mesh" not in _WORKER:
        from damon_ros.core.robot import Robot

        _WORKER["mesh"] = Robot("mesh")
    return _WORKER["mesh"]


def _label_rows(args) -> tuple[np.ndarray, np.ndarray]:
    from damon_ros.core.shapes import Shape

    q, points, radius = args
    mesh = _mesh()
    d = np.array([mesh.clearance(a, [Shape("sphere", (radius,), p)]).distance
                  for a, p in zip(q, points, strict=True)])
    sc = np.array([mesh.self_collision(a) for a in q])
    return d, sc


def _edges_free(args) -> np.ndarray:
    q, rows, cols = args
    mesh = _mesh()
    return np.array([mesh.segment_self_collision_free(q[r], q[c], SELF_CHECK_RESOLUTION)
                     for r, c in zip(rows, cols, strict=True)])


def _parallel(fn, chunks, workers: int, desc: str, progress: bool) -> list:
    from tqdm import tqdm

    pool = mp.get_context("fork").Pool(workers)
    try:
        out = list(tqdm(pool.imap(fn, chunks), total=len(chunks), desc=desc,
                        disable=not progress))
    except BaseException:
        pool.terminate()
        raise
    pool.close()  # not terminate(): its SIGTERM reached the CLI's handler in every worker
    pool.join()
    return out


def prune_self_colliding_edges(graph: LatentGraph, workers: int, progress: bool) -> int:
    """Drop graph edges along which the exact meshes self-collide; returns how many."""
    from scipy import sparse

    coo = sparse.triu(graph.adjacency()).tocoo()
    rows, cols = coo.row, coo.col
    chunks = [(graph.q, rows[i:i + 2000], cols[i:i + 2000]) for i in range(0, len(rows), 2000)]
    free = np.concatenate(_parallel(_edges_free, chunks, workers, "self-collision", progress)) \
        if chunks else np.zeros(0, bool)
    keep = sparse.coo_matrix((coo.data[free], (rows[free], cols[free])), shape=coo.shape)
    adj = (keep + keep.T).tocsr()
    adj.sort_indices()
    graph.indptr = adj.indptr.astype(np.int64)
    graph.indices = adj.indices.astype(np.int32)
    graph.weights = adj.data.astype(np.float32)
    return int((~free).sum())


def build_model_graph(data: dict, data_meta: dict, codec, config: GraphBuildConfig,
                      workers: int = 2, progress: bool = True) -> tuple[LatentGraph, dict]:
    from damon_ros.core.limits import joint_limits

    limits = joint_limits("panda")
    nodes = np.asarray(data_meta["nodes"], float)
    radius = float(data_meta["radius"])
    samples = dict(data)
    # a self-colliding sample is never a safe vertex
    samples["distance"] = np.where(data["self_collision"], -1.0, data["distance"])

    def label(q: np.ndarray, points: np.ndarray) -> np.ndarray:
        chunks = [(q[i:i + 500], points[i:i + 500], radius) for i in range(0, len(q), 500)]
        parts = _parallel(_label_rows, chunks, workers, "label grid", progress)
        d = np.concatenate([p[0] for p in parts])
        sc = np.concatenate([p[1] for p in parts])
        return np.where(sc, -1.0, d)

    t0 = time.perf_counter()
    graph = build_graph(samples, nodes, codec.encode, codec.decode, label, limits.lower,
                        limits.upper, config)
    t_build = time.perf_counter() - t0
    pruned = prune_self_colliding_edges(graph, workers, progress)
    stats = {
        "n_vertices": graph.n_vertices, "n_edges": graph.n_edges,
        "n_obstacle_nodes": len(nodes), "safe_share": float(graph.safe.mean()),
        "grid_vertices": int(graph.origin.sum()),
        "edges_pruned_self_collision": pruned,
        "build_seconds": t_build, "prune_seconds": time.perf_counter() - t0 - t_build,
        **graph.connectivity(),
    }
    return graph, stats


def load_inputs(data_dir: str | Path, model: Path) -> tuple[dict, dict, object, dict]:
    """(data, data set sidecar, the model's VAE, its ``meta.json``) — the inputs of
    :func:`complete_model` for the model directory ``model`` that ``damon-ros train`` wrote."""
    from damon_ros.learning.dataset import load_dataset
    from damon_ros.learning.vae import load_vae

    data, data_meta = load_dataset(data_dir)
    meta = json.loads((model / "meta.json").read_text())
    return data, data_meta, load_vae(model, meta.get("vae")), meta


def complete_model(model: Path, data: dict, data_meta: dict, codec, meta: dict,
                   config: GraphBuildConfig, gmm_components: int, margin: float,
                   workers: int = 2, progress: bool = True) -> dict:
    """Build, prune and save the graph, fit and save the GMR (λ = ``margin``), record both in
    ``meta.json``; returns the build statistics."""
    from damon_ros.learning.bundle import write_meta
    from damon_ros.learning.gmr import CollisionGMR

    graph, stats = build_model_graph(data, data_meta, codec, config, workers, progress)
    graph.save(model / "graph.npz")
    t0 = time.perf_counter()
    obstacle_rows = graph.distance > -0.5  # self-colliding vertices carry -1, not a clearance
    gmr = CollisionGMR.fit(graph.z[obstacle_rows], graph.distance[obstacle_rows],
                           gmm_components, margin, config.seed)
    gmr.save(model / "gmr.npz")
    stats["gmr_seconds"] = time.perf_counter() - t0
    meta.update(graph=stats, graph_config=config.__dict__, margin=margin,
                gmr={"components": gmm_components, "margin": margin})
    write_meta(model, meta)
    return stats
