"""Which KITTI frames are paired: the standard FCGF chain and the ``"all"`` selection, from frame positions.

* ``"standard"``: the FCGF chain (chrischoy/FCGF ``lib/data_loaders.py``, ``KITTINMPairDataset``, odometry branch;
  GeoTransformer uses the same lists): starting at frame 0, the pair is (the first frame more than 10 m away, minus
  one; the current frame), then the search continues after it (:func:`standard_chain_pairs`). Splits: sequences
  0-5 train, 6-7 val, 8-10 test; FCGF drops the pair ``(08, 58-15)``. Built from ``poses/NN.txt`` this reproduces
  the 1,358 / 180 / 555 pairs of the json lists exactly (checked on the real poses).
* ``"all"``: every pair of frames at least ``min_distance`` apart (:func:`all_pairs`), for denser sampling.

Pairs are ``(frame0, frame1)`` with ``frame0 > frame1``, as the json lists store them: the ground truth maps
``frame1``'s scan (source) into ``frame0``'s scan (reference).
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from lcreg.checks import NonFiniteError, ShapeError

__all__ = [
    "EXCLUDED_PAIRS",
    "KITTI_SPLITS",
    "STANDARD_MIN_DISTANCE",
    "Selection",
    "Split",
    "all_pairs",
    "count_all_pairs",
    "sequence_pairs",
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
        ``(frame0, frame1)`` pairs, ``frame0 > frame1``, in chain order.

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


def count_all_pairs(positions: np.ndarray, min_distance: float, max_frames_apart: int | None) -> int:
    """Number of pairs :func:`all_pairs` would list for ``(F, 3)`` positions (metres), without building them."""
    pos = _check_positions(positions, min_distance)
    return sum(len(_far_partners(pos, i, min_distance, max_frames_apart)) for i in range(len(pos)))


def sequence_pairs(
    positions: np.ndarray, seq_id: int, selection: Selection, min_distance: float, max_frames_apart: int | None
) -> list[tuple[int, int]]:
    """``(frame0, frame1)`` pairs of one sequence: the standard chain without :data:`EXCLUDED_PAIRS`, or all.

    Args:
        positions: ``(F, 3)`` frame positions in metres.
        seq_id: The sequence (for :data:`EXCLUDED_PAIRS`).
        selection: ``"standard"`` or ``"all"``.
        min_distance: Metres between the frames of a pair.
        max_frames_apart: ``"all"`` only: largest frame gap (``None``: no limit).
    """
    if selection == "all":
        return all_pairs(positions, min_distance, max_frames_apart)
    chain = standard_chain_pairs(positions, min_distance)
    return [(a, b) for a, b in chain if (seq_id, a, b) not in EXCLUDED_PAIRS]
