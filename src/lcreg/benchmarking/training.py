"""Training in benchmarks: the training loss of any model, and short ``fit`` runs with a step budget."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING

import torch

from lcreg.benchmarking.building import build_cli_for
from lcreg.benchmarking.measure import timed

if TYPE_CHECKING:
    from lightning.pytorch import LightningDataModule, Trainer

    from lcreg.models.base import RegistrationModule
    from lcreg.types import RegistrationBatch

__all__ = ["SELECTION_METRIC", "FitResult", "epoch_overrides", "fit", "fit_overrides", "training_loss"]

SELECTION_METRIC = "val/rre_mean_deg"
"""Checkpoints of benchmark runs are chosen on the validation registration error (never the test set)."""


def training_loss(model: RegistrationModule, batch: RegistrationBatch) -> dict[str, torch.Tensor]:
    """Every training-loss term of ``model`` on ``batch``, exactly as the shared training step computes them.

    ``model.training_losses(model.training_forward(batch), batch)``: the host's loss plus injected terms such as
    local consistency. Benchmarks never call ``compute_loss``, which leaves those terms out.

    Returns:
        Loss terms by name; ``"loss"`` is the optimised total (a scalar).
    """
    return model.training_losses(model.training_forward(batch), batch)


def fit_overrides(max_steps: int, val_every: int, run_dir: str | Path, name: str = "", seed: int = 0) -> list[str]:
    """``lcreg fit`` arguments of a short benchmark run: a step budget, periodic validation, quiet, own folder.

    Args:
        max_steps: Optimiser steps (epochs unbounded).
        val_every: Validate every this many training steps (across epochs).
        run_dir: Folder of the logs and checkpoints (``<run_dir>/<name>/version_k``).
        name: Logger name (``""``: directly under ``run_dir``).
        seed: ``seed_everything`` (initialisation and training order).
    """
    budget = [
        f"--trainer.max_steps={max_steps}",
        "--trainer.max_epochs=-1",
        f"--trainer.val_check_interval={val_every}",
        "--trainer.check_val_every_n_epoch=null",
    ]
    return [f"--seed_everything={seed}", *budget, *_quiet_run(run_dir, name)]


def epoch_overrides(max_epochs: int, run_dir: str | Path, name: str = "", seed: int = 0) -> list[str]:
    """``lcreg fit`` arguments of a run with an epoch budget (the papers' unit), validated after every epoch.

    Args:
        max_epochs: Training epochs (steps unbounded).
        run_dir: Folder of the logs and checkpoints (``<run_dir>/<name>/version_k``).
        name: Logger name (``""``: directly under ``run_dir``).
        seed: ``seed_everything`` (initialisation and training order).
    """
    budget = [
        "--trainer.max_steps=-1",
        f"--trainer.max_epochs={max_epochs}",
        "--trainer.val_check_interval=1.0",
        "--trainer.check_val_every_n_epoch=1",
    ]
    return [f"--seed_everything={seed}", *budget, *_quiet_run(run_dir, name)]


def _quiet_run(run_dir: str | Path, name: str) -> list[str]:
    """No progress bar or model summary; logs and checkpoints under ``<run_dir>/<name>``."""
    return [
        "--trainer.enable_progress_bar=false",
        "--trainer.enable_model_summary=false",
        f"--trainer.logger.init_args.save_dir={run_dir}",
        f"--trainer.logger.init_args.name={name}",
        f"--trainer.default_root_dir={run_dir}",
    ]


@dataclass
class FitResult:
    """A finished ``fit``: the trained objects, the best checkpoint on :data:`SELECTION_METRIC` and the time."""

    model: RegistrationModule
    datamodule: LightningDataModule
    trainer: Trainer
    best_checkpoint: Path
    seconds: float


def fit(
    name: str, overrides: Sequence[str] = (), configs: Sequence[str | Path] = (), validate_first: bool = False
) -> FitResult:
    """Train method ``name`` as ``lcreg fit`` would (its configs, then ``overrides``, e.g. :func:`fit_overrides`).

    Args:
        name: Method of the registry.
        overrides: CLI arguments after the configs.
        configs: Extra config files after the method's own.
        validate_first: Validate the initial weights before training, so the run's ``metrics.csv`` starts with a
            step-0 validation row (learning curves start at the untrained model).

    Raises:
        ValueError: If the config's checkpoint callback does not select on :data:`SELECTION_METRIC`.
        RuntimeError: If training wrote no best checkpoint.
    """
    from lcreg.models.base import RegistrationModule

    cli = build_cli_for(name, configs, overrides)
    callback = cli.trainer.checkpoint_callback
    monitor = getattr(callback, "monitor", None)
    if monitor != SELECTION_METRIC:
        raise ValueError(f"{name}: the checkpoint callback monitors {monitor!r}, not {SELECTION_METRIC}")
    if not isinstance(cli.model, RegistrationModule):  # pragma: no cover - the CLI only builds RegistrationModules
        raise TypeError(f"{name} built a {type(cli.model).__name__}, not a RegistrationModule")
    if validate_first:
        cli.trainer.validate(cli.model, datamodule=cli.datamodule, verbose=False)
    _, seconds = timed(partial(cli.trainer.fit, cli.model, datamodule=cli.datamodule))
    best = getattr(callback, "best_model_path", "")
    if not best:
        raise RuntimeError(f"training {name} wrote no checkpoint (did validation run? see val_check_interval)")
    return FitResult(cli.model, cli.datamodule, cli.trainer, Path(best), seconds)
