"""The GPU payload: packed ModelNet40 folders unpack to the same bytes (normals included), and lies are caught."""

from __future__ import annotations

import lzma
import re
import subprocess
from pathlib import Path

import numpy as np
import pytest
from tests.benchmarks.test_smoke import BENCHMARKS, load

from lcreg.data.modelnet40 import load_modelnet40_h5

from _shared_data import shared_data  # type: ignore[import-not-found]


def _packed(tmp_path: Path) -> tuple[Path, Path]:
    """A small h5 folder (with normals) and its packed copy."""
    payload = load("device_payload")
    source = payload._smoke_folder()
    payload.pack_dataset(source, tmp_path / "carry" / "mini")
    return source, tmp_path / "carry" / "mini"


def test_smoke_run_packs_and_unpacks(capsys: pytest.CaptureFixture[str]) -> None:
    payload = load("device_payload")
    assert payload.main(["--smoke"]) == 0
    out = Path(capsys.readouterr().out.split(":")[0])
    assert sorted(p.name for p in out.iterdir()) == [
        "MANIFEST.json",
        "ply_data_test0.h5.xz",
        "ply_data_train0.h5.xz",
        "test_files.txt",
        "train_files.txt",
    ]


def test_unpack_restores_every_file_bit_for_bit(tmp_path: Path) -> None:
    source, packed = _packed(tmp_path)
    restored = load("device_payload").unpack_all(packed.parent, tmp_path / "data")
    assert sorted(p.name for p in restored) == sorted(p.name for p in source.iterdir())
    for path in source.iterdir():
        assert (tmp_path / "data" / "mini" / path.name).read_bytes() == path.read_bytes(), path.name
    points, normals, labels = load_modelnet40_h5(tmp_path / "data" / "mini", "train")
    expected = load_modelnet40_h5(source, "train")
    assert normals is not None and expected[1] is not None
    np.testing.assert_array_equal(normals, expected[1])
    np.testing.assert_array_equal(points, expected[0])
    np.testing.assert_array_equal(labels, expected[2])


def test_unpack_rejects_a_changed_or_missing_file(tmp_path: Path) -> None:
    payload = load("device_payload")
    _, packed = _packed(tmp_path)
    train = packed / "ply_data_train0.h5.xz"
    data = bytearray(lzma.decompress(train.read_bytes()))
    data[-1] ^= 1
    train.write_bytes(lzma.compress(bytes(data)))
    with pytest.raises(payload.PayloadError, match=re.escape("ply_data_train0.h5: its bytes differ")):
        payload.unpack_dataset(packed, tmp_path / "data")
    train.unlink()
    with pytest.raises(payload.PayloadError, match=re.escape("'ply_data_train0.h5' is in MANIFEST.json but neither")):
        payload.unpack_dataset(packed, tmp_path / "data")
    (packed / "MANIFEST.json").unlink()
    with pytest.raises(payload.PayloadError, match=re.escape("no MANIFEST.json")):
        payload.unpack_dataset(packed, tmp_path / "data")


def test_travelling_bytes_counts_tracked_untracked_and_carried_but_not_ignored(tmp_path: Path) -> None:
    repo = tmp_path / "repo"
    repo.mkdir()
    subprocess.run(["git", "init", "-q", str(repo)], check=True)
    (repo / ".gitignore").write_text("ignored/\n")  # 9 bytes, untracked
    (repo / "tracked.txt").write_bytes(b"x" * 100)
    subprocess.run(["git", "-C", str(repo), "add", "tracked.txt"], check=True)
    (repo / "ignored").mkdir()
    (repo / "ignored" / "big").write_bytes(b"x" * 10_000)
    (repo / "ignored" / "carried").mkdir()
    (repo / "ignored" / "carried" / "f").write_bytes(b"x" * 1_000)
    assert load("device_payload").travelling_bytes(repo, repo / "ignored" / "carried") == 100 + 9 + 1_000


def test_packed_modelnet40_test_split_gives_the_same_arrays(tmp_path: Path) -> None:
    """On the real files (the test split only: packing the train file takes a minute)."""
    root = shared_data("modelnet40_mini")
    subset = tmp_path / "modelnet40_mini"
    subset.mkdir()
    for name in ("ply_data_test0.h5", "test_files.txt", "shape_names.txt"):
        (subset / name).symlink_to(root / name)
    payload = load("device_payload")
    payload.pack_dataset(subset, tmp_path / "carry" / "modelnet40_mini")
    payload.unpack_all(tmp_path / "carry", tmp_path / "data")
    points, normals, labels = load_modelnet40_h5(root, "test")
    got_points, got_normals, got_labels = load_modelnet40_h5(tmp_path / "data" / "modelnet40_mini", "test")
    assert normals is not None and got_normals is not None
    np.testing.assert_array_equal(got_points, points)
    np.testing.assert_array_equal(got_normals, normals)
    np.testing.assert_array_equal(got_labels, labels)


def test_device_chunk_script_is_valid_bash_and_names_existing_options() -> None:
    script = BENCHMARKS / "device_chunk.sh"
    subprocess.run(["bash", "-n", str(script)], check=True)
    options = load("train_queue").parse(["run", "--only", "x", "--max-minutes", "1", "--runs", "r", "--results", "s"])
    assert options.only == ["x"] and options.max_minutes == 1.0
    text = script.read_text()
    assert "train_queue.py run --only" in text and "device_payload.py --unpack .carry --to ../shared/data" in text
    with pytest.raises(SystemExit):
        load("device_payload").main(["--unpack", "/nonexistent", "--to", "x"])
