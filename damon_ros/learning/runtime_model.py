"""DAMON module 3 as a predictor: from a planned route to the task's runtime and re-routes.

The paper's per-step cost is t_i = t_p / (1 − p_i) + t_r: a step is re-planned with
probability p_i = P(d ≤ λ | z_i), so it costs 1 / (1 − p_i) plans on average, plus its
motion time. Here a route is planned once and re-routed only when something threatens it,
so a route of planned duration D takes

    T = t_p · (1 + E) + κ · D + t_0 + c_r · E

with E the expected number of re-routes, t_p the planning time at this graph size
(measured), κ the executed/planned motion ratio (the PID follower trails the reference),
t_0 the fixed cost of arriving (settling, holding the goal) and c_r the motion a re-route
adds; κ, t_0 and c_r are fitted by non-negative least squares on *fit* tasks and judged on
other, held-out tasks.

p_i comes from a GMR fitted on what the planner meets, not on the training samples: each
step of each planned fit-task route (its configuration every 0.25 s of motion) as the
latent point of [q_i, the closest obstacle point when planned, flag 0], paired with its
:func:`threat_distances` — how close any obstacle, moving as the scenario moves it, comes
to q_i before the arm has passed it (modelled as log clearance, see the analysis tool). The
route's re-route probability r is
1 − Π(1 − p_i) mapped through :class:`RouteCalibration`, and E = r / (1 − r).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import nnls

P_CAP = 0.99  # p_i is capped below 1, so one sure-to-collide waypoint is not infinitely many


def threat_distances(distance_at: Callable[[np.ndarray, float], np.ndarray],
                     path: np.ndarray, passed_at: np.ndarray, horizon: float,
                     step: float = 0.05) -> np.ndarray:
    """Per waypoint, the least clearance to the scene over [0, passed_at_i + horizon]:
    what the runtime would have to react to before the arm leaves that waypoint.
    ``distance_at(Q, t)`` gives the clearance of configurations ``Q`` at time ``t``."""
    end = float(np.max(passed_at)) + horizon if len(passed_at) else 0.0
    times = np.arange(0.0, end + step, step)
    best = np.full(len(path), np.inf)
    for t in times:
        live = passed_at + horizon >= t
        if live.any():
            best[live] = np.minimum(best[live], distance_at(path[live], float(t)))
    return best


def route_risk(p: np.ndarray) -> float:
    """1 − Π(1 − p_i): the route's re-route probability if its steps were independent."""
    p = np.clip(np.asarray(p, float), 0.0, P_CAP)
    return float(1.0 - np.prod(1.0 - p))


def expected_reroutes(r: float) -> float:
    """Re-routes of a route re-routed with probability ``r`` each time (geometric)."""
    r = min(max(float(r), 0.0), P_CAP)
    return r / (1.0 - r)


@dataclass(frozen=True)
class RouteCalibration:
    """P(re-routed) = σ(a + b · logit(route_risk)): neighbouring steps see the same passing
    obstacle, so their p_i are far from independent and 1 − Π(1 − p_i) over-counts; this
    monotone map (Platt scaling) is fitted on the fit tasks' outcomes."""

    a: float = 0.0
    b: float = 1.0

    @classmethod
    def fit(cls, risk: Sequence[float], rerouted: Sequence[bool]) -> RouteCalibration:
        y = np.asarray(rerouted, bool)
        if y.all() or not y.any():  # one class: only the base rate can be learnt
            rate = (y.sum() + 0.5) / (len(y) + 1.0)
            return cls(float(np.log(rate / (1 - rate))), 0.0)
        from sklearn.linear_model import LogisticRegression

        x = _logit(np.asarray(risk, float))[:, None]
        lr = LogisticRegression(C=1.0).fit(x, y)
        return cls(float(lr.intercept_[0]), float(lr.coef_[0, 0]))

    def __call__(self, risk: float) -> float:
        return float(1.0 / (1.0 + np.exp(-(self.a + self.b * _logit(np.array([risk]))[0]))))


def _logit(p: np.ndarray) -> np.ndarray:
    p = np.clip(p, 1e-4, 1 - 1e-4)
    return np.log(p / (1 - p))


def log_loss(p: np.ndarray, y: np.ndarray) -> float:
    """Mean negative log-likelihood of binary outcomes ``y`` under predictions ``p``."""
    p = np.clip(np.asarray(p, float), 1e-6, 1 - 1e-6)
    y = np.asarray(y, bool)
    return float(-np.mean(np.where(y, np.log(p), np.log(1 - p))))


@dataclass(frozen=True)
class RuntimeModel:
    """T = t_p · (1 + E) + κ · D + t_0 + c_r · E (see the module docstring)."""

    kappa: float
    t0: float
    c_reroute: float

    @classmethod
    def fit(cls, t_plan: Sequence[float], duration: Sequence[float],
            reroutes: Sequence[float], measured: Sequence[float]) -> RuntimeModel:
        """Non-negative least squares over fit tasks (each with its size's t_p)."""
        t_plan, e = np.asarray(t_plan, float), np.asarray(reroutes, float)
        x = np.column_stack([duration, np.ones(len(e)), e])
        y = np.asarray(measured, float) - t_plan * (1.0 + e)
        if len(y) < 3:
            raise ValueError(f"need at least 3 fit tasks, got {len(y)}")
        (kappa, t0, c_r), _ = nnls(x, y)
        return cls(float(kappa), float(t0), float(c_r))

    def predict(self, t_plan: float, duration: float, reroutes: float) -> float:
        return float(t_plan * (1.0 + reroutes) + self.kappa * duration + self.t0
                     + self.c_reroute * reroutes)

