"""Benchmark output: Markdown tables, ``mean ± std`` cells, resumable JSONL results and the machine line."""

from __future__ import annotations

import json
import math
import platform
import tempfile
from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

if TYPE_CHECKING:
    from lcreg.experiments.evaluation import EvaluationReport

__all__ = [
    "REPORT_COLUMNS",
    "ResultLog",
    "format_mean_std",
    "machine_line",
    "markdown_row",
    "markdown_table",
    "mean_std_row",
    "output_path",
    "report_table",
    "significant",
    "write_or_print",
    "write_text",
]

REPORT_COLUMNS = (
    ("rmse_r_deg", "RMSE(R) °"),
    ("mae_r_deg", "MAE(R) °"),
    ("rmse_t", "RMSE(t)"),
    ("mae_t", "MAE(t)"),
    ("rre_mean_deg", "mean RRE °"),
    ("rre_median_deg", "median RRE °"),
    ("recall_r2_t0p01", "recall (2°, 0.01)"),
    ("recall_r5_t0p05", "recall (5°, 0.05)"),
)
"""Metric keys of :func:`lcreg.experiments.evaluation.evaluate` and their column titles in :func:`report_table`."""


def markdown_row(cells: Sequence[object]) -> str:
    """One Markdown table row; cells are written with ``str``, a ``|`` inside a cell escaped (``|X1| = 64``)."""
    return "| " + " | ".join(str(cell).replace("|", "\\|") for cell in cells) + " |"


def markdown_table(header: Sequence[str], rows: Iterable[Sequence[object]] = ()) -> str:
    """A Markdown table (no trailing newline); with no rows, the header and separator lines (rows follow later)."""
    return "\n".join([markdown_row(header), "|---" * len(header) + "|", *(markdown_row(row) for row in rows)])


def significant(value: float, digits: int = 2) -> str:
    """``value`` to ``digits`` significant digits in fixed-point notation, trailing zeros kept.

    1.02 is ``"1.0"``, not ``format``'s ``"1"`` (``.2g``), which reads as a spread known to one digit; 0 is ``"0"``,
    123 is ``"120"``.
    """
    if value == 0 or not math.isfinite(value):
        return f"{value:g}"
    exponent = math.floor(math.log10(abs(value)))
    decimals = digits - 1 - exponent
    if math.floor(math.log10(abs(round(value, decimals)))) > exponent:  # rounding carried: 0.996 is "1.0", not "1.00"
        decimals -= 1
    return f"{round(value, decimals):.{max(decimals, 0)}f}"


def format_mean_std(
    values: Sequence[float],
    mean_fmt: str | None = None,
    std_fmt: str | None = None,
    scale: float = 1.0,
    digits: int = 3,
) -> str:
    """``"mean ± std"`` of ``values`` times ``scale`` (sample standard deviation; 0 for a single value).

    Args:
        values: The values (e.g. one per seed).
        mean_fmt: A format spec for the mean; ``None`` (default) gives it ``digits`` significant digits with trailing
            zeros kept (:func:`significant`: 2.00, not ``.3g``'s 2, which reads as a mean known to one digit).
        std_fmt: A format spec for the spread; ``None`` (default) gives it two significant digits.
        scale: Multiplies every value (100 for a percentage).
        digits: Significant digits of the mean when ``mean_fmt`` is ``None``.
    """
    t = torch.tensor(list(values), dtype=torch.float64) * scale
    std = float(t.std()) if len(t) > 1 else 0.0
    mean = float(t.mean())
    spread = significant(std) if std_fmt is None else f"{std:{std_fmt}}"
    return f"{significant(mean, digits) if mean_fmt is None else format(mean, mean_fmt)} ± {spread}"


def _metric_cell(key: str, value: float) -> str:
    return f"{100 * value:.1f} %" if key.startswith("recall") else f"{value:.4g}"


def report_table(reports: Sequence[EvaluationReport]) -> str:
    """One row per report: RMSE/MAE of R (degrees) and t (point units), median RRE, recalls (%), ms/pair, pairs."""
    header = ["method", *(title for _, title in REPORT_COLUMNS), "ms/pair", "pairs"]
    rows = [
        [r.name, *(_metric_cell(k, r.metrics[k]) for k, _ in REPORT_COLUMNS), f"{r.ms_per_pair:.1f}", r.num_pairs]
        for r in reports
    ]
    return markdown_table(header, rows)


def _mean_std_cell(key: str, values: list[float]) -> str:
    if key.startswith("recall"):
        return format_mean_std(values, scale=100.0) + " %"
    return format_mean_std(values)


def mean_std_row(reports: Sequence[EvaluationReport], name: str) -> str:
    """One row of :func:`report_table` with ``mean ± std`` over ``reports`` (e.g. seeds) in every column."""
    cells = [_mean_std_cell(key, [r.metrics[key] for r in reports]) for key, _ in REPORT_COLUMNS]
    ms = _mean_std_cell("ms", [r.ms_per_pair for r in reports])
    return markdown_row([name, *cells, ms, reports[0].num_pairs])


class ResultLog:
    """Finished benchmark rows in a JSONL file: appended as they finish, read back so a rerun skips them.

    Args:
        path: The ``.jsonl`` file (created with its folder on the first :meth:`append`).
        key: Fields that identify a row (e.g. ``("key", "setting")``); rows with the same key are the same run.
    """

    def __init__(self, path: str | Path, key: Sequence[str] = ()) -> None:
        self.path = Path(path)
        self.key = tuple(key)
        self.rows: list[dict[str, Any]] = []
        if self.path.is_file():
            lines = self.path.read_text(encoding="utf-8").splitlines()
            self.rows = [json.loads(line) for line in lines if line.strip()]

    def find(self, **key: Any) -> dict[str, Any] | None:
        """The last row whose key fields equal ``key`` (``None`` if there is none)."""
        wanted = tuple(key[k] for k in self.key)
        matches = [row for row in self.rows if tuple(row.get(k) for k in self.key) == wanted]
        return matches[-1] if matches else None

    def done(self, **key: Any) -> bool:
        """Whether a row with this key is finished."""
        return self.find(**key) is not None

    def append(self, row: dict[str, Any]) -> dict[str, Any]:
        """Write ``row`` as one JSON line (flushed at once) and keep it; returns it."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with self.path.open("a", encoding="utf-8") as fh:
            fh.write(json.dumps(row) + "\n")
        self.rows.append(row)
        return row


def training_device() -> torch.device:
    """Where a run with Lightning's ``accelerator="auto"`` trains: the GPU when CUDA is available, else the CPU."""
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


def machine_line(device: str | torch.device = "cpu") -> str:
    """``"<processor or GPU>, torch <version>, <n> threads"`` for table headers.

    A header of runs Lightning trained names :func:`training_device`, not the default CPU.
    """
    device = torch.device(device)
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else platform.processor() or platform.machine()
    return f"{name} ({device.type}), torch {torch.__version__}, {torch.get_num_threads()} threads"


def machines_of(rows: Iterable[Mapping[str, Any]]) -> str:
    """The machines that trained ``rows`` (their ``"machine"`` field), with run counts; no rows: this machine.

    The rows of one queue job may come from a CPU and a lent GPU; rows written before rows recorded it count as not
    recorded. With no rows the header names where this machine would train (:func:`training_device`).
    """
    counts = Counter(r.get("machine") for r in rows)
    if not counts:
        return machine_line(training_device())
    named = sorted(counts.items(), key=lambda item: (item[0] is None, str(item[0])))
    return "; ".join(f"{name or 'not recorded (rows written before lcreg recorded it)'}: {n} runs" for name, n in named)


def write_text(path: str | Path, text: str) -> Path:
    """Write ``text`` to ``path`` (parent folders created); returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
    return path


def output_path(out: str | None, filename: str, smoke: bool) -> Path | None:
    """Where a script writes: ``out``; in a smoke run without ``out``, ``filename`` in a new temporary folder."""
    if out:
        return Path(out)
    return Path(tempfile.mkdtemp(prefix="lcreg-smoke-")) / filename if smoke else None


def write_or_print(text: str, out: str | None, filename: str, smoke: bool) -> Path | None:
    """Write a script's report to :func:`output_path` and say where, or print it when there is no path."""
    path = output_path(out, filename, smoke)
    if path is None:
        print(text, end="")
        return None
    write_text(path, text)
    print(f"wrote {path}")
    return path
