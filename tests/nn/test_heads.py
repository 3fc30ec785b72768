from __future__ import annotations

import pytest
import torch
from torch import nn

from lcreg.nn.heads import NormalHead
from lcreg.nn.mlp import ConditionedPointMLP


def test_normal_head_outputs_unit_normals(dtype: torch.dtype) -> None:
    torch.manual_seed(0)
    head = NormalHead(feature_dim=16, hidden=(32, 8)).to(dtype)
    normals = head(torch.randn(2, 50, 3, dtype=dtype), torch.randn(2, 16, dtype=dtype))
    assert normals.shape == (2, 50, 3) and normals.dtype == dtype
    torch.testing.assert_close(normals.norm(dim=-1), torch.ones(2, 50, dtype=dtype))


def test_normal_head_gradients_flow() -> None:
    torch.manual_seed(0)
    head = NormalHead(feature_dim=8, hidden=(16,))
    points = torch.randn(2, 20, 3, requires_grad=True)
    code = torch.randn(2, 8, requires_grad=True)
    target = nn.functional.normalize(torch.randn(2, 20, 3), dim=-1)
    (1 - (head(points, code) * target).sum(-1)).mean().backward()
    assert points.grad is not None and points.grad.abs().sum() > 0
    assert code.grad is not None and code.grad.abs().sum() > 0
    for name, param in head.named_parameters():
        assert param.grad is not None and torch.isfinite(param.grad).all(), name


@pytest.mark.parametrize("hidden", [(16,), (16, 12, 8)])
def test_conditioned_mlp_equals_concat_then_linear(hidden: tuple[int, ...]) -> None:
    torch.manual_seed(0)
    mlp = ConditionedPointMLP(point_dim=3, code_dim=5, hidden=hidden, out_dim=4).double()
    points = torch.randn(2, 7, 3, dtype=torch.float64)
    code = torch.randn(2, 5, dtype=torch.float64)
    first = nn.Linear(3 + 5, hidden[0]).double()
    with torch.no_grad():
        first.weight.copy_(torch.cat([mlp.point_in.weight, mlp.code_in.weight], dim=1))
        first.bias.copy_(mlp.point_in.bias)
    concat = torch.cat([points, code[:, None, :].expand(-1, 7, -1)], dim=-1)  # [p_i, code] per point
    h = first(concat)
    for layer in mlp.rest:
        h = layer(h)
    out = mlp(points, code)
    assert out.shape == (2, 7, 4)
    torch.testing.assert_close(out, h, atol=1e-12, rtol=1e-12)
    linears = [m for m in mlp.rest if isinstance(m, nn.Linear)]
    assert [m.out_features for m in linears] == [*hidden[1:], 4]
    assert mlp.code_in.bias is None


def test_conditioned_mlp_needs_a_hidden_layer() -> None:
    with pytest.raises(ValueError, match="hidden"):
        ConditionedPointMLP(3, 5, (), 3)
