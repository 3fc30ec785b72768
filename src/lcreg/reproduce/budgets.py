"""Training budgets of ``lcreg reproduce``: the ``smoke``, ``cpu`` and ``paper`` presets and the data of a sweep.

A :class:`RunBudget` is what one run (one variant, one seed) gets: optimiser steps or epochs, points per cloud,
pairs per batch and how often it is validated. Each experiment maps every preset to a budget per *budget group*
(all DVDs variants share one; each LC host has its own, because their steps cost from 0.7 to 13 s on a CPU).
:class:`DataChoice` is the data every run of a sweep reads: ModelNet40 under ``root`` with the pair seed fixed (the
same validation and test pairs in every run), or, for ``smoke``, the tiny embedded synthetic shapes.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from lcreg.benchmarking import cli_args, epoch_overrides, fit_overrides, synthetic_overrides

__all__ = ["DEFAULT_ROOT", "PAIR_SEED", "PRESETS", "SMOKE_PAIRS", "DataChoice", "Preset", "RunBudget"]

Preset = Literal["smoke", "cpu", "paper"]
PRESETS: tuple[Preset, ...] = ("smoke", "cpu", "paper")
DEFAULT_ROOT = "../shared/data/modelnet40_mini"
"""ModelNet40 folder of ``configs/data/modelnet40.yaml`` (relative to the working directory, as there)."""
PAIR_SEED = 1234
"""Seed of the validation carve-out and of the deterministic validation and test pairs (every run, every seed)."""
SMOKE_PAIRS = 2
"""Validation and test pairs of a ``smoke`` run (embedded synthetic shapes)."""


@dataclass(frozen=True)
class RunBudget:
    """The training budget of one run.

    Attributes:
        steps: Optimiser steps (``None``: an epoch budget).
        epochs: Training epochs (``None``: a step budget); exactly one of the two is set.
        points: Points per cloud (``None``: the config's).
        batch: Pairs per batch (``None``: the config's, i.e. the original method's).
        checks: Validations per step-budgeted run (every ``steps // checks`` steps); epoch budgets validate after
            every epoch.
    """

    steps: int | None = None
    epochs: int | None = None
    points: int | None = None
    batch: int | None = None
    checks: int = 4

    def __post_init__(self) -> None:
        if (self.steps is None) == (self.epochs is None):
            raise ValueError(f"a RunBudget needs exactly one of steps and epochs, got {self}")
        if any(v is not None and v < 1 for v in (self.steps, self.epochs, self.points, self.batch, self.checks)):
            raise ValueError(f"RunBudget values must be positive, got {self}")

    @property
    def val_every(self) -> int | None:
        """Steps between validations (``None`` for an epoch budget: after every epoch)."""
        return None if self.steps is None else max(1, self.steps // self.checks)

    def fit_overrides(self, run_dir: str | Path, seed: int) -> list[str]:
        """The ``lcreg fit`` arguments of this budget: steps or epochs, validation, logs under ``run_dir``."""
        if self.steps is not None:
            return fit_overrides(self.steps, self.val_every or 1, run_dir, seed=seed)
        return epoch_overrides(self.epochs or 1, run_dir, seed=seed)

    def describe(self) -> str:
        """E.g. ``"80 steps × 16 pairs × 512 points, validated every 20 steps"``."""
        length = f"{self.steps} steps" if self.steps is not None else f"{self.epochs} epochs"
        batch = f"{self.batch} pairs" if self.batch else "the config's batch"
        points = f"{self.points} points" if self.points else "the config's points"
        checks = f"every {self.val_every} steps" if self.val_every else "after every epoch"
        return f"{length} × {batch} × {points}, validated {checks}"


@dataclass(frozen=True)
class DataChoice:
    """The data of every run of a sweep: ModelNet40 (``root``, ``protocol``) or the embedded synthetic shapes.

    Attributes:
        root: ModelNet40 folder (official ``modelnet40_ply_hdf5_2048`` layout); ``None``: embedded synthetic shapes.
        protocol: ``"unseen_objects"`` (train and test on the first 20 categories) or ``"unseen_categories"``.
        workers: DataLoader workers (``None``: the config's); 0 on a 2-core CPU, where a loader process only
            competes with training.
    """

    root: str | None
    protocol: str = "unseen_objects"
    workers: int | None = 0

    def overrides(self, budget: RunBudget) -> list[str]:
        """Data arguments of a run: the budget's points and batch, the fixed pair seed, the loader workers."""
        if self.root is None:
            return synthetic_overrides(SMOKE_PAIRS, budget.points or 128, budget.batch or 2)
        values = {"root": self.root, "protocol": self.protocol, "seed": PAIR_SEED, "num_workers": self.workers}
        return cli_args("data", {**values, "num_points": budget.points, "batch_size": budget.batch})

    def describe(self) -> str:
        """One line for tables and the JSONL key."""
        if self.root is None:
            return f"embedded synthetic shapes ({SMOKE_PAIRS} validation and test pairs; smoke: numbers mean nothing)"
        return f"ModelNet40 {self.root}, {self.protocol.replace('_', ' ')}"
