"""NumPy reference implementations that several test files compare lcreg against."""

from __future__ import annotations

import numpy as np


def kabsch(src: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Least-squares rigid transform ``(4, 4)`` mapping ``src (N, 3)`` onto ``ref (N, 3)`` (SVD, uniform weights)."""
    mu_s, mu_r = src.mean(0), ref.mean(0)
    u, _, vt = np.linalg.svd((src - mu_s).T @ (ref - mu_r))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    rot = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = rot, mu_r - rot @ mu_s
    return out
