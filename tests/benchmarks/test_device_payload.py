"""The GPU payload: stripped ModelNet40 files hold the same points and labels, and build the same pairs."""

from __future__ import annotations

import subprocess
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch
from tests.benchmarks.test_smoke import BENCHMARKS, load

from lcreg.data.modelnet40 import load_modelnet40_h5
from lcreg.data.pairs import PairProtocol, make_pair

from _shared_data import shared_data  # type: ignore[import-not-found]


def test_smoke_run_strips_normals_and_keeps_every_other_file(capsys: pytest.CaptureFixture[str]) -> None:
    payload = load("device_payload")
    assert payload.main(["--smoke"]) == 0
    out = Path(capsys.readouterr().out.split(":")[0])
    assert sorted(p.name for p in out.iterdir()) == [
        "ply_data_test0.h5",
        "ply_data_train0.h5",
        "test_files.txt",
        "train_files.txt",
    ]
    with h5py.File(out / "ply_data_train0.h5", "r") as f:
        assert sorted(f.keys()) == ["data", "label"] and f["data"].compression == "gzip"


def test_stripped_modelnet40_mini_gives_the_same_objects_and_pairs(tmp_path: Path) -> None:
    root = shared_data("modelnet40_mini")
    load("device_payload").copy_dataset(root, tmp_path / root.name)
    for split in ("train", "test"):
        points, normals, labels = load_modelnet40_h5(root, split)
        stripped, no_normals, stripped_labels = load_modelnet40_h5(tmp_path / root.name, split)
        assert normals is not None and no_normals is None
        np.testing.assert_array_equal(stripped, points)
        np.testing.assert_array_equal(stripped_labels, labels)
    protocol = PairProtocol(num_points=256, noise_sigma=0.01)  # the DCP-family pairs of the lc jobs
    for item in range(3):
        full = make_pair(
            torch.as_tensor(points[item]), torch.as_tensor(normals[item]), protocol, torch.Generator().manual_seed(item)
        )
        bare = make_pair(torch.as_tensor(points[item]), None, protocol, torch.Generator().manual_seed(item))
        for key in ("points_src", "points_ref", "transform_ref_src"):
            assert torch.equal(full[key], bare[key]), key


def test_device_chunk_script_is_valid_bash_and_names_existing_queue_options() -> None:
    script = BENCHMARKS / "device_chunk.sh"
    subprocess.run(["bash", "-n", str(script)], check=True)
    options = load("train_queue").parse(["run", "--only", "x", "--max-minutes", "1", "--runs", "r", "--results", "s"])
    assert options.only == ["x"] and options.max_minutes == 1.0
    assert "train_queue.py run --only" in script.read_text()
