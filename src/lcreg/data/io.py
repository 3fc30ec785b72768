"""Read point clouds from files: ``.ply``, ``.pcd``, ``.xyz`` (and ``.xyzn``, ``.pts``), ``.npy`` and KITTI ``.bin``.

Every reader returns ``(N, 3)`` float32 points and raises a typed error naming the file:

* :class:`FileNotFoundError` when the path does not exist or is not a file;
* :class:`ValueError` for an extension no reader handles;
* :class:`~lcreg.checks.PointCloudFileError` when the file exists but is unreadable, corrupt, empty, or holds
  NaN/Inf coordinates.

Open3D formats go through ``open3d.io.read_point_cloud`` (imported lazily). Open3D does not raise on a missing or
corrupt file: it prints a warning and returns an empty cloud, so an empty result is turned into an error here.
KITTI velodyne scans are raw little-endian float32 records ``(x, y, z, reflectance)``; ``.npy`` files hold an
``(N, 3)`` array or an ``(N, C >= 3)`` array whose first three columns are ``x, y, z``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lcreg.checks import PointCloudFileError

__all__ = ["OPEN3D_SUFFIXES", "SUFFIXES", "read_points"]

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
