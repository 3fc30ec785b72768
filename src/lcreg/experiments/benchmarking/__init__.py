"""The benchmark harness: every script in ``benchmarks/`` is a thin front end of this package.

* :mod:`~lcreg.experiments.benchmarking.registry`: the methods by name (label, config files, learned or not,
  refinement);
* :mod:`~lcreg.experiments.benchmarking.building`: :func:`build` a method as ``lcreg test`` does, from its config
  files and typed :data:`Values` by dotted key (:func:`lcreg.cli.instantiate`; weights: the library's
  :func:`lcreg.weights.load_into`, written by :func:`lcreg.weights.export.save`);
* :mod:`~lcreg.experiments.benchmarking.measure`: :func:`timed` (the one timing primitive, synchronised on CUDA),
  medians of repeats, registration speed, peak memory, fresh-process measurements;
* :mod:`~lcreg.experiments.benchmarking.training`: :func:`training_loss` and short :func:`fit` runs with a step budget;
* :mod:`~lcreg.experiments.benchmarking.data`: deterministic benchmark pairs and the synthetic data of ``--smoke`` runs;
* :mod:`~lcreg.experiments.benchmarking.writers`: Markdown tables, ``mean ± std``, resumable JSONL results;
* :mod:`~lcreg.experiments.benchmarking.curves`: learning curves of ``lcreg fit`` runs (``metrics.csv`` -> PNGs,
  summary table);
* :mod:`~lcreg.experiments.benchmarking.options`: command-line pieces of the scripts (``key=value``, config values
  given as options, budgets, ``--smoke``).
"""

from __future__ import annotations

from lcreg.experiments.benchmarking.building import Values, build, build_cli_for, method_layers
from lcreg.experiments.benchmarking.curves import (
    LR_SERIES,
    X_AXES,
    Band,
    Series,
    aggregate,
    load_runs,
    lr_changes,
    plot_curves,
    read_metrics,
    run_files,
    summary_rows,
    summary_table,
    write_synthetic_metrics,
)
from lcreg.experiments.benchmarking.data import (
    pair_batches,
    pair_batches_and_classes,
    split_batches,
    synthetic_options,
    synthetic_overrides,
)
from lcreg.experiments.benchmarking.measure import (
    RegistrationSpeed,
    Timing,
    device_of,
    peak_memory_mib,
    peak_rss_increase_mib,
    peak_rss_mib,
    registration_speed,
    run_fresh_process,
    synchronize,
    time_call,
    time_calls,
    timed,
)
from lcreg.experiments.benchmarking.options import Budget, add_smoke_argument, apply_smoke, config_values, key_values
from lcreg.experiments.benchmarking.registry import (
    ABLATION_CONFIGS,
    DATA_CONFIGS,
    METHODS,
    REFINE_CONFIG,
    VOXELIZE_CONFIG,
    MethodSpec,
    cli_args,
    config_dir,
    config_path,
    data_config,
    method,
    voxelize_overrides,
)
from lcreg.experiments.benchmarking.training import (
    CONVERGE_METRIC,
    SELECTION_METRIC,
    TERMINATED_EXIT_CODE,
    FitResult,
    converge_overrides,
    epoch_overrides,
    fit,
    fit_overrides,
    last_checkpoint,
    training_loss,
)
from lcreg.experiments.benchmarking.writers import (
    REPORT_COLUMNS,
    ResultLog,
    format_mean_std,
    machine_line,
    machines_of,
    markdown_row,
    markdown_table,
    mean_std_row,
    output_path,
    report_table,
    training_device,
    write_text,
)

__all__ = [
    "ABLATION_CONFIGS",
    "CONVERGE_METRIC",
    "DATA_CONFIGS",
    "LR_SERIES",
    "METHODS",
    "REFINE_CONFIG",
    "REPORT_COLUMNS",
    "SELECTION_METRIC",
    "TERMINATED_EXIT_CODE",
    "VOXELIZE_CONFIG",
    "X_AXES",
    "Band",
    "Budget",
    "FitResult",
    "MethodSpec",
    "RegistrationSpeed",
    "ResultLog",
    "Series",
    "Timing",
    "Values",
    "add_smoke_argument",
    "aggregate",
    "apply_smoke",
    "build",
    "build_cli_for",
    "cli_args",
    "config_dir",
    "config_path",
    "config_values",
    "converge_overrides",
    "data_config",
    "device_of",
    "epoch_overrides",
    "fit",
    "fit_overrides",
    "format_mean_std",
    "key_values",
    "last_checkpoint",
    "load_runs",
    "lr_changes",
    "machine_line",
    "machines_of",
    "markdown_row",
    "markdown_table",
    "mean_std_row",
    "method",
    "method_layers",
    "output_path",
    "pair_batches",
    "pair_batches_and_classes",
    "peak_memory_mib",
    "peak_rss_increase_mib",
    "peak_rss_mib",
    "plot_curves",
    "read_metrics",
    "registration_speed",
    "report_table",
    "run_files",
    "run_fresh_process",
    "split_batches",
    "summary_rows",
    "summary_table",
    "synchronize",
    "synthetic_options",
    "synthetic_overrides",
    "time_call",
    "time_calls",
    "timed",
    "training_device",
    "training_loss",
    "voxelize_overrides",
    "write_synthetic_metrics",
    "write_text",
]
