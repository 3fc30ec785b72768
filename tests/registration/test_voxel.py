"""The automatic voxel size: unit-free, bounded point counts, never below the point spacing."""

from __future__ import annotations

import numpy as np

from lcreg.data.io import voxel_downsample
from lcreg.registration.voxel import (
    SPACING_FACTOR,
    auto_voxel_size,
    cloud_voxel_size,
    median_spacing,
    round_voxel_size,
)


def _grid(n: int, step: float) -> np.ndarray:
    return np.stack(np.meshgrid(*[np.arange(n) * step] * 3), -1).reshape(-1, 3)


def test_sparse_cloud_uses_its_spacing():
    grid = _grid(10, 0.5)  # 1,000 points, spacing 0.5
    assert median_spacing(grid) == 0.5
    assert cloud_voxel_size(grid, target=5000) == SPACING_FACTOR * 0.5


def test_dense_cloud_is_brought_to_about_the_target():
    points = np.random.default_rng(0).random((60_000, 3))
    v = cloud_voxel_size(points, target=2000)
    kept = len(voxel_downsample(points, v))
    assert 1000 < kept <= 2000
    assert len(voxel_downsample(points, v * 0.9)) > 2000  # not much larger than needed


def test_scale_equivariant_on_the_rounding_grid(pair):
    src, ref, _ = pair
    v = auto_voxel_size(src, ref)
    assert v == round_voxel_size(v)
    for factor in (10.0, 1000.0, 0.001):  # decimal units: the same point of the grid, scaled
        assert np.isclose(auto_voxel_size(src * factor, ref * factor), factor * v, rtol=1e-9)


def test_rounding_grid():
    assert round_voxel_size(1.0) == 1.0
    assert round_voxel_size(1.01) == 2**0.25
    assert 0.05 <= round_voxel_size(0.05) < 0.05 * 1.19
