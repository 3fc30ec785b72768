"""Read point clouds from ``.ply``, ``.pcd``, ``.xyz``/``.xyzn``/``.xyzrgb``/``.pts``, ``.npy``, KITTI ``.bin`` files.

Every reader returns ``(N, 3)`` float32 points, ``N >= 1``, all finite, and raises a typed error naming the file:

* :class:`FileNotFoundError` when the path does not exist or is not a file;
* :class:`ValueError` for an extension no reader handles;
* :class:`~lcreg.checks.PointCloudFileError` when the file exists but is unreadable, empty, not exactly what its
  header claims, or holds NaN/Inf coordinates or coordinates beyond the float32 range.

Files are validated before any array is built, so a corrupt file never yields invented points and a lying header
never makes the reader allocate what it claims:

* PLY (``ascii``, ``binary_little_endian``, ``binary_big_endian``): the header is parsed (elements, scalar and list
  properties); a binary file must end exactly after its last element (list elements such as faces are walked), an
  ASCII file must hold exactly one non-blank line per declared record and end with a newline. The ``vertex``
  element needs scalar ``x, y, z`` properties; other properties and elements are skipped.
* PCD (``DATA ascii``, ``binary``, ``binary_compressed``): ``FIELDS/SIZE/TYPE/COUNT`` must agree and hold scalar
  ``x, y, z``, ``POINTS == WIDTH * HEIGHT``; a binary payload must be exactly ``POINTS`` records, an ASCII one exactly
  ``POINTS`` lines (ending with a newline); a compressed payload's size fields must match the file and ``POINTS``
  records, and be a possible LZF expansion, before it is decompressed (and it must expand to exactly that size).
* ``.xyz`` (>= 3 numbers a line), ``.xyzn``/``.xyzrgb`` (6), ``.pts`` (a first line with the point count, then
  >= 3 numbers a line): every non-blank line must be a row of as many numbers as the others.
* ``.npy``: an ``(N, C >= 3)`` integer or float array (``x, y, z`` in the first 3 columns; complex, boolean,
  object and structured dtypes are refused); the header is read with numpy's format helpers and the declared
  ``shape x itemsize`` must equal the payload size before anything is loaded.
* KITTI velodyne ``.bin``: raw little-endian float32 records ``(x, y, z, reflectance)``; the size must be a
  multiple of 16 bytes.

Coordinates are cast to float32 first and checked for finiteness after the cast, so a float64 ``1e39`` is refused.
None of the readers uses Open3D (it does not validate files: it invents points for truncated or lying files).

:func:`voxel_downsample` is the package's one voxel downsampler of point arrays (scene datasets, KITTI ground-truth
ICP): Open3D's ``voxel_down_sample``, whose grid starts half a voxel below the cloud's minimum corner (a grid at the
origin keeps other voxels: 5,170 instead of Open3D's 4,910 points on 7-scenes-redkitchen ``cloud_bin_0`` at 5 cm).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Literal

import numpy as np

from lcreg.checks import NonFiniteError, PointCloudFileError, ShapeError
from lcreg.data import _pointfiles as formats

__all__ = ["SUFFIXES", "read_points", "voxel_downsample"]

READERS: dict[str, Callable[[Path], np.ndarray]] = {
    ".ply": formats.read_ply,
    ".pcd": formats.read_pcd,
    **dict.fromkeys((".xyz", ".xyzn", ".xyzrgb", ".pts"), formats.read_text),
    ".npy": formats.read_npy,
    ".bin": formats.read_kitti_bin,
}
SUFFIXES = tuple(READERS)
NonFinite = Literal["error", "keep"]


def _to_float32(path: Path, columns: np.ndarray, nonfinite: NonFinite) -> np.ndarray:
    """Cast ``(N, 3)`` coordinates to contiguous float32, then refuse (or keep) non-finite ones (overflow gives Inf)."""
    with np.errstate(over="ignore", invalid="ignore"):
        points = np.ascontiguousarray(columns, dtype=np.float32)
    finite = np.isfinite(points).all(axis=1)
    if nonfinite == "error" and not finite.all():
        raise PointCloudFileError(
            path, f"{int((~finite).sum())} point(s) have NaN/Inf coordinates or coordinates beyond the float32 range"
        )
    return points


def read_points(path: str | Path, nonfinite: NonFinite = "error") -> np.ndarray:
    """Read the points of one file, validated against its format (see the module docstring).

    Args:
        path: A ``.ply``, ``.pcd``, ``.xyz``/``.xyzn``/``.xyzrgb``/``.pts``, ``.npy`` or KITTI ``.bin`` file.
        nonfinite: ``"error"``: a NaN/Inf (or float32-overflowing) coordinate is an error; ``"keep"``: such rows
            are returned as they are (NaN/Inf), for a caller that drops them and reports how many (depth sensors
            write NaN for pixels without a return; ``lcreg register`` drops them with a warning).

    Returns:
        ``(N, 3)`` float32 coordinates, ``N >= 1``, all finite unless ``nonfinite="keep"``.

    Raises:
        FileNotFoundError: The path does not exist or is not a file.
        ValueError: Unsupported extension or ``nonfinite`` value.
        PointCloudFileError: Unreadable or empty file, a file that is not exactly what its header claims, or
            (``nonfinite="error"``) coordinates that are NaN/Inf or beyond the float32 range.
    """
    if nonfinite not in ("error", "keep"):
        raise ValueError(f"`nonfinite` must be 'error' or 'keep', got {nonfinite!r}")
    path = Path(path).expanduser()
    if not path.is_file():
        raise FileNotFoundError(f"point-cloud file {str(path)!r} does not exist or is not a file")
    suffix = path.suffix.lower()
    if suffix not in READERS:
        raise ValueError(
            f"point-cloud file {str(path)!r}: unsupported extension {suffix!r}; expected one of {SUFFIXES}"
        )
    if path.stat().st_size == 0:
        raise PointCloudFileError(path, "empty file (0 bytes)")
    try:
        columns = READERS[suffix](path)
    except formats.FileFormatError as err:
        raise PointCloudFileError(path, str(err)) from err
    except OSError as err:
        raise PointCloudFileError(path, f"could not be read ({err})") from err
    if len(columns) == 0:
        raise PointCloudFileError(path, "the file holds no points")
    return _to_float32(path, columns, nonfinite)


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
