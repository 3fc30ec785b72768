"""Training budgets of ``lcreg reproduce``: the ``smoke``, ``cpu``, ``converge`` and ``paper`` presets and the data.

A :class:`RunBudget` is what one run (one variant, one seed) gets: optimiser steps or epochs, points per cloud,
pairs per batch and how often it is validated. A budget with a ``patience`` is a *converge* budget: the run trains
until its validation error (:data:`lcreg.experiments.benchmarking.CONVERGE_METRIC`, the mean of min(RRE, 5°), on
``val_pairs`` pairs per validation object) has not improved for ``patience`` validations, capped by ``steps``, and
resumes from its ``last.ckpt`` when it was cut off. Each experiment maps every preset to a budget per *budget group*
(all DVDs variants share one; each LC host has its own, because their steps cost from 0.7 to 13 s on a CPU).
:class:`DataChoice` is the data every run of a sweep reads: ModelNet40 under ``root`` with the pair seed fixed (the
same validation and test pairs in every run), or, for ``smoke``, the tiny embedded synthetic shapes.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal

from lcreg.experiments.benchmarking import (
    CONVERGE_METRIC,
    SELECTION_METRIC,
    Values,
    cli_args,
    converge_overrides,
    epoch_overrides,
    fit_overrides,
    synthetic_overrides,
)

__all__ = [
    "CONVERGE_DCP",
    "CONVERGE_EPOCHS_OF_8",
    "CONVERGE_LK",
    "CONVERGE_PRNET",
    "CONVERGE_SMALL_BATCH",
    "DEFAULT_ROOT",
    "LR_KEY",
    "PAIR_SEED",
    "PRESETS",
    "SMOKE_PAIRS",
    "DataChoice",
    "Preset",
    "RunBudget",
]

Preset = Literal["smoke", "cpu", "converge", "paper"]
PRESETS: tuple[Preset, ...] = ("smoke", "cpu", "converge", "paper")
DEFAULT_ROOT = "../shared/data/modelnet40_mini"
"""ModelNet40 folder of ``configs/data/modelnet40.yaml`` (relative to the working directory, as there)."""
PAIR_SEED = 1234
"""Seed of the validation carve-out and of the deterministic validation and test pairs (every run, every seed)."""
SMOKE_PAIRS = 2
"""Validation and test pairs of a ``smoke`` run (embedded synthetic shapes)."""
LR_KEY = "model.init_args.optimizer.init_args.lr"
"""The config value :attr:`RunBudget.lr` sets."""


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
        patience: Converge budget: stop after this many validations without improvement (``steps`` is then the
            cap); ``None``: train the whole budget.
        val_pairs: Validation pairs per validation object (``val_pairs_per_object`` of the DataModule).
        metric: Converge budget: the validation metric it stops and selects on (``None``:
            :data:`~lcreg.experiments.benchmarking.CONVERGE_METRIC`).
        lr: The optimiser's learning rate (``model.init_args.optimizer.init_args.lr``; ``None``: the config's), for
            a budget whose batch is far below the method's own (e.g. the linear scaling rule, lr × batch / its batch).
    """

    steps: int | None = None
    epochs: int | None = None
    points: int | None = None
    batch: int | None = None
    checks: int = 4
    patience: int | None = None
    val_pairs: int = 1
    metric: str | None = None
    lr: float | None = None

    def __post_init__(self) -> None:
        if (self.steps is None) == (self.epochs is None):
            raise ValueError(f"a RunBudget needs exactly one of steps and epochs, got {self}")
        values = (self.steps, self.epochs, self.points, self.batch, self.checks, self.patience, self.val_pairs)
        if any(v is not None and v < 1 for v in values):
            raise ValueError(f"RunBudget values must be positive, got {self}")
        if self.patience is not None and self.steps is None:
            raise ValueError(f"a converge RunBudget (patience) needs a step cap, got {self}")
        if self.metric is not None and (self.patience is None or not self.metric.startswith("val/")):
            raise ValueError(f"`metric` is a validation metric (val/...) of a converge RunBudget, got {self}")
        if self.lr is not None and not (isinstance(self.lr, float) and 0 < self.lr < float("inf")):
            raise ValueError(f"`lr` is a positive finite float, got {self}")

    @property
    def converge(self) -> bool:
        """Whether the run stops when validation stops improving (and resumes from ``last.ckpt``)."""
        return self.patience is not None

    @property
    def monitor(self) -> str:
        """The validation metric the checkpoint (and early stopping) selects on."""
        if not self.converge:
            return SELECTION_METRIC
        return self.metric or CONVERGE_METRIC

    @property
    def val_every(self) -> int | None:
        """Steps between validations (``None`` for an epoch budget: after every epoch)."""
        return None if self.steps is None else max(1, self.steps // self.checks)

    def fit_overrides(self, run_dir: str | Path, seed: int) -> Values:
        """The ``lcreg fit`` values of this budget: steps or epochs, validation, logs under ``run_dir``, lr."""
        lr = {} if self.lr is None else {LR_KEY: self.lr}
        if self.steps is not None and self.patience is not None:
            values = converge_overrides(
                self.steps, self.val_every or 1, self.patience, run_dir, seed=seed, monitor=self.monitor
            )
        elif self.steps is not None:
            values = fit_overrides(self.steps, self.val_every or 1, run_dir, seed=seed)
        else:
            values = epoch_overrides(self.epochs or 1, run_dir, seed=seed)
        return {**values, **lr}

    def describe(self) -> str:
        """E.g. ``"80 steps × 16 pairs × 512 points, validated every 20 steps"``."""
        length = f"{self.steps} steps" if self.steps is not None else f"{self.epochs} epochs"
        batch = f"{self.batch} pairs" if self.batch else "the config's batch"
        points = f"{self.points} points" if self.points else "the config's points"
        checks = f"every {self.val_every} steps" if self.val_every else "after every epoch"
        text = f"{length} × {batch} × {points}, validated {checks}"
        if self.converge:
            gain = f"no gain in `{self.metric}`" if self.metric else "no gain"  # the default keeps older rows' keys
            text += f", until {self.patience} validations bring {gain} ({self.val_pairs} pairs per validation object)"
        return text if self.lr is None else f"{text}, lr {self.lr:g}"  # without lr: the older rows' keys


CONVERGE_LK = RunBudget(steps=3000, points=512, batch=16, checks=60, patience=6, val_pairs=4)
"""``converge`` for the IC-LK models (DVDs and its ablations, PointNetLK, FMR-Net, PCRNet): validated every 50 steps
on 312 pairs (``modelnet40_mini``), stopped after 300 steps without gain, capped at 3,000 steps (68 epochs of the
705 training objects). 512 points instead of the paper's 1024 (chosen before any test number was seen): half the
step cost on a CPU; identical for every variant, X and LC + X alike."""
CONVERGE_SMALL_BATCH = RunBudget(
    steps=3000, points=256, batch=8, checks=60, patience=12, val_pairs=4, metric="val/rre_median_deg"
)
"""``converge`` for DCP-v2 and PRNet (3.5 and 11 s per step at 256 points × 8 on one CPU thread; about 0.08 and
0.2 s on an H100). They stop and select on the validation median RRE after 12 validations (600 steps, 7 epochs of
705 objects) without gain: their errors sit near 5°, where the mean of min(RRE, 5°) hardly moves. With it and a
patience of 6, all six DCP-v2 runs of the first GPU session stopped at 450-1,250 steps while their validation
median RRE and recall (5°, 0.05) were still improving (``docs/results/converge/lc_dcp_prnet_converge/
stop_rule_clip5/``)."""
CONVERGE_PRNET = replace(CONVERGE_SMALL_BATCH, lr=2.2e-4)
"""``converge`` for PRNet: :data:`CONVERGE_SMALL_BATCH` with upstream's Adam lr scaled linearly to the batch (1e-3 ×
8 / 36 = 2.2e-4). At lr 1e-3 and batch 8 every PRNet run got worse after step 100-300 (one diverged); at 2.2e-4 three
seeds reached validation median RRE 1.68-1.91° by step 399 against 2.30-3.73° at 1e-3, on the same script and
validation pairs (``docs/results/converge/gpu_prnet_lr_256/``, H100; ``prnet_lr_256``, CPU). Decided on validation,
before any PRNet test number at this lr; X and LC + X alike."""
CONVERGE_DCP = replace(CONVERGE_SMALL_BATCH, lr=2.5e-4)
"""``converge`` for DCP-v2: :data:`CONVERGE_SMALL_BATCH` at lr 2.5e-4 (upstream's 1e-3 at batch 32, scaled linearly
to batch 8). Decided by the rule fixed before its runs (``benchmarks/train_queue.toml``, ``dcp_bf16_lr_256``): 3 seeds
at 2.5e-4 against 3 at 1e-3, all in bf16-mixed on the CPU, were better beyond the spread on both rotation figures
(test RMSE(R) 4.70 ± 0.66° against 5.90 ± 0.16°, MAE(R) 2.76 ± 0.40° against 3.64 ± 0.13°, 164 pairs;
``docs/results/converge/dcp_bf16_lr_seed2_256/lr_rule.md``). X and LC + X alike; the runs at 1e-3 keep their rows
under the old key."""
CONVERGE_EPOCHS_OF_8 = RunBudget(steps=5016, points=512, batch=8, checks=57, patience=8, val_pairs=4)
"""``converge`` for IDAM and DeepGMR (about 1 s per step at 512 × 8): validated once per epoch (88 steps of 8 pairs;
DeepGMR's ``ReduceLROnPlateau`` steps after each validation), at most 57 epochs, stopped after 8 epochs without
gain."""


@dataclass(frozen=True)
class DataChoice:
    """The data of every run of a sweep: ModelNet40 (``root``, ``protocol``) or the embedded synthetic shapes.

    Attributes:
        root: ModelNet40 folder (official ``modelnet40_ply_hdf5_2048`` layout); ``None``: embedded synthetic shapes.
        protocol: ``"unseen_objects"`` (train and test on the first 20 categories) or ``"unseen_categories"``.
        workers: DataLoader workers (``None``: the config's); 0 on a 2-core CPU, where a loader process only
            competes with training.
        partial: ``"none"`` (full clouds) or a crop of every cloud (training, validation and test):
            ``"prnet"`` (PRNet's and IDAM's shared far anchor) or ``"viewpoint"``
            (:class:`~lcreg.data.datamodule.PairDataModule`).
        partial_keep: Points a crop keeps: a fraction of the budget's points (PRNet and IDAM keep 0.75: 768 of
            1024) or a count.
        train_objects: Train on a seeded subset of the training objects: a count or a fraction of them
            (``PairDataModule``'s ``train_objects``); ``None``: all. Validation and test pairs stay the same.
    """

    root: str | None
    protocol: str = "unseen_objects"
    workers: int | None = 0
    partial: str = "none"
    partial_keep: int | float = 0.75
    train_objects: int | float | None = None

    def overrides(self, budget: RunBudget) -> Values:
        """Data values of a run: the budget's points and batch, the fixed pair seed, the loader workers."""
        shared = {
            **cli_args("data", {"val_pairs_per_object": budget.val_pairs if budget.val_pairs > 1 else None}),
            **self._crop(),
            **cli_args("data", {"train_objects": self.train_objects}),
        }
        if self.root is None:
            return {**synthetic_overrides(SMOKE_PAIRS, budget.points or 128, budget.batch or 2), **shared}
        values = {"root": self.root, "protocol": self.protocol, "seed": PAIR_SEED, "num_workers": self.workers}
        return {**cli_args("data", {**values, "num_points": budget.points, "batch_size": budget.batch}), **shared}

    def _crop(self) -> Values:
        """The crop's data values (none for full clouds, so their runs keep the configs' values)."""
        if self.partial == "none":
            return {}
        return cli_args("data", {"partial": self.partial, "partial_keep": self.partial_keep})

    def describe(self) -> str:
        """One line for tables and the JSONL key (full clouds: the same line as before crops existed)."""
        crop = "" if self.partial == "none" else f", partial: {self.partial} crop keeping {self.partial_keep:g}"
        subset = "" if self.train_objects is None else f", training objects: {self.train_objects:g}"
        if self.root is None:
            shapes = f"embedded synthetic shapes ({SMOKE_PAIRS} validation and test pairs; smoke: numbers mean nothing)"
            return shapes + crop + subset
        return f"ModelNet40 {self.root}, {self.protocol.replace('_', ' ')}{crop}{subset}"
