"""Registration metrics as ``torchmetrics.Metric`` shells over :mod:`lcreg.metrics.functional`.

Every metric keeps the per-pair errors of all updates in list states (``dist_reduce_fx="cat"``, so DDP gathers the
pairs themselves and medians/recalls stay exact) and reduces them in ``compute``. ``update`` takes the keyword
arguments ``transform_pred (B, 4, 4)``, ``transform_gt (B, 4, 4)`` and optionally ``index (B,)`` (the pairs'
dataset indices), so one ``MetricCollection.update(transform_pred=..., transform_gt=..., index=...)`` feeds them
all. With indices, a pair seen twice counts once: DDP's ``DistributedSampler`` pads the evaluation set with repeated
pairs so that every process gets as many batches, and those repeats are dropped in ``compute``.

Failure policy (a diverged estimate with NaN/Inf entries, or any pair whose functional error is NaN):

* recall (:class:`RegistrationRecall`) counts the pair as a failure;
* the averaged metrics never drop it (``torchmetrics``' ``MeanMetric``/``CatMetric`` would, by default) and never
  turn into NaN because of it: its errors are replaced by the worst-case or "no-motion" error,
  rotation error -> 180 degrees, each Euler-angle error -> 180 degrees, translation error -> ``||t_gt||`` and each
  translation-component error -> ``|t_gt|`` (the error of predicting the identity);
* :class:`NumFailed` counts such pairs and :class:`PerPairErrors` returns the raw errors with their NaNs.

Ground-truth transforms must be finite rigid motions (:class:`lcreg.checks.NonFiniteError`, ``ValueError``
otherwise). A summary metric's ``compute`` over zero pairs raises :class:`NoPairsError` (it used to return NaN);
:class:`PerPairErrors` returns empty tensors.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence
from typing import Any

import torch
from torchmetrics import Metric, MetricCollection
from torchmetrics.utilities import dim_zero_cat

from lcreg.checks import check_float, check_rigid, check_shape, check_transform
from lcreg.metrics import functional

__all__ = [
    "EulerRotationMAE",
    "EulerRotationRMSE",
    "NoPairsError",
    "NumFailed",
    "PerPairErrors",
    "PoseErrorClippedMean",
    "RegistrationRecall",
    "RotationErrorClippedMean",
    "RotationErrorMean",
    "RotationErrorMedian",
    "TranslationErrorMean",
    "TranslationMAE",
    "TranslationRMSE",
    "check_recall_thresholds",
    "recall_key",
    "registration_metrics",
]

WORST_ROTATION_DEG = 180.0
STANDARD_RECALL_THRESHOLDS: tuple[tuple[float, float], ...] = ((2.0, 0.01), (5.0, 0.05))
"""The recalls every collection logs, ``(degrees, point units)``: the object protocol's (unit-sphere shapes)."""
_STATES = ("rot_err_deg", "trans_err", "euler_err_deg", "trans_errs", "trans_gt", "index")
_TRANSFORM_STATES = ("transform_pred", "transform_gt")
""":class:`PerPairErrors`' extra states: each pair's estimated and true ``transform_ref_src``."""


class NoPairsError(ValueError):
    """A summary metric was computed over zero pairs (no batch with a ground truth was seen)."""


class _PairErrorMetric(Metric):
    """Accumulates raw per-pair errors; subclasses only implement ``compute``.

    States (lists of per-update tensors, concatenated along dim 0): ``rot_err_deg (P,)``, ``trans_err (P,)``,
    ``euler_err_deg (P, 3)``, ``trans_errs (P, 3)`` (raw, NaN for failed pairs) and ``trans_gt (P, 3)``.
    """

    is_differentiable = False
    full_state_update = False

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        for name in _STATES:
            self.add_state(name, default=[], dist_reduce_fx="cat")

    def update(
        self, transform_pred: torch.Tensor, transform_gt: torch.Tensor, index: torch.Tensor | None = None
    ) -> None:
        """Add a batch of pairs.

        Args:
            transform_pred: Estimated ``transform_ref_src`` ``(B, 4, 4)``; NaN/Inf entries mark a failed pair.
            transform_gt: Ground-truth ``transform_ref_src`` ``(B, 4, 4)``, finite.
            index: Dataset indices of the pairs ``(B,)`` (int); a repeated index counts once. ``None``: every pair
                counts (no repeat can be detected).
        """
        check_transform(transform_gt, "transform_gt")  # dtype, (B, 4, 4), finite
        check_rigid(transform_gt, "transform_gt")
        check_shape(check_float(transform_pred, "transform_pred"), (len(transform_gt), 4, 4), "transform_pred")
        values = {
            "rot_err_deg": functional.rotation_error_deg(transform_pred, transform_gt),
            "trans_err": functional.translation_error(transform_pred, transform_gt),
            "euler_err_deg": functional.euler_errors_deg(transform_pred, transform_gt),
            "trans_errs": functional.translation_errors(transform_pred, transform_gt),
            "trans_gt": transform_gt[:, :3, 3],
            "index": torch.full((len(transform_gt),), -1) if index is None else index.reshape(-1).long(),
        }
        for name, value in values.items():
            getattr(self, name).append(value.detach())

    allow_empty: bool = False
    """``compute`` over zero pairs: ``True`` gives empty tensors, ``False`` raises :class:`NoPairsError`."""

    def _state(self, name: str) -> torch.Tensor:
        """Concatenated state ``name`` (an empty tensor before any update).

        Raises:
            NoPairsError: No pair was added and the metric is a summary (``allow_empty`` false).
        """
        value = getattr(self, name)
        if isinstance(value, list) and not value:
            if not self.allow_empty:
                raise NoPairsError(f"{type(self).__name__}: no pairs to summarise (update() was never called)")
            return torch.empty(0, device=self.device, dtype=torch.int64 if name == "index" else self.dtype)
        return dim_zero_cat(value)[self._first_occurrences()]

    def _first_occurrences(self) -> torch.Tensor:
        """Positions ``(P,)`` of the pairs that count: the first of each dataset index (all when any is unknown)."""
        index = dim_zero_cat(getattr(self, "index")).reshape(-1)  # noqa: B009 (a list state, not Module.index)
        if (index < 0).any():
            return torch.arange(len(index), device=index.device)
        order = torch.sort(index, stable=True).indices  # equal indices stay in update order
        first = torch.ones_like(index, dtype=torch.bool)
        first[1:] = index[order][1:] != index[order][:-1]
        return torch.sort(order[first]).values

    def _failed(self) -> torch.Tensor:
        """Per-pair failure flags ``(P,)``: any raw error of the pair is NaN/Inf."""
        return ~(torch.isfinite(self._state("rot_err_deg")) & torch.isfinite(self._state("trans_err")))

    def _rotation(self) -> torch.Tensor:
        """Isotropic rotation errors ``(P,)`` in degrees, failures at 180."""
        err = self._state("rot_err_deg")
        return torch.where(torch.isfinite(err), err, torch.full_like(err, WORST_ROTATION_DEG))

    def _translation(self) -> torch.Tensor:
        """Translation errors ``(P,)``, failures at ``||t_gt||``."""
        err = self._state("trans_err")
        return torch.where(torch.isfinite(err), err, self._state("trans_gt").reshape(-1, 3).norm(dim=-1))

    def _euler(self) -> torch.Tensor:
        """Euler-angle errors ``(P, 3)`` in degrees, failures at 180 per angle."""
        err = self._state("euler_err_deg").reshape(-1, 3)
        return torch.where(torch.isfinite(err), err, torch.full_like(err, WORST_ROTATION_DEG))

    def _translation_components(self) -> torch.Tensor:
        """Translation component errors ``(P, 3)``, failures at ``|t_gt|`` per component."""
        err = self._state("trans_errs").reshape(-1, 3)
        return torch.where(torch.isfinite(err), err, self._state("trans_gt").reshape(-1, 3).abs())


class EulerRotationRMSE(_PairErrorMetric):
    """DCP's RMSE(R): root mean square of the ``[z, y, x]`` Euler errors over all pairs and angles, degrees."""

    higher_is_better = False

    def compute(self) -> torch.Tensor:
        """Return the scalar RMSE in degrees."""
        return self._euler().square().mean().sqrt()


class EulerRotationMAE(_PairErrorMetric):
    """DCP's MAE(R): mean absolute Euler error over all pairs and angles, degrees."""

    higher_is_better = False

    def compute(self) -> torch.Tensor:
        """Return the scalar MAE in degrees."""
        return self._euler().abs().mean()


class TranslationRMSE(_PairErrorMetric):
    """DCP's RMSE(t): root mean square over all pairs and the 3 translation components, point units."""

    higher_is_better = False

    def compute(self) -> torch.Tensor:
        """Return the scalar RMSE."""
        return self._translation_components().square().mean().sqrt()


class TranslationMAE(_PairErrorMetric):
    """DCP's MAE(t): mean absolute translation component error over all pairs and components, point units."""

    higher_is_better = False

    def compute(self) -> torch.Tensor:
        """Return the scalar MAE."""
        return self._translation_components().abs().mean()


class RotationErrorMean(_PairErrorMetric):
    """Mean isotropic rotation error (RRE) in degrees."""

    higher_is_better = False

    def compute(self) -> torch.Tensor:
        """Return the scalar mean in degrees."""
        return self._rotation().mean()


class RotationErrorMedian(_PairErrorMetric):
    """Median isotropic rotation error in degrees (mean of the two middle values for an even count)."""

    higher_is_better = False

    def compute(self) -> torch.Tensor:
        """Return the scalar median in degrees."""
        return torch.quantile(self._rotation(), 0.5)


class RotationErrorClippedMean(_PairErrorMetric):
    """Mean of ``min(RRE, clip_deg)`` in degrees: the model-selection error of long training runs.

    A pair that fails counts as ``clip_deg`` however far off it is, so one failed pair moves the value by at most
    ``clip_deg / pairs`` (the plain mean moves by up to ``180 / pairs``), while pairs below the clip count with their
    exact error (the median ignores them once they are below it). It ranks checkpoints by accuracy and failure
    rate at once.

    Args:
        clip_deg: Clip in degrees (> 0); 5 is the looser recall threshold of the object protocol.
        **kwargs: Forwarded to ``torchmetrics.Metric``.
    """

    higher_is_better = False

    def __init__(self, clip_deg: float = 5.0, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        if not _positive_number(clip_deg):
            raise ValueError(f"`clip_deg` must be a finite number > 0, got {clip_deg!r}")
        self.clip_deg = float(clip_deg)

    def compute(self) -> torch.Tensor:
        """Return the scalar clipped mean in degrees (failed pairs count as ``clip_deg``)."""
        return self._rotation().clamp(max=self.clip_deg).mean()


class PoseErrorClippedMean(_PairErrorMetric):
    """Mean of ``min(max(RRE / rot_unit_deg, RTE / trans_unit), clip)``: the pose error in recall-threshold units.

    A pair is within the recall at ``(rot_unit_deg, trans_unit)`` exactly when its value is below 1, so this is a
    smooth, translation-aware companion of that recall for model selection: it counts rotation and translation alike
    (:class:`RotationErrorClippedMean` sees only the rotation), and a failed pair counts as ``clip`` however far off.

    Args:
        rot_unit_deg: Rotation unit in degrees (> 0), the recall's rotation threshold.
        trans_unit: Translation unit in point units (> 0), the recall's translation threshold.
        clip: Clip in units (> 0); 2.5 caps a pair at (5 deg, 0.025) for the (2 deg, 0.01) units.
        **kwargs: Forwarded to ``torchmetrics.Metric``.
    """

    higher_is_better = False

    def __init__(self, rot_unit_deg: float = 2.0, trans_unit: float = 0.01, clip: float = 2.5, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        for name, value in (("rot_unit_deg", rot_unit_deg), ("trans_unit", trans_unit), ("clip", clip)):
            if not _positive_number(value):
                raise ValueError(f"`{name}` must be a finite number > 0, got {value!r}")
        self.rot_unit_deg, self.trans_unit, self.clip = float(rot_unit_deg), float(trans_unit), float(clip)

    def compute(self) -> torch.Tensor:
        """Return the scalar clipped mean in units (failed pairs count as ``clip``)."""
        units = torch.maximum(self._rotation() / self.rot_unit_deg, self._translation() / self.trans_unit)
        return torch.where(self._failed(), torch.full_like(units, self.clip), units.clamp(max=self.clip)).mean()


class TranslationErrorMean(_PairErrorMetric):
    """Mean translation error (RTE) ``||t_pred - t_gt||`` in point units."""

    higher_is_better = False

    def compute(self) -> torch.Tensor:
        """Return the scalar mean."""
        return self._translation().mean()


class RegistrationRecall(_PairErrorMetric):
    """Fraction of pairs with rotation error ``< rot_thr_deg`` and translation error ``< trans_thr``.

    Args:
        rot_thr_deg: Rotation threshold in degrees.
        trans_thr: Translation threshold in point units.
        **kwargs: Forwarded to ``torchmetrics.Metric``.
    """

    higher_is_better = True

    def __init__(self, rot_thr_deg: float = 2.0, trans_thr: float = 0.01, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        if not rot_thr_deg > 0 or not trans_thr > 0:
            raise ValueError(f"thresholds must be > 0, got rot_thr_deg={rot_thr_deg}, trans_thr={trans_thr}")
        self.rot_thr_deg = rot_thr_deg
        self.trans_thr = trans_thr

    def compute(self) -> torch.Tensor:
        """Return the recall in ``[0, 1]``; failed (NaN) pairs count as misses."""
        return functional.registration_recall(
            self._state("rot_err_deg"), self._state("trans_err"), self.rot_thr_deg, self.trans_thr
        )


class NumFailed(_PairErrorMetric):
    """Number of failed pairs (non-finite estimate), as a float tensor."""

    higher_is_better = False

    def compute(self) -> torch.Tensor:
        """Return the count of failed pairs."""
        return self._failed().sum().to(self.dtype)


class PerPairErrors(_PairErrorMetric):
    """Raw per-pair errors for curves and tables (failed pairs keep their NaN).

    ``compute`` returns ``(rot_err_deg (P,), trans_err (P,), index (P,))`` concatenated over all updates (and
    processes), empty before any update; :meth:`transforms` the pairs' estimated and true transforms.
    """

    allow_empty = True

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        for name in _TRANSFORM_STATES:
            self.add_state(name, default=[], dist_reduce_fx="cat")

    def update(
        self, transform_pred: torch.Tensor, transform_gt: torch.Tensor, index: torch.Tensor | None = None
    ) -> None:
        """Add a batch of pairs, keeping their transforms too (arguments as the summary metrics' ``update``)."""
        super().update(transform_pred, transform_gt, index)
        for name, value in zip(_TRANSFORM_STATES, (transform_pred, transform_gt), strict=True):
            getattr(self, name).append(value.detach())

    def transforms(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``(transform_pred (P, 4, 4), transform_gt (P, 4, 4))`` as given, in the order of :meth:`per_pair`.

        A failed pair keeps its NaN/Inf prediction. Under DDP every process's pairs, each once.
        """
        with self.sync_context():
            return tuple(self._state(name).reshape(-1, 4, 4) for name in _TRANSFORM_STATES)  # type: ignore[return-value]

    def compute(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Return ``(rotation errors in degrees, translation errors, dataset indices)``, each ``(P,)``.

        Indices are ``-1`` where ``update`` got none. Under DDP they cover every process's pairs, each once.
        """
        return self._state("rot_err_deg"), self._state("trans_err"), self._state("index")

    def per_pair(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The per-pair errors of :meth:`compute`, each ``(P,)`` even for a single pair.

        torchmetrics squeezes a one-element result of ``compute`` to a 0-d tensor; use this, not ``compute``.
        """
        rot, trans, index = self.compute()
        return rot.reshape(-1), trans.reshape(-1), index.reshape(-1)

    def components(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The per-pair parts of DCP's four figures, in the order of :meth:`per_pair`.

        Returns:
            ``(euler_err_deg (P, 3), trans_errs (P, 3))``: the signed ``[z, y, x]`` Euler-angle errors in degrees and
            the signed translation component errors, as :class:`EulerRotationRMSE`, :class:`EulerRotationMAE`,
            :class:`TranslationRMSE` and :class:`TranslationMAE` count them (a failed pair at 180 degrees per angle
            and ``|t_gt|`` per component). So RMSE(R) over any subset of pairs is the root mean square of its rows,
            MAE(R) their mean absolute value, and likewise RMSE(t), MAE(t): figures per class, say, of one test.
            Under DDP every process's pairs, each once, as :meth:`per_pair` returns them.
        """
        with self.sync_context():  # compute() gathers the processes' states; a method of its own must ask for it
            return self._euler().reshape(-1, 3), self._translation_components().reshape(-1, 3)


def recall_key(rot_thr_deg: float, trans_thr: float) -> str:
    """The metric name of the recall at ``(rot_thr_deg, trans_thr)``: ``recall_r{rot}_t{trans}``, ``.`` as ``p``.

    Module names cannot contain ``.``; each threshold is written as Python prints the float, without a trailing
    ``.0``, so distinct thresholds get distinct names.

    Example:
        >>> recall_key(15.0, 0.3), recall_key(5, 2), recall_key(2.0, 0.01)
        ('recall_r15_t0p3', 'recall_r5_t2', 'recall_r2_t0p01')
    """
    return f"recall_r{_number(rot_thr_deg)}_t{_number(trans_thr)}"


def _number(value: float) -> str:
    """``value`` as in a metric name: ``15.0 -> "15"``, ``0.3 -> "0p3"``."""
    text = repr(float(value))
    return text.removesuffix(".0").replace(".", "p")


def check_recall_thresholds(value: Any, name: str = "recall_thresholds") -> tuple[tuple[float, float], ...]:
    """Validated recall thresholds: a sequence of ``(rotation degrees, translation in point units)`` pairs.

    Args:
        value: The pairs, e.g. ``[[15, 0.3]]`` (YAML) or ``((5.0, 2.0),)``.
        name: The argument named in the error.

    Returns:
        The pairs as a tuple of ``(float, float)``, in the given order.

    Raises:
        ValueError: If ``value`` is not a sequence of pairs of finite numbers > 0 (the message names ``name``).

    Example:
        >>> check_recall_thresholds([[15, 0.3]])
        ((15.0, 0.3),)
    """
    if isinstance(value, (str, bytes)) or not isinstance(value, Sequence):
        raise ValueError(f"`{name}` must be a list of [degrees, translation] pairs, got {value!r}")
    pairs = []
    for pair in value:
        if isinstance(pair, (str, bytes)) or not isinstance(pair, Sequence) or len(pair) != 2:
            raise ValueError(f"`{name}` must hold [degrees, translation] pairs, got {pair!r} in {value!r}")
        if not all(_positive_number(v) for v in pair):
            raise ValueError(f"`{name}` thresholds must be finite numbers > 0, got {list(pair)!r} in {value!r}")
        pairs.append((float(pair[0]), float(pair[1])))
    return tuple(pairs)


def _positive_number(value: Any) -> bool:
    """Whether ``value`` is a finite real number (not a bool) above 0."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value) and float(value) > 0


def registration_metrics(prefix: str = "", recall_thresholds: Sequence[tuple[float, float]] = ()) -> MetricCollection:
    """The standard metric collection logged by every registration model.

    Keys (after ``prefix``): ``rmse_r_deg``, ``mae_r_deg`` (DCP Euler), ``rmse_t``, ``mae_t``, ``rre_mean_deg``,
    ``rre_median_deg``, ``rre_clip5_deg`` (mean of ``min(RRE, 5°)``, :class:`RotationErrorClippedMean`),
    ``pose_clip_r2_t0p01`` (mean of ``min(max(RRE / 2°, RTE / 0.01), 2.5)``, :class:`PoseErrorClippedMean`),
    ``rte_mean``, ``recall_r2_t0p01`` (2 degrees and 0.01) and ``recall_r5_t0p05``
    (5 degrees and 0.05), then one :func:`recall_key` per extra pair of ``recall_thresholds`` (e.g.
    ``recall_r15_t0p3``; a pair already listed adds nothing). Module names cannot contain ``.``, hence ``0p01``
    for 0.01.

    Args:
        prefix: Prepended to every key, e.g. ``"val/"``.
        recall_thresholds: Extra ``(rotation degrees, translation in point units)`` recalls.

    Returns:
        A ``MetricCollection`` to ``update(transform_pred=..., transform_gt=...)`` and ``compute()``.

    Raises:
        ValueError: If ``recall_thresholds`` is not a sequence of pairs of finite numbers > 0.

    Example:
        >>> metrics = registration_metrics("test/", recall_thresholds=[(15.0, 0.3)])
        >>> metrics.update(transform_pred=torch.eye(4)[None], transform_gt=torch.eye(4)[None])
        >>> values = metrics.compute()
        >>> float(values["test/recall_r2_t0p01"]), float(values["test/recall_r15_t0p3"])
        (1.0, 1.0)
    """
    thresholds = STANDARD_RECALL_THRESHOLDS + check_recall_thresholds(recall_thresholds)
    recalls = {recall_key(rot, trans): (rot, trans) for rot, trans in thresholds}
    return MetricCollection(
        {
            "rmse_r_deg": EulerRotationRMSE(),
            "mae_r_deg": EulerRotationMAE(),
            "rmse_t": TranslationRMSE(),
            "mae_t": TranslationMAE(),
            "rre_mean_deg": RotationErrorMean(),
            "rre_median_deg": RotationErrorMedian(),
            "rre_clip5_deg": RotationErrorClippedMean(clip_deg=5.0),
            "pose_clip_r2_t0p01": PoseErrorClippedMean(rot_unit_deg=2.0, trans_unit=0.01, clip=2.5),
            "rte_mean": TranslationErrorMean(),
            **{key: RegistrationRecall(rot_thr_deg=rot, trans_thr=trans) for key, (rot, trans) in recalls.items()},
        },
        prefix=prefix,
    )
