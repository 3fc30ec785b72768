"""Evaluation experiments of ``lcreg reproduce`` (``robustness``, ``recall-curves``): trained models × test conditions.

Two stages, both resumable:

1. **Models.** Every learned method of the experiment is trained once per seed by :func:`run_sweep` (the shared
   ``models`` experiment: clean, complete clouds of the first 20 ModelNet40 categories, as the paper's figures; the
   checkpoint with the lowest ``val/rre_mean_deg`` is kept, never chosen on test). Rows go to ``<out>/models.jsonl``;
   ``robustness`` and ``recall-curves`` share it, so the second experiment run into the same ``--out`` reuses the
   first one's weights (same budget, same data).
2. **Conditions.** Each :class:`Condition` (a noise level, a crop, a protocol, a scene dataset) makes its test pairs
   once; every method registers the same pairs (:func:`lcreg.experiments.evaluation.evaluate`): learned methods with
   each seed's selected weights, classical methods once (they have no weights; their row has ``seed`` ``None``). One
   JSONL row per (method, seed, condition) holds the per-pair rotation and translation errors, so any recall or curve
   can be computed from the file; a rerun skips the rows already there.
"""

from __future__ import annotations

import fnmatch
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, TypeVar, cast

import torch

from lcreg.experiments.benchmarking import (
    METHODS,
    ResultLog,
    build,
    data_config,
    format_mean_std,
    machine_line,
    markdown_table,
    pair_batches,
    split_batches,
    synthetic_overrides,
    training_device,
)
from lcreg.experiments.evaluation import evaluate
from lcreg.experiments.reproduce.budgets import PAIR_SEED, DataChoice, Preset, RunBudget
from lcreg.experiments.reproduce.spec import Experiment, Variant
from lcreg.experiments.reproduce.sweep import PresetRun, Sweep, finished_rows, run_sweep
from lcreg.metrics.functional import registration_recall
from lcreg.models.base import RegistrationModule
from lcreg.types import RegistrationBatch

__all__ = [
    "KEY_FIELDS",
    "MODELS_STEM",
    "Condition",
    "EvalBudget",
    "EvalExperiment",
    "EvalRun",
    "method_label",
    "percent_cell",
    "recall_of",
    "report_header",
    "run_conditions",
    "seed_values",
]

KEY_FIELDS = ("experiment", "method", "seed", "condition", "budget", "data")
"""Fields that identify an evaluation row: a row with the same values is skipped on a rerun."""
T = TypeVar("T")
MODELS_STEM = "models"
"""Stem of the shared training log ``<out>/models.jsonl``."""
TRAIN_PROTOCOL = "unseen_categories"
"""Protocol named in the training key (the training pool, the first 20 categories, is the same for both)."""


@dataclass(frozen=True)
class Condition:
    """One set of test pairs.

    Attributes:
        key: Name in the JSONL and in tables (``"noise/0.02"``).
        panel: The figure panel or table block it belongs to (``"noise"``).
        x: Its value on the panel's x axis (noise sigma, kept fraction; 0 for categorical panels).
        label: Column heading.
        dataset: ``"modelnet40"``, or a scene data add-on of :data:`lcreg.experiments.benchmarking.DATA_CONFIGS`
            (``"sevenscenes"``, ``"kitti"``), whose DataModule makes the pairs.
        options: ModelNet40: :class:`~lcreg.data.datamodule.PairDataModule` options (``noise_sigma``, ``partial``,
            ``protocol``...). Scenes: values by dotted key over the data add-on (``{"data.init_args.x": y}``).
        methods: The methods evaluated here (``None``: every method of the experiment; scenes name the learned
            methods and their own classical pipeline, because the object-scale classical configs do not fit metres).
    """

    key: str
    panel: str
    x: float
    label: str
    dataset: str = "modelnet40"
    options: Mapping[str, Any] = field(default_factory=dict)
    methods: tuple[str, ...] | None = None


@dataclass(frozen=True)
class EvalBudget:
    """What one preset trains and evaluates.

    Attributes:
        train: Budget of each learned method (by registry name; ``"*"``: the default).
        points: Points per ModelNet40 test cloud.
        pairs: Test pairs per ModelNet40 condition (``None``: every pair of the protocol's test set).
        scene_pairs: Test pairs per scene condition (``None``: all).
    """

    train: Mapping[str, RunBudget]
    points: int
    pairs: int | None = None
    scene_pairs: int | None = None

    def for_method(self, name: str) -> RunBudget:
        """The training budget of ``name``."""
        return self.train.get(name) or self.train["*"]

    def describe(self) -> str:
        """One line for the JSONL key and the report."""
        pairs = "all" if self.pairs is None else str(self.pairs)
        scenes = "all" if self.scene_pairs is None else str(self.scene_pairs)
        return f"{self.points} points, {pairs} ModelNet40 pairs and {scenes} scene pairs per condition"


@dataclass(frozen=True)
class EvalExperiment:
    """An evaluation experiment: methods, conditions, budgets, and how the report and figure are drawn.

    Attributes:
        name: Command-line name and stem of the output files.
        title: Heading of the report.
        paper_figure: The paper's figure reproduced.
        methods: Registry names (learned and classical), in legend order.
        conditions: The test conditions, in panel and x order.
        panels: Panel key -> x-axis title.
        budgets: Preset -> budget.
        notes: How the experiment differs from the paper.
    """

    name: str
    title: str
    paper_figure: str
    methods: tuple[str, ...]
    conditions: tuple[Condition, ...]
    panels: Mapping[str, str]
    budgets: Mapping[Preset, EvalBudget]
    notes: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if unknown := [m for m in self.methods if m not in METHODS]:
            raise ValueError(f"{self.name}: methods not in the registry: {unknown}")
        for cond in self.conditions:
            if cond.panel not in self.panels:
                raise ValueError(f"{self.name}: condition {cond.key} has no panel {cond.panel!r}")
            if cond.methods and (extra := set(cond.methods) - set(self.methods)):
                raise ValueError(f"{self.name}: condition {cond.key} names methods outside the list: {sorted(extra)}")

    def learned(self) -> tuple[str, ...]:
        """The methods that are trained."""
        return tuple(m for m in self.methods if METHODS[m].learned)

    def methods_of(self, condition: Condition) -> tuple[str, ...]:
        """The methods evaluated on ``condition``, in legend order."""
        return tuple(m for m in self.methods if condition.methods is None or m in condition.methods)

    def select(self, patterns: Sequence[str]) -> EvalExperiment:
        """Only the methods matching a pattern (``fnmatch``; none: all).

        Raises:
            ValueError: If a pattern matches no method.
        """
        if not patterns:
            return self
        for pattern in patterns:
            if not fnmatch.filter(self.methods, pattern):
                known = ", ".join(self.methods)
                raise ValueError(f"--only {pattern!r} matches no method of {self.name}; known: {known}")
        kept = tuple(m for m in self.methods if any(fnmatch.fnmatchcase(m, p) for p in patterns))
        return replace(self, methods=kept)


@dataclass(frozen=True)
class EvalRun(PresetRun):
    """An evaluation experiment under one preset, seeds and data, writing ``<out>/<stem>.{md,jsonl,png}``."""

    experiment: EvalExperiment

    @property
    def budget(self) -> EvalBudget:
        """The preset's budget."""
        return cast(EvalBudget, self.experiment.budgets[self.preset])

    def models(self) -> Sweep:
        """The training sweep of the learned methods (``<out>/models.jsonl``, shared by the experiments)."""
        variants = tuple(Variant(m, m, m) for m in self.experiment.learned())
        budgets = {self.preset: {m: self.budget.for_method(m) for m in self.experiment.learned()}}
        spec = Experiment("models", "Trained models", "", {}, variants, (), (), budgets, {})
        data = DataChoice(self.data.root, TRAIN_PROTOCOL, self.data.workers)
        return Sweep(spec, self.preset, self.seeds, data, self.out, MODELS_STEM)

    def key(self, method: str, seed: int | None, condition: Condition) -> dict[str, Any]:
        """The :data:`KEY_FIELDS` of an evaluation row."""
        return {
            "experiment": self.experiment.name,
            "method": method,
            "seed": seed,
            "condition": condition.key,
            "budget": self.budget.describe(),
            "data": self.data.describe(),
        }

    def open_log(self) -> ResultLog:
        """The evaluation JSONL."""
        return ResultLog(self.log_path, KEY_FIELDS)

    def seeds_of(self, method: str) -> tuple[int | None, ...]:
        """The seeds a method is evaluated with (classical methods: once, ``None``)."""
        return self.seeds if METHODS[method].learned else (None,)


def _modelnet_batches(run: EvalRun, condition: Condition) -> list[RegistrationBatch]:
    """The test pairs of a ModelNet40 condition (synthetic shapes under ``smoke``), deterministic."""
    options = {k: v for k, v in condition.options.items() if k != "protocol"}
    protocol = condition.options.get("protocol", "unseen_categories")
    if run.data.root is None:  # smoke: the embedded shapes (no protocol)
        batches, _ = pair_batches(None, "test", run.budget.pairs, run.budget.points, 8, seed=PAIR_SEED, **options)
    else:
        batches, _ = pair_batches(
            run.data.root, "test", run.budget.pairs, run.budget.points, 8, protocol, seed=PAIR_SEED, **options
        )
    return batches


def _scene_batches(run: EvalRun, condition: Condition) -> list[RegistrationBatch]:
    """The test pairs of a scene condition: its data add-on's DataModule (synthetic shapes under ``smoke``)."""
    if run.data.root is None:
        configs, values = [], synthetic_overrides(2, 64, 1)
    else:
        configs, values = [data_config(condition.dataset)], dict(condition.options)
    _, datamodule = build("icp", None, configs, values, with_data=True)
    batches = split_batches(datamodule, "test")
    return batches if run.budget.scene_pairs is None else batches[: run.budget.scene_pairs]


def condition_batches(run: EvalRun, condition: Condition) -> list[RegistrationBatch]:
    """The test pairs of ``condition`` (the same for every method and seed)."""
    if condition.dataset == "modelnet40":
        return _modelnet_batches(run, condition)
    return _scene_batches(run, condition)


def _model(name: str, weights: str | None) -> RegistrationModule:
    return build(name, weights)


def _row_fields(report: Any, weights: str | None) -> dict[str, Any]:
    rre = [round(float(v), 5) for v in report.rotation_error_deg.reshape(-1)]
    rte = [round(float(v), 6) for v in report.translation_error.reshape(-1)]
    return {
        "label": report.name,
        "weights": weights,
        "pairs": report.num_pairs,
        "ms_per_pair": round(report.ms_per_pair, 2),
        "rre_deg": rre,
        "rte": rte,
    }


def _weights_of(run: EvalRun, method: str, seed: int | None) -> tuple[bool, str | None]:
    """(available, path) of a method's weights for ``seed`` (classical: no weights needed)."""
    if seed is None:
        return True, None
    sweep = run.models()
    rows = finished_rows(sweep, sweep.open_log()).get(method, [])
    row = next((r for r in rows if r.get("seed") == seed), None)
    return (row is not None, None if row is None else str(row["weights"]))


def run_conditions(
    run: EvalRun,
    progress: Callable[[str], None] = lambda _: None,
    rerun: bool = False,
    train: Callable[..., dict[str, Any]] | None = None,
) -> ResultLog:
    """Train what is missing (stage 1), then evaluate every unfinished (method, seed, condition) (stage 2).

    Args:
        run: What to run.
        progress: Called with one line per training run and per evaluated (method, seed, condition).
        rerun: Train and evaluate finished runs again too (the newest row counts).
        train: The training run (``None``: :func:`lcreg.experiments.reproduce.sweep.train_and_test`; tests pass a fake).

    Returns:
        The evaluation log.
    """
    if run.experiment.learned():
        run_sweep(run.models(), train=train, progress=progress, rerun=rerun)
    log = run.open_log()
    batches: dict[str, list[RegistrationBatch]] = {}
    for seed in (None, *run.seeds):  # classical methods first, then seed by seed: partial results are useful
        for method in run.experiment.methods:
            if seed not in run.seeds_of(method):
                continue
            todo = [
                c
                for c in run.experiment.conditions
                if method in run.experiment.methods_of(c) and (rerun or not log.done(**run.key(method, seed, c)))
            ]
            if not todo:
                continue
            available, weights = _weights_of(run, method, seed)
            if not available:
                progress(f"{method} seed {seed}: no trained weights (its training failed), not evaluated")
                continue
            model = _model(method, weights)
            for condition in todo:
                if condition.key not in batches:
                    batches[condition.key] = condition_batches(run, condition)
                torch.manual_seed(0)
                report = evaluate(model, batches[condition.key], METHODS[method].label)
                key = run.key(method, seed, condition)
                row = log.append({**key, "preset": run.preset, **_row_fields(report, weights)})
                recall = 100 * recall_of(row, 2.0, 0.01)
                progress(f"{method} seed {seed} {condition.key}: recall (2°, 0.01) {recall:.1f} %")
    return log


def recall_of(row: Mapping[str, Any], rot_deg: float, trans: float | None) -> float:
    """Fraction of the row's pairs with RRE < ``rot_deg`` (and RTE < ``trans`` unless ``None``)."""
    rre = torch.tensor(row["rre_deg"], dtype=torch.float64)
    if not len(rre):
        return float("nan")
    rte = torch.tensor(row["rte"], dtype=torch.float64) if trans is not None else torch.zeros_like(rre)
    return float(registration_recall(rre, rte, rot_deg, trans if trans is not None else 1.0))


def seed_values(
    run: EvalRun, log: ResultLog, method: str, condition: Condition, value: Callable[[Mapping[str, Any]], T]
) -> list[T]:
    """``value(row)`` for every finished seed of (``method``, ``condition``) in ``log``."""
    rows = [log.find(**run.key(method, seed, condition)) for seed in run.seeds_of(method)]
    return [value(r) for r in rows if r is not None]


def method_label(run: EvalRun, log: ResultLog, method: str, conditions: Sequence[Condition]) -> str:
    """The method's label, with ``" (k of n seeds)"`` when some of its seeds are not evaluated on ``conditions``."""
    expected = len(run.seeds_of(method))
    done = min((len(seed_values(run, log, method, c, lambda r: 0)) for c in conditions), default=expected)
    label = METHODS[method].label
    return label if done == expected else f"{label} ({done} of {expected} seeds)"


def percent_cell(values: Sequence[float]) -> str:
    """``"mean ± std"`` of fractions in percent (one seed: the value; none: ``"-"``)."""
    if not values:
        return "-"
    return format_mean_std([100 * v for v in values], ".1f", ".1f")


def report_header(run: EvalRun, command: str) -> list[str]:
    """Title, command, machine, data, budgets and the trained models (selected checkpoints) of a report."""
    exp, budget = run.experiment, run.budget
    lines = [
        f"# {exp.title}",
        "",
        f"Reproduces the paper's {exp.paper_figure}. The paper gives it only as a figure (no numbers in the LaTeX), "
        "so there is no paper column or ratio here: compare the shapes of the curves.",
        "",
        f"- Command: `{command}`",
        f"- Machine: {machine_line(training_device())}",
        f"- Preset `{run.preset}`: {budget.describe()}; seeds {', '.join(map(str, run.seeds))} (learned methods; "
        "classical methods have no weights and run once); cells are mean ± sample std over seeds.",
        f"- Data: {run.data.describe()}; pair seed {PAIR_SEED} (every method registers the same pairs).",
    ]
    learned = exp.learned()
    if learned:
        lines += ["", "## Trained models (`models.jsonl`, shared by the evaluation experiments)", ""]
        sweep = run.models()
        rows = finished_rows(sweep, sweep.open_log())
        table = []
        for name in learned:
            runs = rows.get(name, [])
            val = [float(r["best_val_rre_mean_deg"]) for r in runs if r.get("best_val_rre_mean_deg") is not None]
            train_s = [float(r["train_s"]) for r in runs]
            table.append(
                [
                    METHODS[name].label,
                    f"`{' '.join(METHODS[name].configs)}`",
                    budget.for_method(name).describe(),
                    len(runs),
                    format_mean_std(val, ".2f", ".2f") if val else "-",
                    format_mean_std(train_s, ".0f", ".0f") if train_s else "-",
                ]
            )
        header = ["method", "configs", "budget", "seeds trained", "val mean RRE ° (selected)", "train s"]
        lines.append(markdown_table(header, table))
    return lines
