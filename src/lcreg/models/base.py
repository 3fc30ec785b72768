"""The interface every registration model implements, and the one train/val/test step they share.

Subclasses implement only:

* ``forward(points_src (B, N, 3), points_ref (B, M, 3)) -> RegistrationResult``;
* ``_compute_loss(result, batch) -> dict[str, Tensor]`` with a ``"loss"`` entry (the model's own objective).

Everything else is injected through the constructor (LightningCLI YAML), so a configured model is complete:
``optimizer``/``lr_scheduler`` factories, extra ``loss_terms`` (:mod:`lcreg.models.loss_terms`, e.g. local
consistency), and a ``refiner`` run after ``forward`` outside training. Hosts pass these through ``**kwargs``.
The one public way to get a model's training losses is :meth:`RegistrationModule.training_losses` (own terms plus
every injected term, each weighted and logged as ``{stage}/{name}``).

The base validates batches, runs ``forward``, logs every loss term as ``{stage}/{name}``, updates the registration
metrics (:func:`lcreg.metrics.registration.registration_metrics`) on val/test batches that carry a ground truth (plus
the recalls of ``recall_thresholds``, else of the DataModule's ``recall_thresholds``: the scene benchmarks' in metres),
prints a one-line summary per validation/test epoch and writes per-pair test errors to ``test_per_pair.csv`` in the
logger's directory. Optimisers are injected (``optimizer``/``lr_scheduler`` callables, LightningCLI style).

A training step whose loss or gradient is not finite (NaN normals or poses in the data, a diverging model) is
skipped before the optimiser sees it, with a warning naming the batch's dataset indices; ``max_bad_steps``
consecutive skipped steps stop training (:class:`NonFiniteTrainingError`).
"""

from __future__ import annotations

import csv
import functools
import inspect
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any, ClassVar, Literal

import torch
from lightning.pytorch import LightningModule
from lightning.pytorch.utilities import rank_zero_info, rank_zero_warn

from lcreg.checks import TooFewPointsError, check_extent, check_points, check_same_batch
from lcreg.metrics.registration import (
    STANDARD_RECALL_THRESHOLDS,
    PerPairErrors,
    check_recall_thresholds,
    recall_key,
    registration_metrics,
)
from lcreg.models.loss_terms import LossTerm
from lcreg.nn.dtypes import module_dtype, to_module_dtype
from lcreg.types import RegistrationBatch, RegistrationResult

__all__ = ["COMPONENT_ARGS", "EVALUATION_ARGS", "NonFiniteTrainingError", "RegistrationModule"]

Stage = Literal["train", "val", "test"]
OptimizerFactory = Callable[[Iterable[torch.nn.Parameter]], torch.optim.Optimizer]
# Typed return (not Any): jsonargparse only accepts a scheduler `class_path` for a callable returning a scheduler.
SchedulerFactory = Callable[
    [torch.optim.Optimizer], torch.optim.lr_scheduler.LRScheduler | torch.optim.lr_scheduler.ReduceLROnPlateau
]


COMPONENT_ARGS = ("optimizer", "lr_scheduler", "loss_terms", "refiner", "voxel_grid")
"""Constructor arguments that are components, not hyper-parameters: never saved in a checkpoint's ``hparams``."""

EVALUATION_ARGS = ("recall_thresholds",)
"""Constructor arguments that only choose what evaluation reports: saved in ``hparams`` like the others, but the CLI
never lets a checkpoint's value override the one of the run (``lcreg test --ckpt_path ...``)."""


class NonFiniteTrainingError(RuntimeError):
    """Training stopped: too many consecutive steps had a non-finite loss or gradient."""


class RegistrationModule(LightningModule):
    """Base LightningModule for registration methods.

    Inputs: ``forward`` and ``register`` validate both clouds first (:meth:`validate_inputs`, a forward pre-hook:
    typed errors that name ``points_src`` or ``points_ref``, before any layer runs). They accept float32 and float64
    clouds (numpy's default) and compute in the model's dtype (:func:`lcreg.nn.dtypes.module_dtype`; float32 unless
    converted with ``.double()``): the pre-hook casts the inputs, a forward hook returns ``transform_ref_src`` in the
    caller's dtype. Training batches are cast to the model's dtype in the shared step.

    Class attribute ``has_loss``: ``False`` for methods with nothing to train (classical baselines); their
    validation then only updates metrics.

    Class attribute ``min_points``: smallest cloud the model itself accepts (hosts set it in their constructor); the
    effective :attr:`min_points` also covers the injected loss terms (LC needs ``num_local_points``).

    Class attribute ``training_only_modules``: names of the submodules inference never uses (the injected loss terms;
    DVDs adds its decoder and normal head). Exported pretrained weights (:mod:`lcreg.weights`) leave them out, and
    loading such weights into a configured model leaves them as initialised. Class attribute ``inference_hparams``:
    hyper-parameters under which those modules are not even built (DVDs: both loss weights 0), used by the export.

    Args:
        optimizer: Callable building the optimiser from the trainable parameters (default Adam, lr 1e-3).
        lr_scheduler: Optional callable building a scheduler from the optimiser (stepped per epoch;
            ``ReduceLROnPlateau`` steps on ``val/loss``).
        loss_terms: Extra training-loss terms (:class:`~lcreg.models.loss_terms.LossTerm`), each added as
            ``weight * value`` and logged as ``{stage}/{name}``; e.g. ``[LocalConsistencyLoss()]``.
        refiner: A registration method run after ``forward`` at validation/test/predict/``register``, starting
            from the model's estimate (e.g. :class:`lcreg.baselines.classical.ICP`); never used in training, not a
            submodule, not saved in checkpoints (``configs/refine/icp.yaml``).
        unit_scale: ``register`` only: scale each pair about the origin so that the reference cloud's largest
            distance from its centroid is ``unit_scale`` (the scale the model was trained at: 1.0 for unit-sphere
            ModelNet40), register, and map the translation back, so the result does not depend on the unit of the
            clouds (mm, m, km). ``None`` (default for most models): the clouds are used as given.
        max_bad_steps: Consecutive training steps with a non-finite loss or gradient (each skipped: no parameter or
            optimiser-state change, a warning naming the batch) after which training stops with
            :class:`NonFiniteTrainingError`.
        recall_thresholds: Extra recalls logged at validation and test, as ``(rotation degrees, translation in point
            units)`` pairs, each as ``{stage}/recall_r{deg}_t{trans}`` (``.`` written ``p``:
            ``[[15, 0.3]]`` -> ``recall_r15_t0p3``), besides ``recall_r2_t0p01`` and ``recall_r5_t0p05``.
            ``None``: the ``recall_thresholds`` of the trainer's DataModule, if it has any (7-Scenes/3DMatch
            ``((15.0, 0.3),)``, KITTI ``((5.0, 2.0),)``; object datasets none), added in :meth:`setup`.

    Raises:
        TypeError: If a loss term is not a ``LossTerm`` or the refiner is not a ``RegistrationModule``.
        ValueError: If two loss terms share a name, ``max_bad_steps < 1``, ``unit_scale`` is not > 0 or
            ``recall_thresholds`` is not a list of pairs of finite numbers > 0.
    """

    has_loss: bool = True
    training_only_modules: ClassVar[tuple[str, ...]] = ("loss_terms",)
    inference_hparams: ClassVar[Mapping[str, Any]] = {}
    _min_points: int = 3
    _refiner: RegistrationModule | None = None
    _recall_thresholds: tuple[tuple[float, float], ...] = ()
    loss_terms: torch.nn.ModuleList

    def __init__(
        self,
        optimizer: OptimizerFactory = torch.optim.Adam,
        lr_scheduler: SchedulerFactory | None = None,
        loss_terms: Sequence[LossTerm] = (),
        refiner: RegistrationModule | None = None,
        unit_scale: float | None = None,
        max_bad_steps: int = 10,
        recall_thresholds: Sequence[tuple[float, float]] | None = None,
    ) -> None:
        super().__init__()
        self._save_constructor_hparams()
        if unit_scale is not None and not (isinstance(unit_scale, (int, float)) and 0 < unit_scale < float("inf")):
            raise ValueError(f"`unit_scale` must be a finite number > 0 or None, got {unit_scale!r}")
        self.unit_scale = None if unit_scale is None else float(unit_scale)
        if max_bad_steps < 1:
            raise ValueError(f"`max_bad_steps` must be >= 1, got {max_bad_steps}")
        self.max_bad_steps = max_bad_steps
        self._bad_steps = 0
        self._step_skipped = False
        self._step_index: list[int] | None = None
        self.optimizer_factory = optimizer
        self.scheduler_factory = lr_scheduler
        self.loss_terms = torch.nn.ModuleList(_checked_terms(loss_terms))
        if refiner is not None and not isinstance(refiner, RegistrationModule):
            raise TypeError(
                f"`refiner` must be a RegistrationModule (e.g. lcreg.baselines.classical.ICP), got {type(refiner)}"
            )
        object.__setattr__(self, "_refiner", refiner)  # plain attribute: not trained, not saved
        self.recall_thresholds = None if recall_thresholds is None else check_recall_thresholds(recall_thresholds)
        self._use_recall_thresholds(self.recall_thresholds or ())
        self.test_pairs = PerPairErrors()
        self._input_dtypes: list[torch.dtype] = []
        self.register_forward_pre_hook(_inputs_to_model_dtype, with_kwargs=True)
        self.register_forward_hook(_transform_to_input_dtype, always_call=True)

    # --- interface -------------------------------------------------------------------------------------------
    def forward(self, points_src: torch.Tensor, points_ref: torch.Tensor) -> RegistrationResult:
        """Estimate ``transform_ref_src`` for ``points_src (B, N, 3)`` and ``points_ref (B, M, 3)``."""
        raise NotImplementedError

    def _compute_loss(self, result: RegistrationResult, batch: RegistrationBatch) -> dict[str, torch.Tensor]:
        """The model's own objective terms; must contain ``"loss"``. Call :meth:`training_losses`, not this."""
        raise NotImplementedError

    def training_losses(self, result: RegistrationResult, batch: RegistrationBatch) -> dict[str, torch.Tensor]:
        """Every loss term the shared step logs and optimises: the model's own plus each injected term.

        This is the one public way to get a model's training losses (benchmarks and scripts use it too): the
        result is ``_compute_loss`` with ``weight * term`` added to ``"loss"`` for every ``loss_terms`` entry, each
        also reported under its name.

        Args:
            result: The estimate of :meth:`training_forward` (training) or ``forward`` (validation).
            batch: The batch the estimate was made on.

        Raises:
            ValueError: If the model's own terms lack ``"loss"`` or reuse an injected term's name.
        """
        losses = dict(self._compute_loss(result, batch))
        if "loss" not in losses:
            raise ValueError(f"{type(self).__name__}._compute_loss must return a 'loss' entry, got {sorted(losses)}")
        for term in self.injected_terms:
            if term.name in losses:
                raise ValueError(f"loss term {term.name!r} clashes with a term of {type(self).__name__}")
            value = term(self, result, batch)
            losses[term.name] = value
            losses["loss"] = losses["loss"] + term.weight * value
        self._log_loss_diagnostics(losses)
        return losses

    @property
    def injected_terms(self) -> list[LossTerm]:
        """The injected :class:`~lcreg.models.loss_terms.LossTerm` s, in order."""
        return [term for term in self.loss_terms if isinstance(term, LossTerm)]

    def _log_loss_diagnostics(self, losses: dict[str, torch.Tensor]) -> None:
        """Hook run on every ``training_losses`` result (DVDs logs gradient norms); default does nothing."""

    @property
    def min_points(self) -> int:
        """Smallest cloud accepted: the model's own minimum and every loss term's."""
        return max([self._min_points, *(term.min_points for term in self.injected_terms)])

    @min_points.setter
    def min_points(self, value: int) -> None:
        self._min_points = value

    @property
    def descriptor_dim(self) -> int:
        """Width ``K`` of :meth:`descriptor_encoder`'s features (``self.encoder.feature_dim`` by default)."""
        dim = getattr(getattr(self, "encoder", None), "feature_dim", None)
        if not isinstance(dim, int):
            raise TypeError(f"{type(self).__name__} does not expose a descriptor width (`encoder.feature_dim`)")
        return dim

    def descriptor_encoder(self) -> Callable[[torch.Tensor], torch.Tensor]:
        """The model's encoder ``psi``: ``(B, n, 3) -> (B, K)`` or ``(B, n, K)`` (``self.encoder`` by default).

        Raises:
            TypeError: If the model has no ``encoder`` (loss terms such as LC need one).
        """
        encoder = getattr(self, "encoder", None)
        if not callable(encoder):
            raise TypeError(f"{type(self).__name__} has no `encoder` for descriptor-based loss terms")
        return encoder

    def _bind_loss_terms(self) -> None:
        """Let every injected term check itself against the built model (run after the outermost constructor)."""
        for term in self.injected_terms:
            term.bind(self)

    def __init_subclass__(cls, **kwargs: Any) -> None:
        """Wrap each subclass constructor: once the outermost one has returned, the loss terms are bound.

        So a host needs no ritual call: its constructor builds its layers, and the injected terms see the finished
        model (LC takes the encoder's width and builds its metric, whose parameters are then in the state dict).
        """
        super().__init_subclass__(**kwargs)
        init = cls.__dict__.get("__init__")
        if init is None:
            return

        @functools.wraps(init)
        def __init__(self: RegistrationModule, *args: Any, **kw: Any) -> None:
            init(self, *args, **kw)
            if _constructor_owner(type(self)) is cls:
                self._bind_loss_terms()

        cls.__init__ = __init__  # type: ignore[method-assign]

    def _save_constructor_hparams(self) -> None:
        """``save_hyperparameters`` of the outermost constructor running for this model, without the components.

        Called by the base constructor: the frames above it are the constructors of the subclasses (their arguments
        are bound when they start), the outermost is the class the user built. Under LightningCLI, Lightning takes
        the CLI's own record instead (with ``_class_path``).
        """
        frame = inspect.currentframe()
        frame = frame.f_back if frame is not None else None
        outermost = None
        while frame is not None and frame.f_code.co_name == "__init__":
            names = frame.f_code.co_varnames
            if not names or frame.f_locals.get(names[0]) is not self:
                break
            if "__class__" in frame.f_locals:  # a constructor (the wrappers above have none)
                outermost = frame
            frame = frame.f_back
        self.save_hyperparameters(ignore=list(COMPONENT_ARGS), frame=outermost)
        del frame, outermost

    def training_forward(self, batch: RegistrationBatch) -> RegistrationResult:
        """The forward pass whose result ``training_losses`` receives during training.

        Default: ``forward`` on the batch's clouds. Override only when training needs more than the clouds (IDAM
        samples its training points with the ground-truth correspondences).
        """
        return self(batch.points_src, batch.points_ref)

    def differentiable_forward(self, points_src: torch.Tensor, points_ref: torch.Tensor) -> RegistrationResult:
        """``forward`` with the autograd graph kept through the estimate (loss terms that train through it).

        Default: ``forward``. Models whose own loss holds the estimate fixed (the IC-LK models) override it.
        """
        return self(points_src, points_ref)

    # --- shared machinery ------------------------------------------------------------------------------------
    @property
    def refiner(self) -> RegistrationModule | None:
        """The refinement step run after ``forward`` outside training (``None``: none)."""
        return self._refiner

    def estimate(self, points_src: torch.Tensor, points_ref: torch.Tensor) -> RegistrationResult:
        """``forward``, then the refiner (if any) from its estimate.

        The refined result keeps the coarse estimate in ``aux["coarse_transform_ref_src"]`` and adds the refiner's
        iterations to ``num_iters``.
        """
        result = self(points_src, points_ref)
        if self._refiner is None:
            return result
        coarse = result.transform_ref_src.detach()
        refined = self._refiner.refine(points_src, points_ref, coarse)
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
        """Raise a typed error (naming the argument) for bad clouds.

        Checks type, dtype, shape, size, NaN/Inf, one batch size, and clouds whose points all coincide
        (:class:`~lcreg.checks.DegenerateCloudError`: no motion to recover).
        """
        check_points(points_src, "points_src", self.min_points)
        check_points(points_ref, "points_ref", self.min_points)
        check_same_batch(points_src=points_src, points_ref=points_ref)
        check_extent(points_src, "points_src")
        check_extent(points_ref, "points_ref")

    @torch.no_grad()
    def register(self, points_src: torch.Tensor, points_ref: torch.Tensor) -> RegistrationResult:
        """Validated inference in eval mode (restores the previous mode), at ``unit_scale`` when it is set.

        Raises:
            TypeError, ShapeError, NonFiniteError, TooFewPointsError: Bad clouds (the message names the argument).
        """
        self.validate_inputs(points_src, points_ref)
        factor = None
        if self.unit_scale is not None:
            centred = points_ref - points_ref.mean(dim=1, keepdim=True)
            factor = self.unit_scale / centred.norm(dim=-1).amax(dim=1)  # (B,)
            points_src, points_ref = points_src * factor[:, None, None], points_ref * factor[:, None, None]
        was_training = self.training
        self.eval()
        try:
            result = self.estimate(points_src, points_ref)
        finally:
            self.train(was_training)
        if factor is not None:  # p_ref = R p_src + t holds at any scale k with t' = k t
            transform = result.transform_ref_src.clone()
            transform[:, :3, 3] /= factor[:, None].to(transform.dtype)
            result.transform_ref_src = transform
        return result

    def refine(self, points_src: torch.Tensor, points_ref: torch.Tensor, init: torch.Tensor) -> RegistrationResult:
        """Improve the estimates ``init (B, 4, 4)``; only local methods (ICP) implement it.

        Raises:
            TypeError: For a model that cannot start from an initial estimate.
        """
        raise TypeError(f"{type(self).__name__} cannot refine an initial estimate; use a local method such as ICP")

    def _common_step(self, batch: RegistrationBatch, stage: Stage) -> torch.Tensor | None:
        self.validate_inputs(batch.points_src, batch.points_ref)
        batch = replace(batch, **to_module_dtype(self, vars(batch)))  # float64 data, float32 model (or the reverse)
        result = self.training_forward(batch) if stage == "train" else self.estimate(batch.points_src, batch.points_ref)
        bs = len(batch)
        loss = None
        if stage == "train" or (stage == "val" and self.has_loss):
            losses = self.training_losses(result, batch)
            loss = losses["loss"]
            if stage == "train":
                self._step_skipped = not bool(torch.isfinite(loss.detach()).all())  # one host sync per step
                if self._step_skipped:
                    return loss  # skipped by training_step: not logged (the epoch means stay finite)
            for name, value in losses.items():
                self.log(
                    f"{stage}/{name}",
                    value.detach(),
                    batch_size=bs,
                    prog_bar=name == "loss",
                    on_step=stage == "train",
                    on_epoch=True,
                    sync_dist=stage != "train",  # epoch means over every process's pairs (DDP)
                )
        if stage != "train" and batch.transform_ref_src is not None:
            metrics = self.val_metrics if stage == "val" else self.test_metrics
            pred, gt = result.transform_ref_src.detach(), batch.transform_ref_src
            # DDP pads evaluation sets with repeated pairs: the metrics count each dataset index once.
            metrics.update(transform_pred=pred, transform_gt=gt, index=batch.index)
            self.log_dict(metrics, batch_size=bs)
            self.log(f"{stage}/iterations", result.num_iters.float().mean(), batch_size=bs, sync_dist=True)
            if stage == "test":
                self.test_pairs.update(transform_pred=pred, transform_gt=gt, index=batch.index)
        return loss

    def training_step(self, batch: RegistrationBatch, batch_idx: int) -> torch.Tensor | None:
        """One optimisation step on a batch; ``None`` (Lightning skips the step) when the loss is not finite."""
        loss = self._common_step(batch, "train")
        if loss is None:  # pragma: no cover - train always computes a loss
            raise RuntimeError("training_losses returned no loss")
        self._step_index = None if batch.index is None else batch.index.detach().cpu().tolist()
        if self._step_skipped:  # set by _common_step
            self._skip_step(f"non-finite loss ({float(loss.detach().float().sum())})")
            return None
        return loss

    def on_before_optimizer_step(self, optimizer: torch.optim.Optimizer) -> None:
        """Skip the update when a gradient is not finite.

        Every gradient is dropped, so the optimiser leaves the parameters and its state as they are.
        """
        if self._step_skipped:
            return
        grads = [p.grad for group in optimizer.param_groups for p in group["params"] if p.grad is not None]
        if grads and not bool(torch.isfinite(torch.nn.utils.get_total_norm(grads))):
            for group in optimizer.param_groups:
                for param in group["params"]:
                    param.grad = None
            self._skip_step("non-finite gradient")
            return
        self._bad_steps = 0

    def _skip_step(self, reason: str) -> None:
        """Warn about a skipped step; stop after ``max_bad_steps`` in a row.

        Raises:
            NonFiniteTrainingError: At the ``max_bad_steps``-th consecutive skipped step.
        """
        self._bad_steps += 1
        where = f"batch indices {self._step_index}" if self._step_index is not None else "a batch without indices"
        if self._bad_steps >= self.max_bad_steps:
            raise NonFiniteTrainingError(
                f"training stopped at step {self.global_step}: {self._bad_steps} consecutive steps with a non-finite "
                f"loss or gradient (last: {reason} on {where}); check the data for NaN/Inf (points, normals, poses) "
                "or lower the learning rate"
            )
        rank_zero_warn(
            f"step {self.global_step} skipped: {reason} on {where} "
            f"({self._bad_steps} in a row; training stops at {self.max_bad_steps})"
        )

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
        """Summary line and ``test_per_pair.csv`` (index, rotation error deg, translation error)."""
        self._summary("test")
        if self.test_pairs.update_count == 0:
            return
        # Every process's pairs (gathered), each once; torchmetrics squeezes a single pair to 0-d.
        rot, trans, index = (t.reshape(-1) for t in self.test_pairs.compute())
        log_dir = self.trainer.log_dir if self.trainer.log_dir else self.trainer.default_root_dir
        if self.trainer.is_global_zero and log_dir:
            if (index < 0).any():  # batches without indices: number the pairs in order
                index = torch.arange(len(rot))
            order = torch.argsort(index)
            index, rot, trans = index[order], rot[order], trans[order]
            path = Path(log_dir) / "test_per_pair.csv"
            path.parent.mkdir(parents=True, exist_ok=True)
            with path.open("w", newline="") as fh:
                writer = csv.writer(fh)
                writer.writerow(["index", "rotation_error_deg", "translation_error"])
                writer.writerows(zip(index.tolist(), rot.tolist(), trans.tolist()))
            rank_zero_info(f"per-pair test errors written to {path}")

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

    def configure_optimizers(self) -> Any:
        """Build the injected optimiser (trainable parameters only) and optional scheduler."""
        self._bind_loss_terms()  # idempotent; every term's parameters exist before the optimiser sees them
        params = [p for p in self.parameters() if p.requires_grad]
        optimizer = self.optimizer_factory(params)
        if self.scheduler_factory is None:
            return optimizer
        scheduler = self.scheduler_factory(optimizer)
        if isinstance(scheduler, torch.optim.lr_scheduler.ReduceLROnPlateau):
            # Plateau schedulers step on a metric: the validation loss (label-free for self-supervised models).
            return {"optimizer": optimizer, "lr_scheduler": {"scheduler": scheduler, "monitor": "val/loss"}}
        return {"optimizer": optimizer, "lr_scheduler": scheduler}


def _constructor_owner(cls: type) -> type:
    """The class whose ``__init__`` runs first when ``cls`` is built (the nearest that defines one)."""
    return next(c for c in cls.__mro__ if "__init__" in c.__dict__)


def _inputs_to_model_dtype(
    module: RegistrationModule, args: tuple[Any, ...], kwargs: dict[str, Any]
) -> tuple[tuple[Any, ...], dict[str, Any]]:
    """Forward pre-hook: validates the two clouds (errors name them), casts them to the model's dtype.

    Remembers the caller's dtype for :func:`_transform_to_input_dtype`.
    """
    if args and isinstance(args[0], RegistrationBatch):  # Lightning's DDP redirects training_step through forward
        module._input_dtypes.append(module_dtype(module) or torch.float32)
        return args, kwargs
    clouds = [*args[:2], *(kwargs[k] for k in ("points_src", "points_ref") if k in kwargs)]
    if len(clouds) == 2:
        module.validate_inputs(*clouds)
    first = next((a for a in (*args, *kwargs.values()) if isinstance(a, torch.Tensor) and a.is_floating_point()), None)
    module._input_dtypes.append(first.dtype if first is not None else module_dtype(module) or torch.float32)
    return to_module_dtype(module, args), to_module_dtype(module, kwargs)


def _transform_to_input_dtype(module: RegistrationModule, args: Any, output: Any) -> Any:
    """Forward hook: ``transform_ref_src`` back in the caller's dtype (float64 in, float64 out)."""
    dtype = module._input_dtypes.pop() if module._input_dtypes else None
    if isinstance(output, RegistrationResult) and dtype is not None and output.transform_ref_src.dtype != dtype:
        output.transform_ref_src = output.transform_ref_src.to(dtype)
    return output


def _checked_terms(terms: Sequence[LossTerm] | None) -> list[LossTerm]:
    """The injected loss terms, type- and name-checked."""
    terms = list(terms or [])
    for term in terms:
        if not isinstance(term, LossTerm):
            raise TypeError(
                f"`loss_terms` must hold lcreg.models.loss_terms.LossTerm modules, got {type(term).__name__}"
            )
    names = [term.name for term in terms]
    if len(set(names)) != len(names):
        raise ValueError(f"loss terms need distinct names, got {names}")
    return terms
