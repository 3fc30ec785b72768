"""``lcreg reproduce runtime``: the paper's running-time table, ms per pair at 500, 1000 and 2000 points.

Nothing is trained: every method of :data:`RUNTIME` is built from its configs (random weights, as in
``benchmarks/bench_runtime.py``) and registers the same pairs one at a time (batch 1) with
:func:`lcreg.experiments.benchmarking.registration_speed` (median of the budget's timed passes after a warm-up). Every
seed draws other pairs (the data's pair seed: rotations, translations, noise, point sampling). Learned methods run on
the CPU and, when ``torch.cuda.is_available()``, on the GPU too; the Open3D methods (ICP, FGR, RANSAC) run on the CPU
only, as in the paper. One JSONL row per method × points × seed × device, appended as it is measured; a rerun skips the
rows already there (same budget and data). :func:`render_runtime` and :func:`plot_runtime` write the table (ours
beside the paper's ms, their ratio, and the ratio to DVDs measured in the same process) and the figure.
"""

from __future__ import annotations

import fnmatch
import statistics
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import torch

from lcreg.experiments.benchmarking import (
    METHODS,
    ResultLog,
    build,
    format_mean_std,
    machine_line,
    markdown_table,
    pair_batches,
    registration_speed,
)
from lcreg.experiments.reproduce.budgets import DataChoice, Preset
from lcreg.experiments.reproduce.paper import RUNTIME_MACHINE, RUNTIME_MS, RUNTIME_POINTS
from lcreg.experiments.reproduce.sweep import PresetRun
from lcreg.figures import agg_figure, save_png

if TYPE_CHECKING:
    from matplotlib.axes import Axes

    from lcreg.experiments.benchmarking.data import Protocol

__all__ = [
    "KEY_FIELDS",
    "NOISE_SIGMA",
    "RUNTIME",
    "RuntimeBudget",
    "RuntimeExperiment",
    "RuntimeRun",
    "measure_runtime",
    "plot_runtime",
    "render_runtime",
]

KEY_FIELDS = ("experiment", "method", "points", "seed", "device", "budget", "data")
"""Fields that identify a measurement in the JSONL: a row with the same values is skipped on a rerun."""
NOISE_SIGMA = 0.01
"""Gaussian noise on both clouds (the paper's runtime pairs are noisy; its σ is not stated)."""
DPI = 110


@dataclass(frozen=True)
class RuntimeBudget:
    """What one preset measures.

    Attributes:
        points: Points per cloud (a subset of the paper's :data:`RUNTIME_POINTS` keeps the paper column).
        pairs: Pairs registered per (method, points, seed), one at a time.
        repeats: Timed passes over the pairs after the warm-up (median reported).
        cuda: Also measure the learned methods on the GPU when one is available.
    """

    points: tuple[int, ...]
    pairs: int
    repeats: int
    cuda: bool = True

    def __post_init__(self) -> None:
        if not self.points or min(self.points, default=1) < 1 or self.pairs < 1 or self.repeats < 1:
            raise ValueError(f"RuntimeBudget values must be positive, got {self}")

    def describe(self) -> str:
        """E.g. ``"4 pairs × median of 3 passes, batch 1"`` (the JSONL key; the points are a key of their own)."""
        return f"{self.pairs} pairs × median of {self.repeats} passes, batch 1"


@dataclass(frozen=True)
class RuntimeExperiment:
    """The runtime experiment: methods, the paper's figures and a budget per preset.

    Attributes:
        name: Command-line name and stem of the output files.
        title: Heading of the report and the figure.
        paper_table: The paper table reproduced.
        paper: The paper's ms per pair at :data:`RUNTIME_POINTS` by method.
        methods: Registry keys, in table order (``"dvds"`` first: the others' ratios are to it).
        budgets: Preset -> budget.
        notes: How the measurement differs from the paper (report bullets).
    """

    name: str
    title: str
    paper_table: str
    paper: Mapping[str, tuple[float, ...]]
    methods: tuple[str, ...]
    budgets: Mapping[Preset, RuntimeBudget]
    notes: tuple[str, ...] = ()

    def select(self, patterns: Sequence[str]) -> RuntimeExperiment:
        """Only the methods whose key matches a pattern (``fnmatch``; none: all).

        Raises:
            ValueError: If a pattern matches no method (the message lists the keys).
        """
        for pattern in patterns:
            if not fnmatch.filter(self.methods, pattern):
                raise ValueError(
                    f"--only {pattern!r} matches no method of {self.name}; known: {', '.join(self.methods)}"
                )
        if not patterns:
            return self
        return replace(self, methods=tuple(m for m in self.methods if any(fnmatch.fnmatchcase(m, p) for p in patterns)))

    def paper_ms(self, method: str, points: int) -> float | None:
        """The paper's ms per pair (``None``: the paper has no such column or row)."""
        if points not in RUNTIME_POINTS or method not in self.paper:
            return None
        return self.paper[method][RUNTIME_POINTS.index(points)]


RUNTIME = RuntimeExperiment(
    name="runtime",
    title='Table "Running time comparisons" (ms per pair)',
    paper_table="Running time comparisons for registering a point cloud pair (\\label{table3})",
    paper=RUNTIME_MS,
    methods=("dvds", "pointnetlk", "fmr", "pcrnet", "dcp", "icp", "fgr", "ransac"),
    budgets={
        "smoke": RuntimeBudget(points=(500,), pairs=1, repeats=1, cuda=False),
        "cpu": RuntimeBudget(points=RUNTIME_POINTS, pairs=4, repeats=3),
        "converge": RuntimeBudget(points=RUNTIME_POINTS, pairs=4, repeats=3),  # nothing is trained: as cpu
        "paper": RuntimeBudget(points=RUNTIME_POINTS, pairs=16, repeats=10),
    },
    notes=(
        "Weights are the configs' initialisation (nothing is trained): the LK methods' iteration counts, and so "
        "their time, depend on the weights; the mean iterations are in the JSONL (`mean_iterations`).",
        "Ratios to the paper compare different machines; the ratio to DVDs measured in the same process (and the "
        "paper's own ratio to DVDs beside it) is the comparable number.",
        f"Pairs carry Gaussian noise σ {NOISE_SIGMA} (the paper's pairs are noisy, σ not stated).",
    ),
)
"""``lcreg reproduce runtime``."""


@dataclass(frozen=True)
class RuntimeRun(PresetRun):
    """The runtime experiment under one preset, seeds and data, writing ``<out>/<stem>.{md,jsonl,png}``."""

    experiment: RuntimeExperiment

    @property
    def budget(self) -> RuntimeBudget:
        """The preset's budget."""
        return cast(RuntimeBudget, self.experiment.budgets[self.preset])

    def devices(self) -> list[str]:
        """``["cpu"]``, plus ``"cuda"`` when the budget asks for it and a GPU is available."""
        return ["cpu", *(["cuda"] if self.budget.cuda and torch.cuda.is_available() else [])]

    def methods_on(self, device: str) -> list[str]:
        """The methods measured on ``device`` (the Open3D ones on the CPU only)."""
        return [m for m in self.experiment.methods if device == "cpu" or METHODS[m].learned]

    def key(self, method: str, points: int, seed: int, device: str) -> dict[str, Any]:
        """The :data:`KEY_FIELDS` of a measurement."""
        data = self.data.describe() + f", noise σ {NOISE_SIGMA}"
        values = (self.experiment.name, method, points, seed, device, self.budget.describe(), data)
        return dict(zip(KEY_FIELDS, values))

    def open_log(self) -> ResultLog:
        """The JSONL (measurements of every budget and data; rows are told apart by their key)."""
        return ResultLog(self.log_path, KEY_FIELDS)

    def rows(self, log: ResultLog) -> dict[tuple[str, str, int], list[dict[str, Any]]]:
        """The newest row of every seed by (device, method, points), for this run's budget and data."""
        found: dict[tuple[str, str, int], list[dict[str, Any]]] = {}
        for device in self.devices():
            for method in self.methods_on(device):
                for n in self.budget.points:
                    rows = [log.find(**self.key(method, n, s, device)) for s in self.seeds]
                    found[(device, method, n)] = [r for r in rows if r is not None]
        return found


Pairs = Callable[[DataChoice, int, int, int], tuple[torch.Tensor, torch.Tensor]]
"""``pairs(data, points, count, seed) -> (points_src, points_ref)``, each ``(count, points, 3)``."""


def modelnet_pairs(data: DataChoice, points: int, count: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The first ``count`` test pairs of ``data`` at ``points`` points, drawn with pair seed ``seed``."""
    protocol = cast("Protocol", data.protocol)
    batches, _ = pair_batches(
        data.root,
        pairs=count,
        num_points=points,
        batch_size=count,
        protocol=protocol,
        seed=seed,
        noise_sigma=NOISE_SIGMA,
    )
    return batches[0].points_src, batches[0].points_ref


def measure_runtime(
    run: RuntimeRun,
    progress: Callable[[str], None] = lambda _: None,
    rerun: bool = False,
    pairs: Pairs = modelnet_pairs,
) -> ResultLog:
    """Measure every (device, method, points, seed) of ``run`` whose row is not in the JSONL, appending each row.

    Methods are built once per device (only if a row of theirs is missing); every method registers the same pairs.

    Args:
        run: What to measure.
        progress: Called with one line per method and device.
        rerun: Measure finished rows again too (their new rows are appended; the newest row counts).
        pairs: Where the pairs come from (:func:`modelnet_pairs`).

    Returns:
        The JSONL log with every row.
    """
    log = run.open_log()
    budget = run.budget
    cache: dict[tuple[int, int], tuple[torch.Tensor, torch.Tensor]] = {}
    for device in run.devices():
        for method in run.methods_on(device):
            todo = [
                (n, s)
                for n in budget.points
                for s in run.seeds
                if rerun or not log.done(**run.key(method, n, s, device))
            ]
            if not todo:
                progress(f"{method} ({device}): measured before, skipped")
                continue
            model = build(method).to(device)
            for n, seed in todo:
                src, ref = cache.setdefault((n, seed), pairs(run.data, n, budget.pairs, seed))
                with torch.no_grad():
                    speed = registration_speed(model, src, ref, 1, budget.repeats)
                log.append(
                    {
                        **run.key(method, n, seed, device),
                        "preset": run.preset,
                        "ms_per_pair": speed.ms_per_pair,
                        "mean_iterations": speed.mean_iterations,
                        "pairs": len(src),
                        "repeats": budget.repeats,
                        "machine": machine_line(device),
                    }
                )
            done = run.rows(log)[(device, method, budget.points[0])]
            progress(f"{method} ({device}): {format_mean_std([r['ms_per_pair'] for r in done], '.1f', '.1f')} ms/pair")
    return log


def _mean(rows: Sequence[Mapping[str, Any]]) -> float:
    return statistics.fmean(r["ms_per_pair"] for r in rows)


def _dvds_ratio(rows: Sequence[Mapping[str, Any]], dvds: Sequence[Mapping[str, Any]]) -> str:
    """Mean over seeds of ``ms / DVDs' ms`` on the same pairs (same seed, same process)."""
    by_seed = {r["seed"]: r["ms_per_pair"] for r in dvds}
    ratios = [r["ms_per_pair"] / by_seed[r["seed"]] for r in rows if r["seed"] in by_seed]
    return f"{statistics.fmean(ratios):.2f}×" if ratios else "–"


def _table(run: RuntimeRun, found: Mapping[tuple[str, str, int], Sequence[Mapping[str, Any]]], device: str) -> str:
    header = ["method", "points", "ours ms/pair", "paper ms/pair", "ours / paper", "÷ DVDs (ours)", "÷ DVDs (paper)"]
    body = []
    for method in run.methods_on(device):
        for n in run.budget.points:
            rows = found[(device, method, n)]
            paper = run.experiment.paper_ms(method, n)
            paper_dvds = run.experiment.paper_ms("dvds", n)
            body.append(
                [
                    METHODS[method].label,
                    n,
                    format_mean_std([r["ms_per_pair"] for r in rows], ".1f", ".1f") if rows else "not run",
                    "–" if paper is None else f"{paper:g}",
                    f"{_mean(rows) / paper:.2f}×" if rows and paper else "–",
                    _dvds_ratio(rows, found.get((device, "dvds", n), [])),
                    f"{paper / paper_dvds:.2f}×" if paper and paper_dvds else "–",
                ]
            )
    return markdown_table(header, body)


def render_runtime(run: RuntimeRun, log: ResultLog, command: str) -> str:
    """The Markdown report: per device, ours (mean ± std over seeds) beside the paper's ms and the ratios."""
    found = run.rows(log)
    finished = sum(len(rows) for rows in found.values())
    expected = len(found) * len(run.seeds)
    lines = [
        f"# {run.experiment.title}",
        "",
        f"`{command}`",
        "",
        f"- Paper: {run.experiment.paper_table}; measured on a {RUNTIME_MACHINE}.",
        f"- Ours: {'; '.join(f'{d}: {machine_line(d)}' for d in run.devices())}.",
        f"- Budget `{run.preset}`: {run.budget.describe()} at {'/'.join(map(str, run.budget.points))} points; "
        f"data: {run.data.describe()}, noise σ {NOISE_SIGMA}.",
        f"- Seeds {', '.join(map(str, run.seeds))} (each draws other pairs); ours is mean ± sample std over seeds.",
        f"- Measurements finished: {finished} of {expected}.",
        *(f"- {note}" for note in run.experiment.notes),
    ]
    for device in run.devices():
        where = "GPU for learned methods" if device == "cuda" else "CPU, every method"
        lines += ["", f"## {device} ({where})", "", _table(run, found, device)]
    return "\n".join(lines) + "\n"


def _draw(
    ax: Axes, run: RuntimeRun, found: Mapping[tuple[str, str, int], Sequence[Mapping[str, Any]]], device: str
) -> None:
    """Ours (mean ± std over seeds, solid) and the paper's (dashed, hollow markers) per method, log y."""
    for j, method in enumerate(run.methods_on(device)):
        colour = f"C{j % 10}"
        xs = [n for n in run.budget.points if found[(device, method, n)]]
        means = [_mean(found[(device, method, n)]) for n in xs]
        stds = [
            statistics.stdev(r["ms_per_pair"] for r in found[(device, method, n)])
            if len(found[(device, method, n)]) > 1
            else 0.0
            for n in xs
        ]
        if xs:
            ax.errorbar(
                xs,
                means,
                stds,
                color=colour,
                marker="o",
                markersize=4,
                linewidth=1.4,
                capsize=3,
                label=METHODS[method].label,
            )
        paper = [(n, v) for n in RUNTIME_POINTS if (v := run.experiment.paper_ms(method, n)) is not None]
        if paper:
            ax.plot(
                *zip(*paper),
                color=colour,
                linestyle="--",
                marker="s",
                markersize=4,
                markerfacecolor="none",
                linewidth=1.0,
                alpha=0.8,
            )
    ax.set_yscale("log")
    ax.set_xscale("log")
    ticks = sorted({*RUNTIME_POINTS, *run.budget.points})
    ax.set_xticks(ticks, [str(t) for t in ticks])
    ax.minorticks_off()
    ax.margins(x=0.06)
    ax.set_xlabel("points per cloud", fontsize=9)
    ax.set_ylabel("ms per pair (log)", fontsize=9)
    ax.set_title(f"{device}: {machine_line(device)}", fontsize=8)
    ax.tick_params(labelsize=8)
    ax.grid(True, which="both", alpha=0.3, linewidth=0.5)


def plot_runtime(run: RuntimeRun, log: ResultLog) -> list[Path]:
    """``<out>/<stem>.png``: ms per pair vs points per method, one panel per device; none when nothing is measured."""
    found = run.rows(log)
    if not any(found.values()):
        return []
    from matplotlib.lines import Line2D

    devices = run.devices()
    fig = agg_figure(5.2 * len(devices) + 2.4, 4.6, DPI, "lcreg reproduce plots")
    axes = fig.subplots(1, len(devices), squeeze=False).ravel()
    for ax, device in zip(axes, devices):
        _draw(ax, run, found, device)
    handles, _ = axes[0].get_legend_handles_labels()
    handles += [
        Line2D([], [], color="0.3", marker="o", markersize=4, label="ours (mean ± std)"),
        Line2D(
            [],
            [],
            color="0.3",
            linestyle="--",
            marker="s",
            markerfacecolor="none",
            markersize=4,
            label="paper (Titan Xp / E5-2620)",
        ),
    ]
    fig.legend(handles=handles, loc="outside right center", fontsize=8, frameon=False)
    seeds = ", ".join(map(str, run.seeds))
    fig.suptitle(
        f"{run.experiment.title}\nbudget {run.preset}, {run.budget.describe()}, seeds {seeds}; lower is better",
        fontsize=9,
    )
    return [save_png(fig, run.file_stem.with_suffix(".png"))]
