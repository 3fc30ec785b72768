"""PNG figures of a sweep: grouped bars of our test errors per row and series, the paper's values as markers.

One figure per pair of paper metrics: ``<experiment>_rotation.png`` (RMSE(R), MAE(R)) and
``<experiment>_translation.png`` (RMSE(t), MAE(t)). In each panel the paper's rows are along x (blocks separated by
a dashed line and named above), one bar per series (mean over seeds) with the seeds' standard deviation as error
bar, each seed as a dot and ``ours / paper`` above it, and the paper's value as a black line across the bar.
matplotlib (the ``plot`` extra) is imported when drawing, on an Agg canvas (never pyplot), as in
:mod:`lcreg.experiments.benchmarking.curves`.
"""

from __future__ import annotations

import statistics
from pathlib import Path
from typing import TYPE_CHECKING

from lcreg.experiments.reproduce.report import METRIC_TITLES, values
from lcreg.experiments.reproduce.spec import Experiment, Rows
from lcreg.experiments.reproduce.sweep import Sweep
from lcreg.figures import agg_figure, save_png

if TYPE_CHECKING:
    from matplotlib.axes import Axes

__all__ = ["FIGURES", "bar_positions", "plot_sweep"]

FIGURES = {"rotation": ("rmse_r_deg", "mae_r_deg"), "translation": ("rmse_t", "mae_t")}
"""File suffix -> the metrics drawn, one panel each."""
UNITS = {"rmse_r_deg": "degrees", "mae_r_deg": "degrees", "rmse_t": "unit-sphere units", "mae_t": "unit-sphere units"}
DPI = 110
BAR_GROUP = 0.8
"""Width of the bars of one row together (rows are 1 apart)."""
BLOCK_GAP = 0.6
"""Extra space between blocks."""
LEGEND_ENTRY_INCHES = 2.2
"""Width one legend entry needs (the longest, "paper (full ModelNet40)", at font size 8)."""


def bar_positions(experiment: Experiment) -> dict[tuple[str, str], float]:
    """The x centre of every (block, row), rows 1 apart, blocks :data:`BLOCK_GAP` further apart."""
    positions, x = {}, 0.0
    for i, block in enumerate(experiment.blocks()):
        x += BLOCK_GAP if i else 0.0
        for row in experiment.rows(block):
            positions[(block, row)] = x
            x += 1.0
    return positions


def _draw_panel(ax: Axes, experiment: Experiment, rows: Rows, metric: str) -> None:
    """Bars, error bars, seed dots and paper lines of one metric."""
    series = experiment.series_names()
    width = BAR_GROUP / len(series)
    per_seed = values(rows, metric)
    for (block, row), x in bar_positions(experiment).items():
        for j, name in enumerate(series):
            if (cell := experiment.cell(block, row, name)) is None:
                continue
            centre = x + (j - (len(series) - 1) / 2) * width
            paper = None if cell.paper is None else experiment.paper[cell.paper][metric]
            if seeds := per_seed.get(cell.variant):
                _bar(ax, centre, width, seeds, f"C{j}", paper)
            if paper is not None:
                ax.hlines(paper, centre - width / 2, centre + width / 2, colors="k", linewidth=2.2, zorder=5)
    _style(ax, experiment, METRIC_TITLES[metric].split(" (")[0], UNITS[metric])


def _bar(ax: Axes, x: float, width: float, seeds: list[float], colour: str, paper: float | None) -> None:
    """The mean of ``seeds`` as a bar with the std as error bar, each seed as a dot, ``ours / paper`` above."""
    mean = statistics.fmean(seeds)
    std = statistics.stdev(seeds) if len(seeds) > 1 else 0.0
    ax.bar(x, mean, width * 0.92, color=colour, alpha=0.85, zorder=2)
    if std > 0:
        ax.errorbar(x, mean, std, color="0.15", capsize=3, linewidth=1, zorder=3)
    ax.scatter([x] * len(seeds), seeds, s=7, color="0.15", zorder=4, linewidths=0)
    if paper:  # a paper value printed as 0.000 has no ratio
        top = max(mean + std, *seeds, paper)  # above the paper's line too
        ax.annotate(
            f"{mean / paper:.2g}×",
            (x, top),
            xytext=(0, 2),
            textcoords="offset points",
            ha="center",
            va="bottom",
            fontsize=6.5,
            color="0.25",
        )


def _style(ax: Axes, experiment: Experiment, title: str, unit: str) -> None:
    """Row names as ticks, block names above, dashed lines between blocks, a light y grid."""
    from matplotlib.transforms import blended_transform_factory

    positions = bar_positions(experiment)
    ax.set_xticks(list(positions.values()), [row.replace(", ", ",\n") for _, row in positions], fontsize=8)
    ax.set_title(title, fontsize=10, pad=16 if len(experiment.blocks()) > 1 else 6)
    ax.set_ylabel(unit, fontsize=9)
    ax.margins(y=0.08)
    ax.set_ylim(bottom=0)
    ax.tick_params(axis="y", labelsize=8)
    ax.grid(True, axis="y", alpha=0.3, linewidth=0.5, zorder=0)
    ax.set_axisbelow(True)
    if len(experiment.blocks()) < 2:
        return
    transform = blended_transform_factory(ax.transData, ax.transAxes)
    for i, block in enumerate(experiment.blocks()):
        xs = [positions[(block, row)] for row in experiment.rows(block)]
        ax.text(statistics.fmean(xs), 1.01, block, transform=transform, ha="center", va="bottom", fontsize=8)
        if i:
            ax.axvline(xs[0] - (1 + BLOCK_GAP) / 2, color="0.5", linestyle="--", linewidth=0.8)


def _legend_handles(experiment: Experiment) -> list:
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    handles: list = [Patch(color=f"C{j}", alpha=0.85, label=name) for j, name in enumerate(experiment.series_names())]
    if any(cell.paper is not None for cell in experiment.cells):
        handles.append(Line2D([], [], color="k", linewidth=2.2, label="paper (full ModelNet40)"))
    seed = Line2D([], [], color="0.15", marker="o", markersize=3, linestyle="", label="one seed (bar: mean ± std)")
    return [*handles, seed]


def _figure_title(sweep: Sweep, rows: Rows) -> str:
    pairs = sorted({r["num_test_pairs"] for runs in rows.values() for r in runs})
    seeds = ", ".join(map(str, sweep.seeds))
    return (
        f"{sweep.experiment.title}\nbudget {sweep.preset}, {'/'.join(map(str, pairs))} test pairs, seeds {seeds}; "
        f"lower is better"
    )


def _render(sweep: Sweep, rows: Rows, metrics: tuple[str, ...], path: Path) -> Path:
    width = max(6.0, 0.75 * len(bar_positions(sweep.experiment)) + 2.0)
    fig = agg_figure(width, 2.9 * len(metrics) + 1.2, DPI, "lcreg reproduce plots")
    for ax, metric in zip(fig.subplots(len(metrics), 1, squeeze=False).ravel(), metrics):
        _draw_panel(ax, sweep.experiment, rows, metric)
    handles = _legend_handles(sweep.experiment)
    legend = fig.legend(
        handles=handles,
        loc="outside upper center",
        ncols=min(len(handles), max(1, int(width / LEGEND_ENTRY_INCHES))),  # wraps instead of running off the canvas
        fontsize=8,
        frameon=False,
        title=_figure_title(sweep, rows),
    )
    legend.get_title().set_fontsize(9)
    return save_png(fig, path)


def plot_sweep(sweep: Sweep, rows: Rows) -> list[Path]:
    """Write the figures of :data:`FIGURES` next to the report; none when no run is finished."""
    if not any(rows.values()):
        return []
    return [_render(sweep, rows, m, Path(f"{sweep.file_stem}_{suffix}.png")) for suffix, m in FIGURES.items()]
