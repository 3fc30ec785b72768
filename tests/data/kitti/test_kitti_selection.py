from __future__ import annotations

import numpy as np
import pytest

from lcreg.checks import ShapeError
from lcreg.data.kitti import EXCLUDED_PAIRS, KITTI_SPLITS, all_pairs, read_poses, selection, standard_chain_pairs
from lcreg.data.kitti.selection import count_all_pairs, sequence_pairs

from _kitti_refs import json_rows
from _shared_data import shared_data


def test_standard_chain_on_a_straight_drive() -> None:
    positions = np.c_[np.arange(40.0), np.zeros(40), np.zeros(40)]  # 1 m per frame
    # frame 11 is the first > 10 m from 0 -> pair (10, 0); continue at 11 -> (21, 11), (32, 22); 33..39 < 10 m
    assert standard_chain_pairs(positions) == [(10, 0), (21, 11), (32, 22)]
    assert standard_chain_pairs(positions, min_distance=5.0)[:2] == [(5, 0), (11, 6)]
    assert standard_chain_pairs(positions, max_frames_ahead=5) == []  # no frame of the window is far enough
    stopped = np.concatenate([np.zeros((120, 3)), positions + 0.5])  # 120 frames standing still, then driving
    # frame 130 (10.9 m away) first enters the 100-frame window at frame 31
    assert standard_chain_pairs(stopped)[0] == (129, 31)
    with pytest.raises(ShapeError, match="positions"):
        standard_chain_pairs(np.zeros((5, 2)))
    with pytest.raises(ValueError, match="min_distance"):
        standard_chain_pairs(positions, min_distance=0.0)


def test_all_pairs_matches_a_double_loop() -> None:
    rng = np.random.default_rng(3)
    positions = np.cumsum(rng.uniform(0, 2, (30, 3)), axis=0)
    expected = [
        (j, i) for i in range(30) for j in range(i + 1, 30) if np.linalg.norm(positions[j] - positions[i]) >= 8.0
    ]
    assert all_pairs(positions, 8.0) == expected
    assert all_pairs(positions, 8.0, max_frames_apart=4) == [(j, i) for j, i in expected if j - i <= 4]
    with pytest.raises(ValueError, match="max_frames_apart"):
        all_pairs(positions, 8.0, max_frames_apart=0)


@pytest.mark.data
def test_chain_reproduces_every_standard_json_list() -> None:
    """From poses/NN.txt alone, the FCGF chain gives exactly the 1358 / 180 / 555 json pairs, in order."""
    kitti = shared_data("kitti")
    for split, sequences in KITTI_SPLITS.items():
        rows = [(r["seq_id"], r["frame0"], r["frame1"]) for r in json_rows(kitti, split)]
        chain = []
        for seq_id in sequences:
            positions = read_poses(kitti / "poses" / f"{seq_id:02d}.txt")[:, :3, 3]
            chain += [(seq_id, a, b) for a, b in standard_chain_pairs(positions)]
        assert [c for c in chain if c not in EXCLUDED_PAIRS] == rows, split
    train = [(r["frame0"], r["frame1"]) for r in json_rows(kitti, "train")]
    assert train[:2] == [(11, 0), (23, 12)]
    assert len(json_rows(kitti, "train")) == 1358 and len(json_rows(kitti, "val")) == 180 and len(rows) == 555


@pytest.mark.data
def test_all_pairs_on_the_available_frames_of_sequence_00() -> None:
    kitti = shared_data("kitti")
    positions = read_poses(kitti / "poses" / "00.txt")[:16, :3, 3]
    pairs = all_pairs(positions, 10.0)
    assert len(pairs) == 10
    assert pairs == [(j, i) for i in range(16) for j in range(i + 12, 16)]  # ~0.86 m a frame: 12 frames = 10.3 m


def test_count_and_sequence_pairs_agree_with_the_lists(monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(5)
    positions = np.cumsum(rng.uniform(0, 2, (60, 3)), axis=0)
    assert count_all_pairs(positions, 8.0, None) == len(all_pairs(positions, 8.0))
    assert count_all_pairs(positions, 8.0, 6) == len(all_pairs(positions, 8.0, 6))
    assert sequence_pairs(positions, 0, "all", 8.0, 6) == all_pairs(positions, 8.0, 6)
    chain = standard_chain_pairs(positions, 8.0)
    assert len(chain) > 2 and sequence_pairs(positions, 8, "standard", 8.0, None) == chain
    monkeypatch.setattr(selection, "EXCLUDED_PAIRS", frozenset({(8, *chain[1])}))
    assert sequence_pairs(positions, 8, "standard", 8.0, None) == [chain[0], *chain[2:]]
    assert sequence_pairs(positions, 0, "standard", 8.0, None) == chain  # excluded only in its own sequence
