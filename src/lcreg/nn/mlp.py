"""Shared per-point MLP building blocks (decoder, normal head, baselines' 1x1 convolutions; never copied per model)."""

from __future__ import annotations

from collections.abc import Sequence
from itertools import pairwise
from typing import Literal, cast

import torch
from torch import nn

__all__ = ["ConditionedPointMLP", "PointwiseMLP", "activation"]

Activation = Literal["relu", "leaky_relu"]


def activation(name: Activation) -> nn.Module:
    """``"relu"`` or ``"leaky_relu"`` (slope 0.2, as in DGCNN/PRNet)."""
    if name == "relu":
        return nn.ReLU()
    if name == "leaky_relu":
        return nn.LeakyReLU(0.2)
    raise ValueError(f"unknown activation {name!r}; expected 'relu' or 'leaky_relu'")


class PointwiseMLP(nn.Module):
    """Shared per-point layers (PointNet's 1x1 convolutions) on channels-last features ``(..., C)``.

    Each layer is ``Linear -> [BatchNorm] -> activation``; the last layer's activation (and norm) can be dropped
    with ``last_plain=True``. BatchNorm normalises over every leading dimension (batch, points, neighbours), which is
    what ``BatchNorm1d/2d`` on channels-first tensors do.

    Args:
        channels: ``(C_in, C_1, ..., C_out)``.
        batch_norm: BatchNorm after each linear layer.
        bias: Bias in the linear layers followed by BatchNorm (originals often use ``bias=False`` there); layers
            without BatchNorm always have a bias.
        act: Activation name.
        last_plain: Leave the last layer linear (no norm, no activation).
    """

    def __init__(
        self,
        channels: Sequence[int],
        batch_norm: bool = True,
        bias: bool = True,
        act: Activation = "relu",
        last_plain: bool = False,
    ) -> None:
        super().__init__()
        if len(channels) < 2:
            raise ValueError(f"`channels` needs an input and at least one output width, got {list(channels)}")
        self.linears = nn.ModuleList()
        self.norms = nn.ModuleList()
        self.acts = nn.ModuleList()
        num = len(channels) - 1
        for i, (c_in, c_out) in enumerate(pairwise(channels)):
            plain = last_plain and i == num - 1
            self.linears.append(nn.Linear(c_in, c_out, bias=bias or plain or not batch_norm))
            self.norms.append(nn.BatchNorm1d(c_out) if batch_norm and not plain else nn.Identity())
            self.acts.append(nn.Identity() if plain else activation(act))
        self.out_channels = int(channels[-1])  # output width

    @property
    def first_linear(self) -> nn.Linear:
        """The first linear map (``C_in -> C_1``); built by the constructor, so always an ``nn.Linear``."""
        return cast(nn.Linear, self.linears[0])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Map ``(..., C_in)`` to ``(..., C_out)``."""
        return self.after_first_linear(self.linears[0](x))

    def after_first_linear(self, x: torch.Tensor) -> torch.Tensor:
        """The rest of the MLP, given the first linear layer's output ``(..., C_1)``.

        For callers that compute the first layer more cheaply themselves (e.g. on a concatenation, see
        :func:`lcreg.nn.dgcnn.edge_conv`).
        """
        for i, (linear, norm, act) in enumerate(zip(self.linears, self.norms, self.acts, strict=True)):
            if i > 0:
                x = linear(x)
            if isinstance(norm, nn.BatchNorm1d):
                x = norm(x.reshape(-1, x.shape[-1])).reshape(x.shape)
            x = act(x)
        return x


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
        """Map ``points (B, N, D_p)`` and ``code (B, D_c)`` to ``(B, N, out_dim)``.

        ``points`` may also be ``(N, D_p)``, the same points for every code (a folding grid): their part of the first
        layer is then computed once, not once per code.
        """
        return self.rest(self.point_in(points) + self.code_in(code)[:, None, :])
