"""Evaluation: validation/test metrics, the per-epoch summary line, ``test_per_pair.csv`` and ``predict``.

:class:`EvaluationLogic` is the evaluation half of :class:`~lcreg.models.base.RegistrationModule`. Validation and
test batches run :meth:`~lcreg.models.interface.RegistrationInterface.estimate` (the refiner included); batches that
carry a ground truth update the registration metrics (:func:`lcreg.metrics.registration.registration_metrics`, plus
the recalls of ``recall_thresholds``, else of the DataModule's ``recall_thresholds``: the scene benchmarks' in
metres); validation also logs the training losses (for checkpoint selection). Each validation/test epoch prints a
one-line summary; test epochs write per-pair errors to ``test_per_pair.csv`` in the logger's directory, and the
pairs' transforms to ``test_transforms.npz`` beside it.
"""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from lightning.pytorch.trainer.states import TrainerFn
from lightning.pytorch.utilities import rank_zero_info

from lcreg.checks import NonFiniteError, TooFewPointsError
from lcreg.metrics.registration import (
    STANDARD_RECALL_THRESHOLDS,
    PerPairErrors,
    check_recall_thresholds,
    recall_key,
    registration_metrics,
)
from lcreg.models.training import NonFiniteTrainingError, Stage, TrainingLogic
from lcreg.types import RegistrationBatch, RegistrationResult

__all__ = ["COMPONENT_COLUMNS", "TRANSFORMS_FILE", "EvaluationLogic"]

TRANSFORMS_FILE = "test_transforms.npz"
"""Written beside ``test_per_pair.csv``, its rows in the same order: ``index (P,)``, ``transform_pred (P, 4, 4)`` (the
estimate, NaN/Inf for a failed pair) and ``transform_gt (P, 4, 4)`` (the truth), both ``transform_ref_src``."""

COMPONENT_COLUMNS = (
    "euler_error_z_deg",
    "euler_error_y_deg",
    "euler_error_x_deg",
    "translation_error_x",
    "translation_error_y",
    "translation_error_z",
)
"""The last columns of ``test_per_pair.csv``: each pair's signed ``[z, y, x]`` Euler-angle errors (degrees) and
signed translation component errors, as DCP's RMSE(R), MAE(R), RMSE(t) and MAE(t) count them (a failed pair at 180
degrees per angle and ``|t_gt|`` per component)."""


class EvaluationLogic(TrainingLogic):
    """Validation, test and predict steps and what they write (attributes set by ``RegistrationModule``)."""

    recall_thresholds: tuple[tuple[float, float], ...] | None
    _recall_thresholds: tuple[tuple[float, float], ...] = ()
    test_pairs: PerPairErrors

    def validation_step(self, batch: RegistrationBatch, batch_idx: int) -> None:
        """Validation losses (for checkpoint selection) and metrics."""
        self._evaluation_step(batch, "val")

    def test_step(self, batch: RegistrationBatch, batch_idx: int) -> None:
        """Test metrics; the training losses are not computed."""
        self._evaluation_step(batch, "test")

    def _evaluation_step(self, batch: RegistrationBatch, stage: Literal["val", "test"]) -> None:
        batch = self._model_batch(batch)
        bs = len(batch)
        try:
            result = self.estimate(batch.points_src, batch.points_ref)
            if stage == "val" and self.has_loss:
                self._log_losses(self.training_losses(result, batch), stage, bs)
        except (NonFiniteError, torch.linalg.LinAlgError) as err:
            if self._trainer is None or self._trainer.state.fn != TrainerFn.FITTING:
                raise
            self._check_parameters(f"at the {stage} pass")  # raises naming the parameter, if one is non-finite
            raise NonFiniteTrainingError(
                f"training stopped at step {self.global_step}: the {stage} forward pass produced non-finite values "
                f"from finite parameters ({err}): the model diverged; {self._last_good_state()}"
            ) from err
        if batch.transform_ref_src is None:
            return
        metrics = self.val_metrics if stage == "val" else self.test_metrics
        pred, gt = result.transform_ref_src.detach(), batch.transform_ref_src
        # DDP pads evaluation sets with repeated pairs: the metrics count each dataset index once.
        metrics.update(transform_pred=pred, transform_gt=gt, index=batch.index)
        self.log_dict(metrics, batch_size=bs)
        self.log(f"{stage}/iterations", result.num_iters.float().mean(), batch_size=bs, sync_dist=True)
        if stage == "test":
            self.test_pairs.update(transform_pred=pred, transform_gt=gt, index=batch.index)

    def predict_step(self, batch: RegistrationBatch, batch_idx: int) -> RegistrationResult:
        """Registration results for a batch (``lcreg predict``); ``aux`` carries ``index``/``transform_gt``."""
        self.validate_inputs(batch.points_src, batch.points_ref)
        result = self.estimate(batch.points_src, batch.points_ref)
        if batch.index is not None:
            result.aux["index"] = batch.index
        if batch.transform_ref_src is not None:
            result.aux["transform_gt"] = batch.transform_ref_src
        return result

    def _summary(self, stage: Stage) -> None:
        standard = {recall_key(*pair) for pair in STANDARD_RECALL_THRESHOLDS}
        extra = [k for k in dict.fromkeys(recall_key(*pair) for pair in self._recall_thresholds) if k not in standard]
        keys = ("rre_mean_deg", "rre_median_deg", "rmse_r_deg", "rte_mean", "recall_r2_t0p01", *extra)
        values = {k: self.trainer.callback_metrics.get(f"{stage}/{k}") for k in keys}
        if all(v is not None for v in values.values()):
            text = ", ".join(f"{k}={float(v):.4g}" for k, v in values.items() if v is not None)
            rank_zero_info(f"[{stage}] epoch {self.current_epoch}: {text}")

    def on_validation_epoch_end(self) -> None:
        """Print a one-line summary (readable logs without a progress bar)."""
        if not self.trainer.sanity_checking:
            self._summary("val")

    def on_test_epoch_start(self) -> None:
        """Reset the per-pair error buffer."""
        self.test_pairs.reset()

    def on_test_epoch_end(self) -> None:
        """Summary line and ``test_per_pair.csv``: one row per pair, sorted by dataset index.

        Columns: ``index``, ``rotation_error_deg`` (geodesic) and ``translation_error`` (norm), raw (NaN for a
        failed pair); ``class``, the pair's object class, where the DataModule knows it (``pair_classes``: the
        :class:`~lcreg.data.datamodule.PairDataModule` family); then :data:`COMPONENT_COLUMNS`, the per-pair parts
        of RMSE(R), MAE(R), RMSE(t) and MAE(t) as the test figures count them
        (:meth:`~lcreg.metrics.registration.PerPairErrors.components`), from which those figures follow for any
        subset of the rows (``benchmarks/class_breakdown.py``). Beside it, :data:`TRANSFORMS_FILE` keeps each pair's
        estimated and true transforms (``benchmarks/error_geometry.py`` reads them).
        """
        self._summary("test")
        if self.test_pairs.update_count == 0:
            return
        # Every process's pairs (gathered), each once; torchmetrics squeezes a single pair to 0-d.
        rot, trans, index = self.test_pairs.per_pair()
        euler, components = self.test_pairs.components()
        transforms = self.test_pairs.transforms()  # every process takes part in the gather
        log_dir = self.trainer.log_dir if self.trainer.log_dir else self.trainer.default_root_dir
        if self.trainer.is_global_zero and log_dir:
            numbered = (index < 0).any()  # batches without indices: number the pairs in order
            if numbered:
                index = torch.arange(len(rot))
            order = torch.argsort(index)
            index, rot, trans = index[order], rot[order], trans[order]
            parts = torch.cat([euler, components], dim=1)[order].tolist()  # (P, 6)
            classes = None if numbered else self._pair_classes(index)
            header = ["index", "rotation_error_deg", "translation_error", *(["class"] if classes else [])]
            rows = zip(index.tolist(), rot.tolist(), trans.tolist(), *([classes] if classes else []), strict=True)
            path = Path(log_dir) / "test_per_pair.csv"
            path.parent.mkdir(parents=True, exist_ok=True)
            with path.open("w", newline="") as fh:
                writer = csv.writer(fh)
                writer.writerow([*header, *COMPONENT_COLUMNS])
                writer.writerows([*row, *part] for row, part in zip(rows, parts, strict=True))
            pred, gt = (t[order].double().cpu().numpy() for t in transforms)
            np.savez(path.with_name(TRANSFORMS_FILE), index=index.cpu().numpy(), transform_pred=pred, transform_gt=gt)
            rank_zero_info(f"per-pair test errors written to {path}, the transforms to {TRANSFORMS_FILE} beside it")

    def _pair_classes(self, index: torch.Tensor) -> list[str] | None:
        """The object class of each test pair ``index (K,)``, from the DataModule's ``pair_classes`` if it has one."""
        datamodule = getattr(self.trainer, "datamodule", None)
        pair_classes = getattr(datamodule, "pair_classes", None)
        classes = pair_classes("test", index) if callable(pair_classes) else None
        return classes if classes is not None and len(classes) == len(index) else None

    def setup(self, stage: str) -> None:
        """Before any step: check the data's cloud size; add the data's recalls unless ``recall_thresholds`` is set.

        Lightning calls this after the DataModule's ``setup`` and before it moves the model to its device (the
        metrics added here move with it). A DataModule exposing ``points_per_cloud`` (the
        :class:`~lcreg.data.datamodule.PairDataModule` family) is checked, so ``num_points`` below LC's
        ``num_local_points`` fails here, not at the first training step. A DataModule exposing ``recall_thresholds``
        (the scene DataModules: the benchmark's standard recall in metres) sets the extra recalls of the val/test
        metrics when the model's own ``recall_thresholds`` is ``None``.

        Raises:
            TooFewPointsError: The data yields clouds of fewer than :attr:`min_points` points.
            ValueError: The DataModule's ``recall_thresholds`` is not a sequence of pairs of finite numbers > 0.
        """
        datamodule = getattr(self._trainer, "datamodule", None) if self._trainer is not None else None
        self._check_cloud_size(datamodule)
        if self.recall_thresholds is None:
            thresholds = getattr(datamodule, "recall_thresholds", None) or ()
            thresholds = check_recall_thresholds(thresholds, f"{type(datamodule).__name__}.recall_thresholds")
            if thresholds != self._recall_thresholds:
                self._use_recall_thresholds(thresholds)

    def _check_cloud_size(self, datamodule: Any) -> None:
        """Refuse a DataModule whose ``points_per_cloud`` is below :attr:`min_points` (:class:`TooFewPointsError`)."""
        points = getattr(datamodule, "points_per_cloud", None)
        if isinstance(points, int) and points < self.min_points:
            needs = [f"{type(self).__name__} {self._min_points}"]
            needs += [f"loss term {t.name!r} {t.min_points}" for t in self.injected_terms]
            raise TooFewPointsError(
                f"{type(datamodule).__name__} yields clouds of {points} points (data `num_points`/`partial_keep`), "
                f"but the model needs at least {self.min_points} ({', '.join(needs)}): raise `num_points` or lower "
                "the model's requirement (e.g. LC's `num_local_points`)"
            )

    def _use_recall_thresholds(self, thresholds: tuple[tuple[float, float], ...]) -> None:
        """(Re)build the val/test metric collections with the extra recalls of ``thresholds`` (validated)."""
        self._recall_thresholds = thresholds
        self.val_metrics = registration_metrics("val/", thresholds)
        self.test_metrics = registration_metrics("test/", thresholds)
