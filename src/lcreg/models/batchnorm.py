"""BatchNorm running statistics recomputed for fixed weights ("precise BatchNorm").

In eval mode a BatchNorm layer normalises with its running mean and variance, exponential averages (momentum 0.1 by
default) of the batch statistics seen in training: they mostly reflect the last few batches, of weights that were still
changing. :func:`recompute_batchnorm_statistics` replaces them by the cumulative mean of the batch statistics of the
final weights over many training batches (each layer reset, ``momentum=None``, train-mode forward passes without
gradients); nothing else of the model changes.
"""

from __future__ import annotations

from collections.abc import Iterable
from itertools import islice

import torch
from torch import nn

from lcreg.types import RegistrationBatch

__all__ = ["batchnorm_layers", "recompute_batchnorm_statistics"]


def batchnorm_layers(model: nn.Module) -> list[nn.modules.batchnorm._BatchNorm]:
    """The BatchNorm layers of ``model`` that keep running statistics (the ones eval mode uses)."""
    return [m for m in model.modules() if isinstance(m, nn.modules.batchnorm._BatchNorm) and m.track_running_stats]


def recompute_batchnorm_statistics(model: nn.Module, batches: Iterable[RegistrationBatch], limit: int) -> int:
    """Set every BatchNorm layer's running mean and variance to their mean over ``limit`` training batches.

    Each batch runs ``model(points_src, points_ref)`` in train mode under ``torch.no_grad``; a layer's new running mean
    (variance) is the plain mean of its per-batch means (unbiased variances). The model's mode and each layer's
    momentum are restored; parameters and every other buffer are unchanged.

    Args:
        model: A registration model (``forward(points_src (B, N, 3), points_ref (B, M, 3))``), on the batches' device.
        batches: Training batches (:class:`~lcreg.types.RegistrationBatch`), e.g. a ``train_dataloader()``.
        limit: How many batches to use (fewer if ``batches`` ends first).

    Returns:
        The number of batches used (0 and nothing changed when the model has no BatchNorm layer).

    Raises:
        ValueError: ``limit`` < 1, or ``batches`` is empty (the statistics would be left reset).
    """
    if limit < 1:
        raise ValueError(f"`limit` must be >= 1 batch, got {limit}")
    layers = batchnorm_layers(model)
    if not layers:
        return 0
    momenta, training = [layer.momentum for layer in layers], model.training
    saved = [(layer.running_mean.clone(), layer.running_var.clone()) for layer in layers]  # type: ignore[union-attr]
    for layer in layers:
        layer.reset_running_stats()
        layer.momentum = None  # cumulative moving average: each batch weighs the same
    used = 0
    try:
        model.train()
        with torch.no_grad():
            for batch in islice(batches, limit):  # reads no batch beyond the limit
                model(batch.points_src, batch.points_ref)
                used += 1
    finally:
        model.train(training)
        for layer, momentum in zip(layers, momenta, strict=True):
            layer.momentum = momentum
    if used == 0:
        for layer, (mean, var) in zip(layers, saved, strict=True):
            layer.running_mean.copy_(mean)  # type: ignore[union-attr]
            layer.running_var.copy_(var)  # type: ignore[union-attr]
        raise ValueError("`batches` is empty: no statistics to recompute (the running statistics are kept)")
    return used
