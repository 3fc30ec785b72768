"""Train a model with a quiet Lightning ``Trainer`` on fixed batches (tests of the training step and its schedule)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from lightning.pytorch import Callback, LightningModule, Trainer


def fit_batches(model: LightningModule, batches: Sequence[Any], *callbacks: Callback, **trainer_args: Any) -> None:
    """Fit ``model`` on ``batches`` in order, one epoch of them after another (no logger, checkpoints or bars).

    ``trainer_args`` go to the ``Trainer`` (default one epoch: ``max_epochs=1``).
    """
    loader = torch.utils.data.DataLoader(list(batches), batch_size=None, collate_fn=lambda b: b)
    trainer = Trainer(
        **({"max_epochs": 1} | trainer_args),
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        callbacks=list(callbacks),
    )
    trainer.fit(model, train_dataloaders=loader)
