"""KITTI odometry text files: ``calib.txt``, ``poses/NN.txt``, the json pair lists, and the relative LiDAR pose.

The relative LiDAR pose of frame ``i`` in frame ``j`` (maps points of scan ``i`` into scan ``j``) is
``T_j_i = inv(Tr) inv(P_j) P_i Tr`` (:func:`relative_lidar_pose`), with ``Tr`` the velodyne-to-camera-0 calibration
and ``P_f`` the camera-0 poses. Malformed files raise :class:`~lcreg.checks.DatasetLayoutError` naming the file
(and line); missing files raise ``FileNotFoundError`` with the expected layout.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from lcreg.checks import DatasetLayoutError, NonFiniteError, ShapeError
from lcreg.data.kitti.layout import EXPECTED_LAYOUT

__all__ = ["as_4x4", "read_calib_velo_to_cam", "read_json_pairs", "read_poses", "relative_lidar_pose"]

JsonPair = tuple[int, int, int, np.ndarray]
"""``(seq_id, frame0, frame1, transform (4, 4))`` of a json pair list."""


def _read_lines(path: str | Path, what: str) -> tuple[Path, list[str]]:
    """Return ``path`` and its lines, raising ``FileNotFoundError`` naming the file when it is missing."""
    file = Path(path).expanduser()
    if not file.is_file():
        raise FileNotFoundError(f"KITTI {what} file {str(file)!r} does not exist; {EXPECTED_LAYOUT}")
    return file, file.read_text().splitlines()


def _parse_3x4(values: Sequence[str], file: Path, where: str) -> np.ndarray:
    """Twelve numbers (3x4 row-major) as a ``(4, 4)`` float64 ``[R t; 0 0 0 1]``."""
    if len(values) != 12:
        raise DatasetLayoutError(f"{str(file)!r}, {where}: expected 12 numbers (3x4 row-major), got {len(values)}")
    try:
        numbers = np.array([float(v) for v in values], dtype=np.float64)
    except ValueError as err:
        raise DatasetLayoutError(f"{str(file)!r}, {where}: not a number ({err})") from err
    if not np.all(np.isfinite(numbers)):
        raise DatasetLayoutError(f"{str(file)!r}, {where}: non-finite value")
    matrix = np.eye(4)
    matrix[:3] = numbers.reshape(3, 4)
    return matrix


def read_calib_velo_to_cam(path: str | Path) -> np.ndarray:
    """Read the velodyne-to-camera-0 transform ``Tr`` of a KITTI odometry ``calib.txt``.

    Args:
        path: ``sequences/NN/calib.txt`` (lines ``KEY: values``; the ``Tr`` line holds 12 values, 3x4 row-major).

    Returns:
        ``(4, 4)`` float64 ``[R t; 0 0 0 1]`` mapping velodyne points into the camera-0 frame (metres).

    Raises:
        FileNotFoundError: The file does not exist.
        DatasetLayoutError: No ``Tr`` line, or it does not hold 12 finite numbers (the message names the file).
    """
    file, lines = _read_lines(path, "calibration")
    for number, line in enumerate(lines, start=1):
        key, sep, rest = line.partition(":")
        if sep and key.strip() == "Tr":
            return _parse_3x4(rest.split(), file, f"line {number} ('Tr')")
    raise DatasetLayoutError(f"{str(file)!r} has no 'Tr:' line (velodyne to camera 0); {EXPECTED_LAYOUT}")


def read_poses(path: str | Path) -> np.ndarray:
    """Read a KITTI odometry pose file ``poses/NN.txt``.

    Args:
        path: One line per frame with 12 numbers, the 3x4 row-major camera-0 pose in the world (first camera) frame.

    Returns:
        ``(F, 4, 4)`` float64 poses ``P_f`` (map camera-0 coordinates of frame ``f`` into the world frame, metres).

    Raises:
        FileNotFoundError: The file does not exist.
        DatasetLayoutError: The file holds no pose, or a line is not 12 finite numbers (names the file and line).
    """
    file, lines = _read_lines(path, "pose")
    poses = [_parse_3x4(line.split(), file, f"line {n}") for n, line in enumerate(lines, start=1) if line.strip()]
    if not poses:
        raise DatasetLayoutError(f"{str(file)!r} holds no pose; {EXPECTED_LAYOUT}")
    return np.stack(poses)


def read_json_pairs(file: Path) -> list[JsonPair]:
    """Entries of a standard json pair list (``pairs/<split>.json``).

    Args:
        file: A json list of objects with ``seq_id``, ``frame0``, ``frame1`` and ``transform`` (4x4, maps
            ``frame1``'s scan into ``frame0``'s scan, metres).

    Returns:
        ``(seq_id, frame0, frame1, transform)`` per entry, in file order; ``transform`` is ``(4, 4)`` float64.

    Raises:
        DatasetLayoutError: Not such a list, or an entry without a finite 4x4 transform (names the file and pair).
    """
    try:
        entries = json.loads(file.read_text())
        rows = [
            (int(e["seq_id"]), int(e["frame0"]), int(e["frame1"]), np.array(e["transform"], float)) for e in entries
        ]
    except (ValueError, KeyError, TypeError) as err:
        raise DatasetLayoutError(
            f"{str(file)!r} is not a pair list (a json list of objects with seq_id, frame0, frame1, transform): {err}"
        ) from err
    for seq_id, frame0, frame1, transform in rows:
        if transform.shape != (4, 4) or not np.all(np.isfinite(transform)):
            raise DatasetLayoutError(f"{str(file)!r}: pair {seq_id:02d}/{frame0}-{frame1} has no finite 4x4 transform")
    return rows


def as_4x4(matrix: np.ndarray, name: str) -> np.ndarray:
    """A ``(3, 4)`` or ``(4, 4)`` array as a ``(4, 4)`` float64 transform (last row ``0 0 0 1``).

    Raises:
        ShapeError: Neither ``(3, 4)`` nor ``(4, 4)`` (names ``name``).
        NonFiniteError: NaN or Inf values.
    """
    array = np.asarray(matrix, dtype=np.float64)
    if array.shape not in ((3, 4), (4, 4)):
        raise ShapeError(name, ("3 or 4", 4), array.shape)
    if not np.all(np.isfinite(array)):
        raise NonFiniteError(f"`{name}` has NaN or Inf values")
    out = np.eye(4)
    out[:3] = array[:3]
    return out


def relative_lidar_pose(pose_i: np.ndarray, pose_j: np.ndarray, tr: np.ndarray) -> np.ndarray:
    """Relative LiDAR pose ``T_j_i = inv(Tr) inv(P_j) P_i Tr``: maps points of scan ``i`` into scan ``j``'s frame.

    Args:
        pose_i: ``(4, 4)`` or ``(3, 4)`` camera-0 pose of frame ``i`` (camera -> world).
        pose_j: ``(4, 4)`` or ``(3, 4)`` camera-0 pose of frame ``j``.
        tr: ``(4, 4)`` or ``(3, 4)`` velodyne -> camera-0 calibration (:func:`read_calib_velo_to_cam`).

    Returns:
        ``(4, 4)`` float64 ``[R t; 0 1]`` with ``p_j = R p_i + t`` (metres).

    Raises:
        ShapeError: A matrix is neither ``(3, 4)`` nor ``(4, 4)``.
        NonFiniteError: A matrix holds NaN or Inf.
    """
    p_i, p_j, calib = as_4x4(pose_i, "pose_i"), as_4x4(pose_j, "pose_j"), as_4x4(tr, "tr")
    return np.linalg.inv(calib) @ np.linalg.inv(p_j) @ p_i @ calib
