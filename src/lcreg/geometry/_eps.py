"""Per-dtype thresholds for the Lie-group maps' Taylor branches, and the keeper of non-finite items.

One table of thresholds, used everywhere, and :func:`nan_where_non_finite`, which keeps a non-finite input item
non-finite through branches that would clamp it away.
"""

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


def nan_where_non_finite(out: torch.Tensor, source: torch.Tensor, dims: int) -> torch.Tensor:
    """``out`` with NaN in every item whose ``source`` item holds NaN/Inf (no host sync, other items untouched).

    Clamps and branch selections (``atan2`` of an infinite trace, a small-angle branch) can turn a non-finite input
    into a finite, wrong output; the element-wise maps propagate NaN/Inf instead (the :mod:`lcreg.geometry` policy).

    Args:
        out: Result ``(..., K)``.
        source: Input ``(..., *item)`` with ``dims`` trailing item dimensions.
        dims: Number of trailing dimensions of one ``source`` item (2 for matrices).
    """
    finite = torch.isfinite(source).flatten(-dims).all(-1)
    return torch.where(finite[..., None], out, torch.full_like(out, float("nan")))
