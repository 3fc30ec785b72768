"""The GPU payload: packed ModelNet40 folders unpack to the same bytes (normals included), and lies are caught."""

from __future__ import annotations

import json
import lzma
import os
import re
import subprocess
import sys
import tarfile
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


STUB_QUEUE = """
import json, os, sys, time
from pathlib import Path
argv = sys.argv[1:]
start = time.time()
time.sleep(1.5)
results = Path(argv[argv.index("--results") + 1])
only = argv[argv.index("--only") + 1 : argv.index("--max-minutes")]
for job in only:
    (results / job / "runs").mkdir(parents=True, exist_ok=True)
    (results / job / "runs" / "rows.jsonl").write_text("{}\\n")
    (results / job / "runs" / "last.ckpt").write_text("big")
with open(os.environ["OUT"] + "/calls.jsonl", "a") as f:
    f.write(json.dumps({"argv": argv, "start": start, "end": time.time()}) + "\\n")
"""


def test_device_chunk_runs_plus_joined_groups_at_once_and_packs_their_results(tmp_path: Path) -> None:
    """``a,b@3+c@2``: two queue processes at the same time, each with its jobs in order and its runs at once; the
    results of every job come back in one archive, without checkpoints (stub queue, no GPU, no wheels)."""
    repo, out = tmp_path / "repo", tmp_path / "out"
    (repo / "benchmarks").mkdir(parents=True)
    out.mkdir()
    (repo / "benchmarks" / "device_chunk.sh").write_text((BENCHMARKS / "device_chunk.sh").read_text())
    (repo / "benchmarks" / "train_queue.py").write_text(STUB_QUEUE)
    (repo / "benchmarks" / "device_payload.py").write_text("")
    env = {**os.environ, "OUT": str(out), "PYTHON": sys.executable}
    done = subprocess.run(
        ["bash", "benchmarks/device_chunk.sh", "a,b@3+c@2", "1"], cwd=repo, env=env, capture_output=True, text=True
    )
    assert done.returncode == 0, done.stdout + done.stderr
    calls = sorted((json.loads(line) for line in (out / "calls.jsonl").read_text().splitlines()), key=str)
    got = {tuple(c["argv"][c["argv"].index("--only") + 1 : c["argv"].index("--max-minutes")]): c for c in calls}
    assert set(got) == {("a", "b"), ("c",)}
    assert [got[k]["argv"][got[k]["argv"].index("--jobs") + 1] for k in (("a", "b"), ("c",))] == ["3", "2"]
    first, second = got[("a", "b")], got[("c",)]
    assert first["start"] < second["end"] and second["start"] < first["end"], "the groups did not overlap"
    assert (out / "log-1.txt").is_file() and (out / "log-2.txt").is_file()
    with tarfile.open(out / "results.tgz") as archive:
        names = sorted(archive.getnames())
    assert "a/runs/rows.jsonl" in names and "b/runs/rows.jsonl" in names and "c/runs/rows.jsonl" in names
    assert not any(name.endswith(".ckpt") for name in names)


def _git(repo: Path, *args: str) -> str:
    return subprocess.run(["git", "-C", str(repo), *args], check=True, capture_output=True, text=True).stdout


RESULT_FILES = ["src/a.py", "docs/results/converge/job_a/runs.jsonl", "docs/results/reproduce/big.jsonl"]


def _repo_with_results(tmp_path: Path, files: list[str] = RESULT_FILES) -> Path:
    """A repository whose one commit holds ``files`` (each file's text its name)."""
    repo = tmp_path / "repo"
    for name in files:
        (repo / name).parent.mkdir(parents=True, exist_ok=True)
        (repo / name).write_text(name)
    _git(tmp_path, "init", "-q", str(repo))
    _git(repo, "add", ".")
    _git(repo, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-m", "all")
    return repo


def _travelling(repo: Path) -> set[str]:
    return set(_git(repo, "ls-files", "--cached", "--others", "--exclude-standard").split())


def test_slim_keeps_results_but_the_named_jobs_from_travelling_and_unslim_restores_the_index(tmp_path: Path) -> None:
    payload = load("device_payload")
    files = [*RESULT_FILES, "docs/results/converge/job_b/runs.jsonl"]
    repo = _repo_with_results(tmp_path, files)
    (repo / "docs/results/converge/job_a/new.md").write_text("a row since")  # a result not yet committed

    payload.slim_index(repo, ["job_a"])
    assert _travelling(repo) == {
        "src/a.py",
        "docs/results/converge/job_a/runs.jsonl",
        "docs/results/converge/job_a/new.md",
    }
    assert all((repo / name).is_file() for name in files)  # the working tree is untouched

    payload.unslim_index(repo)
    assert _git(repo, "status", "--porcelain") == "?? docs/results/converge/job_a/new.md\n"
    assert payload.SLIM_EXCLUDE not in (repo / ".git/info/exclude").read_text()
    with pytest.raises(payload.PayloadError, match="job_c"):
        payload.slim_index(repo, ["job_c"])


def _commit(repo: Path) -> subprocess.CompletedProcess[str]:
    argv = ["git", "-C", str(repo), "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-am", "next"]
    return subprocess.run(argv, capture_output=True, text=True)


def test_no_commit_while_slim_so_results_are_never_committed_as_deleted(tmp_path: Path) -> None:
    payload = load("device_payload")
    repo = _repo_with_results(tmp_path)
    (repo / "src/a.py").write_text("changed")

    payload.slim_index(repo, ["job_a"])
    refused = _commit(repo)
    assert refused.returncode != 0 and "--unslim" in refused.stderr
    assert "docs/results/reproduce/big.jsonl" in _git(repo, "ls-tree", "-r", "--name-only", "HEAD")

    payload.unslim_index(repo)
    assert _commit(repo).returncode == 0
    assert "docs/results/reproduce/big.jsonl" in _git(repo, "ls-tree", "-r", "--name-only", "HEAD")
    assert not (repo / ".git/hooks/pre-commit").exists()


def test_slim_refuses_a_repository_with_its_own_pre_commit_hook(tmp_path: Path) -> None:
    payload = load("device_payload")
    repo = _repo_with_results(tmp_path)
    hook = repo / ".git/hooks/pre-commit"
    hook.write_text("#!/bin/sh\nexit 0\n")
    with pytest.raises(payload.PayloadError, match="pre-commit"):
        payload.slim_index(repo, ["job_a"])
    assert _git(repo, "status", "--porcelain") == ""  # the index untouched
    payload.unslim_index(repo)
    assert hook.read_text() == "#!/bin/sh\nexit 0\n"  # --unslim leaves a hook it did not write
