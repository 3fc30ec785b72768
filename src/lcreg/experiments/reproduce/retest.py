"""Test a sweep's kept weights again under another precision, or on other test pairs, without training.

``lcreg reproduce <experiment> ... --retest 32-true``: every finished run of the sweep (its JSONL row) is tested again
from the weights it kept (``row["weights"]``, or the longest tail of that path under ``--out``: a copy of the output
folder made elsewhere, :func:`~lcreg.experiments.reproduce.stops.recorded_file`), with the run's own data, sizes and
config values, under ``trainer.precision`` = the asked precision. It answers what a run's test figure owes to the
precision it was tested in: a run trained under ``bf16-mixed`` is tested under it too, and bfloat16 inference alone
moves per-pair errors (``docs/results/bench_precision.md``). The rows go to ``<stem>.retest-<precision>.jsonl`` (a
rerun skips the runs found there), the table of both tests side by side to ``<stem>.retest-<precision>.md``, each
test's logs and per-pair errors to ``<run folder>/retest-<precision>/``; the sweep's own JSONL, report and run logs
are not changed.

``--retest-data KEY=VALUE`` (:data:`RETEST_DATA`) changes a data value of the test only, so that the same weights are
tested on other pairs: ``protocol=unseen_categories`` tests a model trained on labels 0-19 on labels 20-39 (both
ModelNet40 protocols train and validate on the same objects, :func:`lcreg.data.modelnet40.modelnet40_objects`, so the
selection stays valid), ``noise_sigma=0`` on clean clouds. Its outputs carry the values in their tag
(:attr:`Retest.tag`: ``<stem>.retest-32-true-protocol-unseen_categories.jsonl``, ``<run folder>/retest-32-true-...``).
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any, get_args

from lcreg.data.modelnet40 import Protocol
from lcreg.experiments.benchmarking import (
    REPORT_COLUMNS,
    ResultLog,
    build_cli_for,
    cli_args,
    format_mean_std,
    machine_line,
    markdown_table,
    timed,
    training_device,
)
from lcreg.experiments.reproduce.budgets import DataChoice, RunBudget
from lcreg.experiments.reproduce.stops import recorded_file
from lcreg.experiments.reproduce.sweep import KEY_FIELDS, METRICS, Sweep, finished_rows, run_values
from lcreg.models.batchnorm import recompute_batchnorm_statistics
from lcreg.weights import load_into

__all__ = [
    "PRECISIONS",
    "RETEST_DATA",
    "MissingWeightsError",
    "NoFinishedRunsError",
    "Retest",
    "check_retest_data",
    "is_retest_output",
    "render_retest",
    "retest_path",
    "retest_sweep",
    "retest_weights",
    "trained_precision",
]

PRECISIONS = ("32-true", "bf16-mixed")
"""Precisions ``--retest`` takes (Lightning's ``trainer.precision`` values that every model runs in)."""
DEFAULT_PRECISION = "32-true"
"""The precision of a run whose config values set none (Lightning's default; the shipped configs set none)."""
RETEST_TAG = "retest-"
"""Marks a retest's outputs: ``<stem>.retest-<precision>.{jsonl,md}`` and ``<run folder>/retest-<precision>/``."""
RETEST_DATA = ("protocol", "noise_sigma", "noise_clip")
"""Data values ``--retest-data`` may change: each chooses the test pairs only, not what a run trained or selected on."""
PROTOCOLS: tuple[str, ...] = get_args(Protocol)
TABLE_METRICS = ("rmse_r_deg", "mae_r_deg", "rmse_t", "mae_t")
"""The figures the table sets side by side (the LC table's; every other metric is in the JSONL)."""


class MissingWeightsError(FileNotFoundError):
    """A finished run's kept weights are neither where its row says nor under the output folder."""


class NoFinishedRunsError(LookupError):
    """The sweep the options describe has no finished run in its JSONL: nothing to test again."""


@dataclass(frozen=True)
class Retest:
    """What a retest changes: the precision, and data values of its test (:data:`RETEST_DATA`, in the given order).

    Attributes:
        precision: Lightning's ``trainer.precision`` of the test (one of :data:`PRECISIONS`).
        data: ``(key, value)`` pairs of the data module's arguments that replace the run's for its test only.
        precise_bn: Before the test, recompute the BatchNorm running statistics over this many training batches
            (:func:`lcreg.models.batchnorm.recompute_batchnorm_statistics`); 0: the kept statistics.
    """

    precision: str
    data: tuple[tuple[str, Any], ...] = ()
    precise_bn: int = 0

    @property
    def tag(self) -> str:
        """``retest-<precision>[-<key>-<value>...][-precise_bn-<n>]``: each run's retest folder, the files' suffix."""
        parts = [f"{RETEST_TAG}{self.precision}", *(f"{key}-{_slug(value)}" for key, value in self.data)]
        return "-".join(parts + ([f"precise_bn-{self.precise_bn}"] if self.precise_bn else []))

    @property
    def label(self) -> str:
        """The precision and data values, as the report names them: ``32-true, protocol=unseen_categories``."""
        parts = [self.precision, *(f"{key}={value}" for key, value in self.data)]
        return ", ".join(parts + ([f"precise BatchNorm over {self.precise_bn} batches"] if self.precise_bn else []))


def check_retest_data(key: str, value: Any) -> Any:
    """A ``--retest-data`` value checked for its key: a protocol name, or a finite noise figure >= 0.

    Raises:
        ValueError: A key outside :data:`RETEST_DATA`, or a value it cannot take (the message names both).
    """
    if key not in RETEST_DATA:
        raise ValueError(f"{key!r} is not one of {', '.join(RETEST_DATA)} (values that choose only the test pairs)")
    if key == "protocol":
        if value not in PROTOCOLS:
            raise ValueError(f"protocol must be one of {', '.join(PROTOCOLS)}, got {value!r}")
        return value
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value) or value < 0:
        raise ValueError(f"{key} must be a finite number >= 0, got {value!r}")
    return value


def _slug(value: Any) -> str:
    """``value`` as a file-name part: letters, digits, ``.`` and ``_``."""
    return re.sub(r"[^A-Za-z0-9._]", "_", str(value))


def trained_precision(row: Mapping[str, Any]) -> str:
    """The ``trainer.precision`` a run trained and was tested under: its ``--set`` value, else the default."""
    return str((row.get("overrides") or {}).get("trainer.precision", DEFAULT_PRECISION))


def retest_weights(
    name: str,
    budget: RunBudget,
    data: DataChoice,
    seed: int,
    overrides: Mapping[str, Any],
    weights: str | Path,
    precision: str,
    log_dir: str | Path,
    test_data: Mapping[str, Any] | None = None,
    precise_bn: int = 0,
) -> dict[str, float]:
    """Test ``weights`` of method ``name`` on the run's test pairs under ``precision``, without training.

    Args:
        name: Registry name of the method.
        budget: The run's budget (sizes, validation pairs: the data module is built as the run's was).
        data: The run's data.
        seed: The run's ``seed_everything``.
        overrides: The run's config values (:meth:`Sweep.overrides`); ``trainer.precision`` is replaced.
        weights: The kept weights (:func:`lcreg.weights.export.save`'s format).
        precision: Lightning's ``trainer.precision`` of the test.
        log_dir: Where the test writes its logs (its per-pair errors, ``test_per_pair.csv``, among them).
        test_data: Data module arguments that replace the run's for this test (:data:`RETEST_DATA`).
        precise_bn: Recompute the BatchNorm running statistics over this many batches of the run's training data
            before the test (0: keep the kept ones).

    Returns:
        The test metrics of :data:`~lcreg.experiments.reproduce.sweep.METRICS` (degrees; translations in the data's
        units).
    """
    values = {**run_values(budget, data, Path(log_dir), seed, overrides), "trainer.precision": precision}
    values.update(cli_args("data", dict(test_data or {})))
    cli = build_cli_for(name, (), values)
    load_into(cli.model, weights)
    if precise_bn:
        cli.datamodule.setup("fit")
        recompute_batchnorm_statistics(cli.model, cli.datamodule.train_dataloader(), precise_bn)
    (tested,) = cli.trainer.test(cli.model, datamodule=cli.datamodule, verbose=False)
    return {key: float(tested[f"test/{key}"]) for key in METRICS}


def retest_sweep(sweep: Sweep, retest: Retest, progress: Callable[[str], None] = lambda _: None) -> ResultLog:
    """Test every finished run of ``sweep`` again from its kept weights as ``retest`` says, one row per run.

    Args:
        sweep: The sweep whose JSONL lists the finished runs.
        retest: The precision of the new tests and the data values they change.
        progress: Called with one line per run.

    Returns:
        The log ``<stem>.<retest.tag>.jsonl`` (runs found there are skipped).

    Raises:
        MissingWeightsError: A run's weights are not found; names the file its row records. Runs retested before it
            are kept in the log.
        NoFinishedRunsError: No finished run matches the sweep (its options must repeat the training command's).
    """
    log = ResultLog(retest_path(sweep, retest, ".jsonl"), KEY_FIELDS)
    variants = {variant.key: variant for variant in sweep.experiment.variants}
    finished = finished_rows(sweep, sweep.open_log())
    if not any(finished.values()):
        raise NoFinishedRunsError(_none_finished(sweep))
    for key, rows in finished.items():
        variant = variants[key]
        for row in rows:
            fields = {field: row[field] for field in KEY_FIELDS}
            if log.done(**fields):
                progress(f"{key} seed {row['seed']}: retested before, skipped")
                continue
            weights = recorded_file(row, "weights", sweep.out)
            if weights is None:
                place = sweep.run_dir(variant, int(row["seed"])) / "selected_weights.pt"
                raise MissingWeightsError(
                    f"{key} seed {row['seed']}: its kept weights {row.get('weights')!r} are not there, nor under "
                    f"{sweep.out}; copy them to {place} (the training queue keeps them as "
                    "<job>/best/<variant>-seed<k>.pt)"
                )
            budget = sweep.experiment.budget(sweep.preset, variant)
            seed, overrides = int(row["seed"]), sweep.overrides(variant)
            log_dir = sweep.run_dir(variant, seed) / retest.tag
            test_data = dict(retest.data)
            args = (variant.method, budget, sweep.data, seed, overrides, weights, retest.precision, log_dir)
            metrics, seconds = timed(partial(retest_weights, *args, test_data, retest.precise_bn))
            log.append(
                {
                    **fields,
                    "precision": retest.precision,
                    **({"test_data": test_data} if test_data else {}),
                    **({"precise_bn_batches": retest.precise_bn} if retest.precise_bn else {}),
                    "trained_precision": trained_precision(row),
                    "weights": str(weights),
                    "test_s": round(seconds, 1),
                    "machine": machine_line(training_device()),
                    **metrics,
                }
            )
            progress(f"{key} seed {row['seed']}: RMSE(R) {row['rmse_r_deg']:.3f}° -> {metrics['rmse_r_deg']:.3f}°")
    return log


def _none_finished(sweep: Sweep) -> str:
    """Why a retest has nothing to test: no JSONL, or rows of other runs only (a flag that differs from training's)."""
    if not sweep.log_path.is_file():
        return f"--retest: no finished runs to test: {sweep.log_path} does not exist"
    rows = len([line for line in sweep.log_path.read_text().splitlines() if line.strip()])
    return (
        f"--retest: none of the {rows} rows of {sweep.log_path} is a finished run of these variants and seeds with "
        "these options: repeat the training command's options (--budget, --only, --seeds, --partial, --points, "
        "--set, ...) and add --retest"
    )


def retest_path(sweep: Sweep, retest: Retest, suffix: str) -> Path:
    """``<out>/<stem>.<retest.tag><suffix>``."""
    return sweep.file_stem.with_name(f"{sweep.file_stem.name}.{retest.tag}{suffix}")


def is_retest_output(path: str | Path) -> bool:
    """Whether ``path`` was written by a retest: not a run's log or training row.

    A retest writes its JSONL and report beside the sweep's and its tests' logs in each run's ``retest-*`` folder;
    tools that walk an output folder for runs (the training queue) leave these out.
    """
    path = Path(path)
    return f".{RETEST_TAG}" in path.name or any(part.startswith(RETEST_TAG) for part in path.parts[:-1])


def render_retest(sweep: Sweep, log: ResultLog, retest: Retest, command: str) -> str:
    """Markdown: each retested run's test as it ran beside its new test, then the means per variant."""
    labels = dict(REPORT_COLUMNS)
    header = ["variant", "seed", "trained and tested under"]
    header += [f"{labels[m]} {side}" for m in TABLE_METRICS for side in ("(its test)", f"({retest.label})")]
    lines: list[list[object]] = []
    means: list[list[object]] = []
    for key, rows in finished_rows(sweep, sweep.open_log()).items():
        pairs = [(row, new) for row in rows if (new := log.find(**{f: row[f] for f in KEY_FIELDS})) is not None]
        lines += [[key, row["seed"], trained_precision(row), *_cells(row, new)] for row, new in pairs]
        if pairs:
            means.append([key, f"{len(pairs)} seeds", _precisions(pairs), *_mean_cells(pairs)])
    return "\n".join(
        [
            f"# {sweep.experiment.name}: kept weights tested again under `{retest.label}`",
            "",
            f"Command: `{command}`. {_what_was_tested(retest)} tested under `trainer.precision={retest.precision}`",
            "without training; `(its test)` is the row of the sweep's JSONL, the run's own test pairs under the",
            "precision it trained in. Mean ± sample std over seeds.",
            "",
            markdown_table(header, lines),
            "",
            markdown_table(header, means),
            "",
        ]
    )


def _what_was_tested(retest: Retest) -> str:
    bn = (
        f" with every BatchNorm layer's running statistics recomputed over {retest.precise_bn} training batches,"
        if retest.precise_bn
        else ""
    )
    if not retest.data:
        return (
            f"Each finished run's selected weights on its own test pairs (the same data, sizes and config values),{bn}"
        )
    changed = ", ".join(f"`{key}={value}`" for key, value in retest.data)
    return (
        "Each finished run's selected weights on other test pairs: the run's data, sizes and config values but "
        f"{changed} (the training and validation objects are the same),{bn}"
    )


def _cells(row: Mapping[str, Any], new: Mapping[str, Any]) -> list[str]:
    return [f"{float(source[m]):.4g}" for m in TABLE_METRICS for source in (row, new)]


def _mean_cells(pairs: Sequence[tuple[Mapping[str, Any], Mapping[str, Any]]]) -> list[str]:
    return [format_mean_std([float(p[k][m]) for p in pairs], digits=4) for m in TABLE_METRICS for k in (0, 1)]


def _precisions(pairs: Sequence[tuple[Mapping[str, Any], Mapping[str, Any]]]) -> str:
    return ", ".join(sorted({trained_precision(row) for row, _ in pairs}))
