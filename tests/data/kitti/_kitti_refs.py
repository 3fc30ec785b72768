"""Helpers of the KITTI tests: random rigid transforms, pose errors, pose-file lines and symlinked layouts."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from lcreg.data.kitti import scan_path


def rigid(rng: np.random.Generator, scale: float = 5.0) -> np.ndarray:
    """A random ``(4, 4)`` rigid transform, translation components in ``[-scale, scale]``."""
    matrix = np.eye(4)
    matrix[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    matrix[:3, 3] = rng.uniform(-scale, scale, 3)
    return matrix


def pose_errors(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """Rotation angle (degrees) of ``inv(a) b`` and translation distance (metres)."""
    delta = np.linalg.inv(a) @ b
    cos = np.clip((np.trace(delta[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.degrees(np.arccos(cos))), float(np.linalg.norm(a[:3, 3] - b[:3, 3]))


def pose_line(matrix: np.ndarray) -> str:
    """The 3x4 row-major line of a KITTI pose or calibration file."""
    return " ".join(f"{v:.12e}" for v in matrix[:3].reshape(-1))


def json_rows(root: Path, split: str) -> list[dict]:
    return json.loads((root / "pairs" / f"{split}.json").read_text())


def link_layout(tmp_path: Path, kitti: Path, frames: list[int] | None, pairs: bool = True) -> Path:
    """A KITTI root of symlinks to the real files: poses, optionally pairs, and the scans of ``frames`` of seq 00."""
    root = tmp_path / "kitti"
    root.mkdir()
    (root / "poses").symlink_to(kitti / "poses")
    if pairs:
        (root / "pairs").symlink_to(kitti / "pairs")
    if frames is not None:
        velodyne = root / "sequences" / "00" / "velodyne"
        velodyne.mkdir(parents=True)
        (root / "sequences" / "00" / "calib.txt").symlink_to(kitti / "sequences" / "00" / "calib.txt")
        for frame in frames:
            (velodyne / f"{frame:06d}.bin").symlink_to(scan_path(kitti, 0, frame))
    return root
