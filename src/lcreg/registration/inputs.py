"""Clouds a user hands to :func:`lcreg.register`: a file path, numpy, torch or an Open3D ``PointCloud``.

Every input becomes a :class:`Cloud`: ``(N, 3)`` float64 points, all finite. Rows with a NaN/Inf coordinate (depth
sensors write NaN for pixels without a return) are dropped with a :class:`NonFiniteRowsWarning` that says how many;
what is left must have at least ``min_points`` points and a non-zero extent. Errors are typed and name the argument
(``points_src``/``points_ref``) and the file.
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from lcreg.checks import DegenerateCloudError, ShapeError, TooFewPointsError
from lcreg.data.io import read_points

__all__ = ["Cloud", "CloudLike", "NonFiniteRowsWarning", "as_cloud"]

CloudLike = str | os.PathLike[str] | np.ndarray | torch.Tensor | Any
"""A path, an ``(N, 3)`` array or tensor (``(1, N, 3)`` too), or an Open3D ``PointCloud``."""


class NonFiniteRowsWarning(UserWarning):
    """Rows with NaN/Inf coordinates were dropped from a cloud."""


@dataclass(frozen=True)
class Cloud:
    """A validated cloud.

    Attributes:
        points: ``(N, 3)`` float64, finite, in the input's unit.
        label: The file path, or the argument name for in-memory clouds.
        path: The file it was read from (``None`` for in-memory clouds).
        dropped: Rows removed because a coordinate was NaN/Inf.
    """

    points: np.ndarray
    label: str
    path: Path | None = None
    dropped: int = 0


def _array(value: Any, name: str) -> np.ndarray:
    """``value`` as a numpy array (torch tensors and Open3D clouds included)."""
    if isinstance(value, torch.Tensor):
        return value.detach().cpu().numpy()
    if isinstance(value, np.ndarray):
        return value
    if hasattr(value, "points") and hasattr(value, "has_points"):  # open3d.geometry.PointCloud
        return np.asarray(value.points)
    raise TypeError(
        f"`{name}` must be a point-cloud file path, an (N, 3) numpy array or torch tensor, or an Open3D PointCloud; "
        f"got {type(value).__name__}"
    )


def _coordinates(array: np.ndarray, name: str) -> np.ndarray:
    """``(N, 3)`` float64 coordinates of a numeric array (``(1, N, 3)`` accepted)."""
    if array.ndim == 3 and array.shape[0] == 1:
        array = array[0]
    if array.ndim != 2 or array.shape[1] != 3:
        raise ShapeError(name, ("N", 3), array.shape)
    if not (np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.integer)):
        raise TypeError(f"`{name}` must hold real numbers, got dtype {array.dtype}")
    with np.errstate(over="ignore", invalid="ignore"):
        return np.asarray(array, dtype=np.float64)


def as_cloud(value: CloudLike, name: str, min_points: int = 16) -> Cloud:
    """Read or convert one cloud, drop its non-finite rows (with a warning) and check what is left.

    Args:
        value: A file path (any format of :func:`lcreg.data.io.read_points`), an ``(N, 3)`` numpy array (any
            float or integer dtype) or torch tensor, or an Open3D ``PointCloud``.
        name: The argument name used in messages (``"points_src"``).
        min_points: Fewest finite points accepted.

    Returns:
        The cloud in float64.

    Raises:
        FileNotFoundError, lcreg.checks.PointCloudFileError, ValueError: Missing, damaged or unsupported file.
        TypeError: Not a cloud, or a non-numeric dtype.
        lcreg.checks.ShapeError: Not ``(N, 3)``.
        lcreg.checks.TooFewPointsError: Fewer than ``min_points`` finite points (an empty cloud included).
        lcreg.checks.DegenerateCloudError: Every point at one location.
    """
    path: Path | None = None
    if isinstance(value, (str, os.PathLike)):
        path = Path(value).expanduser()
        points = read_points(path, nonfinite="keep").astype(np.float64)
        label = str(path)
    else:
        points = _coordinates(_array(value, name), name)
        label = name
    finite = np.isfinite(points).all(axis=1)
    dropped = int((~finite).sum())
    if dropped:
        warnings.warn(
            f"{name} ({label}): dropped {dropped} of {len(points)} points with NaN/Inf coordinates",
            NonFiniteRowsWarning,
            stacklevel=3,
        )
        points = points[finite]
    where = f"`{name}` ({label})" if path is not None else f"`{name}`"
    if len(points) < min_points:
        raise TooFewPointsError(f"{where} has {len(points)} finite points; at least {min_points} are needed")
    if float(np.ptp(points, axis=0).max()) == 0.0:
        raise DegenerateCloudError(f"{where}: every point is at one location, no motion can be recovered")
    return Cloud(np.ascontiguousarray(points), label, path, dropped)
