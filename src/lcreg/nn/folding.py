"""FoldingNet decoder (Yang et al., CVPR 2018): two folds of a 2-D grid conditioned on the global descriptor."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from lcreg.nn.mlp import ConditionedPointMLP
from lcreg.reference import reference_active

__all__ = ["FoldingDecoder"]


class FoldingDecoder(nn.Module):
    """Reconstruct ``grid_size**2`` points from a ``(B, K)`` codeword.

    Args:
        feature_dim: Codeword size ``K``.
        grid_size: Side of the square 2-D grid in ``[-grid_extent, grid_extent]^2`` (FoldingNet: 45, extent 0.3).
        hidden: Hidden widths of both folding MLPs (FoldingNet: 512, 512).
        grid_extent: Half side of the grid.
    """

    grid: torch.Tensor

    def __init__(
        self, feature_dim: int = 1024, grid_size: int = 32, hidden: Sequence[int] = (256, 256), grid_extent: float = 0.3
    ) -> None:
        super().__init__()
        if grid_size < 2:
            raise ValueError(f"`grid_size` must be >= 2, got {grid_size}")
        axis = torch.linspace(-grid_extent, grid_extent, grid_size)
        grid = torch.stack(torch.meshgrid(axis, axis, indexing="ij"), dim=-1).reshape(-1, 2)
        self.register_buffer("grid", grid, persistent=False)
        self.fold1 = ConditionedPointMLP(2, feature_dim, hidden, 3)
        self.fold2 = ConditionedPointMLP(3, feature_dim, hidden, 3)

    @property
    def num_points(self) -> int:
        """Number of reconstructed points."""
        return int(self.grid.shape[0])

    def forward(self, code: torch.Tensor) -> torch.Tensor:
        """Decode ``(B, K)`` codewords into ``(B, grid_size**2, 3)`` points.

        The grid is shared by every codeword, so the first fold's grid term is computed once (``(G, H)``) and
        broadcast against the per-codeword term.
        """
        if reference_active():
            return self._forward_reference(code)
        return self.fold2(self.fold1(self.grid.to(code.dtype), code), code)

    def _forward_reference(self, code: torch.Tensor) -> torch.Tensor:
        """:meth:`forward` with the grid copied for every codeword (``(B, G, 2)``)."""
        grid = self.grid.to(code.dtype).expand(code.shape[0], -1, -1)
        return self.fold2(self.fold1(grid, code), code)
