"""The base of every registration model: one constructor wiring the model interface, training and evaluation.

:class:`RegistrationModule` is composed of three parts, one job each:

* :class:`~lcreg.models.interface.RegistrationInterface` (``interface.py``): inference, ``forward`` / ``register`` /
  ``estimate`` / ``refine``, input checks, dtype hooks, unit scale, refiner;
* :class:`~lcreg.models.training.TrainingLogic` (``training.py``): ``training_losses`` (the model's own objective
  plus every injected loss term), the training step, the guard against non-finite steps, the optimiser;
* :class:`~lcreg.models.evaluation.EvaluationLogic` (``evaluation.py``): validation/test metrics, the summary line,
  ``test_per_pair.csv``, ``predict``.

Subclasses implement only:

* ``forward(points_src (B, N, 3), points_ref (B, M, 3)) -> RegistrationResult``;
* ``_compute_loss(result, batch) -> dict[str, Tensor]`` with a ``"loss"`` entry (the model's own objective).

Everything else is injected through the constructor (LightningCLI YAML), so a configured model is complete:
``optimizer``/``lr_scheduler`` factories, extra ``loss_terms`` (:mod:`lcreg.models.loss_terms`, e.g. local
consistency), and a ``refiner`` run after ``forward`` outside training. Hosts pass these through ``**kwargs`` and make
no other call: the base records the outermost constructor's arguments as ``hparams`` and binds the loss terms once
that constructor has returned.
"""

from __future__ import annotations

import functools
import inspect
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar, Literal

import torch

from lcreg.metrics.registration import PerPairErrors, check_recall_thresholds
from lcreg.models.evaluation import EvaluationLogic
from lcreg.models.loss_terms import LossTerm
from lcreg.models.training import NonFiniteTrainingError, OptimizerFactory, SchedulerFactory

__all__ = ["COMPONENT_ARGS", "EVALUATION_ARGS", "NonFiniteTrainingError", "RegistrationModule"]


COMPONENT_ARGS = ("optimizer", "lr_scheduler", "loss_terms", "refiner", "voxel_grid")
"""Constructor arguments that are components, not hyper-parameters: never saved in a checkpoint's ``hparams``."""

EVALUATION_ARGS = ("recall_thresholds",)
"""Constructor arguments that only choose what evaluation reports: saved in ``hparams`` like the others, but the CLI
never lets a checkpoint's value override the one of the run (``lcreg test --ckpt_path ...``)."""


class RegistrationModule(EvaluationLogic):
    """Base LightningModule for registration methods.

    Inputs: ``forward`` and ``register`` validate both clouds first (:meth:`validate_inputs`, a forward pre-hook:
    typed errors that name ``points_src`` or ``points_ref``, before any layer runs). They accept float32 and float64
    clouds (numpy's default) and compute in the model's dtype (:func:`lcreg.nn.dtypes.module_dtype`; float32 unless
    converted with ``.double()``): the pre-hook casts the inputs, a forward hook returns ``transform_ref_src`` in the
    caller's dtype. Training and evaluation batches are cast to the model's dtype in each step.

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
        lr_scheduler: Optional callable building a scheduler from the optimiser (stepped as
            ``lr_scheduler_interval`` says; a ``ReduceLROnPlateau`` steps once right after each validation of
            ``fit``, on ``val/loss``, whatever the validation schedule).
        lr_scheduler_interval: ``"epoch"`` (default; the original methods' milestones are epochs of the full
            dataset) or ``"step"``: the scheduler steps after every optimiser step, so its milestones are step
            counts and do not move with the training set's size (e.g. IDAM's 30 epochs of the full ModelNet40 at
            batch 16 are about 18,450 steps). ``ReduceLROnPlateau`` takes ``"epoch"`` only.
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
            ``recall_thresholds`` is not a list of pairs of finite numbers > 0, or ``lr_scheduler_interval`` is not
            ``"epoch"`` or ``"step"`` (or is ``"step"`` for a ``ReduceLROnPlateau``, when the optimisers are built).
    """

    training_only_modules: ClassVar[tuple[str, ...]] = ("loss_terms",)
    inference_hparams: ClassVar[Mapping[str, Any]] = {}

    def __init__(
        self,
        optimizer: OptimizerFactory = torch.optim.Adam,
        lr_scheduler: SchedulerFactory | None = None,
        lr_scheduler_interval: Literal["epoch", "step"] = "epoch",
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
        self._step_index = None
        self.optimizer_factory = optimizer
        self.scheduler_factory = lr_scheduler
        if lr_scheduler_interval not in ("epoch", "step"):
            raise ValueError(f"`lr_scheduler_interval` must be 'epoch' or 'step', got {lr_scheduler_interval!r}")
        self.lr_scheduler_interval = lr_scheduler_interval
        self.loss_terms = torch.nn.ModuleList(_checked_terms(loss_terms))
        self.refiner = refiner  # a plain attribute, checked (RegistrationInterface.__setattr__): not saved
        self.recall_thresholds = None if recall_thresholds is None else check_recall_thresholds(recall_thresholds)
        self._use_recall_thresholds(self.recall_thresholds or ())
        self.test_pairs = PerPairErrors()
        self._install_dtype_hooks()

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


def _constructor_owner(cls: type) -> type:
    """The class whose ``__init__`` runs first when ``cls`` is built (the nearest that defines one)."""
    return next(c for c in cls.__mro__ if "__init__" in c.__dict__)


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
