"""DAMON module 1: the variational autoencoder that learns the 2-D latent manifold.

Input rows are [q (7), obstacle point (3), collision flag]; the encoder is 300-200-75 to a
latent R² (mean and log-variance), the decoder mirrors it. Continuous inputs are
standardised with statistics saved beside the weights; the flag is decoded as a logit
(binary cross-entropy, weighted so that the latent space separates the two labels).

Weights live in ``vae.safetensors`` (tensors only) and the architecture and normalisation
in the ``vae`` section of ``meta.json``: nothing executable is ever loaded. Inference for
the planner runs in numpy (a row costs a few µs, no torch dispatch).
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import numpy as np

HIDDEN = (300, 200, 75)
N_INPUT = 11
N_LATENT = 2
VAE_VERSION = 1


def _torch():
    import torch

    torch.set_num_threads(os.cpu_count() or 1)
    return torch


def build_network(hidden=HIDDEN):
    """Encoder trunk, mean and log-variance heads, decoder, as torch modules."""
    torch = _torch()
    nn = torch.nn

    def mlp(sizes):
        layers = []
        for a, b in zip(sizes[:-1], sizes[1:], strict=True):
            layers += [nn.Linear(a, b), nn.ELU()]
        return nn.Sequential(*layers)

    class VAE(nn.Module):
        def __init__(self):
            super().__init__()
            self.encoder = mlp((N_INPUT, *hidden))
            self.mu = nn.Linear(hidden[-1], N_LATENT)
            self.logvar = nn.Linear(hidden[-1], N_LATENT)
            self.decoder = nn.Sequential(mlp((N_LATENT, *hidden[::-1])),
                                         nn.Linear(hidden[0], N_INPUT))

        def forward(self, x):
            h = self.encoder(x)
            mu, logvar = self.mu(h), self.logvar(h)
            z = mu + torch.randn_like(mu) * torch.exp(0.5 * logvar)
            return self.decoder(z), mu, logvar

    return VAE()


class LatentCodec:
    """Numpy inference of a trained VAE: ``encode`` rows to latent means, ``decode`` back."""

    def __init__(self, weights: dict[str, np.ndarray], config: dict) -> None:
        self.config = config
        self.mean = np.asarray(config["mean"], float)
        self.std = np.asarray(config["std"], float)
        self.weights = {k: np.asarray(v, np.float64) for k, v in weights.items()}
        hidden = tuple(config["hidden"])
        self._enc = [(f"encoder.{2 * i}.weight", f"encoder.{2 * i}.bias")
                     for i in range(len(hidden))]
        self._dec = [(f"decoder.0.{2 * i}.weight", f"decoder.0.{2 * i}.bias")
                     for i in range(len(hidden))] + [("decoder.1.weight", "decoder.1.bias")]

    def _layers(self, x: np.ndarray, layers, last_linear: bool) -> np.ndarray:
        for i, (w, b) in enumerate(layers):
            x = x @ self.weights[w].T + self.weights[b]
            if not (last_linear and i == len(layers) - 1):
                x = np.where(x > 0, x, np.expm1(np.minimum(x, 0)))  # ELU
        return x

    def normalise(self, x: np.ndarray) -> np.ndarray:
        x = np.atleast_2d(np.asarray(x, float))
        if x.shape[1] != N_INPUT:
            raise ValueError(f"VAE rows have {N_INPUT} columns, got {x.shape[1]}")
        out = x.copy()
        out[:, :10] = (x[:, :10] - self.mean) / self.std
        return out

    def encode(self, x: np.ndarray) -> np.ndarray:
        """Latent means (N, 2) of rows [q, point, flag]."""
        h = self._layers(self.normalise(x), self._enc, last_linear=False)
        return h @ self.weights["mu.weight"].T + self.weights["mu.bias"]

    def decode(self, z: np.ndarray) -> np.ndarray:
        """Rows [q, point, p(flag)] decoded from latent points (N, 2)."""
        out = self._layers(np.atleast_2d(np.asarray(z, float)), self._dec, last_linear=True)
        rows = np.empty_like(out)
        rows[:, :10] = out[:, :10] * self.std + self.mean
        rows[:, 10] = 1.0 / (1.0 + np.exp(-out[:, 10]))
        return rows


def rows_from(data: dict[str, np.ndarray]) -> np.ndarray:
    return np.column_stack([data["q"], data["point"], data["collision"]]).astype(np.float32)


def train_vae(x: np.ndarray, epochs: int = 20, batch_size: int = 1024, beta: float = 1e-3,
              flag_weight: float = 10.0, lr: float = 1e-3, seed: int = 0,
              progress: bool = True) -> tuple[LatentCodec, dict, dict]:
    """Train on rows [q, point, flag]; returns (codec, tensors to save, config)."""
    torch = _torch()
    from tqdm import tqdm

    if len(x) < 2 or x.shape[1] != N_INPUT:
        raise ValueError(f"training data must be N×{N_INPUT} with N ≥ 2, got {x.shape}")
    torch.manual_seed(seed)
    mean, std = x[:, :10].mean(axis=0), x[:, :10].std(axis=0) + 1e-6
    xn = x.copy()
    xn[:, :10] = (x[:, :10] - mean) / std
    data = torch.from_numpy(xn.astype(np.float32))
    net = build_network()
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    gen = torch.Generator().manual_seed(seed)
    history = []
    bar = tqdm(range(epochs), desc="train", disable=not progress, unit="epoch")
    for _ in bar:
        order = torch.randperm(len(data), generator=gen)
        total, count = 0.0, 0
        for start in range(0, len(data), batch_size):
            batch = data[order[start:start + batch_size]]
            recon, mu, logvar = net(batch)
            mse = ((recon[:, :10] - batch[:, :10]) ** 2).sum(dim=1).mean()
            bce = torch.nn.functional.binary_cross_entropy_with_logits(recon[:, 10], batch[:, 10])
            kl = (-0.5 * (1 + logvar - mu**2 - logvar.exp()).sum(dim=1)).mean()
            loss = mse + flag_weight * bce + beta * kl
            opt.zero_grad()
            loss.backward()
            opt.step()
            total += loss.item() * len(batch)
            count += len(batch)
        history.append(total / count)
        bar.set_postfix(loss=f"{history[-1]:.4f}")
    tensors = {k: v.detach().cpu().contiguous() for k, v in net.state_dict().items()}
    config = {"version": VAE_VERSION, "hidden": list(HIDDEN), "inputs": N_INPUT,
              "latent": N_LATENT, "mean": mean.tolist(), "std": std.tolist(), "beta": beta,
              "flag_weight": flag_weight, "epochs": epochs, "batch_size": batch_size, "lr": lr,
              "seed": seed, "loss_history": history}
    codec = LatentCodec({k: v.numpy() for k, v in tensors.items()}, config)
    return codec, tensors, config


def evaluate(codec: LatentCodec, x: np.ndarray, seed: int = 0) -> dict[str, float]:
    """Held-out reconstruction error per input group and latent separability (ROC AUC of a
    logistic regression on quadratic features of z predicting the collision flag)."""
    from sklearn.linear_model import LogisticRegression
    from sklearn.metrics import roc_auc_score
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import PolynomialFeatures, StandardScaler

    z = codec.encode(x)
    recon = codec.decode(z)
    flag = x[:, 10] > 0.5
    metrics = {
        "joint_rmse_rad": float(np.sqrt(np.mean((recon[:, :7] - x[:, :7]) ** 2))),
        "point_rmse_m": float(np.sqrt(np.mean((recon[:, 7:10] - x[:, 7:10]) ** 2))),
        "flag_accuracy": float(np.mean((recon[:, 10] > 0.5) == flag)),
    }
    if flag.all() or not flag.any():
        metrics["latent_auc"] = float("nan")
        return metrics
    half = len(z) // 2
    clf = make_pipeline(StandardScaler(), PolynomialFeatures(3), LogisticRegression(max_iter=500))
    clf.fit(z[:half], flag[:half])
    metrics["latent_auc"] = float(roc_auc_score(flag[half:], clf.predict_proba(z[half:])[:, 1]))
    return metrics


def save_vae(tensors: dict, config: dict, directory: str | Path) -> dict:
    """Write ``vae.safetensors``; return the config for the ``vae`` section of meta.json."""
    from safetensors.torch import save_file

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    save_file(tensors, str(directory / "vae.safetensors"))
    return config


def _expected_shapes(hidden) -> dict[str, tuple[int, ...]]:
    shapes = {}
    sizes = (N_INPUT, *hidden)
    for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:], strict=True)):
        shapes[f"encoder.{2 * i}.weight"], shapes[f"encoder.{2 * i}.bias"] = (b, a), (b,)
    shapes["mu.weight"] = shapes["logvar.weight"] = (N_LATENT, hidden[-1])
    shapes["mu.bias"] = shapes["logvar.bias"] = (N_LATENT,)
    sizes = (N_LATENT, *hidden[::-1])
    for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:], strict=True)):
        shapes[f"decoder.0.{2 * i}.weight"], shapes[f"decoder.0.{2 * i}.bias"] = (b, a), (b,)
    shapes["decoder.1.weight"], shapes["decoder.1.bias"] = (N_INPUT, hidden[0]), (N_INPUT,)
    return shapes


def load_vae(directory: str | Path, config: dict | None = None) -> LatentCodec:
    """Rebuild the codec from ``vae.safetensors`` and the ``vae`` section of meta.json,
    checking every tensor's name and shape; a bad file raises ValueError naming it."""
    from safetensors.numpy import load_file

    directory = Path(directory)
    if config is None:
        try:
            config = json.loads((directory / "meta.json").read_text())["vae"]
        except (OSError, KeyError, json.JSONDecodeError) as exc:
            raise ValueError(f"{directory / 'meta.json'}: no readable 'vae' section ({exc})") \
                from exc
    if config.get("version") != VAE_VERSION:
        raise ValueError(f"{directory}: VAE version {config.get('version')!r}, expected "
                         f"{VAE_VERSION}")
    path = directory / "vae.safetensors"
    try:
        weights = load_file(str(path))
    except Exception as exc:  # safetensors raises its own error types for corrupt headers
        raise ValueError(f"{path}: not a readable safetensors file ({exc})") from exc
    expected = _expected_shapes(tuple(config["hidden"]))
    if set(weights) != set(expected):
        raise ValueError(f"{path}: tensors {sorted(set(weights) ^ set(expected))} do not match "
                         "the VAE architecture in meta.json")
    for name, shape in expected.items():
        if tuple(weights[name].shape) != shape:
            raise ValueError(f"{path}: {name} has shape {tuple(weights[name].shape)}, "
                             f"expected {shape}")
        if not np.all(np.isfinite(weights[name])):
            raise ValueError(f"{path}: {name} holds NaN or inf")
    if len(config["mean"]) != 10 or len(config["std"]) != 10:
        raise ValueError(f"{directory / 'meta.json'}: VAE normalisation must have 10 values")
    return LatentCodec(weights, config)


def main(argv: list[str] | None = None) -> int:
    import argparse

    from damon_ros.collect import load_dataset
    from damon_ros.model import write_meta

    parser = argparse.ArgumentParser(prog="damon-ros train",
                                     description="Train the DAMON VAE on collected samples.")
    parser.add_argument("--data", required=True, help="directory written by damon-ros collect")
    parser.add_argument("--out", required=True, help="model directory to write")
    parser.add_argument("--epochs", type=int, default=20)
    parser.add_argument("--beta", type=float, default=1e-3, help="KL weight")
    parser.add_argument("--flag-weight", type=float, default=10.0)
    parser.add_argument("--batch-size", type=int, default=1024)
    parser.add_argument("--lr", type=float, default=1e-3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--max-rows", type=int, default=0, help="train on at most this many")
    parser.add_argument("--quiet", action="store_true")
    args = parser.parse_args(argv)
    try:
        data, data_meta = load_dataset(args.data)
    except ValueError as exc:
        print(f"damon-ros train: {exc}", file=sys.stderr)
        return 2
    x = rows_from(data)
    rng = np.random.default_rng(args.seed)
    order = rng.permutation(len(x))
    if args.max_rows:
        order = order[: args.max_rows]
    split = int(0.9 * len(order))
    t0 = time.perf_counter()
    codec, tensors, config = train_vae(x[order[:split]], args.epochs, args.batch_size, args.beta,
                                       args.flag_weight, args.lr, args.seed, not args.quiet)
    config["train_seconds"] = time.perf_counter() - t0
    config["train_rows"] = split
    config["metrics"] = evaluate(codec, x[order[split:]], args.seed)
    save_vae(tensors, config, args.out)
    write_meta(Path(args.out), {"robot": "panda", "vae": config, "data": {
        k: data_meta[k] for k in ("n_samples", "seed", "spacing", "radius", "margin",
                                  "collision_ratio")}})
    m = config["metrics"]
    print(f"trained on {split} rows in {config['train_seconds']:.0f} s; held-out: joints RMSE "
          f"{m['joint_rmse_rad']:.3f} rad, point RMSE {m['point_rmse_m']:.3f} m, flag accuracy "
          f"{m['flag_accuracy']:.3f}, latent AUC {m['latent_auc']:.4f}")
    return 0
