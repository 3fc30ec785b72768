"""The interface every registration model implements, and the one train/val/test step they share.

Subclasses implement only:

* ``forward(points_src (B, N, 3), points_ref (B, M, 3)) -> RegistrationResult``;
* ``compute_loss(result, batch) -> dict[str, Tensor]`` with a ``"loss"`` entry (training objective).

The base validates batches, runs ``forward``, logs every loss term as ``{stage}/{name}``, updates the registration
metrics (:func:`lcreg.metrics.registration.registration_metrics`) on val/test batches that carry a ground truth,
prints a one-line summary per validation/test epoch and writes per-pair test errors to ``test_per_pair.csv`` in the
logger's directory. Optimisers are injected (``optimizer``/``lr_scheduler`` callables, LightningCLI style).
"""

from __future__ import annotations

import csv
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any, Literal, Protocol

import torch
from lightning.pytorch import LightningModule
from lightning.pytorch.utilities import rank_zero_info

from lcreg.checks import check_points, check_same_batch
from lcreg.metrics.registration import PerPairErrors, registration_metrics
from lcreg.types import RegistrationBatch, RegistrationResult

__all__ = ["Refiner", "RegistrationModule"]

Stage = Literal["train", "val", "test"]
OptimizerFactory = Callable[[Iterable[torch.nn.Parameter]], torch.optim.Optimizer]
# Typed return (not Any): jsonargparse only accepts a scheduler `class_path` for a callable returning a scheduler.
SchedulerFactory = Callable[
    [torch.optim.Optimizer], torch.optim.lr_scheduler.LRScheduler | torch.optim.lr_scheduler.ReduceLROnPlateau
]


class Refiner(Protocol):
    """A local method that improves a coarse estimate, e.g. :class:`lcreg.baselines.classical.ICP`."""

    def __call__(self, points_src: torch.Tensor, points_ref: torch.Tensor, init: torch.Tensor) -> RegistrationResult:
        """Refine ``init (B, 4, 4)`` for ``points_src (B, N, 3)`` and ``points_ref (B, M, 3)``."""
        ...


class RegistrationModule(LightningModule):
    """Base LightningModule for registration methods.

    Class attribute ``has_loss``: ``False`` for methods with nothing to train (classical baselines); their
    validation then only updates metrics.

    Args:
        optimizer: Callable building the optimiser from the trainable parameters (default Adam, lr 1e-3).
        lr_scheduler: Optional callable building a scheduler from the optimiser (stepped per epoch;
            ``ReduceLROnPlateau`` steps on ``val/loss``).
        min_points: Smallest cloud size accepted by :meth:`validate_inputs`.
    """

    has_loss: bool = True
    _refiner: Refiner | None = None

    def __init__(
        self,
        optimizer: OptimizerFactory = torch.optim.Adam,
        lr_scheduler: SchedulerFactory | None = None,
        min_points: int = 3,
    ) -> None:
        super().__init__()
        self.optimizer_factory = optimizer
        self.scheduler_factory = lr_scheduler
        self.min_points = min_points
        self.val_metrics = registration_metrics("val/")
        self.test_metrics = registration_metrics("test/")
        self.test_pairs = PerPairErrors()
        self._test_indices: list[torch.Tensor] = []

    # --- interface -------------------------------------------------------------------------------------------
    def forward(self, points_src: torch.Tensor, points_ref: torch.Tensor) -> RegistrationResult:
        """Estimate ``transform_ref_src`` for ``points_src (B, N, 3)`` and ``points_ref (B, M, 3)``."""
        raise NotImplementedError

    def compute_loss(self, result: RegistrationResult, batch: RegistrationBatch) -> dict[str, torch.Tensor]:
        """Training objective terms; must contain ``"loss"``."""
        raise NotImplementedError

    def training_losses(self, result: RegistrationResult, batch: RegistrationBatch) -> dict[str, torch.Tensor]:
        """All loss terms the shared step logs and optimises: ``compute_loss`` plus whatever mixins add.

        Hosts implement ``compute_loss`` only; composable terms (:class:`~lcreg.models.mixins.LocalConsistencyMixin`)
        override this method, so a host's code never has to call them.
        """
        return self.compute_loss(result, batch)

    def training_forward(self, batch: RegistrationBatch) -> RegistrationResult:
        """The forward pass whose result ``compute_loss`` receives during training.

        Default: ``forward`` on the batch's clouds. Override only when training needs more than the clouds (IDAM
        samples its training points with the ground-truth correspondences).
        """
        return self(batch.points_src, batch.points_ref)

    # --- shared machinery ------------------------------------------------------------------------------------
    @property
    def refiner(self) -> Refiner | None:
        """The refinement step run after ``forward`` outside training (``None``: none)."""
        return self._refiner

    def set_refiner(self, refiner: Refiner | None) -> None:
        """Follow every validation/test/predict/``register`` estimate by ``refiner`` (``None`` removes it).

        The refiner starts from this model's estimate (``init``); training never uses it. It is kept outside the
        module tree, so it is neither trained nor saved in checkpoints: ``lcreg test --config x.yaml --refine ...``
        adds it to any trained checkpoint (see :mod:`lcreg.cli`).

        Raises:
            TypeError: If ``refiner`` is not callable.
        """
        if refiner is not None and not callable(refiner):
            raise TypeError(f"`refiner` must be callable (e.g. lcreg.baselines.classical.ICP), got {type(refiner)}")
        object.__setattr__(self, "_refiner", refiner)  # bypass nn.Module registration on purpose

    def load_weights(self, checkpoint: str | Path) -> RegistrationModule:
        """Load the weights of a Lightning checkpoint into this configured model and return it.

        Unlike ``load_from_checkpoint``, which builds a new model from the checkpoint's hyper-parameters, this keeps
        the instance built from a config, including its test-time settings (refiner, voxel grid). The architecture
        must match (strict ``load_state_dict``). Checkpoints are unpickled: load only trusted files.

        Raises:
            FileNotFoundError: If ``checkpoint`` is not a file.
            ValueError: If the file holds no ``state_dict``.
        """
        path = Path(checkpoint)
        if not path.is_file():
            raise FileNotFoundError(f"checkpoint {str(path)!r} does not exist")
        content = torch.load(path, map_location="cpu", weights_only=False)  # Lightning checkpoints hold hparams
        if not isinstance(content, dict) or "state_dict" not in content:
            raise ValueError(f"checkpoint {str(path)!r} has no 'state_dict' (not a Lightning checkpoint)")
        self.load_state_dict(content["state_dict"])
        return self

    def estimate(self, points_src: torch.Tensor, points_ref: torch.Tensor) -> RegistrationResult:
        """``forward``, then the refiner (if any) from its estimate.

        The refined result keeps the coarse estimate in ``aux["coarse_transform_ref_src"]`` and adds the refiner's
        iterations to ``num_iters``.
        """
        result = self(points_src, points_ref)
        if self._refiner is None:
            return result
        coarse = result.transform_ref_src.detach()
        refined = self._refiner(points_src, points_ref, init=coarse)
        refined.aux = {**result.aux, **refined.aux, "coarse_transform_ref_src": coarse}
        refined.num_iters = refined.num_iters.to(result.num_iters.device) + result.num_iters
        return refined

    def ground_truth(self, batch: RegistrationBatch) -> torch.Tensor:
        """``batch.transform_ref_src`` for supervised losses; a clear error when the batch has none."""
        if batch.transform_ref_src is None:
            raise ValueError(
                f"{type(self).__name__} is trained with a ground-truth pose, but the batch has no `transform_ref_src`"
            )
        return batch.transform_ref_src

    def validate_inputs(self, points_src: torch.Tensor, points_ref: torch.Tensor) -> None:
        """Raise a typed error (naming the argument) for bad clouds: type, dtype, shape, size, NaN/Inf."""
        check_points(points_src, "points_src", self.min_points)
        check_points(points_ref, "points_ref", self.min_points)
        check_same_batch(points_src=points_src, points_ref=points_ref)

    @torch.no_grad()
    def register(self, points_src: torch.Tensor, points_ref: torch.Tensor) -> RegistrationResult:
        """Validated inference in eval mode (restores the previous mode)."""
        self.validate_inputs(points_src, points_ref)
        was_training = self.training
        self.eval()
        try:
            return self.estimate(points_src, points_ref)
        finally:
            self.train(was_training)

    def _common_step(self, batch: RegistrationBatch, stage: Stage) -> torch.Tensor | None:
        self.validate_inputs(batch.points_src, batch.points_ref)
        result = self.training_forward(batch) if stage == "train" else self.estimate(batch.points_src, batch.points_ref)
        bs = len(batch)
        loss = None
        if stage == "train" or (stage == "val" and self.has_loss):
            losses = self.training_losses(result, batch)
            loss = losses["loss"]
            for name, value in losses.items():
                self.log(
                    f"{stage}/{name}",
                    value.detach(),
                    batch_size=bs,
                    prog_bar=name == "loss",
                    on_step=stage == "train",
                    on_epoch=True,
                )
        if stage != "train" and batch.transform_ref_src is not None:
            metrics = self.val_metrics if stage == "val" else self.test_metrics
            kwargs = {"transform_pred": result.transform_ref_src.detach(), "transform_gt": batch.transform_ref_src}
            metrics.update(**kwargs)
            self.log_dict(metrics, batch_size=bs)
            self.log(f"{stage}/iterations", result.num_iters.float().mean(), batch_size=bs)
            if stage == "test":
                self.test_pairs.update(**kwargs)
                if batch.index is not None:
                    self._test_indices.append(batch.index.detach().cpu())
        return loss

    def training_step(self, batch: RegistrationBatch, batch_idx: int) -> torch.Tensor:
        """One optimisation step on a batch."""
        loss = self._common_step(batch, "train")
        if loss is None:  # pragma: no cover - train always computes a loss
            raise RuntimeError("compute_loss returned no loss")
        return loss

    def validation_step(self, batch: RegistrationBatch, batch_idx: int) -> None:
        """Validation losses (for checkpoint selection) and metrics."""
        self._common_step(batch, "val")

    def test_step(self, batch: RegistrationBatch, batch_idx: int) -> None:
        """Test metrics; the training losses are not computed."""
        self._common_step(batch, "test")

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
        keys = ("rre_mean_deg", "rre_median_deg", "rmse_r_deg", "rte_mean", "recall_r2_t0p01")
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
        self._test_indices = []

    def on_test_epoch_end(self) -> None:
        """Summary line and ``test_per_pair.csv`` (index, rotation error deg, translation error)."""
        self._summary("test")
        if self.test_pairs.update_count == 0:
            return
        rot, trans = (t.reshape(-1) for t in self.test_pairs.compute())  # torchmetrics squeezes a single pair to 0-d
        log_dir = self.trainer.log_dir if self.trainer.log_dir else self.trainer.default_root_dir
        if self.trainer.is_global_zero and log_dir:
            index = torch.cat(self._test_indices).tolist() if self._test_indices else list(range(len(rot)))
            path = Path(log_dir) / "test_per_pair.csv"
            path.parent.mkdir(parents=True, exist_ok=True)
            with path.open("w", newline="") as fh:
                writer = csv.writer(fh)
                writer.writerow(["index", "rotation_error_deg", "translation_error"])
                writer.writerows(zip(index, rot.tolist(), trans.tolist()))
            rank_zero_info(f"per-pair test errors written to {path}")

    def configure_optimizers(self) -> Any:
        """Build the injected optimiser (trainable parameters only) and optional scheduler."""
        params = [p for p in self.parameters() if p.requires_grad]
        optimizer = self.optimizer_factory(params)
        if self.scheduler_factory is None:
            return optimizer
        scheduler = self.scheduler_factory(optimizer)
        if isinstance(scheduler, torch.optim.lr_scheduler.ReduceLROnPlateau):
            # Plateau schedulers step on a metric: the validation loss (label-free for self-supervised models).
            return {"optimizer": optimizer, "lr_scheduler": {"scheduler": scheduler, "monitor": "val/loss"}}
        return {"optimizer": optimizer, "lr_scheduler": scheduler}
