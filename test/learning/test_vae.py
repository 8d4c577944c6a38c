"""The VAE: training lowers the loss, the latent space separates the labels, numpy inference
equals torch, and saved files round-trip and refuse to load when damaged or mismatched."""

from __future__ import annotations

import json

import numpy as np
import pytest

from damon_ros.learning.bundle import read_meta
from damon_ros.learning.collect import collect
from damon_ros.learning.dataset import load_dataset
from damon_ros.learning.vae import Architecture, VAEError, load_vae, save_vae
from damon_ros.learning.vae_training import evaluate, rows_from, train_vae
from damon_ros.tools.model_build import train_main

EPOCHS = 8


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("data")
    collect(2400, 21, out, workers=1, chunk_size=1200, progress=False)
    return out


@pytest.fixture(scope="module")
def rows(data_dir):
    data, _ = load_dataset(data_dir)
    return rows_from(data)


@pytest.fixture(scope="module")
def trained(rows):
    return train_vae(rows, epochs=EPOCHS, batch_size=128, seed=0, threads=1, progress=False)


@pytest.fixture()
def saved(trained, tmp_path):
    vae, metrics = trained
    section = save_vae(vae, tmp_path, {"metrics": metrics})
    return tmp_path, section


def test_training_lowers_the_loss(trained):
    _, metrics = trained
    history = metrics["loss_history"]
    assert len(history) == EPOCHS
    assert history[-1] < 0.8 * history[0]
    assert metrics["val_loss_history"][-1] < metrics["val_loss_history"][0]


def test_latent_space_separates_collision_from_free(trained, rows):
    vae, metrics = trained
    assert metrics["latent_auc_knn"] > 0.95
    assert metrics["latent_auc_poly3"] > 0.9
    assert metrics["flag_accuracy"] > 0.9
    # reconstructions are far better than guessing the mean of each column
    assert metrics["point_rmse_m"] < float(np.sqrt(rows[:, 7:10].var(axis=0).mean()))
    assert 0.0 < metrics["joint_rmse_rad"] < 2.0


def test_numpy_inference_equals_torch(trained, rows):
    import torch

    vae, _ = trained
    net = vae.to_torch()
    with torch.no_grad():
        mu, _ = net.encode(torch.from_numpy(vae.normalise(rows[:500])))
        out = net.decode(mu)
    assert np.allclose(vae.encode(rows[:500]), mu.numpy(), atol=1e-5)
    assert np.allclose(vae.decode_normalised(mu.numpy()), out.numpy(), atol=1e-4)
    decoded = vae.decode(vae.encode(rows[:500]))
    assert decoded.shape == (500, 11)
    assert np.all((decoded[:, 10] >= 0.0) & (decoded[:, 10] <= 1.0))
    assert vae.encode(rows[0]).shape == (1, 2)  # one row as a flat vector


def test_training_is_deterministic(rows):
    a, _ = train_vae(rows[:600], epochs=2, batch_size=128, seed=3, threads=1, progress=False)
    b, _ = train_vae(rows[:600], epochs=2, batch_size=128, seed=3, threads=1, progress=False)
    assert np.array_equal(a.encode(rows[:50]), b.encode(rows[:50]))


def test_save_load_round_trip(saved, trained, rows):
    directory, section = saved
    vae, _ = trained
    loaded = load_vae(directory)
    assert np.array_equal(loaded.encode(rows), vae.encode(rows))
    assert np.array_equal(loaded.decode(np.zeros((3, 2))), vae.decode(np.zeros((3, 2))))
    # the section for meta.json is accepted as the description too (build-graph does this)
    assert np.array_equal(load_vae(directory, section).encode(rows[:5]), vae.encode(rows[:5]))
    assert json.loads((directory / "vae.json").read_text())["sha256"] == section["sha256"]


def test_truncated_or_tampered_weights_fail_clearly(saved):
    directory, section = saved
    path = directory / "vae.safetensors"
    blob = path.read_bytes()
    path.write_bytes(blob[: len(blob) // 2])
    with pytest.raises(VAEError, match="vae.safetensors: SHA-256 does not match"):
        load_vae(directory)
    # a truncated file whose description was updated to match is still not readable
    import hashlib

    forged = dict(section, sha256=hashlib.sha256(blob[: len(blob) // 2]).hexdigest())
    with pytest.raises(VAEError, match="not a readable safetensors file"):
        load_vae(directory, forged)
    flipped = bytearray(blob)
    flipped[-10] ^= 0x55
    path.write_bytes(bytes(flipped))
    with pytest.raises(VAEError, match="SHA-256"):
        load_vae(directory)
    path.unlink()
    with pytest.raises(VAEError, match="vae.safetensors: missing"):
        load_vae(directory)


def test_mismatched_description_fails_clearly(saved):
    directory, section = saved
    wrong = json.loads(json.dumps(section))
    wrong["architecture"]["hidden"] = [300, 200, 50]
    with pytest.raises(VAEError, match="describes architecture"):
        load_vae(directory, wrong)
    wrong = json.loads(json.dumps(section))
    wrong["mean"][0] += 0.1
    with pytest.raises(VAEError, match="normalisation 'mean' does not match"):
        load_vae(directory, wrong)
    with pytest.raises(VAEError, match="version"):
        load_vae(directory, dict(section, version=99))
    with pytest.raises(VAEError, match="not a damon_ros-vae"):
        load_vae(directory, {"hidden": [1]})
    with pytest.raises(VAEError, match="activation"):
        load_vae(directory, dict(section, architecture=dict(section["architecture"],
                                                            activation="tanh")))
    (directory / "vae.json").write_text("{ not json")
    with pytest.raises(VAEError, match="vae.json: not valid JSON"):
        load_vae(directory)
    (directory / "vae.json").unlink()
    with pytest.raises(VAEError, match="no vae.json"):
        load_vae(directory)


def test_bad_inputs_raise_value_errors(trained, rows):
    vae, _ = trained
    with pytest.raises(ValueError, match=r"\(N, 11\)"):
        train_vae(rows[:, :10], epochs=1, progress=False)
    bad = rows[:100].copy()
    bad[0, 10] = 0.5
    with pytest.raises(ValueError, match="0 or 1"):
        train_vae(bad, epochs=1, progress=False)
    bad[0, 10], bad[1, 3] = 1.0, np.nan
    with pytest.raises(ValueError, match="NaN"):
        train_vae(bad, epochs=1, progress=False)
    with pytest.raises(ValueError, match="epochs"):
        train_vae(rows[:100], epochs=0, progress=False)
    with pytest.raises(ValueError, match=r"\(N, 11\)"):
        vae.encode(np.zeros((2, 7)))
    with pytest.raises(ValueError, match=r"\(N, 2\)"):
        vae.decode(np.zeros((2, 3)))
    with pytest.raises(ValueError, match="architecture"):
        Architecture(hidden=(300, 0))


def test_evaluate_handles_a_single_label(trained, rows):
    vae, _ = trained
    free = rows[rows[:, 10] == 0.0][:200]
    metrics = evaluate(vae, free)
    assert np.isnan(metrics["latent_auc_knn"]) and metrics["collision_share"] == 0.0


def test_train_command_writes_a_model_directory(data_dir, tmp_path, capsys):
    out = tmp_path / "model"
    assert train_main(["--data", str(data_dir), "--out", str(out), "--epochs", "2",
                       "--threads", "1", "--quiet"]) == 0
    assert "latent AUC" in capsys.readouterr().out
    meta = read_meta(out, required=("vae.safetensors",))
    assert meta["vae"]["metrics"]["train_rows"] > 0 and meta["data"]["n_samples"] == 2400
    vae = load_vae(out, meta["vae"])
    assert vae.encode(np.zeros((1, 11))).shape == (1, 2)
    assert train_main(["--data", str(tmp_path / "none"), "--out", str(out), "--quiet"]) == 2
    assert "dataset.json" in capsys.readouterr().err
