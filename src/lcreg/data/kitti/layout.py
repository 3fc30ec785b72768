"""Folder layout of a KITTI odometry root: file paths, which scans exist, and the error text for missing files."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

__all__ = [
    "EXPECTED_LAYOUT",
    "calib_path",
    "describe_missing",
    "pairs_path",
    "pose_path",
    "raise_if_no_pair",
    "scan_frames",
    "scan_path",
]

EXPECTED_LAYOUT = (
    "expected the KITTI odometry layout: <root>/sequences/NN/velodyne/FFFFFF.bin (float32 x, y, z, reflectance), "
    "<root>/sequences/NN/calib.txt (line 'Tr: <12 values>'), <root>/poses/NN.txt (12 values per frame) and "
    "optionally <root>/pairs/{train,val,test}.json (entries seq_id, frame0, frame1, transform)"
)
"""The layout every missing-file or malformed-file message of :mod:`lcreg.data.kitti` ends with."""


def scan_path(root: str | Path, seq_id: int, frame: int) -> Path:
    """Path of a velodyne scan: ``<root>/sequences/<seq_id:02d>/velodyne/<frame:06d>.bin``."""
    return Path(root).expanduser() / "sequences" / f"{seq_id:02d}" / "velodyne" / f"{frame:06d}.bin"


def calib_path(root: Path, seq_id: int) -> Path:
    """``<root>/sequences/<seq_id:02d>/calib.txt``."""
    return root / "sequences" / f"{seq_id:02d}" / "calib.txt"


def pose_path(root: Path, seq_id: int) -> Path:
    """``<root>/poses/<seq_id:02d>.txt``."""
    return root / "poses" / f"{seq_id:02d}.txt"


def pairs_path(root: Path, split: str) -> Path:
    """``<root>/pairs/<split>.json`` (the optional FCGF/GeoTransformer pair list)."""
    return root / "pairs" / f"{split}.json"


def scan_frames(root: Path, seq_id: int) -> set[int] | None:
    """Frames with a scan file in ``sequences/NN/velodyne`` (``None`` when the folder is absent)."""
    folder = scan_path(root, seq_id, 0).parent
    if not folder.is_dir():
        return None
    return {int(p.stem) for p in folder.glob("*.bin") if p.stem.isdigit() and p.is_file()}


def describe_missing(root: Path, needed: dict[int, set[int]], found: dict[int, set[int] | None]) -> str:
    """Which sequences have no velodyne folder and which frames lack a scan (the first five per sequence).

    Args:
        root: KITTI odometry folder.
        needed: Frames the listed pairs use, per sequence.
        found: Frames with a scan file per sequence (:func:`scan_frames`; ``None``: no velodyne folder).

    Returns:
        One clause per incomplete sequence, joined by ``"; "`` (``"no sequence listed"`` when ``needed`` is empty).
    """
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


def raise_if_no_pair(
    pairs: Sequence[object],
    source: str,
    root: Path,
    needed: dict[int, set[int]],
    found: dict[int, set[int] | None],
) -> None:
    """Raise when ``pairs`` is empty: what was listed (``source``), what is missing, and the expected layout.

    Raises:
        FileNotFoundError: ``pairs`` is empty.
    """
    if not pairs:
        raise FileNotFoundError(
            f"no KITTI pair has both scans: {source}; {describe_missing(root, needed, found)}; {EXPECTED_LAYOUT}"
        )
