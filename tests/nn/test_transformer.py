from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from torch import nn

from lcreg.nn.transformer import DCPLayerNorm, PointerTransformer

DIM, HEADS, HIDDEN = 32, 4, 64


def _randomize(module: nn.Module, seed: int = 0) -> None:
    """Random LayerNorm gains/biases and attention biases (the defaults 1/0 would hide wiring mistakes)."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for m in module.modules():
            if isinstance(m, DCPLayerNorm):
                m.gain.copy_(torch.rand(m.gain.shape, generator=gen, dtype=m.gain.dtype) + 0.5)
                m.bias.copy_(torch.randn(m.bias.shape, generator=gen, dtype=m.bias.dtype) * 0.2)
            if isinstance(m, nn.MultiheadAttention):
                assert m.in_proj_bias is not None
                m.in_proj_bias.copy_(torch.randn(m.in_proj_bias.shape, generator=gen, dtype=m.in_proj_bias.dtype))
                m.out_proj.bias.copy_(torch.randn(m.out_proj.bias.shape, generator=gen, dtype=m.out_proj.bias.dtype))


def _net(seed: int = 0, act: str = "relu") -> PointerTransformer:
    torch.manual_seed(seed)
    net = PointerTransformer(DIM, HEADS, HIDDEN, act).double().eval()  # type: ignore[arg-type]
    _randomize(net, seed)
    return net


def _feats(b: int, n: int, seed: int) -> torch.Tensor:
    return torch.randn(b, n, DIM, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)


# --- independent reference: every block written out, attention head by head -------------------------------------
def _ln(norm: DCPLayerNorm, x: torch.Tensor) -> torch.Tensor:
    mean = x.mean(-1, keepdim=True)
    std = ((x - mean) ** 2).sum(-1, keepdim=True).div(x.shape[-1] - 1).sqrt()  # unbiased
    return norm.gain * (x - mean) / (std + 1e-6) + norm.bias


def _mha(attn: nn.MultiheadAttention, query: torch.Tensor, memory: torch.Tensor) -> torch.Tensor:
    """softmax(Q_h K_h^T / sqrt(d_h)) V_h per head, concatenated, then the output projection."""
    assert attn.in_proj_weight is not None and attn.in_proj_bias is not None
    w_q, w_k, w_v = attn.in_proj_weight.chunk(3)
    b_q, b_k, b_v = attn.in_proj_bias.chunk(3)
    q, k, v = query @ w_q.T + b_q, memory @ w_k.T + b_k, memory @ w_v.T + b_v
    d_h = DIM // HEADS
    heads = []
    for h in range(HEADS):
        sl = slice(h * d_h, (h + 1) * d_h)
        weights = torch.softmax(q[..., sl] @ k[..., sl].transpose(-1, -2) / math.sqrt(d_h), dim=-1)
        heads.append(weights @ v[..., sl])
    return torch.cat(heads, dim=-1) @ attn.out_proj.weight.T + attn.out_proj.bias


def _ffn(ffn: nn.Module, x: torch.Tensor, slope: float) -> torch.Tensor:
    first, _, second = ffn.net  # type: ignore[attr-defined]
    z = x @ first.weight.T + first.bias
    return torch.where(z > 0, z, slope * z) @ second.weight.T + second.bias


def _encode(net: PointerTransformer, x: torch.Tensor, slope: float) -> torch.Tensor:
    enc = net.encoder
    h = _ln(enc.norm1, x)
    x = x + _mha(enc.attn, h, h)
    x = x + _ffn(enc.ffn, _ln(enc.norm2, x), slope)
    return _ln(net.encoder_norm, x)


def _decode(net: PointerTransformer, x: torch.Tensor, memory: torch.Tensor, slope: float) -> torch.Tensor:
    dec = net.decoder
    norms = list(dec.norms)
    h = _ln(norms[0], x)  # type: ignore[arg-type]
    x = x + _mha(dec.self_attn, h, h)
    x = x + _mha(dec.cross_attn, _ln(norms[1], x), memory)  # type: ignore[arg-type]
    x = x + _ffn(dec.ffn, _ln(norms[2], x), slope)  # type: ignore[arg-type]
    return _ln(net.decoder_norm, x)


def _reference(
    net: PointerTransformer, f_src: torch.Tensor, f_ref: torch.Tensor, slope: float = 0.0
) -> tuple[torch.Tensor, torch.Tensor]:
    """DCP: phi_ref = decode(ref, encode(src)), phi_src = decode(src, encode(ref)), residual outputs."""
    phi_ref = _decode(net, f_ref, _encode(net, f_src, slope), slope)
    phi_src = _decode(net, f_src, _encode(net, f_ref, slope), slope)
    return f_src + phi_src, f_ref + phi_ref


# --- tests --------------------------------------------------------------------------------------------------------
def test_layer_norm_uses_the_unbiased_std_plus_eps() -> None:
    norm = DCPLayerNorm(5).double()
    with torch.no_grad():
        norm.gain.copy_(torch.tensor([1.0, 2.0, 0.5, -1.0, 3.0]))
        norm.bias.copy_(torch.tensor([0.1, 0.0, -0.2, 0.3, 0.0]))
    x = torch.randn(3, 4, 5, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    xn = x.numpy()
    mean = xn.mean(-1, keepdims=True)
    std = xn.std(-1, ddof=1, keepdims=True)
    expected = norm.gain.detach().numpy() * (xn - mean) / (std + 1e-6) + norm.bias.detach().numpy()
    np.testing.assert_allclose(norm(x).detach().numpy(), expected, rtol=1e-12, atol=1e-12)
    # not torch's LayerNorm (biased variance, eps inside the root): the two differ by sqrt(n / (n - 1))
    assert not torch.allclose(norm(x), F.layer_norm(x, (5,), norm.gain, norm.bias), atol=1e-3)
    constant = torch.full((1, 5), 2.0, dtype=torch.float64)
    torch.testing.assert_close(norm(constant), norm.bias[None].detach())  # zero std: eps keeps it finite


@pytest.mark.parametrize("act,slope", [("relu", 0.0), ("leaky_relu", 0.2)])
def test_forward_matches_a_written_out_encoder_decoder(act: str, slope: float) -> None:
    net = _net(act=act)
    f_src, f_ref = _feats(2, 7, seed=1), _feats(2, 5, seed=2)  # N != M
    with torch.no_grad():
        out_src, out_ref = net(f_src, f_ref)
        exp_src, exp_ref = _reference(net, f_src, f_ref, slope)
    assert out_src.shape == (2, 7, DIM) and out_ref.shape == (2, 5, DIM)
    torch.testing.assert_close(out_src, exp_src)
    torch.testing.assert_close(out_ref, exp_ref)


def test_point_permutation_equivariance() -> None:
    """No positional encoding: permuting one cloud's points permutes its outputs and leaves the other's unchanged."""
    net = _net()
    f_src, f_ref = _feats(2, 9, seed=3), _feats(2, 6, seed=4)
    gen = torch.Generator().manual_seed(5)
    perm_src, perm_ref = torch.randperm(9, generator=gen), torch.randperm(6, generator=gen)
    with torch.no_grad():
        out_src, out_ref = net(f_src, f_ref)
        p_src, p_ref = net(f_src[:, perm_src], f_ref)
        q_src, q_ref = net(f_src, f_ref[:, perm_ref])
    torch.testing.assert_close(p_src, out_src[:, perm_src])
    torch.testing.assert_close(p_ref, out_ref)
    torch.testing.assert_close(q_src, out_src)
    torch.testing.assert_close(q_ref, out_ref[:, perm_ref])


def test_both_directions_share_one_model() -> None:
    """Swapping the inputs swaps the outputs, and each output depends on the other cloud (cross-attention)."""
    net = _net()
    f_src, f_ref = _feats(1, 8, seed=6), _feats(1, 8, seed=7)
    with torch.no_grad():
        out_src, out_ref = net(f_src, f_ref)
        swap_ref, swap_src = net(f_ref, f_src)
        other_src, _ = net(f_src, _feats(1, 8, seed=8))
    torch.testing.assert_close(swap_src, out_src)
    torch.testing.assert_close(swap_ref, out_ref)
    assert not torch.allclose(other_src, out_src, atol=1e-6)


def test_gradients_reach_every_parameter() -> None:
    net = _net().train()
    f_src = _feats(2, 6, seed=9).requires_grad_(True)
    out_src, out_ref = net(f_src, _feats(2, 5, seed=10))
    (out_src.pow(2).sum() + out_ref.pow(3).sum()).backward()
    assert f_src.grad is not None and torch.isfinite(f_src.grad).all()
    for name, p in net.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0, name


def test_dim_must_divide_into_heads() -> None:
    with pytest.raises(ValueError, match="heads"):
        PointerTransformer(30, 4, 64)
