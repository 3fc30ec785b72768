"""Fully connected point-cloud decoder (FMR-Net's): a global descriptor to a fixed number of points."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from lcreg.nn.mlp import PointwiseMLP

__all__ = ["MLPDecoder"]


class MLPDecoder(nn.Module):
    """Decode ``(B, K)`` codewords into ``(B, num_points, 3)`` points.

    ``Linear -> BN -> ReLU`` layers, a linear map to ``3 num_points`` values and ``tanh`` (outputs lie in
    ``(-1, 1)``, the cube around normalised objects).

    Args:
        feature_dim: Codeword size ``K`` (FMR-Net: 1024).
        hidden: Hidden widths (FMR-Net: 1024, 512, 256).
        num_points: Decoded points (FMR-Net: its input size, 2048 in the original).
        batch_norm: BatchNorm after each hidden layer (FMR-Net: yes).
    """

    def __init__(
        self,
        feature_dim: int = 1024,
        hidden: Sequence[int] = (1024, 512, 256),
        num_points: int = 1024,
        batch_norm: bool = True,
    ) -> None:
        super().__init__()
        if num_points < 1 or not hidden:
            raise ValueError(f"`num_points` must be >= 1 and `hidden` non-empty, got {num_points}, {list(hidden)}")
        self.num_points = num_points
        self.mlp = PointwiseMLP([feature_dim, *hidden, 3 * num_points], batch_norm=batch_norm, last_plain=True)

    def forward(self, code: torch.Tensor) -> torch.Tensor:
        """Decode ``code (B, K)`` into ``(B, num_points, 3)``."""
        return torch.tanh(self.mlp(code)).reshape(code.shape[0], self.num_points, 3)
