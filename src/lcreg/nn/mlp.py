"""Shared per-point MLP building blocks (used by the decoder and the normal head; never copied per model)."""

from __future__ import annotations

from collections.abc import Sequence
from itertools import pairwise

import torch
from torch import nn

__all__ = ["ConditionedPointMLP"]


class ConditionedPointMLP(nn.Module):
    """Per-point MLP on ``[p_i, code]``: ``(B, N, D_p)`` points conditioned on a ``(B, D_c)`` code.

    The first layer is split into a point part and a code part, so the code term is computed once per cloud
    instead of once per point (same function as concatenating, ``N`` times cheaper for the code).

    Args:
        point_dim: Per-point input size ``D_p``.
        code_dim: Code size ``D_c``.
        hidden: Hidden widths (ReLU after each).
        out_dim: Output size.
    """

    def __init__(self, point_dim: int, code_dim: int, hidden: Sequence[int], out_dim: int) -> None:
        super().__init__()
        if not hidden:
            raise ValueError("`hidden` needs at least one width")
        self.point_in = nn.Linear(point_dim, hidden[0])
        self.code_in = nn.Linear(code_dim, hidden[0], bias=False)
        layers: list[nn.Module] = []
        for c_in, c_out in pairwise(hidden):
            layers += [nn.ReLU(), nn.Linear(c_in, c_out)]
        layers += [nn.ReLU(), nn.Linear(hidden[-1], out_dim)]
        self.rest = nn.Sequential(*layers)

    def forward(self, points: torch.Tensor, code: torch.Tensor) -> torch.Tensor:
        """Map ``points (B, N, D_p)`` and ``code (B, D_c)`` to ``(B, N, out_dim)``."""
        return self.rest(self.point_in(points) + self.code_in(code)[:, None, :])
