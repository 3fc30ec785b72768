"""Small task heads."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from lcreg.nn.mlp import ConditionedPointMLP

__all__ = ["NormalHead"]


class NormalHead(nn.Module):
    """DVDs normal estimator ``l([p_i, psi(P)])``: per-point unit normals from coordinates and the descriptor.

    Args:
        feature_dim: Descriptor size ``K``.
        hidden: Hidden widths ("a lightweight MLP").
    """

    def __init__(self, feature_dim: int = 1024, hidden: Sequence[int] = (128, 64)) -> None:
        super().__init__()
        self.mlp = ConditionedPointMLP(3, feature_dim, hidden, 3)

    def forward(self, points: torch.Tensor, code: torch.Tensor) -> torch.Tensor:
        """Unit normals ``(B, N, 3)`` for ``points (B, N, 3)`` and descriptors ``(B, K)``."""
        return nn.functional.normalize(self.mlp(points, code), dim=-1, eps=1e-8)
