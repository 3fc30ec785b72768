"""Quiet Lightning ``Trainer``s for tests: training on fixed batches, and testing on a DataModule."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from lightning.pytorch import Callback, LightningModule, Trainer


def fit_batches(model: LightningModule, batches: Sequence[Any], *callbacks: Callback, **trainer_args: Any) -> None:
    """Fit ``model`` on ``batches`` in order, one epoch of them after another (no logger, checkpoints or bars).

    ``trainer_args`` go to the ``Trainer`` (default one epoch: ``max_epochs=1``).
    """
    loader = torch.utils.data.DataLoader(list(batches), batch_size=None, collate_fn=lambda b: b)
    trainer = quiet_trainer(**({"max_epochs": 1, "accelerator": "auto"} | trainer_args), callbacks=list(callbacks))
    trainer.fit(model, train_dataloaders=loader)


def quiet_trainer(root: str | Path | None = None, **trainer_args: Any) -> Trainer:
    """A ``Trainer`` (CPU unless ``trainer_args`` say) without logger, checkpoints, bars or summary.

    Its files (``test_per_pair.csv``, ``test_transforms.npz``) go to ``root``.
    """
    return Trainer(
        **({"accelerator": "cpu"} | trainer_args),
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        default_root_dir=root,
    )
