"""Data collection: obstacle nodes, exact labels, determinism across workers, resuming and
validation of what is read back."""

from __future__ import annotations

import json

import numpy as np
import pytest

from damon_ros.core.kinematics import Chain
from damon_ros.core.robot import Robot
from damon_ros.core.shapes import Shape
from damon_ros.learning.collect import (
    CHAIN_FRAMES,
    SHOULDER,
    CollectConfig,
    Sampler,
    collect,
    workspace_nodes,
)
from damon_ros.learning.dataset import CollectError, load_dataset
from damon_ros.tools.model_build import collect_main

N, CHUNK = 3000, 1000


@pytest.fixture(scope="module")
def robot():
    return Robot("mesh")


@pytest.fixture(scope="module")
def nodes(robot):
    return workspace_nodes(0.15, robot=robot)


@pytest.fixture(scope="module")
def two_workers(tmp_path_factory):
    out = tmp_path_factory.mktemp("w2")
    meta = collect(N, 11, out, workers=2, chunk_size=CHUNK, progress=False)
    return out, meta


def test_nodes_cover_the_reachable_workspace_above_the_table(nodes):
    assert 700 < len(nodes) < 900
    assert np.all(np.linalg.norm(nodes - SHOULDER, axis=1) <= 0.955 + 1e-9)
    assert nodes[:, 2].min() == pytest.approx(0.075)  # first layer: cell centres above z = 0
    gaps = np.diff(np.unique(nodes[:, 0]))
    assert np.allclose(gaps, 0.15)
    # points inside the base column are always occupied by the robot and removed
    assert not np.any(np.all(np.isclose(nodes, [0.0, 0.0, 0.075]), axis=1))
    assert np.any(np.all(np.isclose(nodes, [0.3, 0.0, 0.075]), axis=1))


def test_arm_chain_matches_pinocchio(robot):
    rng = np.random.default_rng(0)
    Q = rng.uniform(robot.limits.lower, robot.limits.upper, (20, 7))
    chain = Chain(robot.model)
    got = chain.positions(Q, chain.frame_block(CHAIN_FRAMES))
    tcp = np.array([robot.fk(q)[:3, 3] for q in Q])
    hand = np.array([robot.fk(q, "panda_link4")[:3, 3] for q in Q])
    assert np.allclose(got[:, -1], tcp, atol=1e-12)
    assert np.allclose(got[:, 2], hand, atol=1e-12)


def test_same_data_whatever_the_number_of_workers(two_workers, tmp_path):
    out2, meta2 = two_workers
    meta1 = collect(N, 11, tmp_path, workers=1, chunk_size=CHUNK, progress=False)
    a, _ = load_dataset(out2)
    b, _ = load_dataset(tmp_path)
    for key in a:
        assert np.array_equal(a[key], b[key]), key
    assert meta1["counts"] == meta2["counts"]
    assert [c["sha256"] for c in meta1["chunks"]] == [c["sha256"] for c in meta2["chunks"]]


def test_columns_and_both_labels(two_workers, robot):
    out, meta = two_workers
    data, sidecar = load_dataset(out)
    assert data["q"].shape == (N, 7) and data["point"].shape == (N, 3)
    assert data["collision"].dtype == bool and data["node"].dtype == np.int32
    assert np.array_equal(data["point"], np.asarray(sidecar["nodes"])[data["node"]])
    assert all(len(column) == N for column in data.values())
    assert np.all((data["q"] >= robot.limits.lower) & (data["q"] <= robot.limits.upper))
    assert np.array_equal(data["collision"], data["distance"] <= 0.0)
    assert np.array_equal(data["near"], data["distance"] <= sidecar["margin"])
    ratio = data["collision"].mean()
    assert 0.05 < ratio < 0.5, ratio  # both labels well represented
    assert sidecar["counts"]["collision"] == int(data["collision"].sum())
    seek = data["source"] == 1
    assert 0.4 < seek.mean() < 0.6
    # contact-seeking samples are the ones close to contact
    assert np.median(data["distance"][seek]) < 0.06 < np.median(data["distance"][~seek])
    assert data["collision"][seek].mean() > 5 * data["collision"][~seek].mean()
    assert not data["self_collision"].any()


def test_labels_agree_with_the_exact_mesh_model(two_workers, robot):
    data, meta = load_dataset(two_workers[0])
    rows = np.concatenate([np.flatnonzero(data["collision"])[:4],
                           np.flatnonzero(~data["collision"])[:4]])
    for i in rows:
        obstacle = Shape("sphere", (meta["radius"],), data["point"][i])
        d = robot.clearance(data["q"][i], [obstacle]).distance
        assert d == pytest.approx(data["distance"][i], abs=1e-9)
        assert (d <= 0.0) == data["collision"][i]
        assert not robot.self_collision(data["q"][i])


def test_resume_rewrites_only_missing_or_broken_chunks(tmp_path):
    collect(N, 5, tmp_path, workers=1, chunk_size=CHUNK, progress=False)
    before, _ = load_dataset(tmp_path)
    kept = (tmp_path / "chunk_00000.npz").stat().st_mtime_ns
    (tmp_path / "chunk_00001.npz").unlink()
    (tmp_path / "chunk_00002.npz").write_bytes(b"truncated")
    meta = collect(N, 5, tmp_path, workers=1, chunk_size=CHUNK, progress=False)
    assert meta["timing"]["samples_this_run"] == 2 * CHUNK
    assert (tmp_path / "chunk_00000.npz").stat().st_mtime_ns == kept
    after, _ = load_dataset(tmp_path)
    for key in before:
        assert np.array_equal(before[key], after[key]), key
    again = collect(N, 5, tmp_path, workers=1, chunk_size=CHUNK, progress=False)
    assert again["timing"]["samples_this_run"] == 0


def test_longer_run_extends_a_shorter_one(tmp_path):
    short = tmp_path / "short"
    collect(1500, 9, short, workers=1, chunk_size=CHUNK, progress=False)
    collect(2500, 9, tmp_path / "long", workers=1, chunk_size=CHUNK, progress=False)
    a, _ = load_dataset(short)
    b, _ = load_dataset(tmp_path / "long")
    assert np.array_equal(a["q"][:CHUNK], b["q"][:CHUNK])
    meta = collect(2500, 9, short, workers=1, chunk_size=CHUNK, progress=False)
    assert meta["timing"]["samples_this_run"] == 1500  # the short last chunk is redone
    c, _ = load_dataset(short)
    assert np.array_equal(c["distance"], b["distance"])


def test_other_parameters_in_the_same_directory_are_refused(two_workers):
    with pytest.raises(CollectError, match="other parameters"):
        collect(N, 12, two_workers[0], workers=1, chunk_size=CHUNK, progress=False)


def test_tampered_or_missing_chunks_fail_with_the_file_name(tmp_path):
    collect(1200, 3, tmp_path, workers=1, chunk_size=600, progress=False)
    chunk = tmp_path / "chunk_00001.npz"
    blob = bytearray(chunk.read_bytes())
    blob[len(blob) // 2] ^= 0xFF
    chunk.write_bytes(bytes(blob))
    with pytest.raises(CollectError, match="chunk_00001.npz: SHA-256"):
        load_dataset(tmp_path)
    chunk.unlink()
    with pytest.raises(CollectError, match="chunk_00001.npz: listed .* but missing"):
        load_dataset(tmp_path)
    (tmp_path / "dataset.json").write_text("{")
    with pytest.raises(CollectError, match="not valid JSON"):
        load_dataset(tmp_path)
    with pytest.raises(CollectError, match="missing"):
        load_dataset(tmp_path / "nowhere")


def test_sidecar_describes_the_data(two_workers):
    out, meta = two_workers
    on_disk = json.loads((out / "dataset.json").read_text())
    assert on_disk["n_samples"] == N and on_disk["seed"] == 11
    assert [c["name"] for c in on_disk["columns"]][:6] == [
        "q", "point", "collision", "near", "distance", "node"]
    assert on_disk["n_nodes"] == len(on_disk["nodes"])
    assert on_disk["versions"]["pin"] and on_disk["timing"]["workers"] == 2
    assert 0.0 < on_disk["collision_ratio"] < 1.0


def test_bad_parameters_raise_value_errors(tmp_path):
    with pytest.raises(ValueError, match="n_samples"):
        collect(0, 0, tmp_path, progress=False)
    with pytest.raises(ValueError, match="radius"):
        collect(10, 0, tmp_path, radius=-1.0, progress=False)
    with pytest.raises(ValueError, match="near_contact_share"):
        CollectConfig(near_contact_share=1.5)
    with pytest.raises(ValueError, match="workers"):
        collect(10, 0, tmp_path, workers=0, progress=False)


def test_sampler_chunk_is_a_pure_function_of_seed_and_index(nodes):
    config = CollectConfig(seed=4, chunk_size=50)
    a = Sampler(config, nodes).chunk(3, 50)
    b = Sampler(config, nodes).chunk(3, 50)
    c = Sampler(config, nodes).chunk(4, 50)
    assert np.array_equal(a["q"], b["q"]) and not np.array_equal(a["q"], c["q"])


def test_a_chunk_does_not_depend_on_the_chunks_its_worker_made_before(nodes):
    """Whatever a worker made before, a chunk is the same: the meshes' self-collision query
    keeps no warm start from earlier states (a chunk re-made alone on a Ray cluster differed
    from the one made after chunk 0 once most states skipped the meshes)."""
    config = CollectConfig(seed=4, chunk_size=200)
    worked = Sampler(config, nodes)
    worked.chunk(0, 200)
    after = worked.chunk(1, 200)
    alone = Sampler(config, nodes).chunk(1, 200)
    for key in after:
        assert np.array_equal(after[key], alone[key]), key


def test_command_line(tmp_path, capsys):
    assert collect_main(["--n", "300", "--out", str(tmp_path), "--workers", "1",
                         "--chunk-size", "300", "--quiet"]) == 0
    assert "300 samples" in capsys.readouterr().out
    assert collect_main(["--n", "300", "--out", str(tmp_path / "x"), "--radius", "0",
                         "--quiet"]) == 2
    assert "radius" in capsys.readouterr().err
