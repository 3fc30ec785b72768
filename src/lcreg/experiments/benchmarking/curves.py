"""Learning curves of ``lcreg fit`` runs: Lightning's ``metrics.csv`` read back, seeds aggregated, figures drawn.

Lightning's ``CSVLogger`` writes ``runs/<name>/version_<k>/metrics.csv``: columns ``epoch``, ``step`` and one per
logged key, sparse rows (training rows every ``log_every_n_steps``, validation rows at their cadence, epoch-end
rows with the ``_epoch`` means). :func:`read_metrics` turns one file into a :class:`Series` per key (``train/x_step``
read as ``train/x``; an ``_epoch`` variant only when nothing finer was logged). Runs are grouped by a label (several
seeds of one variant share it), :func:`aggregate` aligns the seeds of a label on ``step`` (mean, sample std, min,
max) and :func:`plot_curves` draws one PNG per figure of :data:`FIGURES` (panels whose keys no run logged are left
out, and so are figures without panels); keys no figure claims go to ``other.png``. :func:`summary_table` gives the
first (first validation), last and best value of the main metrics per label, ``mean ± std`` over seeds.

The x axis is the optimiser step, or (``load_runs(..., x="pairs")``) the training pairs seen: step × the run's
``batch_size`` from the ``hparams.yaml`` beside its ``metrics.csv`` (:func:`run_batch_size`), which puts runs of
different batch sizes on one axis.

matplotlib (the ``plot`` extra) is imported inside :func:`curve_figures` (which :func:`plot_curves` saves) only, with
the ``Agg`` backend.
"""

from __future__ import annotations

import csv
import fnmatch
import glob
import math
import textwrap
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from lcreg.experiments.benchmarking.writers import format_mean_std, markdown_table
from lcreg.figures import agg_figure, save_png

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure
    from matplotlib.typing import LineStyleType

__all__ = [
    "DPI",
    "FIGURES",
    "LR_SERIES",
    "PANEL_SIZE",
    "SUMMARY_HEADER",
    "SUMMARY_KEYS",
    "X_AXES",
    "Band",
    "CurveFigure",
    "Metrics",
    "Panel",
    "Series",
    "aggregate",
    "canonical_key",
    "curve_figures",
    "ema",
    "figure_pixels",
    "load_runs",
    "lr_changes",
    "plot_curves",
    "read_metrics",
    "run_batch_size",
    "run_files",
    "scale_steps",
    "summary_header",
    "summary_rows",
    "summary_table",
    "write_synthetic_metrics",
]

PANEL_SIZE = (4.0, 3.0)
"""Width and height of one panel, inches."""
DPI = 100
"""Pixels per inch of the written PNGs."""
LEGEND_HEIGHT = 0.45
"""Inches above the panels for the variant legend."""
COLUMNS = 3
"""Panels per figure row."""
TITLE_CHAR_PT = 6.0
"""Width of an average character of the 10 pt figure title, points (wide enough for capitals and digits)."""
X_AXES = {"step": "step", "pairs": "training pairs"}
"""The x axes :func:`load_runs` can put runs on, with their axis labels."""


@dataclass(frozen=True)
class Series:
    """One logged key of one run: increasing unique ``steps`` (int64) and their ``values`` (float64)."""

    steps: np.ndarray
    values: np.ndarray


Metrics = dict[str, Series]
"""The series of one run by canonical key (:func:`canonical_key`)."""
Runs = Mapping[str, Sequence[Metrics]]
"""Runs by label: one :data:`Metrics` per seed."""


@dataclass(frozen=True)
class Band:
    """The seeds of one label on the union of their steps; ``count`` seeds have a value at each step.

    ``std`` is the sample standard deviation (0 where one seed has a value), as in ``format_mean_std``.
    """

    steps: np.ndarray
    mean: np.ndarray
    std: np.ndarray
    low: np.ndarray
    high: np.ndarray
    count: np.ndarray


@dataclass(frozen=True)
class Panel:
    """One axes of a figure: the keys drawn in it (line style per key, colour per label).

    Args:
        title: Axes title.
        keys: Canonical keys or ``fnmatch`` patterns (``"train/*_grad_norm"``), matched in this order.
        ylabel: y-axis label.
        names: Legend names of ``keys`` (default: the key without its ``train/`` or ``val/`` prefix).
        log: Logarithmic y axis (used only when every drawn value is positive).
        scale: Factor of the drawn values (100 for recalls in %).
        by_key: Colour per key and one axes per label (the six twist directions).
    """

    title: str
    keys: tuple[str, ...]
    ylabel: str = ""
    names: tuple[str, ...] = ()
    log: bool = False
    scale: float = 1.0
    by_key: bool = False

    def matches(self, present: Sequence[str]) -> list[str]:
        """The keys of ``present`` drawn in this panel, in the order of :attr:`keys`."""
        found: list[str] = []
        for pattern in self.keys:
            found += [key for key in sorted(present) if fnmatch.fnmatchcase(key, pattern) and key not in found]
        return found

    def name(self, key: str) -> str:
        """Legend name of ``key``: its entry of :attr:`names`, what a pattern's ``*`` matched, or the key unprefixed."""
        if key in self.keys and len(self.names) == len(self.keys):
            return self.names[self.keys.index(key)]
        for pattern in self.keys:
            start, star, end = pattern.partition("*")
            if star and fnmatch.fnmatchcase(key, pattern):
                return key[len(start) : len(key) - len(end)]
        return key.split("/", 1)[-1]


@dataclass(frozen=True)
class CurveFigure:
    """One PNG: ``<name>.png`` with a panel per entry of :attr:`panels` that matches a logged key."""

    name: str
    title: str
    panels: tuple[Panel, ...]


DIRECTIONS = tuple(f"train/j_dir_{d}" for d in ("rx", "ry", "rz", "tx", "ty", "tz"))
VALIDATION = CurveFigure(
    "validation",
    "validation registration",
    (
        Panel(
            "rotation error (RRE)",
            ("val/rre_mean_deg", "val/rre_median_deg", "val/rre_clip5_deg"),
            "degrees",
            ("mean", "median", "mean of min(RRE, 5°)"),
        ),
        Panel("translation error (RTE)", ("val/rte_mean",), "mean RTE"),
        Panel(
            "recall",
            ("val/recall_r5_t0p05", "val/recall_r2_t0p01"),
            "% of pairs",
            ("(5°, 0.05)", "(2°, 0.01)"),
            scale=100.0,
        ),
        Panel("rotation RMSE / MAE", ("val/rmse_r_deg", "val/mae_r_deg"), "degrees", ("RMSE", "MAE")),
        Panel("translation RMSE / MAE", ("val/rmse_t", "val/mae_t"), "", ("RMSE", "MAE")),
    ),
)
JACOBIAN = CurveFigure(
    "jacobian",
    "IC-LK Jacobian and gradient diagnostics (training)",
    (
        Panel("J conditioning σmin/σmax", ("train/j_cond",), "batch median", log=True),
        Panel("J sensitivity σmin/‖φ‖", ("train/j_sensitivity",), "batch median", log=True),
        Panel("gradient norms", ("train/*_grad_norm",), "norm", log=True),
        Panel(
            "per-direction sensitivity ‖J col‖/‖φ‖",
            DIRECTIONS,
            "",
            tuple(d.rsplit("_", 1)[-1] for d in DIRECTIONS),
            log=True,
            by_key=True,
        ),
    ),
)
FIGURES = (VALIDATION, JACOBIAN)
"""Figures with fixed panels; ``training.png`` (one panel per training-loss term) and ``other.png`` follow them."""
LR_SERIES = "train/lr"
"""The learning rate each training step used (:meth:`lcreg.models.training.TrainingLogic._log_learning_rate`)."""
LOSS_ORDER = ("loss", "global", "lc", "recon", "normal")
"""Training-loss terms first in ``training.png`` (then the others alphabetically)."""
SUMMARY_KEYS = (
    "val/rre_mean_deg",
    "val/rre_median_deg",
    "val/rre_clip5_deg",
    "val/pose_clip_r2_t0p01",
    "val/rte_mean",
    "val/recall_r5_t0p05",
    "val/recall_r2_t0p01",
    "val/loss",
    "train/loss",
    "train/j_sensitivity",
    "train/j_cond",
)
"""Keys of :func:`summary_table` (those logged); recalls and the Jacobian diagnostics ``train/j_*`` (how well the
descriptor sees motion) are best when highest, the others when lowest."""


# --------------------------------------------------------------------------------------------------- reading


def canonical_key(key: str) -> tuple[str, int]:
    """``key`` without Lightning's ``_step`` / ``_epoch`` suffix, and its preference (0 ``_step``, 1 none, 2 epoch)."""
    for suffix, rank in (("_step", 0), ("_epoch", 2)):
        if key.endswith(suffix) and len(key) > len(suffix):
            return key[: -len(suffix)], rank
    return key, 1


def _series(points: Mapping[int, float]) -> Series:
    steps = np.array(sorted(points), dtype=np.int64)
    return Series(steps, np.array([points[s] for s in steps], dtype=np.float64))


def segments(path: Path) -> list[Path]:
    """``path`` preceded by the segments of a resumed run, in the order they were written.

    They are the ``metrics.segment<n>.csv`` beside a ``metrics.csv`` (:func:`lcreg.resume.keep_previous_metrics`).
    """
    if path.name != "metrics.csv":
        return [path]
    numbered = {p.stem.removeprefix("metrics.segment"): p for p in path.parent.glob("metrics.segment*.csv")}
    return [numbered[n] for n in sorted((n for n in numbered if n.isdigit()), key=int)] + [path]


def _read_points(path: Path) -> dict[str, dict[int, float]]:
    """Finite values by column and step over the run's :func:`segments` (a repeated step keeps its last value)."""
    points: dict[str, dict[int, float]] = {}
    for part in segments(path):
        with part.open(newline="", encoding="utf-8") as fh:
            for row in csv.DictReader(fh):
                step = int(float(row["step"]))
                for key, text in row.items():
                    if key in (None, "epoch", "step") or not text or not math.isfinite(value := float(text)):
                        continue
                    points.setdefault(key, {})[step] = value
    return points


def read_metrics(path: str | Path) -> Metrics:
    """The series of one ``metrics.csv`` (with the segments of a resumed run before it) by canonical key.

    Of ``train/x_step``, ``train/x`` and ``train/x_epoch`` the first logged one is kept, as ``train/x``; empty
    cells and non-finite values are skipped.

    Raises:
        KeyError: If the file has no ``step`` column.
    """
    path = Path(path)
    chosen: dict[str, tuple[int, dict[int, float]]] = {}
    for column, points in _read_points(path).items():
        key, rank = canonical_key(column)
        if key not in chosen or rank < chosen[key][0]:
            chosen[key] = (rank, points)
    return {key: _series(points) for key, (_, points) in sorted(chosen.items())}


def _training_logs(folder: Path) -> list[Path]:
    """The ``metrics.csv`` files below ``folder``, sorted, without ``lcreg reproduce --retest``'s logs.

    Those lie in ``retest-<precision>/`` folders beside a run's own log and are tests of it, not more seeds.
    """
    found = sorted(folder.rglob("metrics.csv"))
    return [f for f in found if not any(p.startswith("retest-") for p in f.relative_to(folder).parts)]


def run_files(pattern: str | Path) -> list[Path]:
    """The ``metrics.csv`` files of ``pattern``: a file, a folder (searched recursively) or a glob, sorted.

    Raises:
        FileNotFoundError: If nothing matches.
    """
    path = Path(pattern)
    if path.is_dir():
        files = _training_logs(path)
    elif path.is_file():
        files = [path]
    else:
        files = sorted(Path(p) for p in glob.glob(str(pattern), recursive=True))
        files = [f for found in files for f in ([found] if found.is_file() else _training_logs(found))]
    if not files:
        raise FileNotFoundError(f"no metrics.csv at {str(pattern)!r}")
    return files


def _x_label(x: str) -> str:
    """The axis label of ``x``; a name not in :data:`X_AXES` is a ``ValueError``."""
    if x not in X_AXES:
        raise ValueError(f"x must be one of {sorted(X_AXES)}, got {x!r}")
    return X_AXES[x]


def run_batch_size(path: str | Path) -> int:
    """The ``batch_size`` hyper-parameter of the run whose ``metrics.csv`` is ``path`` (its ``hparams.yaml``).

    Raises:
        FileNotFoundError: If there is no ``hparams.yaml`` beside ``path``.
        ValueError: If it has no positive integer ``batch_size``.
    """
    import yaml

    class Lenient(yaml.SafeLoader):
        """Reads Python-tagged values (a logged object) as ``None``."""

    Lenient.add_multi_constructor("", lambda loader, suffix, node: None)
    hparams = Path(path).parent / "hparams.yaml"
    if not hparams.is_file():
        raise FileNotFoundError(f"no hparams.yaml beside {str(path)!r}: its run's batch size is unknown")
    values = yaml.load(hparams.read_text(encoding="utf-8"), Lenient)
    batch = values.get("batch_size") if isinstance(values, dict) else None
    if isinstance(batch, bool) or not isinstance(batch, int) or batch < 1:
        raise ValueError(f"{hparams}: no positive integer batch_size (got {batch!r})")
    return batch


def scale_steps(metrics: Metrics, factor: int) -> Metrics:
    """``metrics`` with every step multiplied by ``factor`` (steps to training pairs: the batch size)."""
    return {key: Series(s.steps * factor, s.values) for key, s in metrics.items()}


def load_runs(runs: Mapping[str, Sequence[str | Path]], x: str = "step") -> dict[str, list[Metrics]]:
    """:func:`read_metrics` of every file (or :func:`run_files` pattern) of each label, in order.

    Args:
        runs: ``metrics.csv`` files or :func:`run_files` patterns by label.
        x: A key of :data:`X_AXES`: ``"step"`` (as logged) or ``"pairs"`` (steps × :func:`run_batch_size`).

    Raises:
        ValueError: If ``x`` is not a key of :data:`X_AXES`.
    """
    _x_label(x)

    def read(path: Path) -> Metrics:
        metrics = read_metrics(path)
        return scale_steps(metrics, run_batch_size(path)) if x == "pairs" else metrics

    return {label: [read(f) for p in patterns for f in run_files(p)] for label, patterns in runs.items()}


# --------------------------------------------------------------------------------------------------- seeds


def aggregate(series: Sequence[Series]) -> Band:
    """The seeds' series aligned on the union of their steps: mean, sample std, min and max of those present.

    Raises:
        ValueError: If ``series`` is empty.
    """
    if not series:
        raise ValueError("aggregate needs at least one series")
    steps = np.unique(np.concatenate([s.steps for s in series]))
    table = np.full((len(series), len(steps)), np.nan)
    for row, s in zip(table, series):
        row[np.searchsorted(steps, s.steps)] = s.values
    present = ~np.isnan(table)
    count = present.sum(axis=0)
    mean = np.where(present, table, 0.0).sum(axis=0) / count
    squares = np.where(present, (table - mean) ** 2, 0.0).sum(axis=0)
    std = np.sqrt(squares / np.maximum(count - 1, 1))
    low = np.where(present, table, np.inf).min(axis=0)
    high = np.where(present, table, -np.inf).max(axis=0)
    return Band(steps, mean, std, low, high, count)


def lr_changes(metrics: Metrics, key: str = LR_SERIES) -> list[tuple[int, float]]:
    """Where a run's logged learning rate changed: the first logged step at each new rate and the factor (new / old).

    The rate is logged every ``log_every_n_steps``, so a step here is within that many steps after the change. A run
    that did not log ``key`` has none.
    """
    series = metrics.get(key)
    if series is None or len(series.values) < 2:
        return []
    values = series.values
    moved = np.flatnonzero(~np.isclose(values[1:], values[:-1], rtol=1e-6, atol=0.0)) + 1
    return [(int(series.steps[i]), float(values[i] / values[i - 1])) for i in moved]


def _seed_series(seeds: Sequence[Metrics], key: str) -> list[Series]:
    return [metrics[key] for metrics in seeds if key in metrics and len(metrics[key].steps)]


# --------------------------------------------------------------------------------------------------- summary


def _higher_is_better(key: str) -> bool:
    name = key.rsplit("/", 1)[-1]
    return "recall" in name or name.startswith("j_")


def _value_cell(key: str, values: Sequence[float]) -> str:
    """``mean ± std`` (a single seed: its value); recalls in %."""
    percent = "recall" in key.rsplit("/", 1)[-1]
    if len(values) == 1:
        return f"{100 * values[0]:.1f} %" if percent else f"{values[0]:.4g}"
    if percent:
        return format_mean_std(values, ".1f", ".1f", scale=100.0) + " %"
    return format_mean_std(values, digits=4)


def _steps_cell(steps: Sequence[int]) -> str:
    return "/".join(str(s) for s in sorted({int(s) for s in steps}))


def _summary_row(key: str, label: str, seeds: Sequence[Series]) -> list[str]:
    best = [int(np.argmax(s.values) if _higher_is_better(key) else np.argmin(s.values)) for s in seeds]
    return [
        key,
        label,
        str(len(seeds)),
        f"{_value_cell(key, [float(s.values[0]) for s in seeds])} @ {_steps_cell([s.steps[0] for s in seeds])}",
        f"{_value_cell(key, [float(s.values[-1]) for s in seeds])} @ {_steps_cell([s.steps[-1] for s in seeds])}",
        _value_cell(key, [float(s.values[i]) for s, i in zip(seeds, best)]),
        _steps_cell([s.steps[i] for s, i in zip(seeds, best)]),
    ]


def summary_header(x: str = "step") -> tuple[str, ...]:
    """The columns of :func:`summary_table` with the x axis ``x`` (a key of :data:`X_AXES`) in their names."""
    return ("metric", "variant", "seeds", f"first @ {x}", f"last @ {x}", "best", f"best at {x}")


SUMMARY_HEADER = summary_header()


def summary_rows(runs: Runs, keys: Sequence[str] = SUMMARY_KEYS) -> list[list[str]]:
    """Rows of :func:`summary_table`: per key (in order), per label that logged it, ``mean ± std`` over seeds.

    Cells: the metric, the label, the seeds that logged it, the first value (first validation for ``val/`` keys)
    and the last value with their steps, the best value (highest recall, lowest anything else) of each seed and the
    steps where the seeds reached it (``/``-separated when they differ). Recalls are in %.
    """
    rows = []
    for key in keys:
        for label, seeds in runs.items():
            if series := _seed_series(seeds, key):
                rows.append(_summary_row(key, label, series))
    return rows


def summary_table(runs: Runs, keys: Sequence[str] = SUMMARY_KEYS, x: str = "step") -> str:
    """:func:`summary_rows` as a Markdown table (:func:`~lcreg.experiments.benchmarking.writers.markdown_table`).

    ``x`` names the x axis the runs were loaded on (:func:`load_runs`) in the column names.
    """
    return markdown_table(summary_header(x), summary_rows(runs, keys))


# --------------------------------------------------------------------------------------------------- figures


LEARNING_RATE = Panel("learning rate", (LR_SERIES,), "lr", log=True)
"""The last panel of ``training.png``: the logged rate (``train/lr``) of each run."""


def _loss_panels(present: Sequence[str]) -> tuple[Panel, ...]:
    """One panel per training-loss term (``train/x`` with its ``val/x``), :data:`LOSS_ORDER` first; the rate last."""
    terms = sorted(
        (key.split("/", 1)[1] for key in present if key.startswith("train/") and key != LR_SERIES),
        key=lambda t: (LOSS_ORDER.index(t) if t in LOSS_ORDER else len(LOSS_ORDER), t),
    )
    names = ("train", "validation")
    losses = tuple(
        Panel("total loss" if t == "loss" else f"{t} loss", (f"train/{t}", f"val/{t}"), "", names, log=True)
        for t in terms
    )
    return (*losses, LEARNING_RATE)


def _layout(present: Sequence[str]) -> list[tuple[CurveFigure, list[tuple[Panel, list[str]]]]]:
    """Each figure with its panels that match a key of ``present`` and the keys they draw (each key drawn once)."""
    left = list(present)
    layout = []
    for fig in FIGURES:
        panels = [(p, p.matches(left)) for p in fig.panels]
        layout.append((fig, [(p, keys) for p, keys in panels if keys]))
        left = [k for k in left if not any(k in keys for _, keys in panels)]
    title = "training losses" + (" and learning rate" if LR_SERIES in left else "")
    for fig in (CurveFigure("training", title, _loss_panels(left)),):
        panels = [(p, keys) for p in fig.panels if (keys := p.matches(left))]
        layout.append((fig, panels))
        left = [k for k in left if not any(k in keys for _, keys in panels)]
    layout.append((CurveFigure("other", "other logged values", ()), [(Panel(k, (k,)), [k]) for k in left]))
    return [(fig, panels) for fig, panels in layout if panels]


def figure_pixels(num_axes: int) -> tuple[int, int]:
    """Width and height (pixels) of a PNG of ``num_axes`` axes: :data:`COLUMNS` per row and the legend above."""
    cols, rows = min(num_axes, COLUMNS), math.ceil(num_axes / COLUMNS)
    return round(cols * PANEL_SIZE[0] * DPI), round((rows * PANEL_SIZE[1] + LEGEND_HEIGHT) * DPI)


def ema(series: Series, weight: float) -> Series:
    """``series`` smoothed by a bias-corrected exponential moving average (``weight`` 0: unchanged; 0.9: smooth)."""
    if weight <= 0:
        return series
    out, acc, norm = np.empty_like(series.values), 0.0, 0.0
    for i, value in enumerate(series.values):
        acc, norm = weight * acc + (1 - weight) * value, weight * norm + (1 - weight)
        out[i] = acc / norm
    return Series(series.steps, out)


AxesSpec = tuple[Panel, list[str], list[str]]
"""A panel, the keys it draws and the labels drawn in it (one label for a ``by_key`` panel)."""


def _axes_specs(panels: Sequence[tuple[Panel, list[str]]], runs: Runs) -> list[AxesSpec]:
    specs: list[AxesSpec] = []
    for panel, keys in panels:
        labels = [label for label, seeds in runs.items() if any(_seed_series(seeds, k) for k in keys)]
        specs += [(panel, keys, [label]) for label in labels] if panel.by_key else [(panel, keys, labels)]
    return specs


STYLES: tuple[LineStyleType, ...] = ("-", "--", ":", "-.")
MARKED = 60
"""Validation series with at most this many points are drawn with a marker on each check."""


def _band(seeds: Sequence[Metrics], key: str, smooth: float) -> Band | None:
    """The seeds' aggregate of ``key`` (training keys smoothed first); ``None`` if no seed logged it."""
    series = _seed_series(seeds, key)
    if not series:
        return None
    raw = key.startswith("val/") or key == LR_SERIES  # a smoothed rate would blur where it dropped
    return aggregate(series if raw else [ema(s, smooth) for s in series])


def _draw(ax: Axes, band: Band, colour: str, style: LineStyleType, scale: float, marked: bool) -> None:
    """Mean line of ``band``; its min–max range shaded where more than one seed has a value."""
    marker = "o" if marked and len(band.steps) <= MARKED else None
    ax.plot(band.steps, band.mean * scale, color=colour, linestyle=style, marker=marker, markersize=3, linewidth=1.2)
    if band.count.max() > 1:
        ax.fill_between(band.steps, band.low * scale, band.high * scale, color=colour, alpha=0.2, linewidth=0)


def _log_scale(ax: Axes, low: float, high: float) -> None:
    """Logarithmic y with plain-number ticks: evenly spaced values within a decade, 1-2-5 within two."""
    from matplotlib.ticker import FuncFormatter, LogLocator, MaxNLocator, NullFormatter

    ax.set_yscale("log")
    if high / low < 100:
        ax.yaxis.set_major_locator(MaxNLocator(5) if high / low < 10 else LogLocator(subs=(1.0, 2.0, 5.0)))
        ax.yaxis.set_major_formatter(FuncFormatter(lambda value, _: f"{value:.3g}"))
        ax.yaxis.set_minor_formatter(NullFormatter())


PANEL_TITLE_PT = 9.0
"""Font size of a panel's title, points."""


def _style_axes(ax: Axes, title: str, ylabel: str, xlabel: str) -> None:
    chars = int(PANEL_SIZE[0] * 72 / (PANEL_TITLE_PT * TITLE_CHAR_PT / 10))  # a 10 pt character is TITLE_CHAR_PT wide
    ax.set_title(textwrap.fill(title, chars, break_long_words=False), fontsize=PANEL_TITLE_PT)
    ax.set_xlabel(xlabel, fontsize=8)
    ax.set_ylabel(ylabel, fontsize=8)
    ax.tick_params(which="both", labelsize=7)
    ax.grid(True, alpha=0.3, which="major", linewidth=0.5)


def _draw_axes(ax: Axes, spec: AxesSpec, runs: Runs, colours: Mapping[str, str], smooth: float, xlabel: str) -> None:
    """One panel: colour per label and style per key, or (``by_key``) colour per key of the one label."""
    from matplotlib.lines import Line2D

    panel, keys, labels = spec
    low, high, handles = math.inf, -math.inf, []
    for j, key in enumerate(keys):
        colour, style = (f"C{j % 10}", "-") if panel.by_key else ("0.3", STYLES[j % len(STYLES)])
        for label in labels:
            if band := _band(runs[label], key, smooth):
                low, high = min(low, float(band.low.min())), max(high, float(band.high.max()))
                _draw(ax, band, colour if panel.by_key else colours[label], style, panel.scale, key.startswith("val/"))
        handles.append(Line2D([], [], color=colour, linestyle=style, label=panel.name(key)))
    _style_axes(ax, f"{panel.title}: {labels[0]}" if panel.by_key else panel.title, panel.ylabel, xlabel)
    if panel.log and low > 0:
        _log_scale(ax, low * panel.scale, high * panel.scale)
    if panel.by_key:  # beside the axes: the lines of the six directions fill it
        ax.legend(handles=handles, fontsize=7, loc="center left", bbox_to_anchor=(1.0, 0.5), frameon=False)
    elif len(keys) > 1:
        ax.legend(handles=handles, fontsize=7, loc="best", framealpha=0.7)


def _legend(fig: Figure, title: str, runs: Runs, colours: Mapping[str, str], labels: Sequence[str]) -> None:
    """The figure's title and its variants once, above the panels (seed counts in the names)."""
    from matplotlib.lines import Line2D

    def name(label: str) -> str:
        return label if len(runs[label]) == 1 else f"{label} ({len(runs[label])} seeds)"

    handles = [Line2D([], [], color=colours[label], linewidth=2, label=name(label)) for label in labels]
    renderer = fig.canvas.get_renderer()  # type: ignore[attr-defined]  # the Agg canvas of agg_figure
    for ncols in range(min(len(handles), 4), 0, -1):  # the most columns (at most 4) whose row fits the width
        legend = fig.legend(
            handles=handles, loc="outside upper center", ncols=ncols, fontsize=8, frameon=False, title=title
        )
        legend.get_title().set_fontsize(10)
        if ncols == 1 or legend.get_window_extent(renderer).width <= fig.bbox.width:
            return
        legend.remove()


def _title(title: str, runs: Runs, specs: Sequence[AxesSpec], smooth: float) -> str:
    """``title`` with what the lines and shades are and the smoothing, where they apply."""
    labels = {label for _, _, labels in specs for label in labels}
    notes = []
    if any(len(runs[label]) > 1 for label in labels):
        notes.append("line: mean over seeds, shade: min–max")
    if smooth > 0 and any(not key.startswith("val/") for _, keys, _ in specs for key in keys):
        notes.append(f"training values smoothed (EMA {smooth:g})")
    return title + (f" ({'; '.join(notes)})" if notes else "")


def _render(title: str, specs: Sequence[AxesSpec], runs: Runs, smooth: float, xlabel: str) -> Figure:
    """Draw ``specs`` on an Agg canvas of :func:`figure_pixels`."""
    width, height = figure_pixels(len(specs))
    fig = agg_figure(width / DPI, height / DPI, DPI, "learning curves")
    axes = fig.subplots(math.ceil(len(specs) / COLUMNS), min(len(specs), COLUMNS), squeeze=False).ravel()
    colours = {label: f"C{i % 10}" for i, label in enumerate(runs)}
    for ax, spec in zip(axes, specs):
        _draw_axes(ax, spec, runs, colours, smooth, xlabel)
    for ax in axes[len(specs) :]:
        ax.set_visible(False)
    drawn = [label for label in runs if any(label in labels for _, _, labels in specs)]
    _legend(fig, _wrapped(_title(title, runs, specs, smooth), width), runs, colours, drawn)
    return fig


def _wrapped(title: str, width_px: int) -> str:
    """``title`` broken into lines that fit ``width_px`` at 10 pt (a one-panel figure is 4 inches wide)."""
    chars = max(20, int(width_px / (TITLE_CHAR_PT * DPI / 72)))
    return textwrap.fill(title, chars, break_long_words=False)


def plot_curves(runs: Runs, out_dir: str | Path, prefix: str = "", smooth: float = 0.0, x: str = "step") -> list[Path]:
    """Write ``<out_dir>/<prefix><figure>.png`` for each figure with a logged key; returns the written files.

    Figures: ``validation`` (RRE mean and median, RTE, recalls at (5°, 0.05) and (2°, 0.01), RMSE/MAE),
    ``jacobian`` (J conditioning and sensitivity, gradient norms, per-direction sensitivity: one panel per label),
    ``training`` (a panel per loss term, training and validation values, log y) and ``other`` (a panel per key
    none of these claims). Panels of keys no run logged are left out. Each label has one colour in every panel,
    named once above the panels; with several seeds the line is their mean and the shade their min–max.

    Args:
        runs: Runs by label, one :data:`Metrics` per seed (:func:`load_runs`).
        out_dir: Folder of the PNGs (created).
        prefix: Start of every file name.
        smooth: :func:`ema` weight of the training (not ``val/``) series, applied per seed before aggregating.
        x: The x axis ``runs`` were loaded on (a key of :data:`X_AXES`; :func:`load_runs`), for its label.
    """
    figures = curve_figures(runs, smooth, x)
    return [save_png(fig, Path(out_dir) / f"{prefix}{name}.png") for name, fig in figures]


def curve_figures(runs: Runs, smooth: float = 0.0, x: str = "step") -> list[tuple[str, Figure]]:
    """The figures of :func:`plot_curves` by name (``validation``, ``jacobian``, ``training``, ``other``), unsaved."""
    xlabel = _x_label(x)
    present = sorted({key for seeds in runs.values() for metrics in seeds for key in metrics})
    figures = []
    for fig, panels in _layout(present):
        if specs := _axes_specs(panels, runs):
            figures.append((fig.name, _render(fig.title, specs, runs, smooth, xlabel)))
    return figures


# --------------------------------------------------------------------------------------------------- smoke data


def _decay(steps: np.ndarray, start: float, end: float, tau: float) -> np.ndarray:
    return end + (start - end) * np.exp(-steps / tau)


def _synthetic_rows(rng: np.random.Generator, steps: int, log_every: int, val_every: int) -> list[dict[str, object]]:
    """Lightning-like sparse rows: training every ``log_every`` steps, validation, epoch ends every 32 steps."""
    rows: list[dict[str, object]] = []
    for s in range(steps):
        noise = rng.lognormal(0.0, 0.1, size=16)
        if (s + 1) % log_every == 0:
            terms = {"loss": 1.0, "global": 0.02, "lc": 0.002, "recon": 1.6, "normal": 1.8}
            row: dict[str, object] = {
                f"train/{t}_step": v * (0.5 + 0.5 * math.exp(-s / 30)) * n for (t, v), n in zip(terms.items(), noise)
            }
            row |= {
                "train/j_cond": 1e-3 * (1 + s / 10) * noise[5],
                "train/j_sensitivity": 1e-2 * noise[6] / (1 + s / 20),
            }
            row |= {d: 10 ** (i / 2 - 2) * noise[7 + i] for i, d in enumerate(DIRECTIONS)}
            row |= {"train/global_grad_norm": 0.08 * noise[13], "train/lc_grad_norm": 0.01 * noise[14]}
            row |= {LR_SERIES: 1e-3 if s < 40 else 1e-4}  # a step schedule's drop at step 40
            rows.append({"epoch": s // 32, "step": s, **row})
        if (s + 1) % val_every == 0:
            rre = float(_decay(np.array(s), 14.0, 4.0, 40.0)) * noise[15]
            val = {
                "val/rre_mean_deg": rre,
                "val/rre_median_deg": 0.6 * rre,
                "val/rte_mean": rre / 400,
                "val/loss": 0.9 * noise[0],
            }
            val |= {"val/recall_r5_t0p05": 1 - rre / 16, "val/recall_r2_t0p01": max(0.0, 0.5 - rre / 30)}
            rows.append({"epoch": s // 32, "step": s, **val})
        if (s + 1) % 32 == 0:
            rows.append({"epoch": s // 32, "step": s, "train/loss_epoch": 0.8 * noise[1]})
    return rows


def write_synthetic_metrics(
    path: str | Path, seed: int = 0, steps: int = 60, log_every: int = 2, val_every: int = 20, batch_size: int = 8
) -> Path:
    """Write a Lightning-like sparse ``metrics.csv`` of a DVDs run (smoke runs and tests); returns the path.

    Training rows every ``log_every`` steps (``train/<term>_step`` losses, Jacobian diagnostics, gradient norms),
    validation rows every ``val_every`` steps and epoch-end rows (``train/loss_epoch``) every 32 steps; values from
    ``numpy.random.default_rng(seed)``. Beside it an ``hparams.yaml`` with ``batch_size`` (:func:`run_batch_size`).
    """
    rows = _synthetic_rows(np.random.default_rng(seed), steps, log_every, val_every)
    columns = ["epoch", "step", *sorted({key for row in rows for key in row} - {"epoch", "step"})]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="", encoding="utf-8") as fh:
        writer = csv.DictWriter(fh, columns)
        writer.writeheader()
        writer.writerows(rows)
    (path.parent / "hparams.yaml").write_text(f"batch_size: {batch_size}\n", encoding="utf-8")
    return path
