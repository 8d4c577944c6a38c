"""The runtime model's parts on data whose answer is known."""

from __future__ import annotations

import numpy as np

from damon_ros.learning.runtime_model import (
    RouteCalibration,
    RuntimeModel,
    expected_reroutes,
    route_risk,
    threat_distances,
)


def test_the_fit_recovers_known_constants_from_noisy_tasks():
    rng = np.random.default_rng(0)
    duration = rng.uniform(0.5, 3.0, 200)
    e = rng.uniform(0.0, 0.5, 200)
    t_plan = np.full(200, 0.01)
    measured = t_plan * (1 + e) + 1.1 * duration + 0.3 + 0.4 * e + rng.normal(0, 0.01, 200)
    model = RuntimeModel.fit(t_plan, duration, e, measured)
    assert abs(model.kappa - 1.1) < 0.01 and abs(model.t0 - 0.3) < 0.02
    assert abs(model.c_reroute - 0.4) < 0.03
    assert abs(model.predict(0.01, 2.0, 0.0) - (0.01 + 2.2 + 0.3)) < 0.05


def test_threat_counts_an_obstacle_only_until_the_arm_has_passed():
    # configurations are 1-D "positions"; the obstacle sits at x = 1 and arrives at t = 2
    def distance_at(q: np.ndarray, t: float) -> np.ndarray:
        obstacle = 10.0 if t < 2.0 else 1.0
        return np.abs(q[:, 0] - obstacle)

    path = np.array([[1.0], [1.0]])
    d = threat_distances(distance_at, path, np.array([0.5, 3.0]), horizon=0.3)
    assert d[0] > 8.0  # passed at 0.5 s (+0.3 s horizon): long gone when it arrives
    assert d[1] == 0.0  # still ahead when it arrives


def test_route_risk_and_calibration():
    assert route_risk(np.array([0.5, 0.5])) == 0.75
    assert expected_reroutes(0.5) == 1.0
    never = RouteCalibration.fit([0.1, 0.3, 0.2], [False, False, False])
    assert never(0.9) < 0.2 and never(0.9) == never(0.1)  # base rate only
    risk = np.linspace(0.01, 0.99, 200)
    outcome = np.random.default_rng(1).random(200) < risk
    fitted = RouteCalibration.fit(risk, outcome)
    assert fitted(0.9) > fitted(0.1)
