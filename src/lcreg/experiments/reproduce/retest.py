"""Test a sweep's kept weights again under another precision, on the same test pairs, without training.

``lcreg reproduce <experiment> ... --retest 32-true``: every finished run of the sweep (its JSONL row) is tested again
from the weights it kept (``row["weights"]``, or the longest tail of that path under ``--out``: a copy of the output
folder made elsewhere, :func:`~lcreg.experiments.reproduce.stops.recorded_file`), with the run's own data, sizes and
config values, under ``trainer.precision`` = the asked precision. It answers what a run's test figure owes to the
precision it was tested in: a run trained under ``bf16-mixed`` is tested under it too, and bfloat16 inference alone
moves per-pair errors (``docs/results/bench_precision.md``). The rows go to ``<stem>.retest-<precision>.jsonl`` (a
rerun skips the runs found there), the table of both tests side by side to ``<stem>.retest-<precision>.md``, each
test's logs and per-pair errors to ``<run folder>/retest-<precision>/``; the sweep's own JSONL, report and run logs
are not changed.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from functools import partial
from pathlib import Path
from typing import Any

from lcreg.experiments.benchmarking import (
    REPORT_COLUMNS,
    ResultLog,
    build_cli_for,
    format_mean_std,
    machine_line,
    markdown_table,
    timed,
    training_device,
)
from lcreg.experiments.reproduce.budgets import DataChoice, RunBudget
from lcreg.experiments.reproduce.stops import recorded_file
from lcreg.experiments.reproduce.sweep import KEY_FIELDS, METRICS, Sweep, finished_rows, run_values
from lcreg.weights import load_into

__all__ = [
    "PRECISIONS",
    "MissingWeightsError",
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
TABLE_METRICS = ("rmse_r_deg", "mae_r_deg", "rmse_t", "mae_t")
"""The figures the table sets side by side (the LC table's; every other metric is in the JSONL)."""


class MissingWeightsError(FileNotFoundError):
    """A finished run's kept weights are neither where its row says nor under the output folder."""


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

    Returns:
        The test metrics of :data:`~lcreg.experiments.reproduce.sweep.METRICS` (degrees; translations in the data's
        units).
    """
    values = {**run_values(budget, data, Path(log_dir), seed, overrides), "trainer.precision": precision}
    cli = build_cli_for(name, (), values)
    load_into(cli.model, weights)
    (tested,) = cli.trainer.test(cli.model, datamodule=cli.datamodule, verbose=False)
    return {key: float(tested[f"test/{key}"]) for key in METRICS}


def retest_sweep(sweep: Sweep, precision: str, progress: Callable[[str], None] = lambda _: None) -> ResultLog:
    """Test every finished run of ``sweep`` again from its kept weights under ``precision``, one row per run.

    Args:
        sweep: The sweep whose JSONL lists the finished runs.
        precision: Lightning's ``trainer.precision`` of the new tests (one of :data:`PRECISIONS`).
        progress: Called with one line per run.

    Returns:
        The log ``<stem>.retest-<precision>.jsonl`` (runs found there are skipped).

    Raises:
        MissingWeightsError: A run's weights are not found; names the file its row records. Runs retested before it
            are kept in the log.
    """
    log = ResultLog(retest_path(sweep, precision, ".jsonl"), KEY_FIELDS)
    variants = {variant.key: variant for variant in sweep.experiment.variants}
    for key, rows in finished_rows(sweep, sweep.open_log()).items():
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
            log_dir = sweep.run_dir(variant, seed) / f"{RETEST_TAG}{precision}"
            test = partial(
                retest_weights, variant.method, budget, sweep.data, seed, overrides, weights, precision, log_dir
            )
            metrics, seconds = timed(test)
            log.append(
                {
                    **fields,
                    "precision": precision,
                    "trained_precision": trained_precision(row),
                    "weights": str(weights),
                    "test_s": round(seconds, 1),
                    "machine": machine_line(training_device()),
                    **metrics,
                }
            )
            progress(f"{key} seed {row['seed']}: RMSE(R) {row['rmse_r_deg']:.3f}° -> {metrics['rmse_r_deg']:.3f}°")
    return log


def retest_path(sweep: Sweep, precision: str, suffix: str) -> Path:
    """``<out>/<stem>.retest-<precision><suffix>``."""
    return sweep.file_stem.with_name(f"{sweep.file_stem.name}.{RETEST_TAG}{precision}{suffix}")


def is_retest_output(path: str | Path) -> bool:
    """Whether ``path`` was written by a retest: not a run's log or training row.

    A retest writes its JSONL and report beside the sweep's and its tests' logs in each run's ``retest-*`` folder;
    tools that walk an output folder for runs (the training queue) leave these out.
    """
    path = Path(path)
    return f".{RETEST_TAG}" in path.name or any(part.startswith(RETEST_TAG) for part in path.parts[:-1])


def render_retest(sweep: Sweep, log: ResultLog, precision: str, command: str) -> str:
    """Markdown: each retested run's test as it ran beside its test under ``precision``, then the means per variant."""
    labels = dict(REPORT_COLUMNS)
    header = ["variant", "seed", "trained and tested under"]
    header += [f"{labels[m]} {side}" for m in TABLE_METRICS for side in ("(its test)", f"({precision})")]
    lines: list[list[object]] = []
    means: list[list[object]] = []
    for key, rows in finished_rows(sweep, sweep.open_log()).items():
        pairs = [(row, new) for row in rows if (new := log.find(**{f: row[f] for f in KEY_FIELDS})) is not None]
        lines += [[key, row["seed"], trained_precision(row), *_cells(row, new)] for row, new in pairs]
        if pairs:
            means.append([key, f"{len(pairs)} seeds", _precisions(pairs), *_mean_cells(pairs)])
    return "\n".join(
        [
            f"# {sweep.experiment.name}: kept weights tested again under `{precision}`",
            "",
            f"Command: `{command}`. Each finished run's selected weights on its own test pairs (the same data, sizes",
            f"and config values), tested under `trainer.precision={precision}` without training; `(its test)` is the",
            "row of the sweep's JSONL, tested under the precision the run trained in. Mean ± sample std over seeds.",
            "",
            markdown_table(header, lines),
            "",
            markdown_table(header, means),
            "",
        ]
    )


def _cells(row: Mapping[str, Any], new: Mapping[str, Any]) -> list[str]:
    return [f"{float(source[m]):.4g}" for m in TABLE_METRICS for source in (row, new)]


def _mean_cells(pairs: Sequence[tuple[Mapping[str, Any], Mapping[str, Any]]]) -> list[str]:
    return [format_mean_std([float(p[k][m]) for p in pairs], digits=4) for m in TABLE_METRICS for k in (0, 1)]


def _precisions(pairs: Sequence[tuple[Mapping[str, Any], Mapping[str, Any]]]) -> str:
    return ", ".join(sorted({trained_precision(row) for row, _ in pairs}))
