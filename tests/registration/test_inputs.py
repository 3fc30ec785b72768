"""Clouds from paths, numpy, torch and Open3D; NaN rows dropped with a count; typed errors naming the argument."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

from lcreg.checks import DegenerateCloudError, PointCloudFileError, ShapeError, TooFewPointsError
from lcreg.registration.inputs import NonFiniteRowsWarning, as_cloud
from lcreg.registration.outputs import write_ply


def test_containers_give_the_same_float64_points(pair, tmp_path):
    src = pair[0]
    path = write_ply(tmp_path / "a.ply", src)
    import open3d as o3d

    o3d_cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src))
    expected = src.astype(np.float32).astype(np.float64)
    for value in (src, src.astype(np.float32), torch.from_numpy(src), torch.from_numpy(src)[None], o3d_cloud, path):
        cloud = as_cloud(value, "points_src")
        assert cloud.points.dtype == np.float64 and cloud.points.shape == (3000, 3)
        np.testing.assert_allclose(cloud.points, expected, atol=1e-6)
    assert as_cloud(path, "points_src").path == path
    assert as_cloud(np.arange(60).reshape(20, 3), "points_src").points.dtype == np.float64


def test_nan_rows_are_dropped_with_their_count(pair, tmp_path):
    src = pair[0].copy()
    src[[3, 10, 11], 1] = np.nan
    src[20, 0] = np.inf
    with pytest.warns(NonFiniteRowsWarning, match=r"points_src .*dropped 4 of 3000 points"):
        cloud = as_cloud(src, "points_src")
    assert cloud.dropped == 4 and len(cloud.points) == 2996
    np.testing.assert_array_equal(cloud.points, np.delete(src, [3, 10, 11, 20], axis=0))
    path = tmp_path / "nan.npy"
    np.save(path, src.astype(np.float32))
    with pytest.warns(NonFiniteRowsWarning, match=r"nan\.npy.*dropped 4 of 3000"):
        assert as_cloud(path, "points_ref").dropped == 4


def test_errors_name_the_argument_or_file(tmp_path):
    with pytest.raises(ShapeError, match="points_src"):
        as_cloud(np.zeros((10, 2)), "points_src")
    with pytest.raises(TypeError, match="points_ref"):
        as_cloud([1, 2, 3], "points_ref")
    with pytest.raises(TypeError, match="points_ref"):
        as_cloud(np.array([["a", "b", "c"]] * 20), "points_ref")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NonFiniteRowsWarning)
        with pytest.raises(TooFewPointsError, match=r"points_src.*0 finite points"):
            as_cloud(np.full((100, 3), np.nan), "points_src")
    with pytest.raises(TooFewPointsError, match="points_src"):
        as_cloud(np.zeros((0, 3)), "points_src")
    with pytest.raises(DegenerateCloudError, match="points_ref"):
        as_cloud(np.ones((50, 3)), "points_ref")
    with pytest.raises(FileNotFoundError, match=r"missing.ply"):
        as_cloud(tmp_path / "missing.ply", "points_src")
    empty = tmp_path / "empty.ply"
    empty.write_bytes(b"")
    with pytest.raises(PointCloudFileError, match=r"empty.ply"):
        as_cloud(empty, "points_src")
