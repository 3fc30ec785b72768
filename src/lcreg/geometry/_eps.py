"""Per-dtype thresholds for the Taylor branches of the Lie-group maps (one table, used everywhere)."""

from __future__ import annotations

import torch

# Below these angles (rad) exp/log switch to series expansions; truncation error is far below the dtype eps.
SMALL_ANGLE = {torch.float32: 1e-2, torch.float64: 1e-4}
# Above pi - NEAR_PI the log map reads the axis from the symmetric part of R instead of its skew part.
NEAR_PI = {torch.float32: 1e-2, torch.float64: 1e-5}


def small_angle(dtype: torch.dtype) -> float:
    """Threshold of the small-angle branch for ``dtype`` (float32/float64)."""
    return SMALL_ANGLE.get(dtype, 1e-2)


def near_pi(dtype: torch.dtype) -> float:
    """Distance to pi under which the log map uses its near-pi branch."""
    return NEAR_PI.get(dtype, 1e-2)
