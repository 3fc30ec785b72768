"""Evaluate registration models on the same deterministic pairs.

Used by ``benchmarks/`` (through :mod:`lcreg.experiments.benchmarking`); every method goes through
:meth:`RegistrationModule.register` and the same :func:`lcreg.metrics.registration.registration_metrics`, so numbers
are comparable. Tables of reports: :func:`lcreg.experiments.benchmarking.report_table` and
:func:`lcreg.experiments.benchmarking.mean_std_row`.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from functools import partial

import torch

from lcreg.experiments.benchmarking.measure import device_of, timed
from lcreg.metrics.registration import PerPairErrors, registration_metrics
from lcreg.models.base import RegistrationModule
from lcreg.types import RegistrationBatch

__all__ = ["EvaluationReport", "choose_start_angle", "evaluate"]


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
        The report; ``ms_per_pair`` is the wall time of ``register`` (:func:`lcreg.experiments.benchmarking.timed`,
        synchronised on CUDA) summed over the batches and divided by the number of pairs.
    """
    metrics = registration_metrics()
    pairs = PerPairErrors()
    device = device_of(model)
    seconds, count, iters = 0.0, 0, 0.0
    for batch in batches:
        if batch.transform_ref_src is None:
            raise ValueError("evaluation needs batches with a ground-truth `transform_ref_src`")
        result, elapsed = timed(partial(model.register, batch.points_src, batch.points_ref), device)
        seconds += elapsed
        count += len(batch)
        iters += float(result.num_iters.float().sum())
        kwargs = {"transform_pred": result.transform_ref_src.float(), "transform_gt": batch.transform_ref_src.float()}
        metrics.update(**kwargs)
        pairs.update(**kwargs)
    values = {k: float(v) for k, v in metrics.compute().items()}
    rot, trans, _ = pairs.per_pair()
    return EvaluationReport(
        name, values, rot, trans, 1000 * seconds / max(count, 1), count, {"mean_iterations": iters / max(count, 1)}
    )


def choose_start_angle(mean_rre_deg: Mapping[float | None, float]) -> float | None:
    """The rule that sets an IC-LK model's ``eval_start_angles_deg`` on validation pairs, before its one test run.

    The setting with the lowest mean RRE wins; ties go to ``None`` (the single identity start), then to the smaller
    angle (fewer wrong basins reachable, the same cost). Issue 23 fixed this rule in session 10 for the shipped files
    and in session 23 for FMR-Net's goal (c) comparison (``docs/results/converge/history.md``).

    Args:
        mean_rre_deg: Mean RRE (degrees) on the validation pairs per setting: ``None`` for one start, ``a`` for the
            starts at ±a degrees about x, y and z.

    Returns:
        The chosen setting (``None`` or an angle in degrees).

    Raises:
        ValueError: If ``mean_rre_deg`` is empty or holds a value that is not finite.
    """
    if not mean_rre_deg:
        raise ValueError("`mean_rre_deg` is empty: nothing to choose from")
    bad = {angle: value for angle, value in mean_rre_deg.items() if not math.isfinite(value)}
    if bad:
        raise ValueError(f"`mean_rre_deg` must be finite, got {bad}")
    return min(mean_rre_deg, key=lambda angle: (mean_rre_deg[angle], -math.inf if angle is None else angle))
