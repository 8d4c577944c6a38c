"""Model files are verified before use and never unpickled: copies of the shipped model,
broken in each way a disk, a copy or an attacker can break them, must fail to load with a
message naming the file, and the planner node must exit with that one line."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import rosutil

from damon_ros.core.resources import default_model_dir, sha256
from damon_ros.learning.bundle import FILES, DamonModel, ModelError
from damon_ros.ros.environment import node_environment


@pytest.fixture
def model_copy(tmp_path) -> Path:
    copy = tmp_path / "model"
    shutil.copytree(default_model_dir(), copy)
    return copy


def _rehash(directory: Path, name: str) -> None:
    """What an attacker who can also write meta.json would do."""
    meta_path = directory / "meta.json"
    meta = json.loads(meta_path.read_text())
    meta["files"][name] = sha256(directory / name)
    meta_path.write_text(json.dumps(meta))


def test_the_shipped_model_loads_and_records_a_hash_for_every_file():
    model = DamonModel.load()
    assert set(model.meta["files"]) == set(FILES)
    for name, digest in model.meta["files"].items():
        assert sha256(model.directory / name) == digest


def _truncate(d: Path) -> None:
    path = d / "graph.npz"
    path.write_bytes(path.read_bytes()[:-1000])


def _swap(d: Path) -> None:
    a, b = (d / "gmr.npz").read_bytes(), (d / "graph.npz").read_bytes()
    (d / "gmr.npz").write_bytes(b)
    (d / "graph.npz").write_bytes(a)


def _flip_a_byte(d: Path) -> None:
    path = d / "vae.safetensors"
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))


def _edit_json(d: Path) -> None:
    path = d / "vae.json"
    path.write_text(path.read_text().replace("2", "3", 1))


@pytest.mark.parametrize(("damage", "words"), [
    (_truncate, r"graph.npz: SHA-256 does not match meta.json"),
    (_swap, r"(gmr|graph).npz: SHA-256 does not match"),
    (_flip_a_byte, r"vae.safetensors: SHA-256 does not match"),
    (_edit_json, r"vae.json: SHA-256 does not match"),
    (lambda d: (d / "gmr.npz").unlink(), r"gmr.npz: missing"),
    (lambda d: (d / "meta.json").unlink(), r"no meta.json"),
    (lambda d: (d / "meta.json").write_text("{\"format\": "), r"meta.json: not valid JSON"),
    (lambda d: (d / "meta.json").write_text("[]"), r"meta.json: not a damon_ros"),
])
def test_a_damaged_model_is_refused_naming_the_file(model_copy, damage, words):
    damage(model_copy)
    with pytest.raises(ModelError, match=words):
        DamonModel.load(model_copy)


class _Payload:
    """Unpickling this would create ``marker``: the proof that code from the file ran."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (self.marker,))


def test_a_pickle_in_a_model_file_is_refused_even_with_a_matching_hash(model_copy, tmp_path):
    marker = tmp_path / "code_ran"
    with np.load(model_copy / "graph.npz") as f:
        arrays = dict(f)
    arrays["q"] = np.array([_Payload(marker)], dtype=object)
    np.savez(model_copy / "graph.npz", **arrays)  # numpy pickles object arrays
    _rehash(model_copy, "graph.npz")
    with pytest.raises(ModelError, match="graph.npz"):
        DamonModel.load(model_copy)
    assert not marker.exists()


def test_the_planner_node_exits_with_one_line_on_a_damaged_model(model_copy, tmp_path):
    _flip_a_byte(model_copy)
    env = node_environment(rosutil.next_domain_id(__file__), tmp_path)
    proc = subprocess.run(
        [sys.executable, "-m", "damon_ros.nodes.planner", "--ros-args", "-p",
         f"model_dir:={model_copy}"], capture_output=True, text=True, timeout=60, env=env)
    assert proc.returncode == 2, proc.stderr
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert lines == [f"planner: cannot load the model: {model_copy / 'vae.safetensors'}: "
                     "SHA-256 does not match meta.json — the file is truncated, swapped or "
                     "modified"], proc.stderr
