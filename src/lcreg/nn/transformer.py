"""The DCP/PRNet attention module: a one-block encoder-decoder transformer between two clouds' embeddings.

As in DCP (and PRNet): pre-norm residual sublayers, a LayerNorm with the *unbiased* standard deviation and
``eps = 1e-6`` added to the std (not the variance), multi-head attention without positional encoding or masks, and a
position-wise FFN ``Linear -> act -> Linear``. :class:`PointerTransformer` returns the residual embeddings
``F_src + phi(F_ref -> F_src)`` and ``F_ref + phi(F_src -> F_ref)``: the decoder of each cloud attends to the
encoded other cloud. Dropout is 0 (the originals ignore theirs).
"""

from __future__ import annotations

import torch
from torch import nn

from lcreg.nn.mlp import Activation, activation

__all__ = ["DCPLayerNorm", "PointerTransformer"]


class DCPLayerNorm(nn.Module):
    """``gain * (x - mean) / (std_unbiased + eps) + bias`` over the last dimension."""

    def __init__(self, dim: int, eps: float = 1e-6) -> None:
        super().__init__()
        self.gain = nn.Parameter(torch.ones(dim))
        self.bias = nn.Parameter(torch.zeros(dim))
        self.eps = eps

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Normalise ``(..., dim)``."""
        mean = x.mean(-1, keepdim=True)
        std = x.std(-1, keepdim=True)
        return self.gain * (x - mean) / (std + self.eps) + self.bias


class _FeedForward(nn.Module):
    def __init__(self, dim: int, hidden: int, act: Activation) -> None:
        super().__init__()
        self.net = nn.Sequential(nn.Linear(dim, hidden), activation(act), nn.Linear(hidden, dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


class _EncoderLayer(nn.Module):
    def __init__(self, dim: int, heads: int, hidden: int, act: Activation) -> None:
        super().__init__()
        self.norm1, self.norm2 = DCPLayerNorm(dim), DCPLayerNorm(dim)
        self.attn = nn.MultiheadAttention(dim, heads, batch_first=True)
        self.ffn = _FeedForward(dim, hidden, act)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = self.norm1(x)
        x = x + self.attn(h, h, h, need_weights=False)[0]
        return x + self.ffn(self.norm2(x))


class _DecoderLayer(nn.Module):
    def __init__(self, dim: int, heads: int, hidden: int, act: Activation) -> None:
        super().__init__()
        self.norms = nn.ModuleList(DCPLayerNorm(dim) for _ in range(3))
        self.self_attn = nn.MultiheadAttention(dim, heads, batch_first=True)
        self.cross_attn = nn.MultiheadAttention(dim, heads, batch_first=True)
        self.ffn = _FeedForward(dim, hidden, act)

    def forward(self, x: torch.Tensor, memory: torch.Tensor) -> torch.Tensor:
        h = self.norms[0](x)
        x = x + self.self_attn(h, h, h, need_weights=False)[0]
        h = self.norms[1](x)
        x = x + self.cross_attn(h, memory, memory, need_weights=False)[0]
        return x + self.ffn(self.norms[2](x))


class PointerTransformer(nn.Module):
    """DCP-v2's "pointer": one encoder block and one decoder block, shared by both directions.

    Args:
        dim: Embedding width ``d_model`` (DCP/PRNet: 512).
        heads: Attention heads (4).
        hidden: FFN width (1024).
        act: FFN activation (``"relu"`` DCP, ``"leaky_relu"`` PRNet).
    """

    def __init__(self, dim: int = 512, heads: int = 4, hidden: int = 1024, act: Activation = "relu") -> None:
        super().__init__()
        if dim % heads:
            raise ValueError(f"`dim` ({dim}) must be divisible by `heads` ({heads})")
        self.encoder = _EncoderLayer(dim, heads, hidden, act)
        self.encoder_norm = DCPLayerNorm(dim)
        self.decoder = _DecoderLayer(dim, heads, hidden, act)
        self.decoder_norm = DCPLayerNorm(dim)

    def _attend(self, query: torch.Tensor, memory: torch.Tensor) -> torch.Tensor:
        memory = self.encoder_norm(self.encoder(memory))
        return self.decoder_norm(self.decoder(query, memory))

    def forward(self, feat_src: torch.Tensor, feat_ref: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Residual embeddings ``(F_src + phi_src, F_ref + phi_ref)``, shapes ``(B, N, dim)`` and ``(B, M, dim)``."""
        phi_ref = self._attend(feat_ref, feat_src)  # target decoded against the encoded source
        phi_src = self._attend(feat_src, feat_ref)
        return feat_src + phi_src, feat_ref + phi_ref
