from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lcreg.checks import ShapeError, TooFewPointsError
from lcreg.data.kitti import icp, kitti_pairs, refine_with_icp, relative_lidar_pose, scan_path
from lcreg.data.kitti.icp import ICP_CACHE_SIZE, SCAN_CACHE_SIZE, clear_icp_cache

from _kitti_refs import pose_errors, pose_line


def _scene(rng: np.random.Generator) -> np.ndarray:
    """Points on a floor, two walls and a box: a scene that constrains all six degrees of freedom."""
    floor = np.c_[rng.uniform(-10, 10, (3000, 2)), np.zeros(3000)]
    wall_x = np.c_[np.full(1500, 8.0), rng.uniform(-10, 10, 1500), rng.uniform(0, 3, 1500)]
    wall_y = np.c_[rng.uniform(-10, 10, 1500), np.full(1500, -6.0), rng.uniform(0, 3, 1500)]
    box = rng.uniform([1, 1, 0], [2, 3, 1.5], (1000, 3))
    return np.concatenate([floor, wall_x, wall_y, box])


def test_refine_with_icp_recovers_a_known_transform() -> None:
    rng = np.random.default_rng(4)
    ref = _scene(rng)
    truth = np.eye(4)
    truth[:3, :3] = Rotation.from_euler("z", 8, degrees=True).as_matrix()
    truth[:3, 3] = [1.5, -0.4, 0.1]
    src = (ref - truth[:3, 3]) @ truth[:3, :3]  # truth maps src onto ref
    init = truth.copy()
    init[:3, :3] = Rotation.from_euler("xyz", [0.5, -0.5, 1.0], degrees=True).as_matrix() @ truth[:3, :3]
    init[:3, 3] += [0.1, -0.1, 0.05]
    refined = refine_with_icp(src, ref, init, voxel_size=None, max_distance=0.5, max_iteration=100)
    rot_err, trans_err = pose_errors(refined, truth)
    assert rot_err < 0.01 and trans_err < 0.002
    assert pose_errors(init, truth)[0] > 1.0  # the start really was off


def test_refine_with_icp_rejects_bad_inputs() -> None:
    cloud = np.random.default_rng(5).normal(size=(100, 3))
    with pytest.raises(ShapeError, match="points_src"):
        refine_with_icp(cloud[:, :2], cloud, np.eye(4))
    with pytest.raises(TooFewPointsError, match="points_ref"):
        refine_with_icp(cloud, np.zeros((0, 3)), np.eye(4))
    with pytest.raises(ShapeError, match="init"):
        refine_with_icp(cloud, cloud, np.eye(3))
    with pytest.raises(ValueError, match="voxel_size"):
        refine_with_icp(cloud, cloud, np.eye(4), voxel_size=0.0)
    far = np.eye(4)
    far[:3, 3] = 100.0
    with pytest.raises(ValueError, match="no source point within"):
        refine_with_icp(cloud, cloud, far, voxel_size=None)


def _synthetic_kitti(tmp_path: Path) -> tuple[Path, np.ndarray]:
    """Sequence 00 with two frames 12 m apart that see the same scene; returns the root and the true T_1_0."""
    rng = np.random.default_rng(6)
    world = _scene(rng)
    tr = np.eye(4)
    tr[:3, :3] = Rotation.from_euler("zyx", [-90, 0, -90], degrees=True).as_matrix()  # LiDAR x forward = camera z
    poses = np.stack([np.eye(4), np.eye(4)])
    poses[1, :3, 3] = [0.5, 0.0, 12.0]
    (tmp_path / "poses").mkdir()
    (tmp_path / "poses" / "00.txt").write_text("\n".join(pose_line(p) for p in poses) + "\n")
    scan_path(tmp_path, 0, 0).parent.mkdir(parents=True)
    (tmp_path / "sequences" / "00" / "calib.txt").write_text(f"Tr: {pose_line(tr)}\n")
    for frame, pose in enumerate(poses):
        lidar = (np.linalg.inv(pose @ tr) @ np.c_[world, np.ones(len(world))].T)[:3].T
        np.c_[lidar, np.zeros(len(lidar))].astype(np.float32).tofile(scan_path(tmp_path, 0, frame))
    return tmp_path, relative_lidar_pose(poses[0], poses[1], tr)


def test_refined_pairs_come_from_a_bounded_cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    root, truth = _synthetic_kitti(tmp_path)
    runs: list[int] = []
    real_icp = icp._icp

    def counting_icp(*args: object) -> np.ndarray:
        runs.append(1)
        return real_icp(*args)  # type: ignore[arg-type]

    monkeypatch.setattr(icp, "_icp", counting_icp)
    clear_icp_cache()
    args = {"split": "train", "selection": "all", "sequences": [0], "voxel_size": 0.2}
    (first,) = kitti_pairs(root, **args)  # type: ignore[arg-type]
    assert first.name == "00/1-0" and len(runs) == 1
    rot_err, trans_err = pose_errors(first.transform_ref_src, truth)
    assert rot_err < 0.05 and trans_err < 0.02
    first.transform_ref_src[:] = 0.0  # callers get copies: the cached transform is untouched
    (again,) = kitti_pairs(root, **args)  # type: ignore[arg-type]
    assert len(runs) == 1 and pose_errors(again.transform_ref_src, truth)[1] < 0.02
    kitti_pairs(root, **{**args, "max_distance": 0.3})  # type: ignore[arg-type]
    assert len(runs) == 2  # other ICP parameters: another entry
    stat = scan_path(root, 0, 1).stat()
    os.utime(scan_path(root, 0, 1), ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))
    kitti_pairs(root, **args)  # type: ignore[arg-type]
    assert len(runs) == 3  # a changed scan file: recomputed
    clear_icp_cache()
    kitti_pairs(root, **args)  # type: ignore[arg-type]
    assert len(runs) == 4
    assert icp._refined.cache_info().maxsize == ICP_CACHE_SIZE and icp._scan.cache_info().maxsize == SCAN_CACHE_SIZE
    clear_icp_cache()
