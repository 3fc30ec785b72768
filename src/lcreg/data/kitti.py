"""KITTI odometry registration pairs: calibration and pose files, the standard pair lists, ICP-refined ground truth.

Layout of ``root`` (the official KITTI odometry download, plus the standard pair lists)::

    root/
      sequences/NN/velodyne/FFFFFF.bin   LiDAR scans, float32 records (x, y, z, reflectance), metres
      sequences/NN/calib.txt             line ``Tr: <12 values>`` = velodyne -> camera 0, 3x4 row-major
      poses/NN.txt                       camera-0 poses in the world frame, one 3x4 row-major line per frame
      pairs/{train,val,test}.json        optional: the FCGF/GeoTransformer pair lists, entries with seq_id, frame0,
                                         frame1 and transform (4x4, maps frame1's scan into frame0's scan)

The relative LiDAR pose of frame ``i`` in frame ``j`` (maps points of scan ``i`` into scan ``j``) is
``T_j_i = inv(Tr) inv(P_j) P_i Tr`` (:func:`relative_lidar_pose`).

Pair selections (:func:`kitti_pairs`):

* ``"standard"``: the FCGF chain (chrischoy/FCGF ``lib/data_loaders.py``, ``KITTINMPairDataset``, odometry branch;
  GeoTransformer uses the same lists): starting at frame 0, the pair is (the first frame more than 10 m away, minus
  one; the current frame), then the search continues after it (:func:`standard_chain_pairs`). Splits: sequences
  0-5 train, 6-7 val, 8-10 test; FCGF drops the pair ``(08, 58-15)``. Built from ``poses/NN.txt`` this reproduces
  the 1,358 / 180 / 555 pairs of the json lists exactly (checked on the real poses).
* ``"all"``: every pair of frames at least ``min_distance`` apart (:func:`all_pairs`), for denser sampling.

Ground truth. The poses' relative transforms are approximate (KITTI's GPS/INS); the standard practice refines each
pair with point-to-point ICP (:func:`refine_with_icp`, FCGF's parameters: 0.2 m correspondence distance, 200
iterations, on voxel-downsampled scans). Where ``pairs/<split>.json`` is used, its transforms are returned
unchanged, so numbers stay comparable with the published ones.

Known issue of the json transforms (measured on the real data here, pair ``00/11-0``): FCGF composed its ICP
correction on the wrong side (``M @ icp`` instead of ``icp @ M``, chrischoy/FCGF issue #65) and used one hard-coded
velodyne-to-camera calibration for every sequence. Re-running FCGF's procedure this way reproduces the json within
0.04 deg / 0.09 m, while the correctly composed ICP result (what :func:`refine_with_icp` returns) differs from the
json by 0.03 deg / 0.25 m and fits the scans better (Open3D fitness at 0.2 m on 0.1 m voxels: 0.386 vs 0.315).
The raw pose transform differs from the json by 1.40 deg / 0.40 m on that pair.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Literal

import numpy as np

from lcreg.checks import DatasetLayoutError, NonFiniteError, ShapeError, TooFewPointsError
from lcreg.data.io import read_points, voxel_downsample
from lcreg.data.scenes import ScenePair, ScenePairDataModule
from lcreg.data.scenes import Split as SceneSplit

__all__ = [
    "EXCLUDED_PAIRS",
    "EXPECTED_LAYOUT",
    "KITTI_SPLITS",
    "KITTIOdometryDataModule",
    "all_pairs",
    "kitti_pairs",
    "read_calib_velo_to_cam",
    "read_poses",
    "refine_with_icp",
    "relative_lidar_pose",
    "scan_path",
    "standard_chain_pairs",
]

Split = Literal["train", "val", "test"]
Selection = Literal["standard", "all"]

KITTI_SPLITS: dict[str, tuple[int, ...]] = {"train": (0, 1, 2, 3, 4, 5), "val": (6, 7), "test": (8, 9, 10)}
"""Sequences of the standard FCGF/GeoTransformer splits."""

EXCLUDED_PAIRS: frozenset[tuple[int, int, int]] = frozenset({(8, 58, 15)})
"""``(seq_id, frame0, frame1)`` pairs FCGF removes from its chain (absent from the standard test json)."""

STANDARD_MIN_DISTANCE = 10.0
"""Distance (metres) the standard json lists were built with."""

EXPECTED_LAYOUT = (
    "expected the KITTI odometry layout: <root>/sequences/NN/velodyne/FFFFFF.bin (float32 x, y, z, reflectance), "
    "<root>/sequences/NN/calib.txt (line 'Tr: <12 values>'), <root>/poses/NN.txt (12 values per frame) and "
    "optionally <root>/pairs/{train,val,test}.json (entries seq_id, frame0, frame1, transform)"
)

_ICP_CACHE: dict[tuple[Any, ...], np.ndarray] = {}
"""Refined transforms keyed by scan files (path, size, mtime), initial transform and ICP parameters."""


# ----------------------------------------------------------------------------------------------------- files


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


def scan_path(root: str | Path, seq_id: int, frame: int) -> Path:
    """Path of a velodyne scan: ``<root>/sequences/<seq_id:02d>/velodyne/<frame:06d>.bin``."""
    return Path(root).expanduser() / "sequences" / f"{seq_id:02d}" / "velodyne" / f"{frame:06d}.bin"


# ----------------------------------------------------------------------------------------------------- geometry


def _as_4x4(matrix: np.ndarray, name: str) -> np.ndarray:
    """A ``(3, 4)`` or ``(4, 4)`` array as a ``(4, 4)`` float64 transform."""
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
    p_i, p_j, calib = _as_4x4(pose_i, "pose_i"), _as_4x4(pose_j, "pose_j"), _as_4x4(tr, "tr")
    return np.linalg.inv(calib) @ np.linalg.inv(p_j) @ p_i @ calib


def _check_positions(positions: np.ndarray, min_distance: float) -> np.ndarray:
    """Validate ``(F, 3)`` positions and a positive distance; return the positions as float64."""
    array = np.asarray(positions, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] != 3:
        raise ShapeError("positions", ("F", 3), array.shape)
    if not np.all(np.isfinite(array)):
        raise NonFiniteError("`positions` has NaN or Inf values")
    if not min_distance > 0:
        raise ValueError(f"`min_distance` must be > 0 (metres), got {min_distance}")
    return array


def standard_chain_pairs(
    positions: np.ndarray, min_distance: float = 10.0, max_frames_ahead: int = 100
) -> list[tuple[int, int]]:
    """The FCGF chain of KITTI pairs (the standard train/val/test lists).

    From the current frame ``c`` (starting at 0), find the first frame ``k`` among the next ``max_frames_ahead``
    frames (``c .. c + max_frames_ahead - 1``) more than ``min_distance`` away from ``c``; the pair is
    ``(k - 1, c)`` and the search continues at ``k``. When no frame of the window is far enough, the search moves
    on to ``c + 1``. (FCGF would emit a self-pair ``(c, c)`` if ``k = c + 1``, i.e. consecutive frames more than
    ``min_distance`` apart; here the pair becomes ``(c + 1, c)``.)

    Args:
        positions: ``(F, 3)`` frame positions in metres (FCGF uses the camera-0 positions ``P_f[:3, 3]``).
        min_distance: Strict lower bound (metres) on the distance at frame ``k``.
        max_frames_ahead: Length of the search window (FCGF: 100).

    Returns:
        ``(frame0, frame1)`` pairs, ``frame0 > frame1``, in chain order, as the json lists store them: the
        ground truth maps ``frame1``'s scan (source) into ``frame0``'s scan (reference).

    Raises:
        ShapeError: ``positions`` is not ``(F, 3)``.
        NonFiniteError: ``positions`` holds NaN or Inf.
        ValueError: ``min_distance <= 0`` or ``max_frames_ahead < 2``.
    """
    pos = _check_positions(positions, min_distance)
    if max_frames_ahead < 2:
        raise ValueError(f"`max_frames_ahead` must be >= 2, got {max_frames_ahead}")
    pairs: list[tuple[int, int]] = []
    current = 0
    while current < len(pos):
        window = pos[current : current + max_frames_ahead]
        far = np.flatnonzero(np.linalg.norm(window - pos[current], axis=1) > min_distance)
        if far.size == 0:
            current += 1
            continue
        partner = current + max(int(far[0]) - 1, 1)
        pairs.append((partner, current))
        current = partner + 1
    return pairs


def _far_partners(pos: np.ndarray, i: int, min_distance: float, max_frames_apart: int | None) -> np.ndarray:
    """Frames ``j > i`` (within ``max_frames_apart``) at least ``min_distance`` from frame ``i``."""
    stop = len(pos) if max_frames_apart is None else min(len(pos), i + max_frames_apart + 1)
    distances = np.linalg.norm(pos[i + 1 : stop] - pos[i], axis=1)
    return np.flatnonzero(distances >= min_distance) + i + 1


def all_pairs(
    positions: np.ndarray, min_distance: float = 10.0, max_frames_apart: int | None = None
) -> list[tuple[int, int]]:
    """Every pair of frames at least ``min_distance`` apart.

    Args:
        positions: ``(F, 3)`` frame positions in metres.
        min_distance: Inclusive lower bound (metres) on the distance between the two frames.
        max_frames_apart: When given, keep only pairs with ``frame0 - frame1 <= max_frames_apart`` (a full
            sequence without this bound gives millions of pairs).

    Returns:
        ``(frame0, frame1)`` pairs with ``frame0 > frame1`` (same convention as :func:`standard_chain_pairs`),
        sorted by ``frame1`` then ``frame0``.

    Raises:
        ShapeError: ``positions`` is not ``(F, 3)``.
        NonFiniteError: ``positions`` holds NaN or Inf.
        ValueError: ``min_distance <= 0`` or ``max_frames_apart < 1``.
    """
    pos = _check_positions(positions, min_distance)
    if max_frames_apart is not None and max_frames_apart < 1:
        raise ValueError(f"`max_frames_apart` must be >= 1 or None, got {max_frames_apart}")
    pairs: list[tuple[int, int]] = []
    for i in range(len(pos)):
        pairs.extend((int(j), i) for j in _far_partners(pos, i, min_distance, max_frames_apart))
    return pairs


def _count_all_pairs(positions: np.ndarray, min_distance: float, max_frames_apart: int | None) -> int:
    """Number of pairs :func:`all_pairs` would list, without building them."""
    return sum(len(_far_partners(positions, i, min_distance, max_frames_apart)) for i in range(len(positions)))


# ----------------------------------------------------------------------------------------------------- ICP


def _check_cloud(points: np.ndarray, name: str) -> np.ndarray:
    """Validate an ``(N, 3)`` cloud; return it as float64."""
    array = np.asarray(points, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] != 3:
        raise ShapeError(name, ("N", 3), array.shape)
    if len(array) == 0:
        raise TooFewPointsError(f"`{name}` is empty")
    if not np.all(np.isfinite(array)):
        raise NonFiniteError(f"`{name}` has NaN or Inf values")
    return array


def _icp(src: np.ndarray, ref: np.ndarray, init: np.ndarray, max_distance: float, max_iteration: int) -> np.ndarray:
    """Point-to-point ICP of prepared float64 clouds; raises when no point lies within ``max_distance``."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    result = reg.registration_icp(
        o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src)),
        o3d.geometry.PointCloud(o3d.utility.Vector3dVector(ref)),
        max_distance,
        init,
        reg.TransformationEstimationPointToPoint(with_scaling=False),
        reg.ICPConvergenceCriteria(relative_fitness=1e-6, relative_rmse=1e-6, max_iteration=max_iteration),
    )
    if result.fitness == 0.0:
        raise ValueError(
            f"ICP found no source point within `max_distance`={max_distance} m of the reference after `init`: "
            "the initial transform is too far off (or the clouds do not overlap)"
        )
    return np.array(result.transformation, dtype=np.float64)


def _check_icp_args(voxel_size: float | None, max_distance: float, max_iteration: int) -> None:
    if voxel_size is not None and not voxel_size > 0:
        raise ValueError(f"`voxel_size` must be > 0 (metres) or None, got {voxel_size}")
    if not max_distance > 0:
        raise ValueError(f"`max_distance` must be > 0 (metres), got {max_distance}")
    if max_iteration < 1:
        raise ValueError(f"`max_iteration` must be >= 1, got {max_iteration}")


def refine_with_icp(
    points_src: np.ndarray,
    points_ref: np.ndarray,
    init: np.ndarray,
    voxel_size: float | None = 0.1,
    max_distance: float = 0.2,
    max_iteration: int = 200,
) -> np.ndarray:
    """Refine a ground-truth transform with Open3D point-to-point ICP (the FCGF/GeoTransformer KITTI refinement).

    FCGF (``KITTIPairDataset``) runs ``registration_icp`` point-to-point, ``max_correspondence_distance=0.2`` m,
    ``ICPConvergenceCriteria(max_iteration=200)`` (Open3D's relative fitness/RMSE of 1e-6), from the pose-derived
    transform, on scans quantised at 5 cm. Here the scans are averaged on ``voxel_size`` voxels first (default
    10 cm: about 60k of 120k points remain, 6-9 s a pair on 2 CPU cores, vs ~22 s at 5 cm). Point-to-point ICP on
    these scans is weakly constrained along the driving direction: on pair ``00/11-0`` the results at 5 and 10 cm
    differ by 0.05 deg / 0.13 m, and ICP run to full convergence (or point-to-plane / generalized ICP) slides a
    further ~0.9 m along the road, so keep FCGF's iteration cap. The result is the full transform (``init``
    included, composed as ``icp @ init``, not FCGF's ``init @ icp``).

    Args:
        points_src: ``(N, 3)`` source points (metres).
        points_ref: ``(M, 3)`` reference points (metres).
        init: ``(4, 4)`` or ``(3, 4)`` initial transform mapping source into reference (e.g. the pose-derived one).
        voxel_size: Downsampling voxel (metres) applied to both clouds; ``None`` uses every point.
        max_distance: Correspondence distance gate (metres).
        max_iteration: Maximum ICP iterations.

    Returns:
        ``(4, 4)`` float64 ``[R t; 0 1]`` mapping source points into the reference frame.

    Raises:
        ShapeError: A cloud is not ``(N, 3)`` or ``init`` not ``(4, 4)``/``(3, 4)``.
        TooFewPointsError: A cloud is empty.
        NonFiniteError: NaN or Inf in a cloud or in ``init``.
        ValueError: Non-positive ``voxel_size``/``max_distance``/``max_iteration``, or ICP found no correspondence.
    """
    src, ref = _check_cloud(points_src, "points_src"), _check_cloud(points_ref, "points_ref")
    start = _as_4x4(init, "init")
    _check_icp_args(voxel_size, max_distance, max_iteration)
    if voxel_size is not None:
        src, ref = voxel_downsample(src, voxel_size), voxel_downsample(ref, voxel_size)
    return _icp(src, ref, start, max_distance, max_iteration)


class _ScanCache:
    """Downsampled scans of one :func:`kitti_pairs` call (a frame is often in several pairs)."""

    def __init__(self, voxel_size: float | None) -> None:
        self.voxel_size = voxel_size
        self.clouds: dict[Path, np.ndarray] = {}

    def get(self, path: Path) -> np.ndarray:
        if path not in self.clouds:
            points = read_points(path).astype(np.float64)
            self.clouds[path] = points if self.voxel_size is None else voxel_downsample(points, self.voxel_size)
        return self.clouds[path]


def _file_key(path: Path) -> tuple[str, int, int]:
    stat = path.stat()
    return str(path.resolve()), stat.st_size, stat.st_mtime_ns


def _refine_pair(pair: ScenePair, scans: _ScanCache, max_distance: float, max_iteration: int) -> np.ndarray:
    """Refined transform of one pair (from the module cache when already computed)."""
    key = (
        _file_key(pair.path_src),
        _file_key(pair.path_ref),
        pair.transform_ref_src.tobytes(),
        scans.voxel_size,
        max_distance,
        max_iteration,
    )
    if key not in _ICP_CACHE:
        src, ref = scans.get(pair.path_src), scans.get(pair.path_ref)
        _ICP_CACHE[key] = _icp(src, ref, pair.transform_ref_src, max_distance, max_iteration)
    return _ICP_CACHE[key].copy()


# ----------------------------------------------------------------------------------------------------- pair lists


def _scan_frames(root: Path, seq_id: int) -> set[int] | None:
    """Frames with a scan file in ``sequences/NN/velodyne`` (``None`` when the folder is absent)."""
    folder = scan_path(root, seq_id, 0).parent
    if not folder.is_dir():
        return None
    return {int(p.stem) for p in folder.glob("*.bin") if p.stem.isdigit() and p.is_file()}


def _read_json_pairs(file: Path) -> list[tuple[int, int, int, np.ndarray]]:
    """Entries ``(seq_id, frame0, frame1, transform)`` of a standard json list."""
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


def _describe_missing(root: Path, needed: dict[int, set[int]], found: dict[int, set[int] | None]) -> str:
    """Which sequences have no velodyne folder and which frames lack a scan (a few per sequence)."""
    parts = []
    for seq_id in sorted(needed):
        frames = found[seq_id]
        if frames is None:
            parts.append(f"sequence {seq_id:02d}: no folder {str(scan_path(root, seq_id, 0).parent)!r}")
            continue
        missing = sorted(needed[seq_id] - frames)
        if missing:
            shown = ", ".join(f"{f:06d}.bin" for f in missing[:5]) + (", ..." if len(missing) > 5 else "")
            parts.append(f"sequence {seq_id:02d}: {len(missing)} of {len(needed[seq_id])} scans missing ({shown})")
    return "; ".join(parts) if parts else "no sequence listed"


def _sequence_pairs(
    positions: np.ndarray, seq_id: int, selection: Selection, min_distance: float, max_frames_apart: int | None
) -> list[tuple[int, int]]:
    """``(frame0, frame1)`` pairs one sequence lists (the standard chain without :data:`EXCLUDED_PAIRS`, or all)."""
    if selection == "all":
        return all_pairs(positions, min_distance, max_frames_apart)
    chain = standard_chain_pairs(positions, min_distance)
    return [(a, b) for a, b in chain if (seq_id, a, b) not in EXCLUDED_PAIRS]


def _pose_pairs(
    root: Path,
    found: dict[int, set[int] | None],
    selection: Selection,
    min_distance: float,
    max_frames_apart: int | None,
) -> tuple[list[tuple[int, int, int]], dict[int, np.ndarray]]:
    """``(seq_id, frame0, frame1)`` pairs from the poses whose two scans exist, and the poses of their sequences."""
    kept: list[tuple[int, int, int]] = []
    poses: dict[int, np.ndarray] = {}
    for seq_id, frames in found.items():
        pose_file = root / "poses" / f"{seq_id:02d}.txt"
        if not frames:
            continue
        if not pose_file.is_file():
            raise FileNotFoundError(
                f"sequence {seq_id:02d} has scans but no pose file {str(pose_file)!r}; {EXPECTED_LAYOUT}"
            )
        poses[seq_id] = read_poses(pose_file)
        positions = poses[seq_id][:, :3, 3]
        if selection == "standard":
            chain = _sequence_pairs(positions, seq_id, selection, min_distance, None)
            kept += [(seq_id, a, b) for a, b in chain if a in frames and b in frames]
            continue
        present = np.array(sorted(f for f in frames if f < len(positions)), dtype=np.int64)
        for a, b in all_pairs(positions[present], min_distance, None) if present.size else []:
            if max_frames_apart is None or present[a] - present[b] <= max_frames_apart:
                kept.append((seq_id, int(present[a]), int(present[b])))
    return kept, poses


def _listed_pairs(
    root: Path, sequences: Sequence[int], selection: Selection, min_distance: float, max_frames_apart: int | None
) -> tuple[str, dict[int, set[int]]]:
    """For the error message: how many pairs the poses list, and the frames those pairs need per sequence."""
    listed = 0
    needed: dict[int, set[int]] = {}
    no_poses = []
    for seq_id in sequences:
        pose_file = root / "poses" / f"{seq_id:02d}.txt"
        if not pose_file.is_file():
            no_poses.append(seq_id)
            continue
        positions = read_poses(pose_file)[:, :3, 3]
        if selection == "all":
            listed += _count_all_pairs(positions, min_distance, max_frames_apart)
            needed[seq_id] = set(range(len(positions)))
        else:
            chain = _sequence_pairs(positions, seq_id, selection, min_distance, None)
            listed += len(chain)
            needed[seq_id] = {f for pair in chain for f in pair}
    missing = f" (no file {str(root / 'poses')!r}/NN.txt for sequences {no_poses})" if no_poses else ""
    return f"the poses list {listed} {selection!r} pairs in sequences {sorted(needed)}{missing}", needed


def kitti_pairs(
    root: str | Path,
    split: Split,
    selection: Selection = "standard",
    min_distance: float = 10.0,
    sequences: Sequence[int] | None = None,
    refine: bool = True,
    *,
    max_frames_apart: int | None = None,
    voxel_size: float | None = 0.1,
    max_distance: float = 0.2,
    max_iteration: int = 200,
) -> list[ScenePair]:
    """KITTI odometry registration pairs of one split, with their ground truth.

    ``"standard"``: when ``<root>/pairs/<split>.json`` exists, lists every requested sequence and ``min_distance``
    is the json's 10 m, its pairs and transforms are used as they are (``refine`` does not apply). Otherwise the
    FCGF chain is built from ``poses/NN.txt`` (:func:`standard_chain_pairs`, minus :data:`EXCLUDED_PAIRS`) with the
    pose-derived ground truth (:func:`relative_lidar_pose`, ``sequences/NN/calib.txt``), refined by ICP when
    ``refine``. ``"all"``: every pair of frames at least ``min_distance`` apart (:func:`all_pairs`) among the frames
    with scans, ground truth from the poses, refined by ICP when ``refine``.

    Only pairs whose two scans exist are kept. ICP results are cached in memory (per scan files, initial transform
    and ICP parameters), so calling this again for the same pairs costs no ICP.

    Args:
        root: KITTI odometry folder (see the module docstring).
        split: ``"train"`` (sequences 0-5), ``"val"`` (6-7) or ``"test"`` (8-10).
        selection: ``"standard"`` or ``"all"``.
        min_distance: Metres between the two frames of a pair (standard: strictly more; all: at least).
        sequences: Sequences to use instead of the split's.
        refine: Refine pose-derived ground truth with :func:`refine_with_icp`.
        max_frames_apart: ``"all"`` only: largest frame gap of a pair (``None``: no limit).
        voxel_size: ICP downsampling voxel (metres), see :func:`refine_with_icp`.
        max_distance: ICP correspondence distance (metres).
        max_iteration: ICP iterations.

    Returns:
        :class:`~lcreg.data.scenes.ScenePair` list, one per pair ``(frame0, frame1)``: ``path_src`` = scan of
        ``frame1``, ``path_ref`` = scan of ``frame0``, ``transform_ref_src`` maps ``frame1``'s points into
        ``frame0``'s frame, ``name`` = ``"NN/frame0-frame1"`` (e.g. ``"00/11-0"``).

    Raises:
        ValueError: Unknown ``split``/``selection`` or a bad numeric argument.
        FileNotFoundError: ``root`` is not a directory, a needed pose/calibration file is missing, or no listed
            pair has both scans (the message gives how many pairs the split lists, what is missing and the layout).
        DatasetLayoutError: A malformed json, pose or calibration file (names the file).
    """
    if split not in KITTI_SPLITS:
        raise ValueError(f"`split` must be one of {sorted(KITTI_SPLITS)}, got {split!r}")
    if selection not in ("standard", "all"):
        raise ValueError(f"`selection` must be 'standard' or 'all', got {selection!r}")
    if not min_distance > 0:
        raise ValueError(f"`min_distance` must be > 0 (metres), got {min_distance}")
    if max_frames_apart is not None and max_frames_apart < 1:
        raise ValueError(f"`max_frames_apart` must be >= 1 or None, got {max_frames_apart}")
    _check_icp_args(voxel_size, max_distance, max_iteration)
    base = Path(root).expanduser()
    if not base.is_dir():
        raise FileNotFoundError(f"KITTI root {str(base)!r} is not a directory; {EXPECTED_LAYOUT}")
    seqs = tuple(KITTI_SPLITS[split] if sequences is None else (int(s) for s in sequences))
    found = {seq_id: _scan_frames(base, seq_id) for seq_id in seqs}
    json_file = base / "pairs" / f"{split}.json"
    rows = _read_json_pairs(json_file) if selection == "standard" and json_file.is_file() else []
    if min_distance == STANDARD_MIN_DISTANCE and rows and set(seqs) <= {row[0] for row in rows}:
        rows = [row for row in rows if row[0] in seqs]
        source = f"{str(json_file)!r} lists {len(rows)} pairs in sequences {list(seqs)}"
        needed: dict[int, set[int]] = {s: set() for s in seqs}
        for seq_id, frame0, frame1, _ in rows:
            needed[seq_id] |= {frame0, frame1}
        pairs = [_scene_pair(base, s, f0, f1, t) for s, f0, f1, t in rows if {f0, f1} <= (found[s] or set())]
        _raise_if_empty(pairs, source, base, needed, found)
        return pairs
    kept, poses = _pose_pairs(base, found, selection, min_distance, max_frames_apart)
    if not kept:
        source, needed = _listed_pairs(base, seqs, selection, min_distance, max_frames_apart)
        _raise_if_empty(kept, f"split {split!r}: {source}", base, needed, found)
    calibs = {s: read_calib_velo_to_cam(base / "sequences" / f"{s:02d}" / "calib.txt") for s in {k[0] for k in kept}}
    pairs = [
        _scene_pair(base, s, f0, f1, relative_lidar_pose(poses[s][f1], poses[s][f0], calibs[s])) for s, f0, f1 in kept
    ]
    if refine:
        scans = _ScanCache(voxel_size)
        pairs = [_with_transform(p, _refine_pair(p, scans, max_distance, max_iteration)) for p in pairs]
    return pairs


def _scene_pair(root: Path, seq_id: int, frame0: int, frame1: int, transform: np.ndarray) -> ScenePair:
    return ScenePair(
        path_src=scan_path(root, seq_id, frame1),
        path_ref=scan_path(root, seq_id, frame0),
        transform_ref_src=np.array(transform, dtype=np.float64),
        name=f"{seq_id:02d}/{frame0}-{frame1}",
    )


def _with_transform(pair: ScenePair, transform: np.ndarray) -> ScenePair:
    return ScenePair(pair.path_src, pair.path_ref, transform, pair.name, pair.overlap)


def _raise_if_empty(
    pairs: Sequence[object],
    source: str,
    root: Path,
    needed: dict[int, set[int]],
    found: dict[int, set[int] | None],
) -> None:
    if not pairs:
        raise FileNotFoundError(
            f"no KITTI pair has both scans: {source}; {_describe_missing(root, needed, found)}; {EXPECTED_LAYOUT}"
        )


class KITTIOdometryDataModule(ScenePairDataModule):
    """KITTI odometry LiDAR pairs (pairs at least 10 m apart, ICP-refined ground truth), for evaluation.

    Defaults follow the FCGF/GeoTransformer protocol that the DVDs paper uses: the standard test split (sequences
    8-10), the real relative pose as the only displacement (no extra random transform, no alignment, original LiDAR
    frames), and 0.3 m voxel downsampling with every remaining point kept (so batches hold one pair). Where scans
    of the split are missing the pairs are dropped; with none left, :func:`kitti_pairs` says which files it needs.

    Args:
        root: KITTI odometry folder (checked in :meth:`setup`).
        test_split: Standard split used as the test set (``"test"``: sequences 8-10).
        val_split: Split used for validation (``None``: none).
        train_split: Split used for training (``None``: none; models here train on objects).
        selection: ``"standard"`` (the FCGF chain / json lists) or ``"all"`` (every pair ``min_distance`` apart).
        min_distance: Metres between the frames of a pair.
        test_sequences: Sequences to use instead of the test split's.
        refine: Refine pose-derived ground truth with ICP (json transforms are used as they are).
        max_frames_apart: ``"all"`` only: largest frame gap of a pair.
        num_points: Points per scan (``None``: every point after downsampling).
        voxel_size: Voxel downsampling edge in metres (``None``: full scans).
        align: Map the source into the reference frame with the ground truth first (off: real displacement).
        center: Put the reference centroid at the origin (off: original LiDAR frames).
        max_angle_deg: Extra random rotation bound (0: none).
        max_translation: Extra random translation bound in metres (0: none).
        batch_size: Pairs per batch (1 when every point is kept).
        num_workers: DataLoader workers.
        seed: Base seed of the deterministic pairs.
    """

    def __init__(
        self,
        root: str,
        test_split: Split = "test",
        val_split: Split | None = None,
        train_split: Split | None = None,
        selection: Selection = "standard",
        min_distance: float = 10.0,
        test_sequences: list[int] | None = None,
        refine: bool = True,
        max_frames_apart: int | None = None,
        num_points: int | None = None,
        voxel_size: float | None = 0.3,
        align: bool = False,
        center: bool = False,
        max_angle_deg: float = 0.0,
        max_translation: float = 0.0,
        batch_size: int = 1,
        num_workers: int = 0,
        seed: int = 1234,
    ) -> None:
        super().__init__(
            num_points, voxel_size, align, center, max_angle_deg, max_translation, batch_size, num_workers, seed
        )
        if selection not in ("standard", "all"):
            raise ValueError(f"`selection` must be 'standard' or 'all', got {selection!r}")
        if not min_distance > 0:
            raise ValueError(f"`min_distance` must be > 0, got {min_distance}")
        self.root = root
        self.splits: dict[str, Split | None] = {"train": train_split, "val": val_split, "test": test_split}
        self.selection: Selection = selection
        self.min_distance = min_distance
        self.test_sequences = test_sequences
        self.refine = refine
        self.max_frames_apart = max_frames_apart

    def pairs(self, split: SceneSplit) -> list[ScenePair]:
        """The pairs of the standard split configured for ``split`` (none when it is not configured)."""
        source = self.splits[split]
        if source is None:
            return []
        sequences = self.test_sequences if split == "test" else None
        return kitti_pairs(
            self.root,
            source,
            self.selection,
            self.min_distance,
            sequences,
            self.refine,
            max_frames_apart=self.max_frames_apart,
        )
