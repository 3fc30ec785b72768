"""Where each run of a sweep stopped, and the learning curves of its validation metrics (issue 23's reports).

A row of a sweep's JSONL names its run's ``metrics.csv`` by the absolute path it was written at. A report written
later, or on another machine, from a copy of the output folder (the training queue commits ``<out>`` under
``docs/results/converge/<job>/runs/``) finds the file by :func:`metrics_file`: the path itself, or the longest tail of
it found under the output folder; :func:`with_metrics_files` rewrites the rows so (``lcreg reproduce`` does it before
reporting).

The curves are drawn by :func:`lcreg.experiments.benchmarking.plot_curves` (one colour per variant, the mean over seeds
with a min-max shade), one set of PNGs per group of variants (the key before ``/``: a host of ``lc``, an objective of
``ablation``): ``<stem>_curves_<group>_validation.png`` and the other figures it draws.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from lcreg.experiments.benchmarking import LR_SERIES, lr_changes, markdown_table, plot_curves, read_metrics
from lcreg.experiments.reproduce.budgets import Preset
from lcreg.experiments.reproduce.spec import Experiment, Rows

__all__ = [
    "metrics_file",
    "plot_learning_curves",
    "recorded_file",
    "stopped_early",
    "stops_table",
    "with_metrics_files",
]

_SEED_FOLDER = re.compile(r"seed\d+")
"""A run's folder under its variant's (:meth:`~lcreg.experiments.reproduce.sweep.Sweep.run_dir`)."""

STOPS_HEADER = [
    "variant",
    "seed",
    "stopped at step",
    "why",
    "selected checkpoint",
    "best validation",
    "lr changes (step: ×factor)",
    "train s (a resumed run: the segments it kept; rows before session 12: the last one)",
    "peak MiB (GPU: allocated; CPU: resident increase)",
]


def metrics_file(row: Mapping[str, Any], out: str | Path | None = None) -> Path | None:
    """The run's ``metrics.csv``: ``row["metrics_csv"]`` if it exists, else its longest tail that exists under ``out``.

    Args:
        row: A JSONL row (``metrics_csv``: the path the run wrote).
        out: The sweep's output folder as it is now (``None``: only the recorded path).

    Returns:
        The file, or ``None`` when neither is found (or the row names none).
    """
    return recorded_file(row, "metrics_csv", out)


def recorded_file(row: Mapping[str, Any], field: str, out: str | Path | None = None) -> Path | None:
    """The file a row's ``field`` names (e.g. ``weights``): the recorded path, else its longest tail under ``out``.

    A tail must keep the run's own folders, ``<variant>/seed<k>`` (the last ``seed<k>`` part and the one before
    it): a shorter one (``seed0/metrics.csv``, ``lcreg/version_0/metrics.csv``) may be another run's file, whose
    curves or weights would then be reported as this run's. A recorded path without a ``seed<k>`` part is only
    found where it was written.

    Returns:
        The file, or ``None`` when neither is found (or the row names none).
    """
    recorded = row.get(field)
    if not recorded:
        return None
    path = Path(recorded)
    if path.is_file():
        return path
    if out is None:
        return None
    parts = path.parts
    seeds = [k for k, part in enumerate(parts) if _SEED_FOLDER.fullmatch(part)]
    last_start = seeds[-1] - 1 if seeds else 0  # the tail starts at the variant's folder at the latest
    tails = (Path(out, *parts[k:]) for k in range(1, last_start + 1))  # longest tail first
    return next((tail for tail in tails if tail.is_file()), None)


def with_metrics_files(rows: Rows, out: str | Path) -> Rows:
    """``rows`` with each ``metrics_csv`` replaced by :func:`metrics_file` where that finds the file under ``out``."""
    resolved: dict[str, list[Mapping[str, Any]]] = {}
    for key, runs in rows.items():
        resolved[key] = []
        for row in runs:
            found = metrics_file(row, out)
            resolved[key].append({**row, "metrics_csv": str(found)} if found is not None else row)
    return resolved


def _seed(row: Mapping[str, Any]) -> int:
    """Sort key: the run's seed (rows of older JSONL versions without one go first)."""
    return int(row.get("seed", -1))


def stopped_early(row: Mapping[str, Any]) -> bool | None:
    """Whether a run stopped before its step cap (``None``: its row does not say).

    The cap is the row's ``--set trainer.max_steps`` where it records one: rows written before session 44 compared
    the steps with the budget's own cap, so a run stopped early below a raised cap reads ``stopped_early: false``.
    """
    cap = (row.get("overrides") or {}).get("trainer.max_steps")
    if row.get("stopped_early") is None or cap is None or row.get("steps") is None:
        return row.get("stopped_early")
    return int(row["steps"]) < int(cap)


def _why(row: Mapping[str, Any], converge: bool) -> str:
    if not converge:
        return "end of the budget"
    return "early stop (no gain)" if stopped_early(row) else "step cap"


def _best(row: Mapping[str, Any]) -> str:
    value, metric = row.get("best_val"), row.get("selected_on")
    return "–" if value is None else f"{float(value):.4g} (`{metric or 'val'}`)"


def _lr_cell(row: Mapping[str, Any]) -> str:
    """The run's learning-rate changes from its ``metrics.csv`` (:func:`lr_changes`); ``–`` where none was logged."""
    path = metrics_file(row)
    metrics = read_metrics(path) if path is not None else {}
    if LR_SERIES not in metrics:
        return "–"
    changes = lr_changes(metrics)
    return ", ".join(f"{step}: ×{factor:.3g}" for step, factor in changes) if changes else "none"


def stops_table(experiment: Experiment, rows: Rows, preset: Preset) -> str:
    """One line per finished run, in the experiment's variant order, then by seed: where and why it stopped.

    Why: ``early stop (no gain)`` or ``step cap`` for a converge budget, ``end of the budget`` for a fixed one. The
    learning rate's changes (a schedule stepped per epoch moves them with the training set's size) are read from the
    run's ``metrics.csv`` (``–``: not found, or logged before the rate was).
    """
    lines = []
    for variant in experiment.variants:
        converge = experiment.budgets[preset][variant.budget_group].converge
        for row in sorted(rows.get(variant.key, []), key=_seed):
            selected = f"`{row['selected']}`" if row.get("selected") else "–"
            steps, seconds = row.get("steps"), row.get("train_s")
            lines.append(
                [
                    variant.key,
                    str(row.get("seed", "–")),
                    "–" if steps is None else str(steps),
                    _why(row, converge),
                    selected,
                    _best(row),
                    _lr_cell(row),
                    "–" if seconds is None else f"{float(seconds):.0f}",
                    "–" if row.get("peak_mib") is None else f"{float(row['peak_mib']):.0f}",
                ]
            )
    return markdown_table(STOPS_HEADER, lines)


def _groups(experiment: Experiment) -> dict[str, list[str]]:
    """Variant keys by the part before ``/`` (a host of ``lc``, an objective of ``ablation``), in variant order."""
    groups: dict[str, list[str]] = {}
    for variant in experiment.variants:
        groups.setdefault(variant.key.split("/", 1)[0], []).append(variant.key)
    return groups


def plot_learning_curves(experiment: Experiment, rows: Rows, out: Path, stem: str) -> list[Path]:
    """Write ``<out>/<stem>_curves_<group>_<figure>.png`` for each group with a run whose ``metrics.csv`` exists.

    Args:
        experiment: The experiment (its variants, in order, and their groups).
        rows: Finished runs by variant key (:func:`with_metrics_files` first for a copied output folder).
        out: Folder of the PNGs.
        stem: Start of their names (the report's stem).

    Returns:
        The written files (none when no run's metrics are found, e.g. rows of runs trained elsewhere).
    """
    written = []
    for group, keys in _groups(experiment).items():
        runs = {key: _curves(rows.get(key, [])) for key in keys}
        runs = {key: seeds for key, seeds in runs.items() if seeds}
        if runs:
            written += plot_curves(runs, out, prefix=f"{stem}_curves_{group}_")
    return written


def _curves(runs: Sequence[Mapping[str, Any]]) -> list[Any]:
    """Each run's logged series without ``test/`` keys (one value at the run's end: not a curve)."""
    files = (metrics_file(row) for row in sorted(runs, key=_seed))
    metrics = (read_metrics(f) for f in files if f is not None)
    return [{k: v for k, v in m.items() if not k.startswith("test/")} for m in metrics]
