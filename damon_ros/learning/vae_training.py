"""Training the VAE of :mod:`damon_ros.learning.vae`: the loss, the training loop, held-out
metrics, and turning a collected data set into a model directory's VAE.

Apart from :mod:`damon_ros.learning.vae` because only training needs torch's autograd,
scikit-learn, the data set reader and the model directory's ``meta.json`` writer; the
planner and the nodes load a trained VAE without any of them.
"""

from __future__ import annotations

import math
import os
import time
from pathlib import Path

import numpy as np

from damon_ros.learning.bundle import write_meta
from damon_ros.learning.dataset import load_dataset
from damon_ros.learning.vae import FLAG, VAE, Architecture, build_network, save_vae

STALE_FILES = ("graph.npz", "gmr.npz")
"""Model files built from a VAE's latent space: a new VAE makes them stale."""


def rows_from(data: dict[str, np.ndarray]) -> np.ndarray:
    """VAE rows [q, point, collision] (N, 11) from a collected data set."""
    return np.column_stack([data["q"], data["point"],
                            np.asarray(data["collision"], np.float64)])


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



# ---- a data set into a model directory ------------------------------------------------
def load_training_rows(data_dir: str | Path, max_rows: int = 0,
                       seed: int = 0) -> tuple[np.ndarray, dict]:
    """(VAE rows, sidecar) of a collected data set; at most ``max_rows`` rows (0: all),
    drawn at random from ``seed``."""
    data, data_meta = load_dataset(data_dir)
    x = rows_from(data)
    if max_rows:
        x = x[np.random.default_rng(seed).permutation(len(x))[:max_rows]]
    return x, data_meta


def save_trained(out: Path, vae: VAE, metrics: dict, data_dir: str,
                 data_meta: dict) -> list[str]:
    """Write the VAE and a fresh ``meta.json`` (with the data set's provenance) into the
    model directory ``out``; returns the files there that belonged to the previous VAE."""
    section = save_vae(vae, out, {"metrics": metrics, "data": data_dir})
    stale = [name for name in STALE_FILES if (out / name).exists()]
    write_meta(out, {"robot": "panda", "vae": section, "data": {
        k: data_meta.get(k) for k in ("n_samples", "seed", "spacing", "radius", "margin",
                                      "collision_ratio", "fingerprint")}})
    return stale
