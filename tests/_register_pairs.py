"""Synthetic pairs with a known motion for the register tests (two samplings of one procedural shape)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from lcreg.data.synthetic import synthetic_shapes


def motion(seed: int, angle_deg: float = 60.0, shift: float = 0.4) -> np.ndarray:
    """A ``(4, 4)`` rigid motion: rotation of ``angle_deg`` about a random axis, translation of norm ``shift``."""
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    transform = np.eye(4)
    transform[:3, :3] = Rotation.from_rotvec(np.radians(angle_deg) * axis / np.linalg.norm(axis)).as_matrix()
    direction = rng.normal(size=3)
    transform[:3, 3] = shift * direction / np.linalg.norm(direction)
    return transform


def make_pair() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(source (3000, 3), reference (3000, 3), ground truth (4, 4))`` float64: the reference = the moved source."""
    points = synthetic_shapes(1, 6000, seed=3)[0][0].astype(np.float64)
    gt = motion(0)
    src, ref = points[:3000], points[3000:]
    return src, ref @ gt[:3, :3].T + gt[:3, 3], gt


def errors(estimate: np.ndarray, gt: np.ndarray) -> tuple[float, float]:
    """``(rotation error degrees, translation error)``."""
    delta = np.linalg.inv(gt) @ estimate
    cos = np.clip((np.trace(delta[:3, :3]) - 1) / 2, -1.0, 1.0)
    return float(np.degrees(np.arccos(cos))), float(np.linalg.norm(estimate[:3, 3] - gt[:3, 3]))
