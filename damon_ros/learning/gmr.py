"""DAMON module 3: Gaussian-mixture regression of clearance given latent position.

A K-component GMM over (z1, z2, d), fitted by EM, gives by conditioning a mixture
p(d | z) = Σ_k π_k(z) N(d; μ_k(z), σ_k²). The collision probability for a user margin λ is
the closed-form integral P(d ≤ λ | z) = Σ_k π_k(z) Φ((λ − μ_k(z)) / σ_k).

The paper integrates over 0 ≤ d ≤ λ; our distances are signed (d < 0 is penetration,
which is a collision too), so the lower bound is −∞. The runtime model of a task is
T = Σ_i t_p / (1 − p_i) + t_r: planning time inflated by the expected number of re-routes
at each step, plus motion time.
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.special import erf

GMR_VERSION = 1


@dataclass
class CollisionGMR:
    """Mixture parameters over (z1, z2, d) and the margin λ they are evaluated with."""

    weights: np.ndarray  # (K,)
    means: np.ndarray  # (K, 3)
    covariances: np.ndarray  # (K, 3, 3)
    margin: float

    def __post_init__(self) -> None:
        szz = self.covariances[:, :2, :2]
        sdz = self.covariances[:, 2, :2]
        self._szz_inv = np.linalg.inv(szz)
        self._gain = np.einsum("ki,kij->kj", sdz, self._szz_inv)  # Σ_dz Σ_zz⁻¹, (K, 2)
        self._var = self.covariances[:, 2, 2] - np.einsum("kj,kj->k", self._gain, sdz)
        self._var = np.maximum(self._var, 1e-10)
        self._log_norm = np.log(self.weights) - 0.5 * np.log(
            (2 * np.pi) ** 2 * np.linalg.det(szz))

    @classmethod
    def fit(cls, z: np.ndarray, d: np.ndarray, n_components: int = 8, margin: float = 0.02,
            seed: int = 0, max_samples: int = 200_000) -> CollisionGMR:
        """EM fit (scikit-learn, full covariances) on at most ``max_samples`` rows."""
        from sklearn.mixture import GaussianMixture

        x = np.column_stack([z, d]).astype(np.float64)
        if len(x) > max_samples:
            x = x[np.random.default_rng(seed).choice(len(x), max_samples, replace=False)]
        gmm = GaussianMixture(n_components=n_components, covariance_type="full",
                              random_state=seed, reg_covar=1e-6, max_iter=300).fit(x)
        return cls(gmm.weights_, gmm.means_, gmm.covariances_, margin)

    def condition(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Responsibilities π_k(z) (N,K), conditional means μ_k(z) (N,K), std σ_k (K,)."""
        z = np.atleast_2d(np.asarray(z, float))
        diff = z[:, None, :] - self.means[None, :, :2]  # (N, K, 2)
        maha = np.einsum("nki,kij,nkj->nk", diff, self._szz_inv, diff)
        log_p = self._log_norm[None] - 0.5 * maha
        log_p -= log_p.max(axis=1, keepdims=True)
        resp = np.exp(log_p)
        resp /= resp.sum(axis=1, keepdims=True)
        mu = self.means[None, :, 2] + np.einsum("kj,nkj->nk", self._gain, diff)
        return resp, mu, np.sqrt(self._var)

    def expected_distance(self, z: np.ndarray) -> np.ndarray:
        resp, mu, _ = self.condition(z)
        return (resp * mu).sum(axis=1)

    def collision_probability(self, z: np.ndarray, margin: float | None = None) -> np.ndarray:
        """P(d ≤ λ | z), closed form."""
        lam = self.margin if margin is None else margin
        resp, mu, sigma = self.condition(z)
        cdf = 0.5 * (1.0 + erf((lam - mu) / (np.sqrt(2.0) * sigma[None])))
        return np.clip((resp * cdf).sum(axis=1), 0.0, 1.0)

    def save(self, path: str | Path) -> None:
        np.savez(path, version=np.array(GMR_VERSION), weights=self.weights, means=self.means,
                 covariances=self.covariances, margin=np.array(self.margin))

    @classmethod
    def load(cls, path: str | Path) -> CollisionGMR:
        try:
            with np.load(path, allow_pickle=False) as f:
                data = {k: f[k] for k in ("version", "weights", "means", "covariances", "margin")}
        except KeyError as exc:
            raise ValueError(f"{path}: GMR file lacks array {exc}") from exc
        except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
            raise ValueError(f"{path}: not a readable GMR npz ({exc})") from exc
        if int(data["version"]) != GMR_VERSION:
            raise ValueError(f"{path}: GMR version is not {GMR_VERSION}")
        k = len(data["weights"])
        if data["means"].shape != (k, 3) or data["covariances"].shape != (k, 3, 3):
            raise ValueError(f"{path}: GMR arrays have inconsistent shapes")
        if not np.isclose(data["weights"].sum(), 1.0, atol=1e-6):
            raise ValueError(f"{path}: GMR weights do not sum to 1")
        return cls(data["weights"], data["means"], data["covariances"], float(data["margin"]))


def predicted_runtime(p_collision: np.ndarray, t_plan: float, t_motion: np.ndarray) -> float:
    """T = Σ_i t_p / (1 − p_i) + t_r,i over the steps of a route (p capped below 1)."""
    p = np.clip(np.asarray(p_collision, float), 0.0, 0.99)
    return float(np.sum(t_plan / (1.0 - p) + np.asarray(t_motion, float)))


def reliability(p_predicted: np.ndarray, collided: np.ndarray, bins: int = 10):
    """Reliability curve of p(collision): per bin the mean prediction, the observed frequency
    and the count; and the count-weighted mean absolute calibration error."""
    p = np.asarray(p_predicted, float)
    y = np.asarray(collided, float)
    edges = np.linspace(0.0, 1.0, bins + 1)
    idx = np.clip(np.digitize(p, edges) - 1, 0, bins - 1)
    rows = []
    for b in range(bins):
        m = idx == b
        if m.any():
            rows.append((float(p[m].mean()), float(y[m].mean()), int(m.sum())))
    rows = np.array(rows)
    error = float(np.average(np.abs(rows[:, 0] - rows[:, 1]), weights=rows[:, 2]))
    return rows, error
