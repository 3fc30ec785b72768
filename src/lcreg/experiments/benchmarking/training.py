"""Training in benchmarks: the training loss of any model, and short ``fit`` runs with a step budget."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from lcreg.callbacks import validate_starting_weights
from lcreg.experiments.benchmarking.building import Values, build_cli_for
from lcreg.experiments.benchmarking.measure import timed
from lcreg.resume import TERMINATED_EXIT_CODE

if TYPE_CHECKING:
    from lightning.pytorch import LightningDataModule, Trainer

    from lcreg.cli import LcregCLI
    from lcreg.models.base import RegistrationModule
    from lcreg.types import RegistrationBatch

__all__ = [
    "CONVERGE_METRIC",
    "SELECTION_METRIC",
    "TERMINATED_EXIT_CODE",
    "FitResult",
    "converge_overrides",
    "epoch_overrides",
    "fit",
    "fit_overrides",
    "last_checkpoint",
    "training_loss",
]

SELECTION_METRIC = "val/rre_mean_deg"
"""Checkpoints of benchmark runs are chosen on the validation registration error (never the test set)."""
CONVERGE_METRIC = "val/rre_clip5_deg"
"""Checkpoints and early stopping of ``converge`` runs: the mean of ``min(RRE, 5°)`` over the validation pairs
(:class:`lcreg.metrics.registration.RotationErrorClippedMean`): one failed pair moves it by at most 5° / pairs."""


def training_loss(model: RegistrationModule, batch: RegistrationBatch) -> dict[str, torch.Tensor]:
    """Every training-loss term of ``model`` on ``batch``, exactly as the shared training step computes them.

    ``model.training_losses(model.training_forward(batch), batch)``: the host's loss plus injected terms such as
    local consistency. Benchmarks never call ``compute_loss``, which leaves those terms out.

    Returns:
        Loss terms by name; ``"loss"`` is the optimised total (a scalar).
    """
    return model.training_losses(model.training_forward(batch), batch)


def fit_overrides(max_steps: int, val_every: int, run_dir: str | Path, name: str = "", seed: int = 0) -> Values:
    """``lcreg fit`` values of a short benchmark run: a step budget, periodic validation, quiet, own folder.

    Args:
        max_steps: Optimiser steps (epochs unbounded).
        val_every: Validate every this many training steps (across epochs).
        run_dir: Folder of the logs and checkpoints (``<run_dir>/<name>/version_k``).
        name: Logger name (``""``: directly under ``run_dir``).
        seed: ``seed_everything`` (initialisation and training order).
    """
    budget = {
        "trainer.max_steps": max_steps,
        "trainer.max_epochs": -1,
        "trainer.val_check_interval": val_every,
        "trainer.check_val_every_n_epoch": None,
    }
    return {"seed_everything": seed, **budget, **_quiet_run(run_dir, name)}


def epoch_overrides(max_epochs: int, run_dir: str | Path, name: str = "", seed: int = 0) -> Values:
    """``lcreg fit`` values of a run with an epoch budget (the papers' unit), validated after every epoch.

    Args:
        max_epochs: Training epochs (steps unbounded).
        run_dir: Folder of the logs and checkpoints (``<run_dir>/<name>/version_k``).
        name: Logger name (``""``: directly under ``run_dir``).
        seed: ``seed_everything`` (initialisation and training order).
    """
    budget = {
        "trainer.max_steps": -1,
        "trainer.max_epochs": max_epochs,
        "trainer.val_check_interval": 1.0,
        "trainer.check_val_every_n_epoch": 1,
    }
    return {"seed_everything": seed, **budget, **_quiet_run(run_dir, name)}


def converge_overrides(
    max_steps: int,
    val_every: int,
    patience: int,
    run_dir: str | Path,
    name: str = "",
    seed: int = 0,
    monitor: str = CONVERGE_METRIC,
    min_delta: float = 0.0,
) -> Values:
    """``lcreg fit`` values of a run trained until its validation error stops improving, capped by a step limit.

    :func:`fit_overrides` plus early stopping (:class:`lcreg.callbacks.MinimumEarlyStopping`: stop after
    ``patience`` validations without an improvement of more than ``min_delta``, counted also across a
    ``trainer.min_steps``) and a ``ModelCheckpoint`` that keeps the best checkpoint on the same ``monitor`` (both
    minimise it). Both callbacks keep their state in ``last.ckpt``, and the run logs to the fixed
    folder ``<run_dir>/<name>/run``, so a run resumed with :func:`fit` (``resume=True``) goes on where it stopped.

    Args:
        max_steps: Step cap (optimiser steps).
        val_every: Validate every this many training steps.
        patience: Validations without improvement before stopping (>= 1).
        run_dir: Folder of the logs and checkpoints.
        name: Logger name.
        seed: ``seed_everything``.
        monitor: Validation metric to minimise (default :data:`CONVERGE_METRIC`).
        min_delta: Smallest decrease that counts as an improvement, in the metric's unit.

    Raises:
        ValueError: If ``patience`` < 1 or ``min_delta`` < 0.
    """
    if patience < 1 or min_delta < 0:
        raise ValueError(f"`patience` must be >= 1 and `min_delta` >= 0, got {patience} and {min_delta}")
    stem = monitor.replace("/", "_")
    stop = {"monitor": monitor, "mode": "min", "patience": patience, "min_delta": min_delta}
    best = {
        "monitor": monitor,
        "mode": "min",
        "filename": f"step{{step:06d}}-{stem}{{{monitor}:.4f}}",
        "auto_insert_metric_name": False,
    }
    callbacks: list[dict[str, Any]] = [
        {"class_path": "lcreg.callbacks.MinimumEarlyStopping", "init_args": stop},
        {"class_path": "lightning.pytorch.callbacks.ModelCheckpoint", "init_args": best},
    ]
    # A fixed logger version: a resumed run finds its last.ckpt in the same folder (a later value may rename it).
    fixed = {"trainer.logger.init_args.version": "run", "trainer.callbacks": callbacks}
    return {**fit_overrides(max_steps, val_every, run_dir, name, seed), **fixed}


def last_checkpoint(log_dir: str | Path) -> Path | None:
    """``<log_dir>/checkpoints/last.ckpt`` if a run in ``log_dir`` left one (the state to resume from)."""
    from lcreg.resume import LAST

    path = Path(log_dir) / "checkpoints" / LAST
    return path if path.is_file() else None


def _changed_since_last_segment(cli: LcregCLI, log_dir: Path) -> list[str]:
    """The model and data keys of ``cli``'s config that differ from the last segment trained in ``log_dir``.

    Read from that segment's ``config.yaml`` (:func:`lcreg.resume.changed_settings`); none without one.
    """
    import yaml

    from lcreg.resume import changed_settings

    try:
        saved = yaml.safe_load((log_dir / "config.yaml").read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError):
        return []
    current = yaml.safe_load(cli.parser.dump(cli.config, skip_none=False))
    return changed_settings(saved, current) if isinstance(saved, dict) and isinstance(current, dict) else []


def _quiet_run(run_dir: str | Path, name: str) -> Values:
    """No progress bar or model summary; logs and checkpoints under ``<run_dir>/<name>``."""
    return {
        "trainer.enable_progress_bar": False,
        "trainer.enable_model_summary": False,
        "trainer.logger.init_args.save_dir": str(run_dir),
        "trainer.logger.init_args.name": name,
        "trainer.default_root_dir": str(run_dir),
    }


@dataclass
class FitResult:
    """A finished ``fit``: the trained objects, the best checkpoint on :data:`SELECTION_METRIC` and the time.

    ``seconds`` is the training time of the whole run, a resumed one's earlier segments included
    (:class:`lcreg.callbacks.TrainingClock`); ``segment_seconds`` that of this call alone.
    """

    model: RegistrationModule
    datamodule: LightningDataModule
    trainer: Trainer
    best_checkpoint: Path
    seconds: float
    segment_seconds: float


def fit(
    name: str,
    values: Mapping[str, Any] | None = None,
    configs: Sequence[str | Path] = (),
    validate_first: bool = False,
    monitor: str = SELECTION_METRIC,
    resume: bool = False,
) -> FitResult:
    """Train method ``name`` as ``lcreg fit`` would (its configs, then ``values``, e.g. :func:`fit_overrides`).

    Args:
        name: Method of the registry.
        values: Values by dotted key applied after the configs (:data:`~lcreg.experiments.benchmarking.Values`).
        configs: Extra config files after the method's own (see
            :func:`~lcreg.experiments.benchmarking.building.method_layers`).
        validate_first: Validate the initial weights before training, so the run's ``metrics.csv`` starts with a
            step-0 validation row (learning curves start at the untrained model), and make those weights a candidate
            of the checkpoint selection and the early-stopping baseline
            (:func:`~lcreg.callbacks.validate_starting_weights`): a run that never beats its starting point selects it;
            the training draws the same random numbers as without it.
            Not repeated when resuming.
        monitor: The metric the checkpoint callback must select on (:data:`CONVERGE_METRIC` with
            :func:`converge_overrides`).
        resume: Continue from the run folder's ``last.ckpt`` when there is one (model, optimiser, scheduler,
            loops, early-stopping state, position in the training stream); the earlier ``metrics.csv`` is kept as
            ``metrics.segment<n>.csv``. Without one the run starts from scratch, and the metrics files of a lost run
            in the folder move to ``abandoned/<n>/`` (:func:`lcreg.resume.set_aside_metrics`).

    Raises:
        ValueError: If the config's checkpoint callback does not select on ``monitor``.
        lcreg.config.ConfigValueError: A malformed key or a value a constructor refuses (a ValueError too).
        RuntimeError: If training wrote no best checkpoint.
        SystemExit: Code :data:`TERMINATED_EXIT_CODE` when the run was stopped by SIGTERM (resumable).
    """
    from lcreg.callbacks import TrainingClock
    from lcreg.models.base import RegistrationModule
    from lcreg.resume import keep_previous_metrics, restore_unlogged_metrics, set_aside_metrics, set_aside_run

    cli = build_cli_for(name, configs, values)
    callback = cli.trainer.checkpoint_callback
    selected = getattr(callback, "monitor", None)
    if selected != monitor:
        raise ValueError(f"{name}: the checkpoint callback monitors {selected!r}, not {monitor}")
    if not isinstance(cli.model, RegistrationModule):  # pragma: no cover - the CLI only builds RegistrationModules
        raise TypeError(f"{name} built a {type(cli.model).__name__}, not a RegistrationModule")
    log_dir = Path(cli.trainer.log_dir or cli.trainer.default_root_dir)
    start = last_checkpoint(log_dir) if resume else None
    if start is not None and (changed := _changed_since_last_segment(cli, log_dir)):
        aside = set_aside_run(log_dir)
        print(
            f"{name}: the unfinished run in {log_dir} has other settings ({', '.join(changed)}): moved to {aside}; "
            "this run starts from scratch",
            flush=True,
        )
        start = None
    kept = None
    if start is not None:
        kept = keep_previous_metrics(log_dir)
    else:  # from scratch: a lost run's curve in this folder is not an earlier segment of this one
        set_aside_metrics(log_dir)
        if validate_first:
            validate_starting_weights(cli.trainer, cli.model, cli.datamodule)
    clock = next(c for c in getattr(cli.trainer, "callbacks", []) if isinstance(c, TrainingClock))  # LcregCLI's
    run = partial(cli.trainer.fit, cli.model, datamodule=cli.datamodule, ckpt_path=start)
    try:
        _, seconds = timed(run)
    except SystemExit as stop:  # Lightning's SIGTERMException is a SystemExit with code None: the process exits 0
        if stop.code not in (None, 0):
            raise
        raise SystemExit(TERMINATED_EXIT_CODE) from stop
    finally:
        restore_unlogged_metrics(kept, cli.trainer.loggers)
    best = getattr(callback, "best_model_path", "")
    if not best:
        raise RuntimeError(f"training {name} wrote no checkpoint (did validation run? see val_check_interval)")
    return FitResult(cli.model, cli.datamodule, cli.trainer, Path(best), clock.seconds(), seconds)
