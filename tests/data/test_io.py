from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from lcreg.checks import PointCloudFileError
from lcreg.data.io import read_points

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
