"""Precise BatchNorm: running statistics recomputed for fixed weights, checked against the batch statistics by hand."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
import torch
from torch import nn

from lcreg.models.batchnorm import batchnorm_layers, recompute_batchnorm_statistics
from lcreg.types import RegistrationBatch


class _Net(nn.Module):
    """Linear -> BatchNorm1d on every point of both clouds (the BatchNorm sees the clouds as one batch of points)."""

    def __init__(self, batch_norm: bool = True) -> None:
        super().__init__()
        self.linear = nn.Linear(3, 4)
        self.norm = nn.BatchNorm1d(4) if batch_norm else nn.Identity()

    def features(self, points_src: torch.Tensor, points_ref: torch.Tensor) -> torch.Tensor:
        return self.linear(torch.cat([points_src, points_ref], dim=1).reshape(-1, 3))

    def forward(self, points_src: torch.Tensor, points_ref: torch.Tensor) -> torch.Tensor:
        return self.norm(self.features(points_src, points_ref))


def _batches(count: int, seed: int = 0) -> list[RegistrationBatch]:
    generator = torch.Generator().manual_seed(seed)
    shift = torch.arange(count, dtype=torch.float32)  # batches whose statistics differ
    return [
        RegistrationBatch(
            points_src=torch.randn(2, 5, 3, generator=generator) + s,
            points_ref=torch.randn(2, 6, 3, generator=generator) * (1 + s),
            transform_ref_src=None,
        )
        for s in shift
    ]


def test_running_statistics_become_the_mean_of_the_batch_statistics() -> None:
    net = _Net().eval()
    for _ in range(3):  # running statistics of "training": anything else
        net.train()(torch.randn(2, 5, 3) * 7, torch.randn(2, 6, 3))
    net.eval()
    weights = {k: v.clone() for k, v in net.state_dict().items() if "running" not in k and "tracked" not in k}
    batches = _batches(4)
    with torch.no_grad():
        features = [net.features(b.points_src, b.points_ref) for b in batches[:3]]
    used = recompute_batchnorm_statistics(net, iter(batches), limit=3)
    assert used == 3 and not net.training and net.norm.momentum == 0.1  # mode and momentum restored
    expected_mean = torch.stack([f.mean(0) for f in features]).mean(0)
    expected_var = torch.stack([f.var(0, unbiased=True) for f in features]).mean(0)
    torch.testing.assert_close(net.norm.running_mean, expected_mean)
    torch.testing.assert_close(net.norm.running_var, expected_var)
    for key, value in weights.items():
        torch.testing.assert_close(net.state_dict()[key], value)  # parameters untouched


def test_the_limit_stops_reading_the_batches() -> None:
    read = 0

    def counted() -> Iterator[RegistrationBatch]:
        nonlocal read
        for batch in _batches(10):
            read += 1
            yield batch

    net = _Net().train()
    assert recompute_batchnorm_statistics(net, counted(), limit=4) == 4 and read == 4
    assert net.training  # a model in train mode stays in it
    assert recompute_batchnorm_statistics(_Net(), _batches(2), limit=5) == 2  # fewer batches than the limit


def test_a_model_without_batchnorm_is_left_alone() -> None:
    net = _Net(batch_norm=False)
    assert batchnorm_layers(net) == [] and recompute_batchnorm_statistics(net, _batches(2), limit=2) == 0


def test_empty_batches_and_a_bad_limit_are_refused_and_change_nothing() -> None:
    net = _Net()
    net.train()(torch.randn(2, 5, 3) + 3, torch.randn(2, 6, 3))
    before = net.norm.running_mean.clone()
    with pytest.raises(ValueError, match="`batches` is empty"):
        recompute_batchnorm_statistics(net, [], limit=3)
    torch.testing.assert_close(net.norm.running_mean, before)
    with pytest.raises(ValueError, match="`limit` must be >= 1"):
        recompute_batchnorm_statistics(net, _batches(1), limit=0)
