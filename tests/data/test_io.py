from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from lcreg.checks import NonFiniteError, PointCloudFileError, ShapeError
from lcreg.data.io import read_points, voxel_downsample

from _shared_data import shared_data  # type: ignore[import-not-found]

POINTS = np.random.default_rng(0).normal(size=(50, 3)).astype(np.float32)


def _write_open3d(path: Path, points: np.ndarray) -> None:
    o3d = pytest.importorskip("open3d")
    cloud = o3d.geometry.PointCloud()
    cloud.points = o3d.utility.Vector3dVector(points.astype(np.float64))
    assert o3d.io.write_point_cloud(str(path), cloud)


@pytest.mark.parametrize("suffix", [".ply", ".pcd", ".xyz"])
def test_open3d_formats_round_trip(tmp_path: Path, suffix: str) -> None:
    path = tmp_path / f"cloud{suffix}"
    _write_open3d(path, POINTS)
    got = read_points(path)
    assert got.dtype == np.float32 and got.shape == (50, 3)
    np.testing.assert_allclose(got, POINTS, atol=1e-5)


def test_npy_and_kitti_bin_round_trip(tmp_path: Path) -> None:
    np.save(tmp_path / "a.npy", POINTS.astype(np.float64))
    np.testing.assert_array_equal(read_points(tmp_path / "a.npy"), POINTS)
    with_intensity = np.concatenate([POINTS, np.ones((50, 1), np.float32)], axis=1)
    np.save(tmp_path / "b.npy", with_intensity)
    np.testing.assert_array_equal(read_points(tmp_path / "b.npy"), POINTS)
    with_intensity.astype("<f4").tofile(tmp_path / "000000.bin")
    np.testing.assert_array_equal(read_points(tmp_path / "000000.bin"), POINTS)


def test_missing_file_names_the_path(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match=r"nope\.ply"):
        read_points(tmp_path / "nope.ply")
    with pytest.raises(FileNotFoundError, match="does not exist or is not a file"):
        read_points(tmp_path)


@pytest.mark.parametrize("name", ["empty.ply", "empty.pcd", "empty.xyz", "empty.bin", "empty.npy"])
def test_empty_files_are_clear_errors(tmp_path: Path, name: str) -> None:
    pytest.importorskip("open3d")
    path = tmp_path / name
    path.write_bytes(b"")
    with pytest.raises(PointCloudFileError, match=re.escape(name)) as info:
        read_points(path)
    assert info.value.path == str(path)


@pytest.mark.parametrize("name", ["corrupt.ply", "corrupt.pcd", "corrupt.npy"])
def test_corrupt_files_are_clear_errors(tmp_path: Path, name: str) -> None:
    pytest.importorskip("open3d")
    path = tmp_path / name
    path.write_bytes(b"\x00\x01garbage that is not a point cloud\xff" * 3)
    with pytest.raises(PointCloudFileError, match=re.escape(name)):
        read_points(path)


def test_bad_contents_are_clear_errors(tmp_path: Path) -> None:
    (tmp_path / "odd.bin").write_bytes(b"\x00" * 20)
    with pytest.raises(PointCloudFileError, match="16 bytes"):
        read_points(tmp_path / "odd.bin")
    np.save(tmp_path / "flat.npy", np.zeros(9, np.float32))
    with pytest.raises(PointCloudFileError, match=r"\(N, 3\)"):
        read_points(tmp_path / "flat.npy")
    nan = POINTS.copy()
    nan[3, 1] = np.nan
    np.save(tmp_path / "nan.npy", nan)
    with pytest.raises(PointCloudFileError, match="1 point"):
        read_points(tmp_path / "nan.npy")
    (tmp_path / "cloud.las").write_bytes(b"x")
    with pytest.raises(ValueError, match=r"unsupported extension '\.las'"):
        read_points(tmp_path / "cloud.las")


@pytest.mark.data
def test_reads_real_3dmatch_and_kitti_files() -> None:
    root = shared_data("3dmatch")
    ply = read_points(root / "fragments" / "7-scenes-redkitchen" / "cloud_bin_0.ply")
    assert ply.ndim == 2 and ply.shape[1] == 3 and len(ply) > 1000
    scan = shared_data("kitti") / "sequences" / "00" / "velodyne" / "000000.bin"
    kitti = read_points(scan)
    assert len(kitti) == scan.stat().st_size // 16 and len(kitti) > 100_000
    assert np.linalg.norm(kitti, axis=1).max() < 200  # metres around the sensor


# ------------------------------------------------------------------------------------------------ voxel_downsample


def _open3d_downsample(points: np.ndarray, voxel_size: float) -> np.ndarray:
    o3d = pytest.importorskip("open3d")
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
    return np.asarray(cloud.voxel_down_sample(voxel_size).points)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_voxel_downsample_is_open3d_voxel_down_sample(dtype: type) -> None:
    points = (np.random.default_rng(1).uniform(-1, 1, (3000, 3)) + 5.0).astype(dtype)
    got = voxel_downsample(points, 0.2)
    assert got.dtype == dtype
    np.testing.assert_array_equal(got, _open3d_downsample(points, 0.2).astype(dtype))


def test_voxel_downsample_grid_starts_half_a_voxel_below_the_minimum() -> None:
    """Independent per-voxel mean on the documented grid (origin ``min - v / 2``) gives the same centroids."""
    points = np.random.default_rng(2).uniform(-1, 1, (2000, 3)) + 3.3
    voxel = 0.25
    keys = np.floor((points - (points.min(0) - voxel / 2)) / voxel).astype(int)
    groups: dict[tuple[int, ...], list[np.ndarray]] = {}
    for key, point in zip(map(tuple, keys), points):
        groups.setdefault(key, []).append(point)
    expected = np.array(sorted(np.mean(g, axis=0).tolist() for g in groups.values()))
    got = np.array(sorted(voxel_downsample(points, voxel).tolist()))
    np.testing.assert_allclose(got, expected, atol=1e-12)


def test_voxel_downsample_errors_name_the_argument() -> None:
    points = np.zeros((4, 3))
    assert voxel_downsample(np.zeros((0, 3), np.float32), 0.1).shape == (0, 3)
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="voxel_size"):
            voxel_downsample(points, bad)
    with pytest.raises(ValueError, match=r"voxel_size.*too small"):
        voxel_downsample(np.array([[0.0, 0.0, 0.0], [1e9, 0.0, 0.0]]), 1e-3)
    with pytest.raises(ShapeError, match="points"):
        voxel_downsample(np.zeros((4, 2)), 0.1)
    with pytest.raises(TypeError, match="points"):
        voxel_downsample(np.zeros((4, 3), np.int64), 0.1)
    with pytest.raises(NonFiniteError, match="points"):
        voxel_downsample(np.full((4, 3), np.nan), 0.1)


@pytest.mark.data
def test_voxel_downsample_count_on_a_real_fragment() -> None:
    """7-scenes-redkitchen cloud_bin_0 at 5 cm: Open3D keeps 4,910 of 18,977 points (a grid at the origin: 5,170)."""
    points = read_points(shared_data("3dmatch") / "fragments" / "7-scenes-redkitchen" / "cloud_bin_0.ply")
    assert len(points) == 18_977
    assert len(voxel_downsample(points, 0.05)) == len(_open3d_downsample(points, 0.05)) == 4_910
