"""DAMON module 1: the variational autoencoder that learns the 2-D latent manifold.

Rows are the paper's 11 numbers, [q (7), obstacle point (3), collision flag]. The network
is the paper's: an encoder 11-300-200-75 with two heads to a latent R² (mean, log-variance)
and the mirrored decoder 2-75-200-300-11, ELU activations (smooth, so the decoded grid the
graph densifies with varies smoothly). All 11 inputs are standardised with the training
set's mean and std; the decoder returns the 10 continuous values standardised (squared
error) and the flag as a logit (binary cross-entropy, weighted by ``flag_weight`` so that
the latent space separates colliding from free samples, which is what the graph needs).

Files: ``vae.safetensors`` holds the tensors only (weights and normalisation; the
architecture is repeated in its string metadata) and ``vae.json`` the architecture,
normalisation, the file's SHA-256 and the training record; :func:`save_vae` returns the
same dict for the ``vae`` section of ``meta.json``. Nothing executable is ever loaded, and
:func:`load_vae` checks hash, architecture, names, shapes and values, raising ValueError
that names the file and the problem.

Inference (:meth:`VAE.encode`, :meth:`VAE.decode`) is plain numpy: no torch import, and
per row about a third of torch's per-call cost (see :data:`INFERENCE_TIMING`).
torch is imported only to train.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from damon_ros.core.resources import sha256

VAE_FORMAT = "damon_ros-vae"
VAE_VERSION = 2
WEIGHTS_FILE = "vae.safetensors"
CONFIG_FILE = "vae.json"
FLAG = 10  # column of the collision flag in a row
ACTIVATIONS = ("elu", "relu")
INFERENCE_TIMING = """Measured on the shared 2-core development machine with
:func:`benchmark_inference` (best of 400; paper-size network): encode one row 22 µs numpy vs
64 µs torch.no_grad; 10,000 rows 31–36 ms numpy vs 45–52 ms torch (1 or 2 threads). numpy
is faster at both sizes, needs no torch import, and is what :class:`VAE` uses."""


class VAEError(ValueError):
    """A VAE file or configuration is missing, corrupt or inconsistent."""


@dataclass(frozen=True)
class Architecture:
    """Layer sizes of the encoder (the decoder mirrors them) and the activation."""

    inputs: int = 11
    hidden: tuple[int, ...] = (300, 200, 75)
    latent: int = 2
    activation: str = "elu"

    def __post_init__(self) -> None:
        ok = (self.inputs == 11 and self.latent >= 1 and len(self.hidden) >= 1
              and all(isinstance(h, int) and h >= 1 for h in self.hidden)
              and self.activation in ACTIVATIONS)
        if not ok:
            raise VAEError(f"invalid VAE architecture {self.to_dict()}: inputs must be 11, "
                           f"hidden positive integers, activation one of {ACTIVATIONS}")

    def to_dict(self) -> dict:
        return {"inputs": self.inputs, "hidden": list(self.hidden), "latent": self.latent,
                "activation": self.activation}

    @classmethod
    def from_dict(cls, d: dict, where: str = "architecture") -> Architecture:
        try:
            return cls(int(d["inputs"]), tuple(int(h) for h in d["hidden"]), int(d["latent"]),
                       str(d["activation"]))
        except (KeyError, TypeError, ValueError) as exc:
            if isinstance(exc, VAEError):
                raise VAEError(f"{where}: {exc}") from exc
            raise VAEError(f"{where}: not a VAE architecture ({exc!r})") from exc

    def encoder_sizes(self) -> list[tuple[int, int]]:
        sizes = (self.inputs, *self.hidden)
        return list(zip(sizes[:-1], sizes[1:], strict=True))

    def decoder_sizes(self) -> list[tuple[int, int]]:
        sizes = (self.latent, *self.hidden[::-1])
        return list(zip(sizes[:-1], sizes[1:], strict=True))

    def tensor_shapes(self) -> dict[str, tuple[int, ...]]:
        """Name → shape of every tensor in ``vae.safetensors`` (torch Linear layout)."""
        shapes: dict[str, tuple[int, ...]] = {}
        for part, sizes in (("encoder", self.encoder_sizes()), ("decoder", self.decoder_sizes())):
            for i, (a, b) in enumerate(sizes):
                shapes[f"{part}.{i}.weight"], shapes[f"{part}.{i}.bias"] = (b, a), (b,)
        for head in ("mu", "logvar"):
            shapes[f"{head}.weight"], shapes[f"{head}.bias"] = (self.latent, self.hidden[-1]), (
                self.latent,)
        shapes["output.weight"], shapes["output.bias"] = (self.inputs, self.hidden[0]), (
            self.inputs,)
        shapes["norm.mean"] = shapes["norm.std"] = (self.inputs,)
        return shapes


# ---- numpy inference ------------------------------------------------------------------
def _activate(x: np.ndarray, kind: str) -> np.ndarray:
    """ReLU or ELU in place on a fresh layer output (ELU = max(x, 0) + expm1(min(x, 0)),
    four times faster than ``np.where`` on a 10k-row batch)."""
    if kind == "relu":
        return np.maximum(x, 0.0, out=x)
    negative = np.minimum(x, 0.0)
    np.expm1(negative, out=negative)
    np.maximum(x, 0.0, out=x)
    x += negative
    return x


class VAE:
    """A trained VAE for inference in numpy: ``encode`` rows to latent means, ``decode``
    latent points to rows. Immutable once built; training makes a new one."""

    def __init__(self, architecture: Architecture, tensors: dict[str, np.ndarray]) -> None:
        check_tensors(architecture, tensors, "tensors")
        self.architecture = architecture
        self.tensors = {k: np.array(v, dtype=np.float32) for k, v in tensors.items()}
        self.mean = self.tensors["norm.mean"].astype(np.float64)
        self.std = self.tensors["norm.std"].astype(np.float64)
        t = self.tensors
        self._enc = [(t[f"encoder.{i}.weight"].T.copy(), t[f"encoder.{i}.bias"])
                     for i in range(len(architecture.hidden))]
        self._dec = [(t[f"decoder.{i}.weight"].T.copy(), t[f"decoder.{i}.bias"])
                     for i in range(len(architecture.hidden))]
        self._mu = (t["mu.weight"].T.copy(), t["mu.bias"])
        self._out = (t["output.weight"].T.copy(), t["output.bias"])

    def _rows(self, x, columns: int, what: str) -> np.ndarray:
        x = np.asarray(x, dtype=np.float64)
        x = x[None] if x.ndim == 1 else x
        if x.ndim != 2 or x.shape[1] != columns or not np.all(np.isfinite(x)):
            raise ValueError(f"{what} must be a finite (N, {columns}) array, got shape "
                             f"{np.shape(x)}")
        return x

    def normalise(self, x) -> np.ndarray:
        """Rows standardised with the training statistics (float32, the network's input)."""
        x = self._rows(x, self.architecture.inputs, "VAE rows")
        return ((x - self.mean) / self.std).astype(np.float32)

    def encode(self, x) -> np.ndarray:
        """Latent means (N, latent) of rows [q, point, flag] (N, 11); float64."""
        h = self.normalise(x)
        for w, b in self._enc:
            h = h @ w
            h += b
            h = _activate(h, self.architecture.activation)
        return (h @ self._mu[0] + self._mu[1]).astype(np.float64)

    def decode_normalised(self, z) -> np.ndarray:
        """The decoder's raw output: 10 standardised values and the flag logit."""
        h = self._rows(z, self.architecture.latent, "latent points").astype(np.float32)
        for w, b in self._dec:
            h = h @ w
            h += b
            h = _activate(h, self.architecture.activation)
        return h @ self._out[0] + self._out[1]

    def decode(self, z) -> np.ndarray:
        """Rows [q, point, p(collision)] (N, 11) decoded from latent points (N, latent)."""
        out = self.decode_normalised(z).astype(np.float64)
        rows = out * self.std + self.mean
        rows[:, FLAG] = 0.5 * (1.0 + np.tanh(0.5 * out[:, FLAG]))  # sigmoid, overflow-free
        return rows

    def reconstruct(self, x) -> np.ndarray:
        return self.decode(self.encode(x))

    def to_torch(self):
        """The same network as a torch module (for torch inference or further training)."""
        import torch

        net = build_network(self.architecture)
        state = {k: torch.from_numpy(v.copy()) for k, v in self.tensors.items()
                 if not k.startswith("norm.")}
        net.load_state_dict(state)
        return net.eval()


def check_tensors(arch: Architecture, tensors: dict, where: str) -> None:
    """Every expected tensor present with its shape and finite values, and nothing else."""
    expected = arch.tensor_shapes()
    missing, extra = sorted(set(expected) - set(tensors)), sorted(set(tensors) - set(expected))
    if missing or extra:
        raise VAEError(f"{where}: tensors do not match the architecture {arch.to_dict()} "
                       f"(missing {missing}, unexpected {extra})")
    for name, shape in expected.items():
        got = tuple(np.shape(tensors[name]))
        if got != shape:
            raise VAEError(f"{where}: tensor {name} has shape {got}, the architecture "
                           f"{arch.to_dict()} needs {shape}")
        if not np.all(np.isfinite(np.asarray(tensors[name], dtype=np.float64))):
            raise VAEError(f"{where}: tensor {name} holds NaN or inf")
    if np.any(np.asarray(tensors["norm.std"]) <= 0.0):
        raise VAEError(f"{where}: norm.std must be positive")


# ---- torch network and training -------------------------------------------------------
def build_network(arch: Architecture):
    """The torch module; parameter names match :meth:`Architecture.tensor_shapes`."""
    import torch
    from torch import nn

    act = nn.ELU if arch.activation == "elu" else nn.ReLU

    class Net(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.encoder = nn.ModuleList(nn.Linear(a, b) for a, b in arch.encoder_sizes())
            self.mu = nn.Linear(arch.hidden[-1], arch.latent)
            self.logvar = nn.Linear(arch.hidden[-1], arch.latent)
            self.decoder = nn.ModuleList(nn.Linear(a, b) for a, b in arch.decoder_sizes())
            self.output = nn.Linear(arch.hidden[0], arch.inputs)
            self.act = act()

        def encode(self, x):
            for layer in self.encoder:
                x = self.act(layer(x))
            return self.mu(x), self.logvar(x)

        def decode(self, z):
            for layer in self.decoder:
                z = self.act(layer(z))
            return self.output(z)

        def forward(self, x):
            mu, logvar = self.encode(x)
            z = mu + torch.randn_like(mu) * torch.exp(0.5 * logvar)
            return self.decode(z), mu, logvar

    return Net()


def _loss(net, batch, flag_weight: float, beta: float):
    """(total, reconstruction, KL) averaged over the batch: squared error summed over the
    10 standardised values, weighted BCE on the flag logit, β·KL to N(0, I)."""
    import torch.nn.functional as F

    recon, mu, logvar = net(batch[0])
    mse = ((recon[:, :FLAG] - batch[0][:, :FLAG]) ** 2).sum(dim=1).mean()
    bce = F.binary_cross_entropy_with_logits(recon[:, FLAG], batch[1])
    kl = (-0.5 * (1.0 + logvar - mu**2 - logvar.exp()).sum(dim=1)).mean()
    rec = mse + flag_weight * bce
    return rec + beta * kl, rec, kl


def split_rows(n: int, val_fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Shuffled (train, held-out) row indices, deterministic from the seed."""
    if not 0.0 < val_fraction < 1.0:
        raise ValueError(f"val_fraction must be in (0, 1), got {val_fraction}")
    order = np.random.default_rng(seed).permutation(n)
    n_val = max(1, int(round(val_fraction * n)))
    return order[n_val:], order[:n_val]


def check_rows(x, what: str = "training rows") -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 11:
        raise ValueError(f"{what} must be an (N, 11) array [q, point, flag], got shape "
                         f"{x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError(f"{what} hold NaN or inf")
    if not np.all((x[:, FLAG] == 0.0) | (x[:, FLAG] == 1.0)):
        raise ValueError(f"{what}: the collision flag (column {FLAG}) must be 0 or 1")
    return x


def train_vae(x, epochs: int = 20, batch_size: int = 512, beta: float = 1e-3,
              lr: float = 1e-3, seed: int = 0, flag_weight: float = 10.0,
              val_fraction: float = 0.1, architecture: Architecture | None = None,
              threads: int | None = None, progress: bool = True) -> tuple[VAE, dict]:
    """Train a VAE on rows [q, point, flag] (N, 11); returns it and metrics on held-out rows
    (reconstruction per input group, latent separability, loss history, timing).

    ``threads`` defaults to every core. Measured here (batch 512): 13 ms per step on one
    thread; two threads are faster only on idle cores — with other processes running they
    spin against them and a step took 95 ms, so pass ``threads=1`` on a busy machine."""
    import torch
    from tqdm import tqdm

    x = check_rows(x)
    if len(x) < 20:
        raise ValueError(f"need at least 20 training rows, got {len(x)}")
    if epochs < 1 or batch_size < 1 or not (lr > 0.0) or beta < 0.0 or flag_weight < 0.0:
        raise ValueError(f"invalid training options: epochs={epochs}, batch_size={batch_size}"
                         f", lr={lr}, beta={beta}, flag_weight={flag_weight}")
    arch = architecture or Architecture()
    torch.set_num_threads(threads or os.cpu_count() or 1)
    torch.manual_seed(seed)
    train_idx, val_idx = split_rows(len(x), val_fraction, seed)
    mean, std = x[train_idx].mean(axis=0), x[train_idx].std(axis=0)
    std = np.where(std > 1e-6, std, 1.0)  # a constant column (e.g. one node) stays as is
    norm = ((x - mean) / std).astype(np.float32)
    inputs = torch.from_numpy(norm)
    flags = torch.from_numpy(x[:, FLAG].astype(np.float32))
    net = build_network(arch)
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    gen = torch.Generator().manual_seed(seed)
    train_t = torch.from_numpy(train_idx)
    n_batches = math.ceil(len(train_idx) / batch_size)
    history, val_history, epoch_seconds = [], [], []
    bar = tqdm(total=epochs * n_batches, desc="train", unit="batch", disable=not progress)
    for _ in range(epochs):
        start, total = time.perf_counter(), 0.0
        net.train()
        order = train_t[torch.randperm(len(train_t), generator=gen)]
        for b in range(n_batches):
            rows = order[b * batch_size:(b + 1) * batch_size]
            loss, _, _ = _loss(net, (inputs[rows], flags[rows]), flag_weight, beta)
            opt.zero_grad()
            loss.backward()
            opt.step()
            total += loss.item() * len(rows)
            bar.update(1)
        history.append(total / len(train_idx))
        val_history.append(_held_out_loss(net, inputs, flags, val_idx, flag_weight, beta))
        epoch_seconds.append(time.perf_counter() - start)
        bar.set_postfix(loss=f"{history[-1]:.3f}", val=f"{val_history[-1]:.3f}")
    bar.close()
    tensors = {k: v.detach().numpy().copy() for k, v in net.state_dict().items()}
    tensors["norm.mean"], tensors["norm.std"] = mean.astype(np.float32), std.astype(np.float32)
    vae = VAE(arch, tensors)
    metrics = evaluate(vae, x[val_idx], x[train_idx], seed)
    metrics.update(
        loss_history=[round(v, 5) for v in history],
        val_loss_history=[round(v, 5) for v in val_history],
        seconds_per_epoch=round(float(np.mean(epoch_seconds)), 3),
        train_seconds=round(float(np.sum(epoch_seconds)), 3),
        train_rows=len(train_idx), val_rows=len(val_idx),
        options={"epochs": epochs, "batch_size": batch_size, "beta": beta, "lr": lr,
                 "seed": seed, "flag_weight": flag_weight, "val_fraction": val_fraction,
                 "threads": torch.get_num_threads()},
    )
    return vae, metrics


def _held_out_loss(net, inputs, flags, val_idx: np.ndarray, flag_weight: float,
                   beta: float) -> float:
    """The loss on (up to 20,000) held-out rows, decoding the latent mean instead of a noisy
    sample so epochs compare without touching the training random stream."""
    import torch
    import torch.nn.functional as F

    net.eval()
    with torch.no_grad():
        rows = torch.from_numpy(val_idx[:20000])
        x, flag = inputs[rows], flags[rows]
        mu, logvar = net.encode(x)
        recon = net.decode(mu)
        mse = ((recon[:, :FLAG] - x[:, :FLAG]) ** 2).sum(dim=1).mean()
        bce = F.binary_cross_entropy_with_logits(recon[:, FLAG], flag)
        kl = (-0.5 * (1.0 + logvar - mu**2 - logvar.exp()).sum(dim=1)).mean()
    return float(mse + flag_weight * bce + beta * kl)


# ---- metrics --------------------------------------------------------------------------
def evaluate(vae: VAE, held_out, reference=None, seed: int = 0,
             max_rows: int = 50000) -> dict:
    """Reconstruction error per input group on ``held_out`` rows and latent separability:
    ROC AUC of classifiers that predict the collision flag from z alone — a k-nearest-
    neighbour vote (k = 25; the graph itself is built from latent neighbours) fitted on
    ``reference`` rows (default: half of ``held_out``), and a logistic regression on cubic
    features of z (a smooth boundary)."""
    from sklearn.linear_model import LogisticRegression
    from sklearn.metrics import roc_auc_score
    from sklearn.neighbors import KNeighborsClassifier
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import PolynomialFeatures, StandardScaler

    rng = np.random.default_rng(seed)
    held_out = check_rows(held_out, "held-out rows")
    held_out = held_out[rng.permutation(len(held_out))[:max_rows]]
    if reference is None:
        half = len(held_out) // 2
        reference, held_out = held_out[:half], held_out[half:]
    reference = check_rows(reference, "reference rows")
    reference = reference[rng.permutation(len(reference))[:max_rows]]
    z = vae.encode(held_out)
    recon = vae.decode(z)
    flag = held_out[:, FLAG] > 0.5
    metrics = {
        "joint_rmse_rad": float(np.sqrt(np.mean((recon[:, :7] - held_out[:, :7]) ** 2))),
        "point_rmse_m": float(np.sqrt(np.mean((recon[:, 7:10] - held_out[:, 7:10]) ** 2))),
        "flag_accuracy": float(np.mean((recon[:, FLAG] > 0.5) == flag)),
        "collision_share": float(flag.mean()),
        "latent_auc_knn": math.nan, "latent_auc_poly3": math.nan,
    }
    z_ref, flag_ref = vae.encode(reference), reference[:, FLAG] > 0.5
    if flag.all() or not flag.any() or flag_ref.all() or not flag_ref.any():
        return metrics  # AUC is undefined with one label
    knn = KNeighborsClassifier(n_neighbors=min(25, len(z_ref))).fit(z_ref, flag_ref)
    metrics["latent_auc_knn"] = float(roc_auc_score(flag, knn.predict_proba(z)[:, 1]))
    poly = make_pipeline(StandardScaler(), PolynomialFeatures(3),
                         LogisticRegression(max_iter=1000))
    poly.fit(z_ref, flag_ref)
    metrics["latent_auc_poly3"] = float(roc_auc_score(flag, poly.predict_proba(z)[:, 1]))
    return metrics


# ---- files ----------------------------------------------------------------------------
def save_vae(vae: VAE, directory: str | Path, record: dict | None = None) -> dict:
    """Write ``vae.safetensors`` and ``vae.json``; return the JSON dict (architecture,
    normalisation, the weights' SHA-256 and ``record``, e.g. training metrics) for the
    ``vae`` section of ``meta.json``."""
    from safetensors.numpy import save_file

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    arch = vae.architecture.to_dict()
    weights = directory / WEIGHTS_FILE
    save_file({k: np.ascontiguousarray(v) for k, v in vae.tensors.items()}, str(weights),
              metadata={"format": VAE_FORMAT, "version": str(VAE_VERSION),
                        "architecture": json.dumps(arch, sort_keys=True)})
    config = {"format": VAE_FORMAT, "version": VAE_VERSION, "architecture": arch,
              "mean": vae.mean.tolist(), "std": vae.std.tolist(), "sha256": sha256(weights),
              **(record or {})}
    (directory / CONFIG_FILE).write_text(json.dumps(config, indent=1) + "\n")
    return config


def _read_config(directory: Path) -> tuple[dict, str]:
    """``vae.json``, else the ``vae`` section of ``meta.json``; with where it came from."""
    for name, key in ((CONFIG_FILE, None), ("meta.json", "vae")):
        path = directory / name
        if not path.is_file():
            continue
        try:
            doc = json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise VAEError(f"{path}: not valid JSON ({exc})") from exc
        doc = doc.get(key) if key and isinstance(doc, dict) else doc
        if isinstance(doc, dict):
            return doc, str(path) + (f" ['{key}']" if key else "")
    raise VAEError(f"{directory}: no {CONFIG_FILE} and no 'vae' section in meta.json")


def load_vae(directory: str | Path, config: dict | None = None) -> VAE:
    """Rebuild the VAE from ``vae.safetensors`` and its JSON description (``config``, else
    ``vae.json``, else ``meta.json['vae']``), verifying hash, architecture, tensor names,
    shapes, values and normalisation. Never executes anything from the files."""
    from safetensors import safe_open

    directory = Path(directory)
    where = "given VAE config"
    if config is None:
        config, where = _read_config(directory)
    if not isinstance(config, dict) or config.get("format") != VAE_FORMAT:
        raise VAEError(f"{where}: not a {VAE_FORMAT} description")
    if config.get("version") != VAE_VERSION:
        raise VAEError(f"{where}: VAE version {config.get('version')!r}, this package reads "
                       f"{VAE_VERSION}")
    arch = Architecture.from_dict(config.get("architecture") or {}, where)
    path = directory / WEIGHTS_FILE
    if not path.is_file():
        raise VAEError(f"{path}: missing")
    if sha256(path) != config.get("sha256"):
        raise VAEError(f"{path}: SHA-256 does not match {where} — the file is truncated, "
                       "swapped or modified")
    try:
        with safe_open(str(path), framework="numpy") as f:
            meta = f.metadata() or {}
            tensors = {k: f.get_tensor(k) for k in f.keys()}
    except Exception as exc:  # safetensors raises its own types for a corrupt header/body
        raise VAEError(f"{path}: not a readable safetensors file ({exc})") from exc
    try:
        file_arch = Architecture.from_dict(json.loads(meta.get("architecture", "{}")), str(path))
    except json.JSONDecodeError as exc:
        raise VAEError(f"{path}: architecture metadata is not JSON ({exc})") from exc
    if file_arch != arch:
        raise VAEError(f"{where} describes architecture {arch.to_dict()} but {path} holds "
                       f"{file_arch.to_dict()}")
    check_tensors(arch, tensors, str(path))
    for key in ("mean", "std"):
        if not _same_values(config.get(key), tensors[f"norm.{key}"]):
            raise VAEError(f"{where}: normalisation '{key}' does not match {path}")
    return VAE(arch, tensors)


def _same_values(listed, tensor: np.ndarray) -> bool:
    """JSON copy of a normalisation vector equals the tensor (to float32 precision)."""
    try:
        values = np.asarray(listed, dtype=np.float64)
    except (TypeError, ValueError):
        return False
    return values.shape == tensor.shape and bool(np.allclose(values, tensor, rtol=1e-6,
                                                             atol=1e-7))


def benchmark_inference(vae: VAE, batch: int = 10000, repeats: int = 200, seed: int = 0) -> dict:
    """Best-of-``repeats`` µs of encode for one row and for ``batch`` rows, numpy vs
    torch.no_grad — the planner encodes single rows on its hot path and whole data sets when
    building graphs. The minimum, as ``timeit`` advises: other processes only add time."""
    import torch

    rng = np.random.default_rng(seed)
    x = vae.mean + vae.std * rng.normal(size=(batch, vae.architecture.inputs))
    net = vae.to_torch()

    def torch_encode(rows: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return net.encode(torch.from_numpy(vae.normalise(rows)))[0].numpy()

    def best_us(fn, rows, n) -> float:
        times = []
        for _ in range(n):
            t = time.perf_counter()
            fn(rows)
            times.append(time.perf_counter() - t)
        return round(1e6 * min(times), 1)

    return {"numpy_1_row_us": best_us(vae.encode, x[:1], repeats),
            "torch_1_row_us": best_us(torch_encode, x[:1], repeats),
            f"numpy_{batch}_rows_us": best_us(vae.encode, x, max(3, repeats // 20)),
            f"torch_{batch}_rows_us": best_us(torch_encode, x, max(3, repeats // 20)),
            "torch_threads": torch.get_num_threads()}


# ---- command line ---------------------------------------------------------------------
def rows_from(data: dict[str, np.ndarray]) -> np.ndarray:
    """VAE rows [q, point, collision] (N, 11) from a collected data set."""
    return np.column_stack([data["q"], data["point"],
                            np.asarray(data["collision"], np.float64)])


def train_main(argv: list[str] | None = None) -> int:
    """``damon-ros train``: train the VAE on a collected data set into a model directory."""
    from damon_ros.learning.bundle import write_meta
    from damon_ros.learning.collect import load_dataset

    parser = argparse.ArgumentParser(
        prog="damon-ros train",
        description="Train the DAMON VAE (11-300-200-75-2) on collected samples; writes "
                    "vae.safetensors, vae.json and meta.json into the model directory.")
    parser.add_argument("--data", required=True, help="directory written by damon-ros collect")
    parser.add_argument("--out", required=True, help="model directory to write")
    parser.add_argument("--epochs", type=int, default=20)
    parser.add_argument("--beta", type=float, default=1e-3, help="KL weight β")
    parser.add_argument("--flag-weight", type=float, default=10.0,
                        help="weight of the collision-flag BCE in the reconstruction loss")
    parser.add_argument("--batch-size", type=int, default=512)
    parser.add_argument("--lr", type=float, default=1e-3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--val-fraction", type=float, default=0.1)
    parser.add_argument("--max-rows", type=int, default=0, help="use at most this many rows")
    parser.add_argument("--threads", type=int, default=0,
                        help="torch threads (default: all cores; 1 is faster on a busy machine)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    try:
        data, data_meta = load_dataset(args.data)
        x = rows_from(data)
        if args.max_rows:
            x = x[np.random.default_rng(args.seed).permutation(len(x))[:args.max_rows]]
        vae, metrics = train_vae(x, args.epochs, args.batch_size, args.beta, args.lr,
                                 args.seed, args.flag_weight, args.val_fraction,
                                 threads=args.threads or None, progress=not args.quiet)
    except ValueError as exc:
        print(f"damon-ros train: {exc}", file=sys.stderr)
        return 2
    out = Path(args.out)
    section = save_vae(vae, out, {"metrics": metrics, "data": args.data})
    stale = [name for name in ("graph.npz", "gmr.npz") if (out / name).exists()]
    if stale:
        print(f"damon-ros train: {', '.join(stale)} in {out} belong to the previous VAE; "
              "run damon-ros build-graph again", file=sys.stderr)
    write_meta(out, {"robot": "panda", "vae": section, "data": {
        k: data_meta.get(k) for k in ("n_samples", "seed", "spacing", "radius", "margin",
                                      "collision_ratio", "fingerprint")}})
    print(f"trained on {metrics['train_rows']} rows, {metrics['seconds_per_epoch']:.1f} s/epoch;"
          f" held-out: joints RMSE {metrics['joint_rmse_rad']:.3f} rad, point RMSE "
          f"{metrics['point_rmse_m']:.3f} m, flag accuracy {metrics['flag_accuracy']:.3f}, "
          f"latent AUC kNN {metrics['latent_auc_knn']:.4f} / poly3 "
          f"{metrics['latent_auc_poly3']:.4f} -> {out}")
    return 0


main = train_main  # the name ``damon-ros`` (cli.SUBCOMMANDS) calls
