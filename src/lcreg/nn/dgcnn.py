"""DGCNN per-point embedding (Wang et al. 2019) in the two variants the registration baselines use.

* ``graph="static"`` (DCP): the k-NN graph is built once on the input coordinates; the edge tensor
  ``[x_j, x_i]`` (neighbour, centre; 6 channels) goes through the edge layers *sequentially*, and after each layer
  the maximum over the ``k`` neighbours is kept as that layer's per-point output.
* ``graph="dynamic"`` (PRNet, standard DGCNN): before every edge layer the graph is rebuilt on the current
  per-point features, and the edge tensor is ``[f_j, f_i]`` of those features.

Both concatenate the per-layer outputs (64 + 64 + 128 + 256 = 512 channels by default) and map them with a final
per-point layer to ``emb_dims``. No global pooling: the output is per point. Edge features are ``[neighbour,
centre]`` as in the DCP/PRNet code (not DGCNN's ``[neighbour - centre, centre]``; see docs/baselines.md).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import torch
from torch import nn

from lcreg.checks import ShapeError, TooFewPointsError
from lcreg.geometry.neighbors import gather_points, knn_indices, neighbour_max
from lcreg.nn.mlp import Activation, PointwiseMLP

__all__ = ["DGCNN", "edge_conv", "edge_features"]

Graph = Literal["static", "dynamic"]


def edge_features(features: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """``[f_j, f_i]`` for each point ``i`` and neighbour ``j``.

    Args:
        features: Per-point features ``(B, N, C)``.
        idx: Neighbour indices ``(B, N, k)``.

    Returns:
        ``(B, N, k, 2C)``.
    """
    neighbours = gather_points(features, idx)  # (B, N, k, C)
    centre = features[:, :, None, :].expand_as(neighbours)
    return torch.cat([neighbours, centre], dim=-1)


def edge_conv(layer: nn.Module, features: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """``layer(edge_features(features, idx))`` without building the ``2C``-wide edge tensor.

    The first linear map splits over the concatenation, ``W [f_j, f_i] = W_a f_j + W_b f_i``, so it is applied once
    per point and the result gathered: ``k`` times fewer multiplications and no ``(B, N, k, 2C)`` input kept for the
    backward pass. Same function as the direct form (pinned by a test).

    Args:
        layer: A :class:`~lcreg.nn.mlp.PointwiseMLP` edge layer whose first linear map takes ``2C`` channels.
        features: Per-point features ``(B, N, C)``.
        idx: Neighbour indices ``(B, N, k)``.

    Returns:
        ``(B, N, k, C_out)``.
    """
    if not isinstance(layer, PointwiseMLP):
        raise TypeError(f"`layer` must be a PointwiseMLP, got {type(layer).__name__}")
    first = layer.first_linear
    channels = features.shape[-1]
    if first.in_features != 2 * channels:
        raise ShapeError("features", ("B", "N", first.in_features // 2), features.shape)
    h = gather_points(features @ first.weight[:, :channels].T, idx)  # (B, N, k, C_1): W_a f_j
    h = h + (features @ first.weight[:, channels:].T)[:, :, None, :]  # + W_b f_i
    if first.bias is not None:
        h = h + first.bias
    return layer.after_first_linear(h)


class DGCNN(nn.Module):
    """Per-point DGCNN embedding ``(B, N, 3) -> (B, N, emb_dims)``.

    Args:
        emb_dims: Output width (DCP/PRNet: 512).
        k: Neighbours per point (DCP/PRNet: 20). Clouds need at least ``k`` points.
        graph: ``"static"`` (DCP) or ``"dynamic"`` (PRNet), see the module docstring.
        channels: Widths of the edge layers (default 64, 64, 128, 256).
        act: ``"relu"`` (DCP) or ``"leaky_relu"`` (PRNet, slope 0.2).
        batch_norm: BatchNorm after every layer (the originals); ``False``: plain layers with a bias.
    """

    def __init__(
        self,
        emb_dims: int = 512,
        k: int = 20,
        graph: Graph = "static",
        channels: Sequence[int] = (64, 64, 128, 256),
        act: Activation = "relu",
        batch_norm: bool = True,
    ) -> None:
        super().__init__()
        if graph not in ("static", "dynamic"):
            raise ValueError(f"`graph` must be 'static' or 'dynamic', got {graph!r}")
        if k < 1:
            raise ValueError(f"`k` must be >= 1, got {k}")
        self.k, self.graph, self.emb_dims = k, graph, emb_dims
        self.feature_dim = emb_dims  # descriptor width K (the attribute loss terms such as LC read)
        layers = []
        c_in = 3
        for i, c_out in enumerate(channels):
            # Static: layer i > 0 consumes the previous layer's edge tensor; dynamic: edge features of the last output.
            width = 2 * c_in if graph == "dynamic" or i == 0 else c_in
            layers.append(PointwiseMLP([width, c_out], bias=False, batch_norm=batch_norm, act=act))
            c_in = c_out
        self.edge_layers = nn.ModuleList(layers)
        self.head = PointwiseMLP([sum(channels), emb_dims], bias=False, batch_norm=batch_norm, act=act)

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        """Per-point embeddings ``(B, N, emb_dims)`` of ``points (B, N, 3)``."""
        if points.shape[1] < self.k:
            raise TooFewPointsError(f"DGCNN needs at least k={self.k} points per cloud, got {points.shape[1]}")
        outputs = []
        if self.graph == "static":
            idx = knn_indices(points, points, self.k)
            h = edge_conv(self.edge_layers[0], points, idx)  # first layer on [x_j, x_i] (6 channels)
            outputs.append(neighbour_max(h))
            for layer in self.edge_layers[1:]:
                h = layer(h)
                outputs.append(neighbour_max(h))
        else:
            f = points
            for layer in self.edge_layers:
                f = neighbour_max(edge_conv(layer, f, knn_indices(f, f, self.k)))
                outputs.append(f)
        return self.head(torch.cat(outputs, dim=-1))
