from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from lcreg.checks import DatasetLayoutError
from lcreg.data.kitti import all_pairs, kitti_pairs, read_calib_velo_to_cam, read_poses, relative_lidar_pose, scan_path

from _kitti_refs import json_rows, link_layout, pose_errors
from _shared_data import shared_data

# FCGF's hard-coded velodyne -> camera calibration (chrischoy/FCGF lib/data_loaders.py, KITTIPairDataset.velo2cam),
# used for every sequence when the standard json transforms were computed.
FCGF_VELO2CAM_R = [7.533745e-03, -9.999714e-01, -6.166020e-04, 1.480249e-02, 7.280733e-04, -9.998902e-01]
FCGF_VELO2CAM_R += [9.998621e-01, 7.523790e-03, 1.480755e-02]
FCGF_VELO2CAM_T = [-4.069766e-03, -7.631618e-02, -2.717806e-01]


@pytest.mark.data
def test_kitti_pairs_standard_train_keeps_the_pairs_with_scans() -> None:
    kitti = shared_data("kitti")
    pairs = kitti_pairs(kitti, "train")
    assert [p.name for p in pairs] == ["00/11-0"]  # the only json pair inside frames 0-15
    (pair,) = pairs
    assert pair.path_src == scan_path(kitti, 0, 0) and pair.path_ref == scan_path(kitti, 0, 11)
    np.testing.assert_array_equal(pair.transform_ref_src, np.array(json_rows(kitti, "train")[0]["transform"]))
    # sequences overrides the split; val.json has no sequence 00, so the chain comes from the poses
    (chain_pair,) = kitti_pairs(kitti, "val", sequences=[0], refine=False)
    assert chain_pair.name == "00/11-0" and chain_pair.path_src == pair.path_src


@pytest.mark.data
def test_kitti_pairs_all_gives_the_10m_pairs_with_pose_ground_truth() -> None:
    kitti = shared_data("kitti")
    pairs = kitti_pairs(kitti, "train", selection="all", refine=False)
    poses = read_poses(kitti / "poses" / "00.txt")
    tr = read_calib_velo_to_cam(kitti / "sequences" / "00" / "calib.txt")
    assert [p.name for p in pairs] == [f"00/{j}-{i}" for j, i in all_pairs(poses[:16, :3, 3])]
    assert len(pairs) == 10
    for pair, (j, i) in zip(pairs, all_pairs(poses[:16, :3, 3]), strict=True):
        assert pair.path_src == scan_path(kitti, 0, i) and pair.path_ref == scan_path(kitti, 0, j)
        np.testing.assert_allclose(pair.transform_ref_src, relative_lidar_pose(poses[i], poses[j], tr))
    near = kitti_pairs(kitti, "train", selection="all", refine=False, max_frames_apart=12)
    assert [p.name for p in near] == ["00/12-0", "00/13-1", "00/14-2", "00/15-3"]


@pytest.mark.data
def test_raw_pose_ground_truth_vs_the_json_transform() -> None:
    """Pair 00/11-0: raw pose GT vs json, measured 1.40 deg / 0.40 m.

    The json is FCGF's ``M_fcgf @ icp`` (wrong composition side, FCGF issue #65, and FCGF's hard-coded calibration);
    undoing that composition gives the correctly composed transform, 1.40 deg / 0.49 m from the raw GT.
    """
    kitti = shared_data("kitti")
    poses = read_poses(kitti / "poses" / "00.txt")
    raw = relative_lidar_pose(poses[0], poses[11], read_calib_velo_to_cam(kitti / "sequences" / "00" / "calib.txt"))
    truth = np.array(json_rows(kitti, "train")[0]["transform"])
    rot_err, trans_err = pose_errors(raw, truth)
    assert rot_err < 1.5 and trans_err < 0.45
    np.testing.assert_allclose(raw[:3, 3], [-9.45, -0.30, -0.12], atol=0.01)


@pytest.mark.data
def test_icp_refined_chain_from_poses_agrees_with_the_json(tmp_path: Path) -> None:
    """Without the json, the chain comes from the poses and ICP refines it (~6-9 s for the one pair).

    Measured on 00/11-0 (voxel 0.1 m): 0.03 deg / 0.25 m from the json, 0.04 deg / 0.09 m from the json with
    FCGF's composition undone (``inv(M) G M``, ``M`` = FCGF's pose transform with its hard-coded calibration).
    """
    kitti = shared_data("kitti")
    root = link_layout(tmp_path, kitti, list(range(16)), pairs=False)
    (raw_pair,) = kitti_pairs(root, "train", refine=False)
    (pair,) = kitti_pairs(root, "train")
    assert pair.name == raw_pair.name == "00/11-0"
    truth = np.array(json_rows(kitti, "train")[0]["transform"])
    rot_err, trans_err = pose_errors(pair.transform_ref_src, truth)
    assert rot_err < 0.1 and trans_err < 0.3
    assert pose_errors(raw_pair.transform_ref_src, truth)[0] > 1.0  # ICP fixed the raw GT's 1.4 deg
    velo2cam = np.eye(4)
    velo2cam[:3, :3], velo2cam[:3, 3] = np.reshape(FCGF_VELO2CAM_R, (3, 3)), FCGF_VELO2CAM_T
    poses = read_poses(kitti / "poses" / "00.txt")
    fcgf_init = relative_lidar_pose(poses[0], poses[11], velo2cam)
    undone = np.linalg.inv(fcgf_init) @ truth @ fcgf_init
    rot_err, trans_err = pose_errors(pair.transform_ref_src, undone)
    assert rot_err < 0.1 and trans_err < 0.15


@pytest.mark.data
@pytest.mark.slow
def test_all_selection_refined_improves_the_fit() -> None:
    """ICP-refined 'all' pairs fit their scans better than the raw pose GT (4 ICP runs, ~45 s)."""
    import open3d as o3d

    from lcreg.data.io import read_points

    kitti = shared_data("kitti")
    raw = kitti_pairs(kitti, "train", selection="all", refine=False, max_frames_apart=12)
    refined = kitti_pairs(kitti, "train", selection="all", max_frames_apart=12)
    for before, after in zip(raw, refined, strict=True):
        src, ref = (
            o3d.geometry.PointCloud(o3d.utility.Vector3dVector(read_points(p).astype(np.float64))).voxel_down_sample(
                0.1
            )
            for p in (before.path_src, before.path_ref)
        )
        fit = [
            o3d.pipelines.registration.evaluate_registration(src, ref, 0.2, t).fitness
            for t in (before.transform_ref_src, after.transform_ref_src)
        ]
        assert fit[1] > fit[0], before.name
        assert pose_errors(before.transform_ref_src, after.transform_ref_src)[0] < 2.0


@pytest.mark.data
def test_missing_scans_raise_a_clear_error(tmp_path: Path) -> None:
    kitti = shared_data("kitti")
    root = link_layout(tmp_path, kitti, None)
    with pytest.raises(FileNotFoundError, match=r"lists 1358 pairs") as info:
        kitti_pairs(root, "train")
    message = str(info.value)
    assert "sequence 00: no folder" in message and "sequence 05: no folder" in message
    assert "sequences/NN/velodyne/FFFFFF.bin" in message
    (tmp_path / "partial").mkdir()
    partial = link_layout(tmp_path / "partial", kitti, [0, 1])
    with pytest.raises(FileNotFoundError, match=r"sequence 00: \d+ of \d+ scans missing \(000011\.bin"):
        kitti_pairs(partial, "train", sequences=[0])
    with pytest.raises(FileNotFoundError, match=r"poses list \d+ 'all' pairs in sequences \[0\]"):
        kitti_pairs(partial, "train", selection="all", sequences=[0], refine=False)


def test_bad_arguments_and_layouts(tmp_path: Path) -> None:
    bad_split: Any = "trainval"
    bad_selection: Any = "dense"
    with pytest.raises(FileNotFoundError, match="not a directory"):
        kitti_pairs(tmp_path / "missing", "train")
    with pytest.raises(ValueError, match="split"):
        kitti_pairs(tmp_path, bad_split)
    with pytest.raises(ValueError, match="selection"):
        kitti_pairs(tmp_path, "train", selection=bad_selection)
    with pytest.raises(ValueError, match="min_distance"):
        kitti_pairs(tmp_path, "train", min_distance=-1.0)
    (tmp_path / "pairs").mkdir()
    (tmp_path / "pairs" / "train.json").write_text('[{"seq_id": 0}]')
    with pytest.raises(DatasetLayoutError, match=r"train\.json"):
        kitti_pairs(tmp_path, "train")
    velodyne = tmp_path / "sequences" / "03" / "velodyne"
    velodyne.mkdir(parents=True)
    np.zeros((4, 4), np.float32).tofile(velodyne / "000000.bin")
    with pytest.raises(FileNotFoundError, match="has scans but no pose file"):
        kitti_pairs(tmp_path, "train", selection="all", sequences=[3])
