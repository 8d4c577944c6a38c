"""collect → train → build-graph → analyze end to end at a small size, through the CLI."""

from __future__ import annotations

import json

import pytest

from damon_ros.cli import main as cli
from damon_ros.learning.bundle import DamonModel, ModelError


@pytest.fixture(scope="module")
def small_model(tmp_path_factory):
    root = tmp_path_factory.mktemp("pipeline")
    data, model = root / "data", root / "model"
    assert cli(["collect", "--n", "3000", "--seed", "3", "--out", str(data), "--workers", "1",
                "--chunk-size", "1500", "--spacing", "0.3", "--quiet"]) == 0
    assert cli(["train", "--data", str(data), "--out", str(model), "--epochs", "3",
                "--threads", "1", "--quiet"]) == 0
    assert cli(["build-graph", "--data", str(data), "--model", str(model), "--n-vertices",
                "1500", "--grid", "12", "--workers", "1", "--quiet"]) == 0
    return root, data, model


def test_the_small_model_loads_and_describes_itself(small_model):
    _, _, model_dir = small_model
    model = DamonModel.load(model_dir)
    meta = json.loads((model_dir / "meta.json").read_text())
    assert set(meta["files"]) >= {"vae.safetensors", "vae.json", "graph.npz", "gmr.npz"}
    assert model.graph.n_vertices > 1000 and model.graph.n_edges > 0
    assert 0.0 < meta["graph"]["largest_component_share"] <= 1.0
    assert meta["graph"]["grid_vertices"] > 0


def test_a_tampered_model_file_is_refused(small_model, tmp_path):
    _, _, model_dir = small_model
    copy = tmp_path / "model"
    copy.mkdir()
    for f in model_dir.iterdir():
        copy.joinpath(f.name).write_bytes(f.read_bytes())
    graph = copy / "graph.npz"
    graph.write_bytes(graph.read_bytes()[:-100])
    with pytest.raises(ModelError, match="graph.npz"):
        DamonModel.load(copy)


def test_analyze_predicts_held_out_tasks_and_writes_the_plots(small_model, capsys):
    root, data, model_dir = small_model
    out = root / "analysis"
    assert cli(["analyze", "--data", str(data), "--model", str(model_dir), "--sizes", "800",
                "--grid", "8", "--families", "AB", "--tasks", "2", "--fit-tasks", "4",
                "--out", str(out), "--workers", "1", "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "N*" in printed and "T meas." in printed and "runtime model" in printed
    for name in ("latent_manifold.png", "graph_route.png", "sweep.png", "reliability.png"):
        assert (out / name).stat().st_size > 1000
    results = json.loads((out / "results.json").read_text())
    row = results["sweep"][0]
    assert row["N"] == 800 and row["tasks"] == 2
    assert results["tasks"] == {"families": "AB", "validate": 2, "fit": 4, "task_seed": 16,
                                "fit_seed": 1016}
    # validation and fit tasks are different scenes, and every run is kept
    fit = {p.name for p in (out / "tasks" / "fit").glob("*.yaml")}
    validate = {p.name for p in (out / "tasks" / "validate").glob("*.yaml")}
    assert len(fit) == 4 and len(validate) == 2 and not fit & validate
    runs = [json.loads(line) for line in (out / "tasks.jsonl").read_text().splitlines()]
    assert len(runs) == 6 and {r["split"] for r in runs} == {"fit", "validate"}
    assert 0.0 <= results["calibration_error"] <= 1.0


def test_ablation_rewires_the_same_vertices_and_fills_its_section_only(small_model, tmp_path):
    from damon_ros.core.resources import public_scenarios_dir

    _, _, model_dir = small_model
    page = tmp_path / "BENCHMARKS.md"
    page.write_text("# Benchmarks\n\nkept text\n")
    args = ["ablation", "--model", str(model_dir), "--scenarios",
            str(public_scenarios_dir() / "B-001.yaml"), "--generated", "0", "--workers", "1",
            "--out", str(tmp_path / "runs.jsonl"), "--page", str(page), "--quiet"]
    assert cli(args) == 0
    runs = [json.loads(line) for line in (tmp_path / "runs.jsonl").read_text().splitlines()]
    assert len({r["variant"] for r in runs}) == 3 and all(r["set"] == "public" for r in runs)
    text = page.read_text()
    assert "kept text" in text and text.count("<!-- ablation -->") == 1
    assert cli(args) == 0  # a second run replaces the section, nothing else
    again = page.read_text()
    assert again.count("<!-- ablation -->") == 1 and again.startswith("# Benchmarks\n\nkept")
    rows = [line for line in again.splitlines() if line.startswith("| ") and "public" in line]
    assert len(rows) == 3
