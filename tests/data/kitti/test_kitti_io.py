from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from lcreg.checks import DatasetLayoutError, NonFiniteError, ShapeError
from lcreg.data.kitti import read_calib_velo_to_cam, read_poses, relative_lidar_pose
from lcreg.data.kitti.io import as_4x4, read_json_pairs

from _kitti_refs import pose_line, rigid
from _numpy_refs import kabsch


def test_read_calib_returns_the_tr_line_as_4x4(tmp_path: Path) -> None:
    tr = rigid(np.random.default_rng(0), 0.3)
    other = " ".join(["7.0"] * 12)
    file = tmp_path / "calib.txt"
    file.write_text(f"P0: {other}\nP1: {other}\nP2: {other}\nP3: {other}\nTr: {pose_line(tr)}\n")
    np.testing.assert_allclose(read_calib_velo_to_cam(file), tr, atol=1e-12)


@pytest.mark.parametrize(
    ("text", "match"),
    [("P0: " + " ".join(["1"] * 12) + "\n", "no 'Tr:' line"), ("Tr: " + " ".join(["1"] * 11) + "\n", "line 1")],
)
def test_read_calib_errors_name_the_file(tmp_path: Path, text: str, match: str) -> None:
    file = tmp_path / "calib_bad.txt"
    file.write_text(text)
    with pytest.raises(DatasetLayoutError, match=match) as info:
        read_calib_velo_to_cam(file)
    assert "calib_bad.txt" in str(info.value)
    with pytest.raises(FileNotFoundError, match=r"nope\.txt"):
        read_calib_velo_to_cam(tmp_path / "nope.txt")


def test_read_poses_parses_every_line(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    poses = np.stack([rigid(rng) for _ in range(3)])
    file = tmp_path / "00.txt"
    file.write_text("\n".join(pose_line(p) for p in poses) + "\n\n")
    out = read_poses(file)
    assert out.shape == (3, 4, 4) and out.dtype == np.float64
    np.testing.assert_allclose(out, poses, atol=1e-12)


@pytest.mark.parametrize(
    ("second_line", "match"), [(" ".join(["1"] * 11), "line 2: expected 12"), ("1 " * 11 + "x", "line 2: not a number")]
)
def test_read_poses_bad_line_names_file_and_line(tmp_path: Path, second_line: str, match: str) -> None:
    file = tmp_path / "07.txt"
    file.write_text(pose_line(np.eye(4)) + "\n" + second_line + "\n")
    with pytest.raises(DatasetLayoutError, match=match) as info:
        read_poses(file)
    assert "07.txt" in str(info.value)
    (tmp_path / "empty.txt").write_text("\n")
    with pytest.raises(DatasetLayoutError, match=r"empty\.txt.*no pose"):
        read_poses(tmp_path / "empty.txt")


def test_relative_lidar_pose_matches_an_independent_construction() -> None:
    """World points seen from two LiDAR poses (camera pose @ Tr); Kabsch between the two views gives T_j_i."""
    rng = np.random.default_rng(2)
    tr, pose_i, pose_j = rigid(rng, 0.3), rigid(rng, 20.0), rigid(rng, 20.0)
    world = rng.uniform(-30, 30, (50, 3))
    homog = np.c_[world, np.ones(len(world))].T
    in_i = (np.linalg.inv(pose_i @ tr) @ homog)[:3].T
    in_j = (np.linalg.inv(pose_j @ tr) @ homog)[:3].T
    expected = kabsch(in_i, in_j)
    np.testing.assert_allclose(relative_lidar_pose(pose_i, pose_j, tr), expected, atol=1e-9)
    np.testing.assert_allclose(relative_lidar_pose(pose_i[:3], pose_j[:3], tr[:3]), expected, atol=1e-9)
    with pytest.raises(ShapeError, match="pose_j"):
        relative_lidar_pose(pose_i, np.eye(3), tr)
    with pytest.raises(NonFiniteError, match="tr"):
        relative_lidar_pose(pose_i, pose_j, np.full((4, 4), np.nan))


def test_read_json_pairs_returns_rows_and_names_bad_entries(tmp_path: Path) -> None:
    transform = rigid(np.random.default_rng(3))
    file = tmp_path / "train.json"
    file.write_text(json.dumps([{"seq_id": 0, "frame0": 11, "frame1": 0, "transform": transform.tolist()}]))
    ((seq_id, frame0, frame1, got),) = read_json_pairs(file)
    assert (seq_id, frame0, frame1) == (0, 11, 0)
    np.testing.assert_array_equal(got, transform)
    file.write_text(json.dumps([{"seq_id": 0, "frame0": 11, "frame1": 0, "transform": [[1.0, 0.0]]}]))
    with pytest.raises(DatasetLayoutError, match=r"train\.json.*00/11-0 has no finite 4x4"):
        read_json_pairs(file)
    file.write_text("{not json")
    with pytest.raises(DatasetLayoutError, match=r"train\.json.*not a pair list"):
        read_json_pairs(file)


def test_as_4x4_completes_3x4_and_names_the_argument() -> None:
    matrix = rigid(np.random.default_rng(4))
    np.testing.assert_array_equal(as_4x4(matrix[:3], "m"), matrix)
    with pytest.raises(ShapeError, match="`m`"):
        as_4x4(np.eye(3), "m")
    with pytest.raises(NonFiniteError, match="`m`"):
        as_4x4(np.full((4, 4), np.inf), "m")
