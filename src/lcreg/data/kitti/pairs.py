"""KITTI odometry registration pairs of a split, with their ground truth: :func:`kitti_pairs`.

Ground truth. Where ``pairs/<split>.json`` is used, its transforms are returned unchanged, so numbers stay
comparable with the published ones. Otherwise it is the pose-derived relative LiDAR pose
(:func:`~lcreg.data.kitti.io.relative_lidar_pose`), refined by ICP
(:func:`~lcreg.data.kitti.icp.refine_with_icp`, cached).

Known issue of the json transforms (measured on the real data here, pair ``00/11-0``): FCGF composed its ICP
correction on the wrong side (``M @ icp`` instead of ``icp @ M``, chrischoy/FCGF issue #65) and used one hard-coded
velodyne-to-camera calibration for every sequence. Re-running FCGF's procedure this way reproduces the json within
0.04 deg / 0.09 m, while the correctly composed ICP result (what :func:`~lcreg.data.kitti.icp.refine_with_icp`
returns) differs from the json by 0.03 deg / 0.25 m and fits the scans better (Open3D fitness at 0.2 m on 0.1 m
voxels: 0.386 vs 0.315). The raw pose transform differs from the json by 1.40 deg / 0.40 m on that pair.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from lcreg.checks import dataset_root
from lcreg.data.kitti.icp import check_icp_args, refine_pair
from lcreg.data.kitti.io import JsonPair, read_calib_velo_to_cam, read_json_pairs, read_poses, relative_lidar_pose
from lcreg.data.kitti.layout import (
    EXPECTED_LAYOUT,
    calib_path,
    pairs_path,
    pose_path,
    raise_if_no_pair,
    scan_frames,
    scan_path,
)
from lcreg.data.kitti.selection import (
    KITTI_SPLITS,
    STANDARD_MIN_DISTANCE,
    Selection,
    Split,
    all_pairs,
    count_all_pairs,
    sequence_pairs,
)
from lcreg.data.scenes import ScenePair

__all__ = ["kitti_pairs"]

Triple = tuple[int, int, int]
"""``(seq_id, frame0, frame1)``."""


def _check_args(split: str, selection: str, min_distance: float, max_frames_apart: int | None) -> None:
    if split not in KITTI_SPLITS:
        raise ValueError(f"`split` must be one of {sorted(KITTI_SPLITS)}, got {split!r}")
    if selection not in ("standard", "all"):
        raise ValueError(f"`selection` must be 'standard' or 'all', got {selection!r}")
    if not min_distance > 0:
        raise ValueError(f"`min_distance` must be > 0 (metres), got {min_distance}")
    if max_frames_apart is not None and max_frames_apart < 1:
        raise ValueError(f"`max_frames_apart` must be >= 1 or None, got {max_frames_apart}")


def _scene_pair(root: Path, seq_id: int, frame0: int, frame1: int, transform: np.ndarray) -> ScenePair:
    return ScenePair(
        path_src=scan_path(root, seq_id, frame1),
        path_ref=scan_path(root, seq_id, frame0),
        transform_ref_src=np.array(transform, dtype=np.float64),
        name=f"{seq_id:02d}/{frame0}-{frame1}",
    )


def _with_transform(pair: ScenePair, transform: np.ndarray) -> ScenePair:
    return ScenePair(pair.path_src, pair.path_ref, transform, pair.name, pair.overlap)


# ----------------------------------------------------------------------------------------------------- json lists


def _usable_json(
    json_file: Path, selection: Selection, min_distance: float, seqs: tuple[int, ...]
) -> list[JsonPair] | None:
    """Rows of ``seqs`` in the split's json list when it applies (standard selection, its 10 m, every sequence)."""
    rows = read_json_pairs(json_file) if selection == "standard" and json_file.is_file() else []
    if min_distance == STANDARD_MIN_DISTANCE and rows and set(seqs) <= {row[0] for row in rows}:
        return [row for row in rows if row[0] in seqs]
    return None


def _json_split_pairs(
    root: Path, json_file: Path, rows: list[JsonPair], seqs: tuple[int, ...], found: dict[int, set[int] | None]
) -> list[ScenePair]:
    """The json pairs (``rows``, of ``seqs``) whose two scans exist, with the json transforms."""
    needed: dict[int, set[int]] = {s: set() for s in seqs}
    for seq_id, frame0, frame1, _ in rows:
        needed[seq_id] |= {frame0, frame1}
    pairs = [_scene_pair(root, s, f0, f1, t) for s, f0, f1, t in rows if {f0, f1} <= (found[s] or set())]
    source = f"{str(json_file)!r} lists {len(rows)} pairs in sequences {list(seqs)}"
    raise_if_no_pair(pairs, source, root, needed, found)
    return pairs


# ----------------------------------------------------------------------------------------------------- poses


def _present_pairs(
    positions: np.ndarray,
    seq_id: int,
    frames: set[int],
    selection: Selection,
    min_distance: float,
    max_frames_apart: int | None,
) -> list[tuple[int, int]]:
    """``(frame0, frame1)`` pairs of one sequence whose two scans are in ``frames`` ("all": among those frames)."""
    if selection == "standard":
        chain = sequence_pairs(positions, seq_id, selection, min_distance, None)
        return [(a, b) for a, b in chain if a in frames and b in frames]
    present = np.array(sorted(f for f in frames if f < len(positions)), dtype=np.int64)
    if not present.size:
        return []
    return [
        (int(present[a]), int(present[b]))
        for a, b in all_pairs(positions[present], min_distance, None)
        if max_frames_apart is None or present[a] - present[b] <= max_frames_apart
    ]


def _pose_pairs(
    root: Path,
    found: dict[int, set[int] | None],
    selection: Selection,
    min_distance: float,
    max_frames_apart: int | None,
) -> tuple[list[Triple], dict[int, np.ndarray]]:
    """``(seq_id, frame0, frame1)`` pairs from the poses whose two scans exist, and the poses of their sequences."""
    kept: list[Triple] = []
    poses: dict[int, np.ndarray] = {}
    for seq_id, frames in found.items():
        pose_file = pose_path(root, seq_id)
        if not frames:
            continue
        if not pose_file.is_file():
            raise FileNotFoundError(
                f"sequence {seq_id:02d} has scans but no pose file {str(pose_file)!r}; {EXPECTED_LAYOUT}"
            )
        poses[seq_id] = read_poses(pose_file)
        pairs = _present_pairs(poses[seq_id][:, :3, 3], seq_id, frames, selection, min_distance, max_frames_apart)
        kept += [(seq_id, a, b) for a, b in pairs]
    return kept, poses


def _listed_pairs(
    root: Path, sequences: Sequence[int], selection: Selection, min_distance: float, max_frames_apart: int | None
) -> tuple[str, dict[int, set[int]]]:
    """For the error message: how many pairs the poses list, and the frames those pairs need per sequence."""
    listed = 0
    needed: dict[int, set[int]] = {}
    no_poses = []
    for seq_id in sequences:
        pose_file = pose_path(root, seq_id)
        if not pose_file.is_file():
            no_poses.append(seq_id)
            continue
        positions = read_poses(pose_file)[:, :3, 3]
        if selection == "all":
            listed += count_all_pairs(positions, min_distance, max_frames_apart)
            needed[seq_id] = set(range(len(positions)))
        else:
            chain = sequence_pairs(positions, seq_id, selection, min_distance, None)
            listed += len(chain)
            needed[seq_id] = {f for pair in chain for f in pair}
    missing = f" (no file {str(root / 'poses')!r}/NN.txt for sequences {no_poses})" if no_poses else ""
    return f"the poses list {listed} {selection!r} pairs in sequences {sorted(needed)}{missing}", needed


def _pose_split_pairs(
    root: Path,
    split: str,
    seqs: tuple[int, ...],
    found: dict[int, set[int] | None],
    selection: Selection,
    min_distance: float,
    max_frames_apart: int | None,
) -> list[ScenePair]:
    """Pairs built from the poses whose two scans exist, with the pose-derived (unrefined) ground truth."""
    kept, poses = _pose_pairs(root, found, selection, min_distance, max_frames_apart)
    if not kept:
        source, needed = _listed_pairs(root, seqs, selection, min_distance, max_frames_apart)
        raise_if_no_pair(kept, f"split {split!r}: {source}", root, needed, found)
    calibs = {s: read_calib_velo_to_cam(calib_path(root, s)) for s in {k[0] for k in kept}}
    return [
        _scene_pair(root, s, f0, f1, relative_lidar_pose(poses[s][f1], poses[s][f0], calibs[s])) for s, f0, f1 in kept
    ]


# ----------------------------------------------------------------------------------------------------- public


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
    FCGF chain is built from ``poses/NN.txt`` (:func:`~lcreg.data.kitti.selection.standard_chain_pairs`, minus
    :data:`~lcreg.data.kitti.selection.EXCLUDED_PAIRS`) with the pose-derived ground truth
    (:func:`~lcreg.data.kitti.io.relative_lidar_pose`, ``sequences/NN/calib.txt``), refined by ICP when ``refine``.
    ``"all"``: every pair of frames at least ``min_distance`` apart (:func:`~lcreg.data.kitti.selection.all_pairs`)
    among the frames with scans, ground truth from the poses, refined by ICP when ``refine``.

    Only pairs whose two scans exist are kept. ICP results are cached in memory by a bounded LRU cache (per scan
    files, initial transform and ICP parameters; :mod:`lcreg.data.kitti.icp`), so calling this again for the same
    pairs costs no ICP.

    Args:
        root: KITTI odometry folder (layout: :data:`~lcreg.data.kitti.layout.EXPECTED_LAYOUT`).
        split: ``"train"`` (sequences 0-5), ``"val"`` (6-7) or ``"test"`` (8-10).
        selection: ``"standard"`` or ``"all"``.
        min_distance: Metres between the two frames of a pair (standard: strictly more; all: at least).
        sequences: Sequences to use instead of the split's.
        refine: Refine pose-derived ground truth with :func:`~lcreg.data.kitti.icp.refine_with_icp`.
        max_frames_apart: ``"all"`` only: largest frame gap of a pair (``None``: no limit).
        voxel_size: ICP downsampling voxel (metres), see :func:`~lcreg.data.kitti.icp.refine_with_icp`.
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
    _check_args(split, selection, min_distance, max_frames_apart)
    check_icp_args(voxel_size, max_distance, max_iteration)
    base = dataset_root(root, "KITTI", EXPECTED_LAYOUT)
    seqs = tuple(KITTI_SPLITS[split] if sequences is None else (int(s) for s in sequences))
    found = {seq_id: scan_frames(base, seq_id) for seq_id in seqs}
    json_file = pairs_path(base, split)
    rows = _usable_json(json_file, selection, min_distance, seqs)
    if rows is not None:
        return _json_split_pairs(base, json_file, rows, seqs, found)
    pairs = _pose_split_pairs(base, split, seqs, found, selection, min_distance, max_frames_apart)
    if not refine:
        return pairs
    icp = functools.partial(refine_pair, voxel_size=voxel_size, max_distance=max_distance, max_iteration=max_iteration)
    return [_with_transform(p, icp(p.path_src, p.path_ref, p.transform_ref_src)) for p in pairs]
