"""The saved model bundle ``models/<name>/``: VAE, latent graph, GMR and ``meta.json``.

Loading a model must never execute code from it, and a truncated, swapped or tampered file
must fail with a clear message rather than plan with garbage: every file is safetensors,
npz (``allow_pickle=False``) or JSON, and ``meta.json`` records each file's SHA-256, which
is checked before anything is parsed.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from damon_ros.core.resources import default_model_dir, read_versioned_json, sha256

MODEL_FORMAT = "damon_ros-model"
MODEL_VERSION = 1
FILES = ("vae.safetensors", "graph.npz", "gmr.npz", "vae.json")


class ModelError(ValueError):
    """A model directory is missing, corrupt or does not match this version."""


def write_meta(directory: Path, meta: dict) -> Path:
    """Write ``meta.json`` with the hashes of the files present now."""
    directory = Path(directory)
    meta = dict(meta, format=MODEL_FORMAT, version=MODEL_VERSION)
    meta["files"] = {name: sha256(directory / name) for name in FILES
                     if (directory / name).exists()}
    path = directory / "meta.json"
    path.write_text(json.dumps(meta, indent=2, sort_keys=True) + "\n")
    return path


def read_meta(directory: Path, required: tuple[str, ...] = FILES) -> dict:
    """Read ``meta.json`` and verify that every required file exists with its recorded hash."""
    directory = Path(directory)
    path = directory / "meta.json"
    meta = read_versioned_json(
        path, MODEL_FORMAT, MODEL_VERSION, ModelError, document="file", versioned="model",
        missing=f"{directory}: no meta.json — not a damon_ros model directory")
    hashes = meta.get("files", {})
    for name in required:
        file = directory / name
        if not file.is_file():
            raise ModelError(f"{file}: missing")
        if name not in hashes:
            raise ModelError(f"{path}: records no SHA-256 for {name}")
        if sha256(file) != hashes[name]:
            raise ModelError(f"{file}: SHA-256 does not match meta.json — the file is truncated, "
                             "swapped or modified")
    return meta


@dataclass
class DamonModel:
    """A loaded, verified model: the VAE, the latent graph, the GMR and their metadata."""

    directory: Path
    meta: dict
    vae: object
    graph: object
    gmr: object | None

    @classmethod
    def load(cls, directory: str | Path | None = None) -> DamonModel:
        from damon_ros.learning.gmr import CollisionGMR
        from damon_ros.learning.graph import LatentGraph
        from damon_ros.learning.vae import load_vae

        directory = Path(directory) if directory is not None else default_model_dir()
        meta = read_meta(directory)
        try:
            vae = load_vae(directory)
        except ValueError as exc:
            raise ModelError(str(exc)) from exc
        try:
            graph = LatentGraph.load(directory / "graph.npz")
            gmr = CollisionGMR.load(directory / "gmr.npz")
        except ValueError as exc:
            raise ModelError(str(exc)) from exc
        return cls(directory=directory, meta=meta, vae=vae, graph=graph, gmr=gmr)

    def collision_probability(self, robot, q, obstacles) -> float:
        """The GMR's p(collision | z) at the latent point of [q, closest obstacle point, flag]
        (the paper's runtime signal; the planner's certification does not depend on it)."""
        if not obstacles or self.gmr is None:
            return 0.0
        c = robot.clearance(q, obstacles)
        row = np.concatenate([np.asarray(q, float), c.obstacle_point, [float(c.distance <= 0)]])
        return float(self.gmr.collision_probability(self.vae.encode(row[None]))[0])

    @property
    def margin(self) -> float:
        return float(self.meta.get("margin", 0.02))
