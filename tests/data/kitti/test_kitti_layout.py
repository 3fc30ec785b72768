from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lcreg.data.kitti.layout import (
    EXPECTED_LAYOUT,
    calib_path,
    describe_missing,
    pairs_path,
    pose_path,
    raise_if_no_pair,
    scan_frames,
    scan_path,
)


def test_paths_follow_the_odometry_layout(tmp_path: Path) -> None:
    assert scan_path(tmp_path, 8, 58) == tmp_path / "sequences" / "08" / "velodyne" / "000058.bin"
    assert calib_path(tmp_path, 8) == tmp_path / "sequences" / "08" / "calib.txt"
    assert pose_path(tmp_path, 10) == tmp_path / "poses" / "10.txt"
    assert pairs_path(tmp_path, "val") == tmp_path / "pairs" / "val.json"
    assert "sequences/NN/velodyne/FFFFFF.bin" in EXPECTED_LAYOUT


def test_scan_frames_lists_numbered_bin_files(tmp_path: Path) -> None:
    assert scan_frames(tmp_path, 0) is None
    folder = scan_path(tmp_path, 0, 0).parent
    folder.mkdir(parents=True)
    for name in ("000000.bin", "000007.bin", "notes.bin", "000003.txt"):
        np.zeros((1, 4), np.float32).tofile(folder / name)
    (folder / "000009.bin").mkdir()  # a folder is not a scan
    assert scan_frames(tmp_path, 0) == {0, 7}


def test_missing_files_are_described_per_sequence(tmp_path: Path) -> None:
    needed = {0: set(range(8)), 3: {1}, 5: {2}}
    found: dict[int, set[int] | None] = {0: {0, 1}, 3: None, 5: {2}}
    message = describe_missing(tmp_path, needed, found)
    assert message.startswith("sequence 00: 6 of 8 scans missing (000002.bin, 000003.bin, 000004.bin, 000005.bin, ")
    assert "..." in message and "sequence 03: no folder" in message and "sequence 05" not in message
    assert describe_missing(tmp_path, {}, {}) == "no sequence listed"
    raise_if_no_pair([object()], "listed", tmp_path, needed, found)  # pairs left: no error
    with pytest.raises(FileNotFoundError, match=r"no KITTI pair has both scans: listed; sequence 00: 6 of 8") as info:
        raise_if_no_pair([], "listed", tmp_path, needed, found)
    assert str(info.value).endswith(EXPECTED_LAYOUT)
