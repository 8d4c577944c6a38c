"""DAMON data collection: joint configurations next to point obstacles, labelled by exact
geometry.

Each sample is a joint configuration ``q`` (7), the position of a point obstacle (3) and
whether the robot touches it, plus what the later modules need: the exact minimum distance
``d`` between the robot's collision meshes and the obstacle (the GMR's target), a second
flag ``near = d <= margin`` (the paper's λ) and the index of the obstacle node.

Choices (where the paper says only "random arm motion, with enough collision samples"):

- **Obstacle nodes** (the graph's top layer) are a regular grid: x, y at multiples of the
  spacing, z at the cell centres ``(k + ½)·spacing`` above the table plane, so every point
  above the table is within half a cell of a node; clipped to a ball of radius ``reach``
  about the shoulder (0.855 m arm reach + 0.1 m of hand, default 0.955 m) and with the
  nodes the robot itself always occupies removed (the base column and the shoulder
  housing: a node colliding in every one of 32 random configurations). With 0.15 m this
  gives 814 nodes. The point obstacle is a sphere of radius ``radius`` (default 3 cm)
  centred on its node; the obstacle point stored is the node itself, so that a sample's
  distance is the distance the graph assigns to that node.
- **Configurations** are valid states of a table-mounted arm: uniform within the joint
  limits, without self-collision (exact meshes), with every link frame and the TCP above
  the table plane. A share ``near_contact_share`` (default ½) is *contact-seeking*: joints
  2–7 uniform, then joint 1 — a pure rotation of the whole arm about the base z axis — is
  solved in closed form so that a chosen point of the arm's skeleton lies a chosen distance
  from the node. Measured on 200,000 samples (seed 0, defaults): uniform samples collide
  1.0 % of the time (median clearance 0.47 m), contact-seeking ones 29.6 % with 67 % within
  the 5 cm margin (median 0.027 m); overall 15.3 % colliding (colliding : free = 0.18) and
  every node gets 190–290 samples. Of uniform draws 7 % reach below the table plane and
  5.6 % of the rest self-collide; both are drawn again.
- **Labels** come only from :meth:`Robot.clearance` on the exact meshes; the skeleton is
  only an aim.
- **Determinism**: chunk ``k`` draws from ``SeedSequence(seed, spawn_key=(k,))``, so the
  data are a function of (seed, chunk size, parameters) whatever the number of workers,
  and a longer run with the same seed extends a shorter one.
- **Output**: ``out_dir/chunk_00000.npz`` … (``np.savez``, no object arrays) written
  atomically, and ``out_dir/dataset.json`` (columns, parameters, nodes, counts, versions,
  timing, each chunk's SHA-256; the format is :mod:`damon_ros.learning.dataset`'s). Chunks
  already present with matching parameters are kept.
"""

from __future__ import annotations

import hashlib
import json
import math
import multiprocessing
import os
import platform
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass
from importlib import metadata
from pathlib import Path

import numpy as np

from damon_ros.core.kinematics import Chain
from damon_ros.learning.dataset import (
    SIDECAR,
    CollectError,
    chunk_complete,
    chunk_path,
    chunk_ranges,
    read_sidecar,
    sidecar_header,
    summarise_chunks,
    write_chunk,
    write_sidecar,
)

SHOULDER = np.array([0.0, 0.0, 0.333])
ARM_REACH = 0.855
HAND_LENGTH = 0.1
CHAIN_FRAMES = tuple(f"panda_link{i}" for i in range(2, 9)) + ("panda_hand", "panda_hand_tcp")
SKELETON_STEP = 0.03  # m between aim points along the link-frame polyline
AIM_MAX = 0.18
"""Contact-seeking aims a skeleton point at a distance uniform in [0, AIM_MAX] from the node:
the Panda's links are ~6 cm about that axis, so with a 3 cm obstacle touching is ~0.09 m, and
the aims are symmetric about contact. Other links and the links' real shape spread the exact
distances: about 30 % of these samples collide and 67 % lie within 5 cm."""
BATCH = 16  # candidate postures per contact-seeking sample (batched kinematics)
AIM_PATIENCE = 2  # contact-seeking batches before a node gets the best closest approach
MAX_BATCHES = 50  # candidate batches for one sample before giving up (never reached)
OCCUPIED_PROBES = 32  # random configurations that decide a node is always occupied


LABELLER_VERSION = 2
"""Part of every chunk's fingerprint. 2: the collector's kinematics became
`core.kinematics.Chain` (joint angles of the closed-form aim differ from version 1 by up to
1.5e-8 rad), so a run resumed across that change does not mix the two kinds of chunk."""

@dataclass(frozen=True)
class CollectConfig:
    """Every parameter that changes the data (the sample count only decides how many chunks)."""

    seed: int = 0
    chunk_size: int = 5000
    spacing: float = 0.15
    reach: float = ARM_REACH + HAND_LENGTH
    radius: float = 0.03
    margin: float = 0.05
    near_contact_share: float = 0.5
    floor: float = 0.0

    def __post_init__(self) -> None:
        checks = {
            "seed": isinstance(self.seed, int) and self.seed >= 0,
            "chunk_size": isinstance(self.chunk_size, int) and self.chunk_size >= 1,
            "spacing": 0.02 <= self.spacing <= 1.0,
            "reach": 0.2 <= self.reach <= 2.0,
            "radius": 0.0 < self.radius <= 0.5,
            "margin": 0.0 <= self.margin <= 1.0,
            "near_contact_share": 0.0 <= self.near_contact_share <= 1.0,
            "floor": math.isfinite(self.floor) and -1.0 <= self.floor <= SHOULDER[2],
        }
        bad = [f"{k}={getattr(self, k)!r}" for k, ok in checks.items() if not ok]
        if bad:
            raise CollectError("invalid collection parameters: " + ", ".join(bad))

    def fingerprint(self) -> str:
        """Short hash of the parameters, stored in every chunk so a resumed run never mixes
        chunks made with different parameters or a different labeller."""
        text = json.dumps(dict(asdict(self), labeller=LABELLER_VERSION), sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:16]


# ---- obstacle nodes -------------------------------------------------------------------
def workspace_nodes(spacing: float = 0.15, reach: float = ARM_REACH + HAND_LENGTH,
                    floor: float = 0.0, robot=None) -> np.ndarray:
    """Obstacle nodes (M, 3): grid points within ``reach`` of the shoulder, above ``floor``,
    excluding those the robot's base and shoulder always occupy (see the module docstring).

    ``robot`` is a mesh-model :class:`~damon_ros.core.robot.Robot`, built here when not given."""
    CollectConfig(spacing=spacing, reach=reach, floor=floor)  # validates
    n_xy = int(math.floor(reach / spacing))
    axis = spacing * np.arange(-n_xy, n_xy + 1)
    z = floor + spacing * (np.arange(int(math.ceil((SHOULDER[2] + reach - floor) / spacing)))
                           + 0.5)
    grid = np.stack(np.meshgrid(axis, axis, z, indexing="ij"), axis=-1).reshape(-1, 3)
    grid = grid[np.linalg.norm(grid - SHOULDER, axis=1) <= reach]
    return grid[~_always_occupied(grid, robot)]


def _always_occupied(points: np.ndarray, robot=None) -> np.ndarray:
    """True for points where a 1 cm sphere touches the robot in every probe configuration:
    inside the base or the shoulder housing, where no obstacle can be and no motion helps.
    Only points near the base axis can qualify, so only those are probed."""
    from damon_ros.core.robot import Robot
    from damon_ros.core.shapes import Shape

    robot = robot if robot is not None else Robot("mesh")
    rng = np.random.default_rng(0)
    probes = rng.uniform(robot.limits.lower, robot.limits.upper, (OCCUPIED_PROBES, 7))
    occupied = np.zeros(len(points), bool)
    for i in np.flatnonzero(np.hypot(points[:, 0], points[:, 1]) < 0.3):
        obstacle = [Shape("sphere", (0.01,), points[i])]
        occupied[i] = all(robot.clearance(q, obstacle).distance <= 0.0 for q in probes)
    return occupied


# ---- sampling (inside a worker) -------------------------------------------------------
class Sampler:
    """Draws labelled samples for one chunk at a time. Holds the robot model, so it is built
    inside each worker process (pinocchio/coal objects are never shared across processes)."""

    def __init__(self, config: CollectConfig, nodes: np.ndarray) -> None:
        from damon_ros.core.robot import Robot
        from damon_ros.core.shapes import Shape

        self.config = config
        self.robot = Robot("mesh")
        self.lower = np.asarray(self.robot.limits.lower, float)
        self.upper = np.asarray(self.robot.limits.upper, float)
        self.nodes = np.asarray(nodes, float)
        self.obstacles = [Shape("sphere", (config.radius,), p) for p in self.nodes]
        self.node_rho = np.hypot(self.nodes[:, 0], self.nodes[:, 1])
        self.node_phi = np.arctan2(self.nodes[:, 1], self.nodes[:, 0])
        self.rejected = {"self_collision": 0, "below_floor": 0, "unreachable_aim": 0}
        self.chain = Chain(self.robot.model)
        self.frames = self.chain.frame_block(CHAIN_FRAMES)
        self.skeleton_weights = _polyline_weights(self.arm_frames(np.zeros((1, 7)))[0],
                                                  SKELETON_STEP)

    def chunk(self, index: int, size: int) -> dict[str, np.ndarray]:
        """The ``size`` samples of chunk ``index``: a pure function of (config, index)."""
        rng = np.random.default_rng(np.random.SeedSequence(self.config.seed,
                                                           spawn_key=(index,)))
        node = rng.integers(0, len(self.nodes), size).astype(np.int32)
        seek = rng.random(size) < self.config.near_contact_share
        q = np.empty((size, 7))
        q[~seek] = self.uniform(rng, int((~seek).sum()))
        postures, aims, chains = self.candidates(rng, int(seek.sum()))
        for j, i in enumerate(np.flatnonzero(seek)):
            q[i] = self.contact_seeking(rng, int(node[i]), postures[j], aims[j], chains[j])
        distance = np.array([self.robot.clearance(qi, [self.obstacles[m]]).distance
                             for qi, m in zip(q, node, strict=True)])
        return {"q": q, "point": self.nodes[node], "collision": distance <= 0.0,
                "near": distance <= self.config.margin, "distance": distance, "node": node,
                "source": seek.astype(np.int8)}

    def uniform(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """``n`` valid configurations (n, 7) drawn uniformly within the joint limits: in
        order, the candidates above the table and free of self-collision."""
        out: list[np.ndarray] = []
        for _ in range(MAX_BATCHES):
            if len(out) == n:
                break
            Q = rng.uniform(self.lower, self.upper, (int(1.3 * (n - len(out))) + 8, 7))
            for q, above in zip(Q, self.above_floor(Q), strict=True):
                if len(out) == n:
                    break
                if not above:
                    self.rejected["below_floor"] += 1
                elif self.robot.self_collision(q):
                    self.rejected["self_collision"] += 1
                else:
                    out.append(q)
        if len(out) < n:
            raise RuntimeError(f"only {len(out)} of {n} valid uniform configurations")
        return np.array(out).reshape(n, 7)

    def arm_frames(self, Q: np.ndarray) -> np.ndarray:
        """Positions (N, K, 3) of the arm's axis — the frames link2 … link8, hand and TCP —
        for configurations Q (N, 7): to aim contact-seeking samples and to test the table
        plane, a whole batch of candidate postures in one call."""
        return self.chain.positions(Q, self.frames)

    def above_floor(self, Q: np.ndarray) -> np.ndarray:
        """Every arm frame and the TCP above the table plane, per configuration (N,)."""
        return self.arm_frames(Q)[:, :, 2].min(axis=1) >= self.config.floor

    def candidates(self, rng: np.random.Generator, n: int) -> tuple[np.ndarray, ...]:
        """``n`` batches of BATCH candidate postures with joint 1 at 0 (n, BATCH, 7), their
        aim distances (n, BATCH) and arm frames (n, BATCH, K, 3) — the kinematics of a whole
        chunk in one numpy call, which costs what a few single calls do."""
        Q = rng.uniform(self.lower, self.upper, (n, BATCH, 7))
        Q[..., 0] = 0.0
        aims = AIM_MAX * rng.random((n, BATCH))
        chains = self.arm_frames(Q.reshape(-1, 7)).reshape(n, BATCH, -1, 3)
        return Q, aims, chains

    def contact_seeking(self, rng: np.random.Generator, node: int, postures: np.ndarray,
                        aims: np.ndarray, chains: np.ndarray) -> np.ndarray:
        """A valid configuration whose arm passes close to ``node``. Each candidate posture
        (joints 2–7 uniform) aims a random point of its skeleton at its aim distance from
        the node (uniform in [0, AIM_MAX], symmetric about touching) by turning joint 1; the
        first candidate that can, above the table and free of self-collision, is taken. When
        a batch has none, new batches are drawn; a node few postures can reach (the rim of
        the workspace) gets, after ``AIM_PATIENCE`` batches, the closest approach of the
        best posture seen."""
        best = (math.inf, None)  # (closest approach, posture) of the best candidate so far
        for attempt in range(MAX_BATCHES):
            if attempt:
                postures, aims, chains = (a[0] for a in self.candidates(rng, 1))
            above = chains[:, :, 2].min(axis=1) >= self.config.floor
            self.rejected["below_floor"] += int((~above).sum())
            skeletons = self.skeleton_weights @ chains
            closest = self._closest_approach(skeletons, node)
            closest[~above] = math.inf
            for b in range(len(postures)):
                usable = np.flatnonzero(closest[b] <= aims[b])
                if len(usable) == 0:
                    self.rejected["unreachable_aim"] += int(above[b])
                    continue
                q = self._turned(postures[b], skeletons[b, rng.choice(usable)], node, aims[b],
                                 rng)
                if q is not None:
                    return q
            b, k = np.unravel_index(int(np.argmin(closest)), closest.shape)
            if closest[b, k] < best[0]:
                best = (float(closest[b, k]), postures[b], skeletons[b, k])
            if attempt + 1 >= AIM_PATIENCE and best[1] is not None:
                q = self._turned(best[1], best[2], node, best[0], rng)
                best = (math.inf, None)  # used once: if it fails, look for another
                if q is not None:
                    return q
        raise RuntimeError(f"no valid contact-seeking configuration in "
                           f"{MAX_BATCHES * BATCH} draws")

    def _turned(self, q: np.ndarray, point: np.ndarray, node: int, aim: float,
                rng: np.random.Generator) -> np.ndarray | None:
        """``q`` with joint 1 set by :meth:`_yaw_for`, or None if no such angle exists or the
        result self-collides."""
        yaw = self._yaw_for(point, node, aim, rng)
        if yaw is None:
            return None
        q = q.copy()
        q[0] = yaw
        if self.robot.self_collision(q):
            self.rejected["self_collision"] += 1
            return None
        return q

    def _closest_approach(self, skeletons: np.ndarray, node: int) -> np.ndarray:
        """Smallest distance from each skeleton point (joint 1 at 0) to the node over all
        joint-1 angles: turning joint 1 moves a point on a circle about the base z axis."""
        rho = np.hypot(skeletons[..., 0], skeletons[..., 1])
        return np.hypot(rho - self.node_rho[node], skeletons[..., 2] - self.nodes[node, 2])

    def _yaw_for(self, point: np.ndarray, node: int, aim: float,
                 rng: np.random.Generator) -> float | None:
        """Joint-1 angle ψ that puts ``point`` (computed with joint 1 at 0) at distance ``aim``
        from the node, or None outside the joint limits. Turning by ψ moves a point at
        cylinder coordinates (ρ, φ, z) to (ρ, φ + ψ, z), so its distance to the node
        (ρn, φn, zn) obeys d² = ρ² + ρn² − 2ρρn·cos(φ + ψ − φn) + (z − zn)²."""
        rho, rn = float(np.hypot(point[0], point[1])), float(self.node_rho[node])
        if rho * rn < 1e-6:  # point or node on the base axis: the yaw does not matter
            return float(rng.uniform(self.lower[0], self.upper[0]))
        dz = float(point[2] - self.nodes[node, 2])
        cos_a = (rho**2 + rn**2 + dz**2 - aim**2) / (2.0 * rho * rn)
        alpha = math.acos(min(max(cos_a, -1.0), 1.0))
        phi = math.atan2(point[1], point[0])
        sign = 1.0 if rng.random() < 0.5 else -1.0
        for s in (sign, -sign):
            yaw = math.remainder(self.node_phi[node] + s * alpha - phi, 2.0 * math.pi)
            if self.lower[0] <= yaw <= self.upper[0]:
                return yaw
        return None


def _polyline_weights(chain: np.ndarray, step: float) -> np.ndarray:
    """Matrix W (P, K) such that ``W @ chain`` puts points at most ``step`` apart along the
    polyline through the K rows of ``chain``, both ends included."""
    rows = [np.eye(len(chain))[0]]
    for i in range(len(chain) - 1):
        n = max(1, math.ceil(float(np.linalg.norm(chain[i + 1] - chain[i])) / step))
        for t in np.linspace(0.0, 1.0, n + 1)[1:]:
            w = np.zeros(len(chain))
            w[i], w[i + 1] = 1.0 - t, t
            rows.append(w)
    return np.array(rows)


_WORKER: Sampler | None = None


def _init_worker(config: dict, nodes: list) -> None:
    global _WORKER
    _WORKER = Sampler(CollectConfig(**config), np.asarray(nodes, float))


def _run_chunk(job: tuple[str, int, int]) -> dict:
    """Make, write and summarise one chunk (in a worker); returns only small counts."""
    out_dir, index, size = job
    start = time.perf_counter()
    before = dict(_WORKER.rejected)
    arrays = _WORKER.chunk(index, size)
    seconds = time.perf_counter() - start
    write_chunk(chunk_path(Path(out_dir), index), arrays, _WORKER.config.fingerprint(), index)
    rejected = {k: v - before[k] for k, v in _WORKER.rejected.items()}
    return {"index": index, "size": size, "seconds": seconds, "rejected": rejected}


# ---- the collection run ---------------------------------------------------------------
def collect(n_samples: int, seed: int, out_dir: str | Path, workers: int | None = None,
            chunk_size: int = 5000, spacing: float = 0.15, radius: float = 0.03,
            margin: float = 0.05, near_contact_share: float = 0.5,
            reach: float = ARM_REACH + HAND_LENGTH, floor: float = 0.0,
            progress: bool = True) -> dict:
    """Collect ``n_samples`` labelled samples into ``out_dir`` (resumable) and return the
    sidecar written to ``out_dir/dataset.json``."""
    if not isinstance(n_samples, int) or n_samples < 1:
        raise CollectError(f"n_samples must be a positive integer, got {n_samples!r}")
    workers = (os.cpu_count() or 1) if workers is None else workers
    if not isinstance(workers, int) or workers < 1:
        raise CollectError(f"workers must be a positive integer, got {workers!r}")
    config = CollectConfig(seed=seed, chunk_size=chunk_size, spacing=spacing, reach=reach,
                           radius=radius, margin=margin, near_contact_share=near_contact_share,
                           floor=floor)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    nodes = _nodes_for(out_dir, config)
    fingerprint = config.fingerprint()
    todo = [(str(out_dir), k, size) for k, size in chunk_ranges(n_samples, chunk_size)
            if not chunk_complete(chunk_path(out_dir, k), size, fingerprint, k)]
    start = time.perf_counter()
    reports = _run_jobs(todo, config, nodes, min(workers, max(1, len(todo))), n_samples,
                        progress)
    wall = time.perf_counter() - start
    return _write_sidecar(out_dir, config, nodes, n_samples, reports, wall, workers)


def _nodes_for(out_dir: Path, config: CollectConfig) -> np.ndarray:
    """The nodes of an existing sidecar with the same parameters (so resuming does not pay
    for them again), else freshly computed; a sidecar with other parameters is an error."""
    sidecar = out_dir / SIDECAR
    if sidecar.is_file():
        meta = read_sidecar(out_dir)
        if meta["fingerprint"] != config.fingerprint():
            raise CollectError(f"{out_dir} holds a data set made with other parameters "
                               f"({meta['config']}); use a new directory")
        return np.asarray(meta["nodes"], float)
    return workspace_nodes(config.spacing, config.reach, config.floor)


def _run_jobs(jobs: list, config: CollectConfig, nodes: np.ndarray, workers: int,
              n_samples: int, progress: bool) -> list[dict]:
    """Run chunk jobs in-process (one worker) or on a process pool, with one progress bar.

    The pool forks (Linux), so a plain script needs no ``__main__`` guard; each worker
    still builds its own robot model in ``_init_worker`` — nothing made by the parent's
    pinocchio/coal is used across processes. Where fork is missing, spawn is used."""
    from tqdm import tqdm

    if not jobs:
        return []
    done = n_samples - sum(size for _, _, size in jobs)
    bar = tqdm(total=n_samples, initial=done, unit="sample", disable=not progress,
               desc="collect", smoothing=0.1)
    reports = []
    init_args = (asdict(config), nodes.tolist())
    try:
        if workers == 1:
            _init_worker(*init_args)
            for job in jobs:
                reports.append(_run_chunk(job))
                bar.update(job[2])
        else:
            methods = multiprocessing.get_all_start_methods()
            ctx = multiprocessing.get_context("fork" if "fork" in methods else "spawn")
            with ProcessPoolExecutor(workers, mp_context=ctx, initializer=_init_worker,
                                     initargs=init_args) as pool:
                # a worker that dies raises BrokenProcessPool here instead of hanging
                for future in as_completed([pool.submit(_run_chunk, job) for job in jobs]):
                    reports.append(future.result())
                    bar.update(reports[-1]["size"])
    finally:
        bar.close()
    return reports


def _versions() -> dict[str, str]:
    out = {"python": platform.python_version()}
    for dist in ("numpy", "pin", "coal", "example-robot-data"):
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[dist] = "unknown"
    return out


def _write_sidecar(out_dir: Path, config: CollectConfig, nodes: np.ndarray, n_samples: int,
                   reports: list[dict], wall: float, workers: int) -> dict:
    """Summarise every chunk of the data set (read back from disk) into ``dataset.json``."""
    counts, chunks = summarise_chunks(out_dir, n_samples, config.chunk_size)
    generated = sum(r["size"] for r in reports)
    rejected = {k: sum(r["rejected"][k] for r in reports) for k in
                ("self_collision", "below_floor", "unreachable_aim")}
    return write_sidecar(out_dir, {
        **sidecar_header(),
        "n_samples": n_samples, "seed": config.seed, "config": asdict(config),
        "fingerprint": config.fingerprint(), "radius": config.radius, "margin": config.margin,
        "spacing": config.spacing,
        "n_nodes": len(nodes), "nodes": nodes.tolist(),
        "counts": counts,
        "collision_ratio": counts["collision"] / n_samples,
        "collision_to_free": counts["collision"] / max(counts["free"], 1),
        "near_ratio": counts["near"] / n_samples,
        "rejected_this_run": rejected,
        "timing": {"wall_s_this_run": round(wall, 3), "samples_this_run": generated,
                   "samples_per_s_this_run": round(generated / wall, 1) if generated else None,
                   "workers": workers,
                   "chunk_cpu_s_this_run": round(sum(r["seconds"] for r in reports), 3)},
        "versions": _versions(),
        "chunks": chunks,
    })
