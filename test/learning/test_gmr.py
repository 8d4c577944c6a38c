"""GMR: conditioning recovers a known relation, P(d ≤ λ | z) is calibrated, files round-trip."""

from __future__ import annotations

import numpy as np
import pytest

from damon_ros.learning.gmr import CollisionGMR, predicted_runtime, reliability


@pytest.fixture(scope="module")
def fitted():
    rng = np.random.default_rng(0)
    z = rng.normal(size=(20000, 2))
    d = 0.1 * z[:, 0] + 0.02 * rng.normal(size=len(z))
    return z, d, CollisionGMR.fit(z, d, n_components=4, margin=0.0, seed=0)


def test_conditional_mean_recovers_the_linear_relation(fitted):
    z, d, gmr = fitted
    assert np.abs(gmr.expected_distance(z) - 0.1 * z[:, 0]).mean() < 0.005


def test_collision_probability_is_calibrated_within_005(fitted):
    z, d, gmr = fitted
    rows, error = reliability(gmr.collision_probability(z), d <= 0.0)
    assert error < 0.05
    assert rows[0, 0] < 0.2 and rows[-1, 0] > 0.8  # it spans the range, not a constant


def test_probability_grows_with_margin(fitted):
    z, _, gmr = fitted
    low = gmr.collision_probability(z[:100], margin=0.0)
    high = gmr.collision_probability(z[:100], margin=0.1)
    assert np.all(high >= low - 1e-12) and np.any(high > low + 0.05)


def test_save_load_round_trip_and_corrupt_file(fitted, tmp_path):
    z, _, gmr = fitted
    gmr.save(tmp_path / "gmr.npz")
    again = CollisionGMR.load(tmp_path / "gmr.npz")
    assert np.allclose(again.collision_probability(z[:50]), gmr.collision_probability(z[:50]))
    (tmp_path / "bad.npz").write_bytes((tmp_path / "gmr.npz").read_bytes()[:200])
    with pytest.raises(ValueError, match="bad.npz"):
        CollisionGMR.load(tmp_path / "bad.npz")


def test_runtime_model_inflates_planning_time_by_expected_reroutes():
    t = predicted_runtime(np.array([0.0, 0.5]), t_plan=0.01, t_motion=np.array([1.0, 2.0]))
    assert t == pytest.approx(0.01 + 0.02 + 3.0)
