"""The Markdown report of a sweep: ours beside the paper's numbers with their ratio, other metrics, the claims.

Each paper metric (RMSE(R), MAE(R), RMSE(t), MAE(t)) gets a table whose rows are the paper's rows and whose column
groups are the experiment's series: ``mean ± std`` over the seeds, the paper's value and ``ours / paper``. The
header states the budget, the data, the number of validation and test pairs, the seeds and how many runs are
finished; the claims section says for each of the paper's claims whether it holds beyond the seed spread
(:mod:`lcreg.experiments.reproduce.claims`).
"""

from __future__ import annotations

import json
import statistics
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from lcreg.experiments.benchmarking import format_mean_std, machines_of, markdown_table
from lcreg.experiments.reproduce.claims import ClaimResult, Comparison, judge
from lcreg.experiments.reproduce.paper import PAPER_METRICS
from lcreg.experiments.reproduce.spec import Cell, Experiment, Rows
from lcreg.experiments.reproduce.stops import stops_table
from lcreg.experiments.reproduce.sweep import Sweep

__all__ = ["CLAIM_METRICS", "METRIC_TITLES", "claim_results", "metric_table", "render", "stops_lines", "values"]

METRIC_TITLES = {
    "rmse_r_deg": "RMSE(R) (°)",
    "mae_r_deg": "MAE(R) (°)",
    "rmse_t": "RMSE(t)",
    "mae_t": "MAE(t)",
    "rre_mean_deg": "mean RRE °",
    "rre_median_deg": "median RRE °",
    "rte_mean": "mean RTE",
    "recall_r2_t0p01": "recall (2°, 0.01)",
    "recall_r5_t0p05": "recall (5°, 0.05)",
}
CLAIM_METRICS = ("rmse_r_deg", "mae_r_deg")
"""The claims are about rotation errors (the paper's headline numbers); each is judged on both."""
OTHER_METRICS = ("rre_mean_deg", "rre_median_deg", "rte_mean", "recall_r2_t0p01", "recall_r5_t0p05")
SPREAD_RULE = (
    "beyond the seed spread: the difference of the seed means is larger than the larger of the two seed standard "
    "deviations; `within spread` otherwise; `one seed`: no spread to compare with"
)
PAPER_SIZE_RULE = (
    "the paper's difference at our level is the paper's relative difference (its better row / its worse row − 1) "
    "times our mean of the worse side; `smaller than the paper's` when our difference is above it by more than the "
    "spread (for a claimed gain: a gain of the paper's size is refuted here), `larger than the paper's` when below "
    "it by more than the spread, `as the paper's` otherwise; a claim is smaller than the paper's when any of its "
    "comparisons is. Added in session 18 of issue 23, after the IDAM and DCP-v2 LC runs had been seen"
)


def values(rows: Rows, metric: str) -> dict[str, list[float]]:
    """Per-seed values of ``metric`` by variant key."""
    return {key: [float(r[metric]) for r in runs] for key, runs in rows.items()}


def _ours(runs: Sequence[Mapping[str, Any]], metric: str) -> str:
    """Mean ± std of ``metric`` over ``runs``; over the runs that recorded it (``k of n``) when older rows lack it."""
    if not runs:
        return "not run"
    recorded = [r[metric] for r in runs if r.get(metric) is not None]
    if not recorded:
        return "–"
    part = "" if len(recorded) == len(runs) else f" ({len(recorded)} of {len(runs)})"
    if metric.startswith("recall"):
        return format_mean_std(recorded, ".1f", ".1f", scale=100.0) + " %" + part
    return format_mean_std(recorded) + part


def _ratio(runs: Sequence[Mapping[str, Any]], metric: str, paper: float | None) -> str:
    if not runs or not paper:  # no run, no paper row, or a paper value printed as 0.000
        return "–"
    return f"{statistics.fmean(r[metric] for r in runs) / paper:.2f}×"


def _paper(experiment: Experiment, key: str | None, metric: str) -> float | None:
    return None if key is None else experiment.paper[key][metric]


def _shared_paper(experiment: Experiment) -> bool:
    """Whether every row has one paper row for all its series (the ablation: one paper column)."""
    return all(
        len({c.paper for c in experiment.cells if (c.block, c.row) == (b, r)}) == 1
        for b in experiment.blocks()
        for r in experiment.rows(b)
    )


def metric_table(experiment: Experiment, rows: Rows, metric: str) -> str:
    """One metric: rows × series with ours (mean ± std), the paper's value and ``ours / paper``.

    When every row has one paper row for all its series (the ablation), the paper's value is one column after the
    row name; otherwise (LC + X) each series has its own paper column. A series the paper does not have (no cell
    names a paper row, e.g. LC (matched) + X) has only its ``ours`` column.
    """
    series, shared = experiment.series_names(), _shared_paper(experiment)
    paperless = {name for name in series if all(c.paper is None for c in experiment.cells if c.series == name)}
    header = ["", "row", *(["paper"] if shared else [])]
    for name in series:
        if name in paperless:
            header.append(f"ours: {name}")
        else:
            header += [*([] if shared else [f"paper: {name}"]), f"ours: {name}", "ours / paper"]
    lines = []
    for block in experiment.blocks():
        for i, row in enumerate(experiment.rows(block)):
            line: list[object] = [block if i == 0 else "", row]
            if shared:
                cells = [experiment.cell(block, row, name) for name in series]
                line.append(_paper_cell(experiment, next(c.paper for c in cells if c), metric))
            for name in series:
                cell = experiment.cell(block, row, name)
                columns = _series_cells(experiment, cell, rows, metric, with_paper=not shared)
                line += columns[-2:-1] if name in paperless else columns
            lines.append(line)
    return markdown_table(header, lines)


def _series_cells(experiment: Experiment, cell: Cell | None, rows: Rows, metric: str, with_paper: bool) -> list[str]:
    """``[paper,] ours, ours / paper`` of one cell (blank where the table has no cell)."""
    if cell is None:
        return ["", "", ""] if with_paper else ["", ""]
    runs = rows.get(cell.variant, [])
    ours = [_ours(runs, metric), _ratio(runs, metric, _paper(experiment, cell.paper, metric))]
    return [_paper_cell(experiment, cell.paper, metric), *ours] if with_paper else ours


def _paper_cell(experiment: Experiment, key: str | None, metric: str) -> str:
    value = _paper(experiment, key, metric)
    return "–" if value is None else f"{value:.3f}"


def other_table(experiment: Experiment, rows: Rows) -> str:
    """The metrics the paper does not report, with the seeds, steps and training time of each cell."""
    header = ["", "row", "series", *(METRIC_TITLES[m] for m in OTHER_METRICS), "seeds", "steps", "train s/run"]
    lines = []
    for block in experiment.blocks():
        for row in experiment.rows(block):
            for series in experiment.series_names():
                if (cell := experiment.cell(block, row, series)) is None or not (runs := rows.get(cell.variant)):
                    continue
                train_s = statistics.fmean(r["train_s"] for r in runs)
                steps = "/".join(sorted({str(r["steps"]) for r in runs}))
                metrics = [_ours(runs, m) for m in OTHER_METRICS]
                lines.append([block, row, series, *metrics, len(runs), steps, f"{train_s:.0f}"])
    return markdown_table(header, lines)


def paper_values(experiment: Experiment, metric: str) -> dict[str, float]:
    """The paper's value of ``metric`` by variant key (a variant in several cells: its first paper row)."""
    found: dict[str, float] = {}
    for cell in experiment.cells:
        if cell.paper is not None and (value := experiment.paper[cell.paper].get(metric)) is not None:
            found.setdefault(cell.variant, value)
    return found


def claim_results(experiment: Experiment, rows: Rows) -> list[tuple[str, ClaimResult]]:
    """Every claim judged on every metric of :data:`CLAIM_METRICS`: ``(metric, result)`` pairs."""
    return [
        (m, judge(claim, values(rows, m), paper_values(experiment, m)))
        for claim in experiment.claims
        for m in CLAIM_METRICS
    ]


def _name(experiment: Experiment, comparison: Comparison) -> tuple[str, str]:
    """Short names of the two sides: their rows, or their series when both sit in one row."""
    cells = [next(c for c in experiment.cells if c.variant == key) for key in (comparison.better, comparison.worse)]
    if cells[0].row != cells[1].row:
        return cells[0].row, cells[1].row
    return cells[0].series, cells[1].series


def claims_table(experiment: Experiment, rows: Rows) -> str:
    """One line per (claim, metric): the verdict and each comparison's difference and spread."""
    if not experiment.claims:
        return "No claim compares only the variants of this run (see `--only`)."
    lines = []
    for metric, result in claim_results(experiment, rows):
        details = []
        for r in result.comparisons:
            better, worse = _name(experiment, r.comparison)
            paper = "" if r.paper_difference is None else f", the paper's {r.paper_difference:+.3g}: {r.size}"
            details.append(f"{better} − {worse} = {r.difference:+.3g} (spread {r.spread:.2g}): {r.verdict}{paper}")
        verdict = f"**{result.verdict}**" if result.verdict in ("holds", "does not hold") else result.verdict
        size = f"**{result.size}**" if result.size == "smaller than the paper's" else result.size
        size = "–" if result.verdict == "not run" else size
        lines.append([result.claim.text, METRIC_TITLES[metric], verdict, size, "; ".join(details) or "–"])
    header = [
        "claim",
        "metric",
        "verdict",
        "against the paper's difference",
        "comparisons (mean difference, seed spread, the paper's difference at our level)",
    ]
    return markdown_table(header, lines)


def _budget_lines(sweep: Sweep) -> list[str]:
    """One line per budget group (one line when all groups share a budget), then the ``--set`` values.

    A set value replaces the budget's own where it names one (``trainer.max_steps`` its steps,
    ``data.init_args.batch_size`` its batch), so it gets its own line rather than trailing the budget's text (the rows'
    keys keep that text: :meth:`Sweep.key`).
    """
    budgets = sweep.experiment.budgets[sweep.preset]
    groups = list(dict.fromkeys(v.budget_group for v in sweep.experiment.variants))
    described = {g: budgets[g].describe() for g in groups}
    if len(set(described.values())) <= 1:
        lines = [f"- Budget `{sweep.preset}` per run: {next(iter(described.values()), '–')}."]
    else:
        lines = [f"- Budget `{sweep.preset}` per run:"] + [f"  - {g}: {d}." for g, d in described.items()]
    if sweep.settings:
        values = ", ".join(f"`{k}={json.dumps(v)}`" for k, v in sweep.settings)
        lines.append(
            f"- Set on every run (`--set`; each replaces the budget's value of its key, if it has one): {values}."
        )
    return lines


def _monitors(sweep: Sweep) -> str:
    """The validation metric(s) the budget's runs select their checkpoint on (``converge``: ``val/rre_clip5_deg``)."""
    budgets = sweep.experiment.budgets[sweep.preset]
    groups = dict.fromkeys(v.budget_group for v in sweep.experiment.variants)
    return " / ".join(f"`{m}`" for m in dict.fromkeys(budgets[g].monitor for g in groups))


def _pairs(rows: Rows, field: str) -> str:
    counts = sorted({r[field] for runs in rows.values() for r in runs})
    return "/".join(map(str, counts)) or "–"


def machines(rows: Rows) -> str:
    """The machines that trained the rows of every variant (:func:`~lcreg.experiments.benchmarking.machines_of`)."""
    return machines_of(r for runs in rows.values() for r in runs)


def header(sweep: Sweep, rows: Rows, command: str, failed: Sequence[str] = ()) -> list[str]:
    """Title, command, budget, data, pair counts, seeds, finished (and failed) runs and time, machine; the series."""
    experiment = sweep.experiment
    done = sum(len(runs) for runs in rows.values())
    total = len(experiment.variants) * len(sweep.seeds)
    hours = sum(r["train_s"] + r.get("test_s", 0.0) for runs in rows.values() for r in runs) / 3600
    lines = [
        f"# {experiment.title}",
        "",
        f'Paper: Table "{experiment.paper_table}". Command: `{command}`',
        "",
        *_budget_lines(sweep),
        f"- Checkpoint chosen on {_monitors(sweep)} (validation pairs carved out of the training objects, never the "
        "test set), then tested once on the deterministic test pairs.",
        f"- Data: {sweep.data.describe()}: **{_pairs(rows, 'num_test_pairs')} test pairs**, "
        f"{_pairs(rows, 'num_val_pairs')} validation pairs (the paper: the full ModelNet40).",
        f"- Seeds: {', '.join(map(str, sweep.seeds))} (mean ± sample std over seeds). Runs finished: {done} of "
        f"{total}; {hours:.2f} h of training and testing in all.",
        *(f"- Failed (non-finite training loss, left out of the means): {run}" for run in failed),
        f"- Machine: {machines(rows)}.",
        "",
        "Series:",
        *(f"- **{name}**: {text}" for name, text in experiment.series.items()),
    ]
    return lines


def stops_lines(sweep: Sweep, rows: Rows, curves: Sequence[Path]) -> list[str]:
    """Where and why each run stopped (:func:`~lcreg.experiments.reproduce.stops.stops_table`), and the curve PNGs."""
    if not any(rows.values()):
        return []
    lines = ["", "## Where each run stopped", "", stops_table(sweep.experiment, rows, sweep.preset)]
    if curves:
        names = ", ".join(f"`{Path(c).name}`" for c in curves)
        lines += ["", f"Learning curves (mean over seeds, min-max shade; every validation of every run): {names}."]
    return lines


def render(sweep: Sweep, rows: Rows, command: str, failed: Sequence[str] = (), curves: Sequence[Path] = ()) -> str:
    """The whole report (Markdown, ends with a newline).

    Args:
        sweep: The sweep reported.
        rows: Its finished runs by variant key.
        command: The command line written in the report.
        failed: The runs that diverged.
        curves: The learning-curve PNGs written beside it
            (:func:`~lcreg.experiments.reproduce.stops.plot_learning_curves`).
    """
    experiment = sweep.experiment
    parts = header(sweep, rows, command, failed)
    parts += [
        "",
        "Ours: mean ± std over seeds; `ours / paper`: the ratio of the means (– where the paper prints "
        "0.000 or has no row).",
    ]
    for metric in PAPER_METRICS:
        parts += ["", f"## {METRIC_TITLES[metric]}", "", metric_table(experiment, rows, metric)]
    parts += ["", "## Other test metrics (not in the paper's table)", "", other_table(experiment, rows)]
    parts += ["", "## The paper's claims", "", f"Rule: {SPREAD_RULE}.", "", f"Against the paper: {PAPER_SIZE_RULE}."]
    parts += ["", claims_table(experiment, rows)]
    parts += stops_lines(sweep, rows, curves)
    if experiment.extra is not None and (extra := experiment.extra(rows)):
        parts += ["", *extra]
    if experiment.notes:
        parts += ["", "## Differences from the paper", "", *(f"- {note}" for note in experiment.notes)]
    return "\n".join(parts) + "\n"
