"""DAMON data collection: [q (7), obstacle point (3), collision flag] with exact labels.

Obstacle nodes (the graph's top layer) are a regular grid over the Panda's reachable
workspace: points ``spacing`` apart inside the sphere of radius ``REACH + 0.05`` m about the
shoulder, above the table (z ≥ 0) and outside the base column (0.15 m around the z axis
below 0.45 m). With the default 0.25 m spacing this is 301 nodes.

Each sample pairs an obstacle node (a point obstacle: a sphere of ``radius``) with a joint
configuration drawn uniformly within the limits; a share of samples (``near_share``) is
drawn near contact instead — the node is the one nearest a random point of the arm's
surface — so both labels are well represented. Labels come from the exact collision meshes:
``collision = d ≤ 0`` and ``near = d ≤ margin`` (λ), plus mesh self-collision.

Output is chunked and resumable: ``chunk_NNNNN.npz`` (no pickle) plus ``dataset.json``;
every chunk is seeded from (seed, chunk index), so the data do not depend on the number
of worker processes.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import sys
import time
from pathlib import Path

import numpy as np

SHOULDER = np.array([0.0, 0.0, 0.333])  # joint 2 of the Panda
REACH = 1.07  # m from the shoulder to the fully stretched TCP (0.855 arm + hand and fingers)
ARM_FRAMES = tuple(f"panda_link{i}" for i in range(2, 8)) + ("panda_hand", "panda_hand_tcp")
COLUMNS = ("q", "point", "collision", "near", "distance", "node", "self_collision")
DATASET_VERSION = 1


def workspace_nodes(spacing: float = 0.25) -> np.ndarray:
    """Grid points covering the reachable workspace (see module docstring)."""
    if spacing <= 0.02:
        raise ValueError(f"node spacing must be > 0.02 m, got {spacing}")
    axis = np.arange(-1.2, 1.2 + 1e-9, spacing)
    grid = np.stack(np.meshgrid(axis, axis, np.arange(0.0, 1.5, spacing), indexing="ij"),
                    axis=-1).reshape(-1, 3)
    inside = np.linalg.norm(grid - SHOULDER, axis=1) <= REACH + 0.05
    column = (np.hypot(grid[:, 0], grid[:, 1]) < 0.15) & (grid[:, 2] < 0.45)
    return grid[inside & ~column]


_WORKER: dict = {}


def _robot():
    """One exact-mesh robot model per worker process (coal objects are not shared)."""
    if not _WORKER:
        from damon_ros.robot import Robot

        _WORKER["mesh"] = Robot("mesh")
    return _WORKER["mesh"]


def collect_chunk(index: int, size: int, seed: int, nodes: np.ndarray, radius: float,
                  margin: float, near_share: float) -> dict[str, np.ndarray]:
    """One chunk of labelled samples, deterministic from (seed, index)."""
    from scipy.spatial import cKDTree

    from damon_ros.shapes import Shape

    mesh = _robot()
    tree = cKDTree(nodes)
    rng = np.random.default_rng(np.random.SeedSequence([seed, index]))
    lower, upper = mesh.limits.lower, mesh.limits.upper
    q = rng.uniform(lower, upper, (size, 7))
    node = rng.integers(len(nodes), size=size)
    near = rng.random(size) < near_share
    for i in np.flatnonzero(near):
        frame = ARM_FRAMES[rng.integers(len(ARM_FRAMES))]
        direction = rng.normal(size=3)
        direction *= rng.uniform(0.03, 0.2) / np.linalg.norm(direction)
        node[i] = tree.query(mesh.fk(q[i], frame)[:3, 3] + direction)[1]
    distance = np.empty(size)
    self_collision = np.empty(size, bool)
    for i in range(size):
        distance[i] = mesh.clearance(q[i], [Shape("sphere", (radius,), nodes[node[i]])]).distance
        self_collision[i] = mesh.self_collision(q[i])
    return {
        "q": q.astype(np.float32), "point": nodes[node].astype(np.float32),
        "collision": distance <= 0.0, "near": distance <= margin,
        "distance": distance.astype(np.float32), "node": node.astype(np.int32),
        "self_collision": self_collision,
    }


def _write_chunk(args) -> str:
    out_dir, index, size, seed, nodes, radius, margin, near_share = args
    path = Path(out_dir) / f"chunk_{index:05d}.npz"
    data = collect_chunk(index, size, seed, nodes, radius, margin, near_share)
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, **data)
    os.replace(tmp, path)  # a chunk is either complete or absent: safe to resume
    return str(path)


def collect(n_samples: int, seed: int, out_dir: str | Path, workers: int | None = None,
            chunk_size: int = 10000, spacing: float = 0.15, radius: float = 0.03,
            margin: float = 0.02, near_share: float = 0.3, progress: bool = True) -> dict:
    """Collect ``n_samples`` rows into ``out_dir`` (resumable); returns the sidecar dict."""
    if n_samples <= 0 or chunk_size <= 0:
        raise ValueError("n_samples and chunk_size must be positive")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    nodes = workspace_nodes(spacing)
    sizes = [min(chunk_size, n_samples - i) for i in range(0, n_samples, chunk_size)]
    todo = [(str(out_dir), i, s, seed, nodes, radius, margin, near_share)
            for i, s in enumerate(sizes) if not (out_dir / f"chunk_{i:05d}.npz").exists()]
    workers = workers or os.cpu_count() or 1
    t0 = time.perf_counter()
    from tqdm import tqdm

    bar = tqdm(total=n_samples, initial=n_samples - sum(t[2] for t in todo), unit="sample",
               disable=not progress, desc="collect")
    if workers == 1:
        for task in todo:
            _write_chunk(task)
            bar.update(task[2])
    else:
        with mp.get_context("fork").Pool(workers) as pool:
            for task, _ in zip(todo, pool.imap(_write_chunk, todo), strict=True):
                bar.update(task[2])
    bar.close()
    elapsed = time.perf_counter() - t0
    data = load_chunks(out_dir, len(sizes))
    meta = {
        "version": DATASET_VERSION, "columns": {
            "q": "joint angles (rad), 7", "point": "obstacle point (m, base frame), 3",
            "collision": "mesh distance <= 0", "near": "mesh distance <= margin",
            "distance": "exact mesh distance to the point obstacle (m)",
            "node": "obstacle-node index", "self_collision": "mesh self-collision"},
        "n_samples": n_samples, "chunks": len(sizes), "chunk_size": chunk_size, "seed": seed,
        "nodes": nodes.tolist(), "spacing": spacing, "radius": radius, "margin": margin,
        "near_share": near_share, "collision_ratio": float(np.mean(data["collision"])),
        "near_ratio": float(np.mean(data["near"])),
        "self_collision_ratio": float(np.mean(data["self_collision"])),
        "seconds_this_run": elapsed, "samples_this_run": sum(t[2] for t in todo),
    }
    (out_dir / "dataset.json").write_text(json.dumps(meta, indent=1) + "\n")
    return meta


def load_chunks(out_dir: Path, n_chunks: int) -> dict[str, np.ndarray]:
    parts = []
    for i in range(n_chunks):
        path = Path(out_dir) / f"chunk_{i:05d}.npz"
        try:
            with np.load(path, allow_pickle=False) as f:
                parts.append({c: f[c] for c in COLUMNS})
        except (OSError, KeyError, ValueError) as exc:
            raise ValueError(f"{path}: missing or corrupt data chunk ({exc})") from exc
    return {c: np.concatenate([p[c] for p in parts]) for c in COLUMNS}


def load_dataset(out_dir: str | Path) -> tuple[dict[str, np.ndarray], dict]:
    """All columns of a collected data set, validated against ``dataset.json``."""
    out_dir = Path(out_dir)
    try:
        meta = json.loads((out_dir / "dataset.json").read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"{out_dir}: no readable dataset.json ({exc})") from exc
    data = load_chunks(out_dir, int(meta["chunks"]))
    if len(data["q"]) != meta["n_samples"]:
        raise ValueError(f"{out_dir}: {len(data['q'])} rows, dataset.json says "
                         f"{meta['n_samples']}")
    return data, meta


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="damon-ros collect",
                                     description="Collect labelled DAMON samples (resumable).")
    parser.add_argument("--n", type=int, default=1_000_000, help="number of samples")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", required=True, help="output directory")
    parser.add_argument("--workers", type=int, default=None, help="processes (default: cores)")
    parser.add_argument("--chunk-size", type=int, default=10000)
    parser.add_argument("--spacing", type=float, default=0.25, help="obstacle-node grid (m)")
    parser.add_argument("--radius", type=float, default=0.03, help="point-obstacle radius (m)")
    parser.add_argument("--margin", type=float, default=0.02, help="λ for the near flag (m)")
    parser.add_argument("--near-share", type=float, default=0.3)
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    try:
        meta = collect(args.n, args.seed, args.out, args.workers, args.chunk_size, args.spacing,
                       args.radius, args.margin, args.near_share, progress=not args.quiet)
    except ValueError as exc:
        print(f"damon-ros collect: {exc}", file=sys.stderr)
        return 2
    rate = meta["samples_this_run"] / max(meta["seconds_this_run"], 1e-9)
    print(f"{meta['n_samples']} samples, {len(meta['nodes'])} obstacle nodes, colliding "
          f"{100 * meta['collision_ratio']:.1f} %, within λ {100 * meta['near_ratio']:.1f} %, "
          f"self-colliding {100 * meta['self_collision_ratio']:.1f} %; this run "
          f"{meta['samples_this_run']} samples in {meta['seconds_this_run']:.1f} s "
          f"({rate:.0f}/s)")
    return 0
