"""Read point clouds from files (``.ply``, ``.pcd``, ``.xyz``/``.xyzn``/``.pts``, ``.npy``, KITTI ``.bin``); downsample.

Every reader returns ``(N, 3)`` float32 points and raises a typed error naming the file:

* :class:`FileNotFoundError` when the path does not exist or is not a file;
* :class:`ValueError` for an extension no reader handles;
* :class:`~lcreg.checks.PointCloudFileError` when the file exists but is unreadable, corrupt, empty, or holds
  NaN/Inf coordinates.

Open3D formats go through ``open3d.io.read_point_cloud`` (imported lazily). Open3D does not raise on a missing or
corrupt file: it prints a warning and returns an empty cloud, so an empty result is turned into an error here.
KITTI velodyne scans are raw little-endian float32 records ``(x, y, z, reflectance)``; ``.npy`` files hold an
``(N, 3)`` array or an ``(N, C >= 3)`` array whose first three columns are ``x, y, z``.

:func:`voxel_downsample` is the package's one voxel downsampler of point arrays (scene datasets, KITTI ground-truth
ICP): Open3D's ``voxel_down_sample``, whose grid starts half a voxel below the cloud's minimum corner (a grid at the
origin keeps other voxels: 5,170 instead of Open3D's 4,910 points on 7-scenes-redkitchen ``cloud_bin_0`` at 5 cm).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lcreg.checks import NonFiniteError, PointCloudFileError, ShapeError

__all__ = ["OPEN3D_SUFFIXES", "SUFFIXES", "read_points", "voxel_downsample"]

OPEN3D_SUFFIXES = (".ply", ".pcd", ".xyz", ".xyzn", ".xyzrgb", ".pts")
SUFFIXES = (*OPEN3D_SUFFIXES, ".npy", ".bin")


def _read_open3d(path: Path) -> np.ndarray:
    import open3d as o3d

    try:
        cloud = o3d.io.read_point_cloud(path, format="auto", print_progress=False)
    except (RuntimeError, ValueError, UnicodeDecodeError) as err:  # pragma: no cover - Open3D usually returns empty
        raise PointCloudFileError(path, f"Open3D could not read it ({err})") from err
    points = np.asarray(cloud.points)
    if points.size == 0:
        raise PointCloudFileError(path, "Open3D read no points (the file is empty, corrupt or not a point cloud)")
    return points


def _read_npy(path: Path) -> np.ndarray:
    try:
        array = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as err:
        raise PointCloudFileError(path, f"not a readable .npy array ({err})") from err
    if array.ndim != 2 or array.shape[1] < 3:
        raise PointCloudFileError(path, f"expected an (N, 3) or (N, C>=3) array, got shape {array.shape}")
    if not np.issubdtype(array.dtype, np.number):
        raise PointCloudFileError(path, f"expected a numeric array, got dtype {array.dtype}")
    return array[:, :3]


def _read_kitti_bin(path: Path) -> np.ndarray:
    size = path.stat().st_size
    if size % 16:
        raise PointCloudFileError(path, f"a KITTI .bin holds float32 (x, y, z, r) records of 16 bytes; size {size}")
    return np.fromfile(path, dtype="<f4").reshape(-1, 4)[:, :3]


def read_points(path: str | Path) -> np.ndarray:
    """Read the points of one file.

    Args:
        path: A ``.ply``, ``.pcd``, ``.xyz``/``.xyzn``/``.xyzrgb``/``.pts``, ``.npy`` or KITTI ``.bin`` file.

    Returns:
        ``(N, 3)`` float32 coordinates, ``N >= 1``, all finite.

    Raises:
        FileNotFoundError: The path does not exist or is not a file.
        ValueError: Unsupported extension.
        PointCloudFileError: Unreadable, corrupt or empty file, or non-finite coordinates.
    """
    path = Path(path).expanduser()
    if not path.is_file():
        raise FileNotFoundError(f"point-cloud file {str(path)!r} does not exist or is not a file")
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise ValueError(
            f"point-cloud file {str(path)!r}: unsupported extension {suffix!r}; expected one of {SUFFIXES}"
        )
    if suffix == ".npy":
        points = _read_npy(path)
    elif suffix == ".bin":
        points = _read_kitti_bin(path)
    else:
        points = _read_open3d(path)
    if len(points) == 0:
        raise PointCloudFileError(path, "the file holds no points")
    if not np.isfinite(points).all():
        bad = int((~np.isfinite(points).all(axis=1)).sum())
        raise PointCloudFileError(path, f"{bad} point(s) have NaN/Inf coordinates")
    return np.ascontiguousarray(points, dtype=np.float32)


def voxel_downsample(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """Centroid of the points of every occupied cubic voxel: Open3D's ``voxel_down_sample`` (imported lazily).

    The grid is Open3D's: voxel ``floor((p - (min_corner - voxel_size / 2)) / voxel_size)``, where ``min_corner`` is
    the cloud's smallest coordinate per axis. Open3D computes in float64; the output has the dtype of ``points``.

    Args:
        points: ``(N, 3)`` float points, finite (any unit, e.g. metres); ``N = 0`` gives an empty result.
        voxel_size: Voxel edge in the unit of the points, ``> 0``.

    Returns:
        ``(N', 3)`` centroids, ``N' <= N``, in Open3D's order (not the input order), dtype of ``points``.

    Raises:
        ShapeError: ``points`` is not ``(N, 3)``.
        TypeError: ``points`` is not a float array.
        NonFiniteError: ``points`` holds NaN or Inf.
        ValueError: ``voxel_size`` is not ``> 0``, or so small that the grid overflows Open3D's int32 voxel index.

    Example:
        >>> pts = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [2.0, 0.0, 0.0]])
        >>> sorted(voxel_downsample(pts, 1.0)[:, 0].tolist())
        [0.05, 2.0]
    """
    array = np.asarray(points)
    if array.ndim != 2 or array.shape[1] != 3:
        raise ShapeError("points", ("N", 3), array.shape)
    if not np.issubdtype(array.dtype, np.floating):
        raise TypeError(f"`points` must be a float array, got dtype {array.dtype}")
    if not np.isfinite(array).all():
        raise NonFiniteError("`points` has NaN or Inf values")
    if not voxel_size > 0:  # also rejects NaN
        raise ValueError(f"`voxel_size` must be > 0, got {voxel_size}")
    if len(array) == 0:
        return array.copy()
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(array.astype(np.float64)))
    try:
        down = cloud.voxel_down_sample(float(voxel_size))
    except RuntimeError as err:  # Open3D raises "voxel_size is too small" when its int32 voxel index overflows
        raise ValueError(f"`voxel_size`={voxel_size} is too small for a cloud of this extent (Open3D)") from err
    return np.asarray(down.points).astype(array.dtype)
