"""Evaluate registration models on the same deterministic pairs and tabulate the results.

Used by ``benchmarks/`` scripts; every method goes through :meth:`RegistrationModule.register` and the same
:func:`lcreg.metrics.registration.registration_metrics`, so numbers are comparable.
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import dataclass, field

import torch

from lcreg.metrics.registration import PerPairErrors, registration_metrics
from lcreg.models.base import RegistrationModule
from lcreg.types import RegistrationBatch

__all__ = ["EvaluationReport", "evaluate", "format_mean_std", "markdown_table", "mean_std_row"]

COLUMNS = (
    ("rmse_r_deg", "RMSE(R) °"),
    ("mae_r_deg", "MAE(R) °"),
    ("rmse_t", "RMSE(t)"),
    ("mae_t", "MAE(t)"),
    ("rre_median_deg", "median RRE °"),
    ("recall_r2_t0p01", "recall (2°, 0.01)"),
    ("recall_r5_t0p05", "recall (5°, 0.05)"),
)


@dataclass
class EvaluationReport:
    """Metrics, per-pair errors and timing of one method on one set of pairs."""

    name: str
    metrics: dict[str, float]
    rotation_error_deg: torch.Tensor
    translation_error: torch.Tensor
    ms_per_pair: float
    num_pairs: int
    extra: dict[str, float] = field(default_factory=dict)


def evaluate(model: RegistrationModule, batches: Iterable[RegistrationBatch], name: str) -> EvaluationReport:
    """Register every batch with ``model.register`` and compute the standard metrics.

    Args:
        model: Any registration module (eval mode is set by ``register``).
        batches: Batches with ground truth (``transform_ref_src``).
        name: Row label.

    Returns:
        The report; ``ms_per_pair`` is the wall time of ``register`` divided by the number of pairs.
    """
    metrics = registration_metrics()
    pairs = PerPairErrors()
    seconds, count, iters = 0.0, 0, 0.0
    for batch in batches:
        if batch.transform_ref_src is None:
            raise ValueError("evaluation needs batches with a ground-truth `transform_ref_src`")
        start = time.perf_counter()
        result = model.register(batch.points_src, batch.points_ref)
        seconds += time.perf_counter() - start
        count += len(batch)
        iters += float(result.num_iters.float().sum())
        kwargs = {"transform_pred": result.transform_ref_src.float(), "transform_gt": batch.transform_ref_src.float()}
        metrics.update(**kwargs)
        pairs.update(**kwargs)
    values = {k: float(v) for k, v in metrics.compute().items()}
    rot, trans = pairs.compute()
    return EvaluationReport(
        name, values, rot, trans, 1000 * seconds / max(count, 1), count, {"mean_iterations": iters / max(count, 1)}
    )


def markdown_table(reports: list[EvaluationReport]) -> str:
    """A Markdown table with one row per report (RMSE/MAE of R in degrees, of t in point units, recalls in %)."""
    head = "| method | " + " | ".join(c[1] for c in COLUMNS) + " | ms/pair | pairs |"
    sep = "|---" * (len(COLUMNS) + 3) + "|"
    rows = []
    for r in reports:
        cells = []
        for key, _ in COLUMNS:
            v = r.metrics[key]
            cells.append(f"{100 * v:.1f} %" if key.startswith("recall") else f"{v:.4g}")
        rows.append(f"| {r.name} | " + " | ".join(cells) + f" | {r.ms_per_pair:.1f} | {r.num_pairs} |")
    return "\n".join([head, sep, *rows])


def format_mean_std(values: list[float], mean_fmt: str = ".3g", std_fmt: str = ".2g", scale: float = 1.0) -> str:
    """``"mean ± std"`` of ``values`` times ``scale`` (sample std; 0 for a single value)."""
    t = torch.tensor(values, dtype=torch.float64) * scale
    std = float(t.std()) if len(values) > 1 else 0.0
    return f"{float(t.mean()):{mean_fmt}} ± {std:{std_fmt}}"


def _cell(key: str, values: list[float]) -> str:
    if key.startswith("recall"):
        return format_mean_std(values, scale=100.0) + " %"
    return format_mean_std(values)


def mean_std_row(reports: list[EvaluationReport], name: str) -> str:
    """One Markdown row with ``mean ± std`` over ``reports`` (e.g. seeds) for every column of :func:`markdown_table`."""
    cells = [_cell(key, [r.metrics[key] for r in reports]) for key, _ in COLUMNS]
    ms = _cell("ms", [r.ms_per_pair for r in reports])
    return f"| {name} | " + " | ".join(cells) + f" | {ms} | {reports[0].num_pairs} |"
