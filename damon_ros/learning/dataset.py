"""The collected data set on disk: chunk files, the ``dataset.json`` sidecar, and loading.

A data set directory holds ``chunk_00000.npz`` … (``np.savez``, no object arrays, written
atomically) and ``dataset.json`` (columns, parameters, nodes, counts, versions, timing, each
chunk's SHA-256). Kept apart from :mod:`damon_ros.learning.collect` because the readers —
VAE training, graph building, the analysis tools — need only the format, never the sampler
or the robot model.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np

from damon_ros.core.resources import read_versioned_json, sha256

DATASET_FORMAT = "damon_ros-dataset"
DATASET_VERSION = 1
SIDECAR = "dataset.json"
COLUMNS = (
    ("q", 7, "float64", "joint angles panda_joint1..7 (rad)"),
    ("point", 3, "float64", "point obstacle = obstacle node position, base frame (m)"),
    ("collision", 1, "bool", "exact mesh distance d <= 0"),
    ("near", 1, "bool", "exact mesh distance d <= margin"),
    ("distance", 1, "float64", "exact signed robot-obstacle distance (m), < 0 = penetration"),
    ("node", 1, "int32", "index of the obstacle node in 'nodes'"),
    ("source", 1, "int8", "0 = uniform configuration, 1 = contact-seeking configuration"),
)


class CollectError(ValueError):
    """Bad collection parameters, or a data set directory that is missing, corrupt or does
    not match them."""


# ---- chunk files ----------------------------------------------------------------------
def chunk_path(out_dir: Path, index: int) -> Path:
    return Path(out_dir) / f"chunk_{index:05d}.npz"


def chunk_ranges(n_samples: int, chunk_size: int) -> list[tuple[int, int]]:
    """(index, size) of every chunk of an ``n_samples`` data set; the last may be short."""
    return [(k, min(chunk_size, n_samples - k * chunk_size))
            for k in range(math.ceil(n_samples / chunk_size))]


def read_chunk(path: Path) -> dict[str, np.ndarray]:
    try:
        with np.load(path, allow_pickle=False) as f:
            return {k: f[k] for k in f.files}
    except Exception as exc:  # zip, header or pickle refusal: all mean "not a valid chunk"
        raise CollectError(f"{path}: unreadable chunk ({type(exc).__name__}: {exc})") from exc


def chunk_complete(path: Path, size: int, fingerprint: str, index: int) -> bool:
    """A chunk counts as done when it loads and matches the parameters, index and size."""
    if not path.is_file():
        return False
    try:
        arrays = read_chunk(path)
    except CollectError:
        return False
    return (str(arrays.get("fingerprint", "")) == fingerprint
            and int(arrays.get("chunk", -1)) == index
            and all(k in arrays and len(arrays[k]) == size for k, *_ in COLUMNS))


def write_chunk(path: Path, arrays: dict[str, np.ndarray], fingerprint: str,
                 index: int) -> None:
    """Write to a temporary name and rename, so an interrupted run leaves no half chunk.
    Only data go in (no timing), so the same chunk is the same bytes on every run."""
    tmp = path.with_suffix(".tmp")
    with open(tmp, "wb") as f:
        np.savez(f, fingerprint=np.array(fingerprint), chunk=np.array(index), **arrays)
    os.replace(tmp, path)



# ---- the sidecar ----------------------------------------------------------------------
def sidecar_header() -> dict:
    """The first entries of ``dataset.json``: format, version and the column table."""
    return {"format": DATASET_FORMAT, "version": DATASET_VERSION,
            "columns": [{"name": n, "width": w, "dtype": t, "description": d}
                        for n, w, t, d in COLUMNS]}


def summarise_chunks(out_dir: Path, n_samples: int,
                     chunk_size: int) -> tuple[dict[str, int], list[dict]]:
    """(label counts, chunk entries with rows and SHA-256) of every chunk, read back from
    disk so the sidecar describes what is there, not what a run meant to write."""
    chunks, counts = [], {"collision": 0, "near": 0, "contact_seeking": 0,
                          "collision_contact_seeking": 0}
    for k, size in chunk_ranges(n_samples, chunk_size):
        path = chunk_path(out_dir, k)
        arrays = read_chunk(path)
        counts["collision"] += int(arrays["collision"].sum())
        counts["near"] += int(arrays["near"].sum())
        seeking = arrays["source"] == 1
        counts["contact_seeking"] += int(seeking.sum())
        counts["collision_contact_seeking"] += int((arrays["collision"] & seeking).sum())
        chunks.append({"file": path.name, "rows": size, "sha256": sha256(path)})
    counts["samples"] = n_samples
    counts["free"] = n_samples - counts["collision"]
    return counts, chunks


def write_sidecar(out_dir: Path, meta: dict) -> dict:
    """Write ``meta`` as ``out_dir/dataset.json``; returns it."""
    (out_dir / SIDECAR).write_text(json.dumps(meta, indent=1) + "\n")
    return meta


# ---- reading --------------------------------------------------------------------------
def read_sidecar(out_dir: str | Path) -> dict:
    """``dataset.json`` of a data set directory, with its format checked."""
    path = Path(out_dir) / SIDECAR
    meta = read_versioned_json(path, DATASET_FORMAT, DATASET_VERSION, CollectError,
                               missing=f"{path}: missing — not a damon_ros data set directory",
                               document="sidecar", versioned="data set")
    for key in ("n_samples", "fingerprint", "nodes", "chunks", "columns"):
        if not meta.get(key):
            raise CollectError(f"{path}: no '{key}' entry")
    return meta


def load_dataset(out_dir: str | Path,
                 verify_hashes: bool = True) -> tuple[dict[str, np.ndarray], dict]:
    """(data, sidecar) of a collected data set. ``data`` holds one array per column, all
    with N rows — ``q`` (N,7), ``point`` (N,3), ``collision``, ``near``, ``distance``,
    ``node``, ``source`` and ``self_collision`` (all False: self-colliding configurations are
    rejected at collection; the key is there for callers that mask them). The obstacle nodes
    are ``np.asarray(sidecar["nodes"])`` (M,3). Checked against the sidecar: every chunk
    present, unmodified (SHA-256), of the right size and dtype, node indices in range."""
    out_dir = Path(out_dir)
    meta = read_sidecar(out_dir)
    parts: dict[str, list[np.ndarray]] = {name: [] for name, *_ in COLUMNS}
    for entry in meta["chunks"]:
        path = out_dir / entry["file"]
        if not path.is_file():
            raise CollectError(f"{path}: listed in {SIDECAR} but missing")
        if verify_hashes and sha256(path) != entry["sha256"]:
            raise CollectError(f"{path}: SHA-256 does not match {SIDECAR} — the chunk was "
                               "truncated, replaced or modified")
        arrays = read_chunk(path)
        for name, width, dtype, _ in COLUMNS:
            a = arrays.get(name)
            shape = (entry["rows"],) if width == 1 else (entry["rows"], width)
            if a is None or a.shape != shape or a.dtype != np.dtype(dtype):
                got = None if a is None else f"{a.dtype}{a.shape}"
                raise CollectError(f"{path}: column '{name}' should be {dtype}{shape}, got {got}")
            parts[name].append(a)
    data = {name: np.concatenate(chunks) for name, chunks in parts.items()}
    if len(data["q"]) != meta["n_samples"]:
        raise CollectError(f"{out_dir}: {len(data['q'])} rows, {SIDECAR} says "
                           f"{meta['n_samples']}")
    n_nodes = len(meta["nodes"])
    if data["node"].min() < 0 or data["node"].max() >= n_nodes:
        raise CollectError(f"{out_dir}: node indices outside the {n_nodes} nodes")
    data["self_collision"] = np.zeros(len(data["q"]), bool)
    return data, meta

