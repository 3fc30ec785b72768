"""Training: the model's losses plus the injected terms, the optimiser, and the guard against non-finite steps.

:class:`TrainingLogic` is the training half of :class:`~lcreg.models.base.RegistrationModule`. A host implements
``_compute_loss`` (its own objective, with a ``"loss"`` entry); :meth:`TrainingLogic.training_losses` adds every
injected :class:`~lcreg.models.loss_terms.LossTerm` (each weighted and logged as ``{stage}/{name}``): the one public way
to get a model's training losses. Optimisers are injected (``optimizer``/``lr_scheduler`` callables, LightningCLI
style).

A training step whose loss or gradient is not finite (NaN normals or poses in the data, a diverging model), or whose
forward pass produced non-finite values that a check inside it refused, is skipped before the optimiser sees it, with
a warning naming the batch's dataset indices; ``max_bad_steps`` consecutive skipped steps stop training
(:class:`NonFiniteTrainingError`). The parameters are checked before training and after every optimiser step: a
non-finite one stops training at once, naming the step and the parameter, before any checkpoint can record it, so
``last.ckpt`` keeps the last good state (``lcreg fit --ckpt_path last`` resumes from it).
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable, Iterable
from typing import Any, Literal

import torch
from lightning.pytorch.trainer.states import TrainerFn
from lightning.pytorch.utilities import rank_zero_warn

from lcreg.checks import NonFiniteError
from lcreg.models.interface import RegistrationInterface
from lcreg.models.loss_terms import LossTerm
from lcreg.types import RegistrationBatch, RegistrationResult

__all__ = ["NonFiniteTrainingError", "OptimizerFactory", "SchedulerFactory", "Stage", "TrainingLogic", "milestones"]

Stage = Literal["train", "val", "test"]
PLATEAU_MONITOR = "val/loss"  # what a ReduceLROnPlateau steps on (label-free for self-supervised models)
_NEVER = sys.maxsize  # the frequency handed to Lightning for a plateau scheduler this module steps itself
_PLATEAU_DUE_KEY = "lcreg_plateau_due"  # checkpoint entry: the loss of the plateau step due after this checkpoint
OptimizerFactory = Callable[[Iterable[torch.nn.Parameter]], torch.optim.Optimizer]
# Typed return (not Any): jsonargparse only accepts a scheduler `class_path` for a callable returning a scheduler.
SchedulerFactory = Callable[
    [torch.optim.Optimizer], torch.optim.lr_scheduler.LRScheduler | torch.optim.lr_scheduler.ReduceLROnPlateau
]


class NonFiniteTrainingError(RuntimeError):
    """Training stopped: too many consecutive steps had a non-finite loss or gradient."""


class TrainingLogic(RegistrationInterface):
    """The training step, its losses and optimiser (attributes set by the constructor of ``RegistrationModule``).

    Class attribute ``has_loss``: ``False`` for methods with nothing to train (classical baselines).
    """

    has_loss: bool = True
    loss_terms: torch.nn.ModuleList
    optimizer_factory: OptimizerFactory
    scheduler_factory: SchedulerFactory | None
    lr_scheduler_interval: str = "epoch"
    max_bad_steps: int
    _bad_steps: int = 0
    _step_skipped: bool = False
    _step_index: list[int] | None = None
    _resumed_plateau_loss: float | None = None

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

    def _bind_loss_terms(self) -> None:
        """Let every injected term check itself against the built model (run after the outermost constructor)."""
        for term in self.injected_terms:
            term.bind(self)

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

    def training_step(self, batch: RegistrationBatch, batch_idx: int) -> torch.Tensor | None:
        """One optimisation step on a batch; ``None`` (Lightning skips the step) when the loss is not finite.

        A forward pass that raises on non-finite values it made itself (a check inside the model refusing NaN points,
        a linear-algebra routine refusing a NaN matrix: a diverged model) counts as a non-finite loss.
        """
        batch = self._model_batch(batch)
        self._step_index = None if batch.index is None else batch.index.detach().cpu().tolist()
        try:
            losses = self.training_losses(self.training_forward(batch), batch)
        except (NonFiniteError, torch.linalg.LinAlgError) as err:
            self._step_skipped = True
            self._skip_step(f"the forward pass produced non-finite values ({err})")
            return None
        loss = losses["loss"]
        self._step_skipped = not bool(torch.isfinite(loss.detach()).all())  # one host sync per step
        if self._step_skipped:  # not logged: the epoch means stay finite
            bad = sorted(name for name, value in losses.items() if not bool(torch.isfinite(value.detach()).all()))
            self._skip_step(f"non-finite loss (terms {', '.join(bad)})")
            return None
        self._log_losses(losses, "train", len(batch))
        self._log_learning_rate(len(batch))
        return loss

    def _log_learning_rate(self, batch_size: int) -> None:
        """Log the rate of the first optimiser's first parameter group as ``train/lr`` (the rate of this step).

        An injected ``lr_scheduler`` steps per epoch, so where it changes the rate depends on the training set's size;
        the logged rate shows in each run's curves when it did.
        """
        trainer = self._trainer
        optimizers = getattr(trainer, "optimizers", None) if trainer is not None else None
        if optimizers:
            lr = float(optimizers[0].param_groups[0]["lr"])
            self.log("train/lr", lr, on_step=True, on_epoch=False, batch_size=batch_size)

    def on_train_start(self) -> None:
        """Refuse to train from non-finite parameters (loaded weights or checkpoint holding NaN/Inf).

        Then warn about milestones beyond the run, and take the plateau step a resumed checkpoint had due.

        Raises:
            NonFiniteTrainingError: Naming the first non-finite parameter.
        """
        self._check_parameters("before training (the model's weights hold them)", advice="load finite weights")
        self._warn_unreached_milestones()
        self._take_resumed_plateau_step()

    def _warn_unreached_milestones(self) -> None:
        """Warn when a step schedule's milestones lie beyond the run's step or epoch limit (its rate would not move).

        The original methods give their milestones in epochs of the full dataset (DCP-v2's MultiStepLR at 75, 150
        and 200 epochs); a run capped at fewer epochs, or by ``max_steps``, never reaches them.
        """
        trainer = self._trainer
        if trainer is None:
            return
        total = trainer.estimated_stepping_batches  # optimiser steps of the whole run (inf: unknown)
        per_epoch = trainer.num_training_batches / max(1, trainer.accumulate_grad_batches)
        if not (math.isfinite(total) and math.isfinite(per_epoch) and per_epoch > 0):
            return
        for config in trainer.lr_scheduler_configs:
            unit, steps_per = ("epochs", per_epoch) if config.interval == "epoch" else ("steps", 1.0)
            beyond = [m for m in milestones(config.scheduler) if m * config.frequency * steps_per >= total]
            if beyond:
                epochs = total / per_epoch
                rank_zero_warn(
                    f"lr_scheduler: {type(config.scheduler).__name__}'s milestones {beyond} ({unit}) lie beyond this "
                    f"run's {int(total)} optimiser steps ({epochs:.3g} epoch{'' if epochs == 1 else 's'} of "
                    f"{per_epoch:g} steps): "
                    "the rate will not change there. Give milestones within the run, or step counts with "
                    "`lr_scheduler_interval: step`"
                )

    def optimizer_step(self, *args: Any, **kwargs: Any) -> None:
        """The optimiser's step, then a check of the parameters (before any callback can save them).

        Raises:
            NonFiniteTrainingError: The step made a parameter non-finite (step, parameter, last good checkpoint).
        """
        super().optimizer_step(*args, **kwargs)
        self._check_parameters("after this optimiser step (the model diverged: lower the learning rate)")

    def _check_parameters(self, when: str, advice: str | None = None) -> None:
        """Raise when a parameter holds NaN/Inf (one fused reduction and one host sync).

        Args:
            when: Where the check runs, for the message.
            advice: What to do; default: where the last good state is (:meth:`_last_good_state`).
        """
        params = [(name, p) for name, p in self.named_parameters() if p.requires_grad]
        if not params:
            return
        finite = torch.stack([torch.isfinite(p).all() for _, p in params])
        if bool(finite.all()):
            return
        name, value = next((n, p) for (n, p), ok in zip(params, finite.tolist(), strict=True) if not ok)
        bad = int((~torch.isfinite(value)).sum())
        raise NonFiniteTrainingError(
            f"training stopped at step {self.global_step}: parameter `{name}` holds {bad} NaN/Inf value(s) {when}; "
            f"{advice or self._last_good_state()}"
        )

    def _last_good_state(self) -> str:
        """Where the last good state is, as the stop message says it.

        The state file of the first callback that reports one (``saved_state``:
        :class:`lcreg.callbacks.LatestCheckpoint` and its ``last.ckpt``), with its step.
        """
        trainer = self._trainer
        reporters = [c.saved_state for c in getattr(trainer, "callbacks", None) or [] if hasattr(c, "saved_state")]
        saved = reporters[0](trainer) if reporters else None
        if saved is None:
            return "no checkpoint was written before it: start again with a lower learning rate"
        path, step = saved
        return (
            f"the last good state is {path} (step {step}): resume it with `--ckpt_path last`, or start from its "
            f"weights with a lower learning rate (`--weights {path}`)"
        )

    def _log_losses(self, losses: dict[str, torch.Tensor], stage: Stage, batch_size: int) -> None:
        """Log every loss term as ``{stage}/{name}`` (per step in training; epoch means over every process)."""
        for name, value in losses.items():
            self.log(
                f"{stage}/{name}",
                value.detach(),
                batch_size=batch_size,
                prog_bar=name == "loss",
                on_step=stage == "train",
                on_epoch=True,
                sync_dist=stage != "train",  # epoch means over every process's pairs (DDP)
            )

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
                f"or lower the learning rate; {self._last_good_state()}"
            )
        rank_zero_warn(
            f"step {self.global_step} skipped: {reason} on {where} "
            f"({self._bad_steps} in a row; training stops at {self.max_bad_steps})"
        )

    def configure_optimizers(self) -> Any:
        """Build the injected optimiser (trainable parameters only) and optional scheduler."""
        self._bind_loss_terms()  # idempotent; every term's parameters exist before the optimiser sees them
        params = [p for p in self.parameters() if p.requires_grad]
        optimizer = self.optimizer_factory(params)
        if self.scheduler_factory is None:
            return optimizer
        scheduler = self.scheduler_factory(optimizer)
        interval = self.lr_scheduler_interval
        if isinstance(scheduler, torch.optim.lr_scheduler.ReduceLROnPlateau):
            if interval != "epoch":
                raise ValueError(
                    "`lr_scheduler_interval='step'` is for schedules of step counts; ReduceLROnPlateau steps on the "
                    "validation loss after each validation: leave lr_scheduler_interval at 'epoch'"
                )
            return {"optimizer": optimizer, "lr_scheduler": self._plateau_config(scheduler)}
        return {"optimizer": optimizer, "lr_scheduler": {"scheduler": scheduler, "interval": interval}}

    def _plateau_config(self, scheduler: torch.optim.lr_scheduler.ReduceLROnPlateau) -> dict[str, Any]:
        """A plateau scheduler steps once right after each validation of ``fit``, on its validation loss.

        This module takes the steps (:meth:`on_validation_end`); Lightning is given a frequency it never reaches. Its
        own rule counts a step-interval frequency in batches of the epoch and an epoch-interval one in epochs, so with
        validations every N steps on epochs N does not divide, every k epochs or several times an epoch, its steps
        missed validations or read a stale metric (the rate halved between validations, or never moved).
        """
        return {"scheduler": scheduler, "monitor": PLATEAU_MONITOR, "frequency": _NEVER, "strict": False}

    def on_validation_end(self) -> None:
        """Step the plateau scheduler on this validation's loss (a validation of ``fit``; none before ``fit``).

        Lightning calls this after every callback's ``on_validation_end``, so checkpoints written in this validation
        precede the step (:meth:`on_save_checkpoint` keeps it due).
        """
        scheduler, loss = self._plateau_due()
        if scheduler is None:
            return
        if loss is None:
            rank_zero_warn(f"ReduceLROnPlateau: validation logged no {PLATEAU_MONITOR!r}; the rate stays as it is")
            return
        self.lr_scheduler_step(scheduler, loss)

    def _plateau_scheduler(self) -> Any:
        """The plateau scheduler this module steps (:meth:`_plateau_config`), or None."""
        configs = self._trainer.lr_scheduler_configs if self._trainer is not None else []
        return next((c.scheduler for c in configs if c.reduce_on_plateau and c.frequency == _NEVER), None)

    def _plateau_due(self) -> tuple[Any, torch.Tensor | None]:
        """The plateau scheduler and the loss it steps on, while a validation of ``fit`` awaits its step.

        ``(None, None)`` outside such a validation or without a plateau scheduler.
        """
        trainer = self._trainer
        if trainer is None or trainer.state.fn != TrainerFn.FITTING or trainer.sanity_checking:
            return None, None
        scheduler = self._plateau_scheduler() if trainer.validating else None
        return (scheduler, trainer.callback_metrics.get(PLATEAU_MONITOR)) if scheduler is not None else (None, None)

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        """Keep the plateau step still due when a validation writes the checkpoint (a run resumed from it takes it)."""
        _, loss = self._plateau_due()
        if loss is not None:
            checkpoint[_PLATEAU_DUE_KEY] = float(loss)

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        """Keep the checkpoint's due plateau step until training starts (:meth:`on_train_start`)."""
        self._resumed_plateau_loss = checkpoint.get(_PLATEAU_DUE_KEY)

    def _take_resumed_plateau_step(self) -> None:
        """Take the plateau step a resumed checkpoint had due (a resumed run does not repeat that validation)."""
        loss, self._resumed_plateau_loss = self._resumed_plateau_loss, None
        scheduler = self._plateau_scheduler()
        if loss is not None and scheduler is not None and self._trainer is not None and self._trainer.ckpt_path:
            self.lr_scheduler_step(scheduler, torch.tensor(loss))


def milestones(scheduler: Any) -> list[int]:
    """Where a step schedule changes the rate, in its own steps (epochs or optimiser steps).

    A ``MultiStepLR``'s milestones (sorted), a ``StepLR``'s first step; ``[]`` for other schedules (their rate
    changes from the start, or on a plateau).
    """
    if isinstance(scheduler, torch.optim.lr_scheduler.MultiStepLR):
        return sorted(scheduler.milestones)
    if isinstance(scheduler, torch.optim.lr_scheduler.StepLR):
        return [scheduler.step_size]
    return []
