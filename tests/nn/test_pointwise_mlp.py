from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from lcreg.nn.mlp import ConditionedPointMLP, PointwiseMLP, activation


def _randomize_norms(mlp: PointwiseMLP, seed: int = 0) -> None:
    """Non-trivial affine terms and running statistics in every BatchNorm."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for norm in mlp.norms:
            if isinstance(norm, nn.BatchNorm1d):
                c = norm.num_features
                norm.weight.copy_(torch.rand(c, generator=gen, dtype=torch.float64) + 0.5)
                norm.bias.copy_(torch.randn(c, generator=gen, dtype=torch.float64) * 0.3)
                norm.running_mean.copy_(torch.randn(c, generator=gen, dtype=torch.float64))
                norm.running_var.copy_(torch.rand(c, generator=gen, dtype=torch.float64) + 0.2)


def _reference_eval(mlp: PointwiseMLP, x: torch.Tensor, slope: float, last_plain: bool) -> torch.Tensor:
    """Formula per layer: ``act(gamma (W x + b - mu) / sqrt(var + eps) + beta)``."""
    num = len(mlp.linears)
    for i, (lin, norm) in enumerate(zip(mlp.linears, mlp.norms)):
        assert isinstance(lin, nn.Linear)
        x = x @ lin.weight.T + (lin.bias if lin.bias is not None else 0)
        plain = last_plain and i == num - 1
        if isinstance(norm, nn.BatchNorm1d):
            assert norm.running_mean is not None and norm.running_var is not None
            x = norm.weight * (x - norm.running_mean) / torch.sqrt(norm.running_var + norm.eps) + norm.bias
        if not plain:
            x = torch.where(x > 0, x, slope * x)
    return x


@pytest.mark.parametrize("act,slope", [("relu", 0.0), ("leaky_relu", 0.2)])
@pytest.mark.parametrize("last_plain", [False, True])
def test_eval_forward_matches_the_layer_formula(act: str, slope: float, last_plain: bool) -> None:
    torch.manual_seed(0)
    mlp = PointwiseMLP([5, 7, 4], bias=False, act=act, last_plain=last_plain).double()  # type: ignore[arg-type]
    _randomize_norms(mlp)
    mlp.eval()
    x = torch.randn(2, 6, 3, 5, dtype=torch.float64)  # any leading dims
    out = mlp(x)
    assert out.shape == (2, 6, 3, 4) and mlp.out_channels == 4
    torch.testing.assert_close(out, _reference_eval(mlp, x, slope, last_plain))
    if last_plain:
        assert (out < 0).any()  # the last layer is linear: no activation clips it
        assert isinstance(mlp.norms[-1], nn.Identity)


def test_bias_flags() -> None:
    mlp = PointwiseMLP([3, 4, 5], bias=False, batch_norm=True, last_plain=True)
    first, last = mlp.linears
    assert isinstance(first, nn.Linear) and isinstance(last, nn.Linear)
    assert first.bias is None  # bias-free before BatchNorm
    assert last.bias is not None  # a plain last layer keeps its bias
    no_norm = PointwiseMLP([3, 4], bias=False, batch_norm=False)
    lin = no_norm.linears[0]
    assert isinstance(lin, nn.Linear) and lin.bias is not None  # without a norm the bias is always kept
    assert all(isinstance(n, nn.Identity) for n in no_norm.norms)


def test_training_batch_norm_pools_every_leading_dimension_like_batchnorm2d() -> None:
    """On (B, N, k, C) the statistics are taken over B, N and k: BatchNorm2d on the channels-first (B, C, N, k)."""
    torch.manual_seed(0)
    mlp = PointwiseMLP([4, 6], bias=False).double().train()
    x = torch.randn(3, 10, 5, 4, dtype=torch.float64) * 2 + 1
    out = mlp(x)
    lin = mlp.linears[0]
    norm = mlp.norms[0]
    assert isinstance(lin, nn.Linear) and isinstance(norm, nn.BatchNorm1d)
    z = (x @ lin.weight.T).permute(0, 3, 1, 2)  # (B, C, N, k)
    bn2d = nn.BatchNorm2d(6).double().train()
    expected = torch.relu(bn2d(z)).permute(0, 2, 3, 1)
    torch.testing.assert_close(out, expected)
    torch.testing.assert_close(norm.running_mean, bn2d.running_mean)
    torch.testing.assert_close(norm.running_var, bn2d.running_var)
    z_flat = z.transpose(0, 1).reshape(6, -1)
    manual = (z_flat - z_flat.mean(1, keepdim=True)) / torch.sqrt(z_flat.var(1, unbiased=False, keepdim=True) + 1e-5)
    torch.testing.assert_close(out.permute(3, 0, 1, 2).reshape(6, -1), torch.relu(manual))


def test_activation_names() -> None:
    x = torch.tensor([-2.0, 0.0, 3.0])
    assert isinstance(activation("relu"), nn.ReLU)
    torch.testing.assert_close(activation("relu")(x), torch.tensor([0.0, 0.0, 3.0]))
    torch.testing.assert_close(activation("leaky_relu")(x), torch.tensor([-0.4, 0.0, 3.0]))
    with pytest.raises(ValueError, match="gelu"):
        activation("gelu")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="gelu"):
        PointwiseMLP([3, 4], act="gelu")  # type: ignore[arg-type]


def test_channels_need_two_widths() -> None:
    with pytest.raises(ValueError, match="channels"):
        PointwiseMLP([3])


def test_gradients_reach_input_and_every_parameter() -> None:
    torch.manual_seed(0)
    mlp = PointwiseMLP([3, 8, 2], last_plain=True).double().train()
    x = torch.randn(2, 9, 3, dtype=torch.float64, requires_grad=True)
    (mlp(x) * torch.randn(2, 9, 2, dtype=torch.float64)).sum().backward()
    assert x.grad is not None and x.grad.abs().sum() > 0
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in mlp.parameters())


def test_conditioned_mlp_equals_the_concatenated_input_mlp() -> None:
    """Splitting the first layer into point and code parts is the MLP on ``[p_i, code]``."""
    torch.manual_seed(0)
    net = ConditionedPointMLP(point_dim=3, code_dim=5, hidden=(8, 6), out_dim=2).double()
    points, code = torch.randn(2, 7, 3, dtype=torch.float64), torch.randn(2, 5, dtype=torch.float64)
    w = torch.cat([net.point_in.weight, net.code_in.weight], dim=1)  # (8, 3 + 5)
    joint = torch.cat([points, code[:, None].expand(-1, 7, -1)], dim=-1)
    h = F.linear(joint, w, net.point_in.bias)
    torch.testing.assert_close(net(points, code), net.rest(h))
    with pytest.raises(ValueError, match="hidden"):
        ConditionedPointMLP(3, 5, (), 2)


def test_conditioned_mlp_with_points_shared_by_every_code() -> None:
    """``(N, D_p)`` points (a folding grid) give the result of the same points copied for every code."""
    torch.manual_seed(0)
    net = ConditionedPointMLP(point_dim=2, code_dim=5, hidden=(8, 6), out_dim=3).double()
    grid, code = torch.randn(7, 2, dtype=torch.float64), torch.randn(4, 5, dtype=torch.float64)
    shared = net(grid, code)
    assert shared.shape == (4, 7, 3)
    torch.testing.assert_close(shared, net(grid.expand(4, -1, -1), code))
