"""The automatic voxel size of :func:`lcreg.register`: one unit-free rule for objects, rooms and LiDAR scans.

Every radius and gate of the classical steps is a multiple of one voxel size ``v`` (``lcreg.baselines.classical``).
A fixed ``v`` only fits one scale, so ``v`` follows the cloud:

* ``v_spacing = SPACING_FACTOR x`` the median nearest-neighbour distance (a sample of the points): below it a cloud
  is sparser than its own voxels and normals/FPFH see too few neighbours;
* ``v_count``: the smallest ``v`` (bisection in log scale) whose voxel grid keeps at most ``target`` points; larger
  clouds are downsampled to about ``target`` points, which bounds the cost of normals, FPFH and RANSAC whatever the
  cloud's size (millions of points) and unit;
* ``v = max(v_spacing, v_count)`` per cloud, the larger of the two clouds' values for the pair (both clouds must be
  described at the same scale), rounded up to the grid ``10^e 2^(k/4)`` (``e`` the decade of ``v``) so that pairs
  sharing a file share its cached features. The grid is the same in every decimal unit: the same scans in metres and
  in millimetres get voxel sizes exactly 1000 apart, hence the same registration (a grid ``2^(k/4)`` of absolute
  values would put them on different points of the grid, up to 19 % apart).

The constants were set from the clouds' statistics, then checked on validation pairs (``docs/results/register.md``):
ModelNet40 objects of 1,024 points (spacing about 0.036 in unit-sphere units: ``v`` = 0.054, the 0.05 chosen on
ModelNet40 validation for RANSAC), 3DMatch fragments (11k-49k points: ``v`` about 5 cm, the usual 3DMatch value)
and KITTI scans (about 120k points: ``v`` about 0.7 m).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from lcreg.data.io import voxel_downsample

__all__ = [
    "SPACING_FACTOR",
    "TARGET_POINTS",
    "auto_voxel_size",
    "cloud_voxel_size",
    "median_spacing",
    "round_voxel_size",
]

TARGET_POINTS = 5000
"""Points kept per cloud (about) by the automatic voxel size."""
SPACING_FACTOR = 1.5
"""Smallest voxel, in median nearest-neighbour distances."""
_SAMPLE = 200_000
_SPACING_SAMPLE = 2_000
_BISECTION_STEPS = 14


def median_spacing(points: np.ndarray, seed: int = 0) -> float:
    """Median distance from a point to its nearest neighbour (at most 2,000 query points, seeded).

    Args:
        points: ``(N, 3)`` float, ``N >= 2``.
        seed: Seed of the sample of query points.

    Returns:
        The median distance in the points' unit (``> 0`` unless more than half the points are duplicates).
    """
    rng = np.random.default_rng(seed)
    query = points if len(points) <= _SPACING_SAMPLE else points[rng.choice(len(points), _SPACING_SAMPLE, False)]
    distances, _ = cKDTree(points).query(query, k=2)
    return float(np.median(distances[:, 1]))


def round_voxel_size(value: float) -> float:
    """``value`` rounded up to the grid ``10^e 2^(k/4)``, ``e = floor(log10(value))`` (at most +19 %).

    Scaling ``value`` by a power of ten scales the result by the same power (metres, millimetres, kilometres).
    """
    decade = 10.0 ** math.floor(math.log10(value) + 1e-12)
    mantissa = value / decade  # in [1, 10)
    return float(decade * 2.0 ** (math.ceil(math.log2(mantissa) * 4 - 1e-9) / 4))


def cloud_voxel_size(points: np.ndarray, target: int = TARGET_POINTS, seed: int = 0) -> float:
    """``max(v_spacing, v_count)`` of one cloud (see the module docstring), not rounded.

    Args:
        points: ``(N, 3)`` float, finite, non-zero extent.
        target: Points to keep at most after downsampling.
        seed: Seed of the samples (clouds above 200,000 points are sampled for the spacing and the count).

    Returns:
        The voxel size in the points' unit.
    """
    rng = np.random.default_rng(seed)
    sample = points if len(points) <= _SAMPLE else points[rng.choice(len(points), _SAMPLE, False)]
    # Above 200,000 points the spacing of the sample (larger than the cloud's) is used: v_count dominates there.
    spacing = median_spacing(sample, seed)
    extent = float(np.linalg.norm(np.ptp(points, axis=0)))
    low = max(SPACING_FACTOR * spacing, extent * 1e-6)
    if len(sample) <= target or len(voxel_downsample(sample, low)) <= target:
        return low
    high = extent
    for _ in range(_BISECTION_STEPS):
        middle = math.sqrt(low * high)
        if len(voxel_downsample(sample, middle)) <= target:
            high = middle
        else:
            low = middle
    return high


def auto_voxel_size(points_src: np.ndarray, points_ref: np.ndarray, target: int = TARGET_POINTS) -> float:
    """The voxel size of a pair: the larger of the two clouds' values, rounded up (:func:`round_voxel_size`).

    Args:
        points_src: ``(N, 3)`` float64 source points.
        points_ref: ``(M, 3)`` float64 reference points.
        target: Points per cloud after downsampling (about).

    Returns:
        ``v`` in the points' unit.

    Example:
        >>> grid = np.stack(np.meshgrid(*[np.arange(10.0)] * 3), -1).reshape(-1, 3)  # spacing 1
        >>> auto_voxel_size(grid, grid)  # 1.5 rounded up to 10^0 2^(k/4)
        1.681792830507429
    """
    return round_voxel_size(max(cloud_voxel_size(points_src, target), cloud_voxel_size(points_ref, target)))
