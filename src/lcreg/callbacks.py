"""Lightning callbacks and the step-0 candidate of a run's checkpoint selection.

Callbacks: latest-state checkpoint, RNG state, predictions, a time-based progress bar, a training clock, early
stopping that honours the trainer's minimum.
:func:`validate_starting_weights` makes the weights a run starts from one of its checkpoints.
"""

from __future__ import annotations

import random
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from lightning.pytorch import LightningDataModule, LightningModule, Trainer
from lightning.pytorch.callbacks import (
    BasePredictionWriter,
    Callback,
    Checkpoint,
    EarlyStopping,
    ModelCheckpoint,
    TQDMProgressBar,
)
from lightning.pytorch.callbacks.early_stopping import EarlyStoppingReason
from lightning.pytorch.trainer.states import TrainerFn
from lightning.pytorch.utilities import rank_zero_info, rank_zero_warn
from lightning.pytorch.utilities.exceptions import SIGTERMException

from lcreg.types import RegistrationResult

__all__ = [
    "LatestCheckpoint",
    "MinimumEarlyStopping",
    "RngState",
    "TimedProgressBar",
    "TrainingClock",
    "TransformWriter",
    "follow_moved_folder",
    "keep_initial_weights_as_candidate",
    "validate_starting_weights",
]


class LatestCheckpoint(Checkpoint):
    """Keep ``last.ckpt`` the latest training state (model, optimiser, scheduler, loops, callbacks, data position).

    A :class:`~lightning.pytorch.callbacks.Checkpoint`, so Lightning runs its hooks after the other callbacks and,
    placed after the ``ModelCheckpoint`` (as :class:`lcreg.cli.LcregCLI` places it), after that one too: the state
    it saves after a validation already records that validation's best checkpoint and early-stopping count.

    Lightning's ``ModelCheckpoint(save_last=True)`` rewrites ``last.ckpt`` only when it also saves a top-k
    checkpoint, so ``last.ckpt`` trails the run. This callback writes it every ``every_n_train_steps`` optimiser
    steps, at the last step (``max_steps``), after every validation, at the end of every complete training epoch and
    when SIGTERM stops ``fit`` (at most once per step; a step followed by a validation is saved after it), through
    ``Trainer.save_checkpoint`` (an atomic write: a killed run leaves the previous file whole). The file goes to
    the directory of the trainer's first ``ModelCheckpoint`` (``<log_dir>/checkpoints`` by default).

    Args:
        every_n_train_steps: Optimiser steps between two saves (0: only after validations and epochs).
        filename: File name in the checkpoint directory.

    Raises:
        ValueError: If ``every_n_train_steps < 0``.
    """

    def __init__(self, every_n_train_steps: int = 50, filename: str = "last.ckpt") -> None:
        if every_n_train_steps < 0:
            raise ValueError(f"`every_n_train_steps` must be >= 0, got {every_n_train_steps}")
        self.every_n_train_steps = every_n_train_steps
        self.filename = filename
        self._saved_step = -1

    @property
    def state_key(self) -> str:
        """Key of this callback's entry in checkpoints."""
        return self._generate_state_key(every_n_train_steps=self.every_n_train_steps, filename=self.filename)

    def path(self, trainer: Trainer) -> Path:
        """Where ``last.ckpt`` is written."""
        checkpoint = trainer.checkpoint_callback
        dirpath = getattr(checkpoint, "dirpath", None)
        if dirpath is None:
            dirpath = Path(trainer.log_dir or trainer.default_root_dir) / "checkpoints"
        return Path(dirpath) / self.filename

    def saved_state(self, trainer: Trainer) -> tuple[Path, int] | None:
        """``last.ckpt`` and its optimiser step, if this run wrote it (the state a stopped run resumes from)."""
        path = self.path(trainer)
        return (path, self._saved_step) if self._saved_step >= 0 and path.is_file() else None

    def _save(self, trainer: Trainer) -> None:
        if (
            bool(getattr(trainer, "fast_dev_run", False))
            or trainer.sanity_checking
            or trainer.state.fn != TrainerFn.FITTING
            or trainer.global_step == self._saved_step
        ):
            return
        self._saved_step = trainer.global_step
        trainer.save_checkpoint(self.path(trainer), weights_only=False)  # the full state, not weights only

    def on_train_batch_end(
        self, trainer: Trainer, pl_module: LightningModule, outputs: Any, batch: Any, batch_idx: int
    ) -> None:
        """Save every ``every_n_train_steps`` optimiser steps, and after an epoch's last batch (see below).

        The end of an epoch is saved here, at its last batch, unless a validation follows or a ``ModelCheckpoint``
        or ``EarlyStopping`` takes its update in at the epoch's end (then :meth:`on_train_epoch_end` saves). Lightning
        2.6 resumes a file from this hook exactly; a file written in ``on_train_epoch_end`` of a ``max_steps`` run
        makes the resumed run end that epoch again after one more batch (its fit loop always restarts an
        iteration-based run; a related report: Lightning-AI/pytorch-lightning#19617).
        """
        step, n = trainer.global_step, self.every_n_train_steps
        due = (n > 0 and step > 0 and step % n == 0) or step == trainer.max_steps
        due = due or (_epoch_complete(trainer) and not _validation_taken_in_at_epoch_end(trainer))
        if due and not _validation_follows(trainer):
            self._save(trainer)

    def on_train_start(self, trainer: Trainer, pl_module: LightningModule) -> None:
        """Warn when this run's epoch-end saves will not resume exactly (see :meth:`on_train_batch_end`)."""
        batches = trainer.num_training_batches
        ends = trainer.max_steps != -1 and batches != float("inf") and batches <= trainer.max_steps
        if ends and _validation_taken_in_at_epoch_end(trainer):
            rank_zero_warn(
                "lcreg: this run has a step budget and a listed ModelCheckpoint or EarlyStopping takes each "
                "validation in at the end of its epoch, where last.ckpt is then written; a run resumed from such a "
                "file ends that epoch again and does not repeat the uninterrupted run (a related report: "
                "Lightning-AI/pytorch-lightning#19617). It resumes exactly with `save_on_train_epoch_end: false` "
                "(ModelCheckpoint) and `check_on_train_epoch_end: false` (EarlyStopping), or with the same schedule "
                f"in steps: `--trainer.val_check_interval={int(batches)} --trainer.check_val_every_n_epoch=null`"
            )

    def on_validation_end(self, trainer: Trainer, pl_module: LightningModule) -> None:
        """Save after every validation during ``fit`` (also the step-cadence save of the batch before it).

        With one validation per epoch, Lightning's ``ModelCheckpoint`` and ``EarlyStopping`` take the validation in at
        the epoch's end unless told otherwise (lcreg's default ``ModelCheckpoint`` is), so the state is then saved at
        the epoch's end (:meth:`on_train_epoch_end`), already holding their update. Otherwise they take it in here,
        before this callback (it runs after every ``ModelCheckpoint``), and it is saved here: a checkpoint from the
        epoch-end hook would resume a ``max_steps`` run one step late.
        """
        if not (_epoch_complete(trainer) and _validation_taken_in_at_epoch_end(trainer)):
            self._save(trainer)

    def on_load_checkpoint(self, trainer: Trainer, pl_module: LightningModule, checkpoint: dict[str, Any]) -> None:
        """Keep the checkpoint selection of a run resumed in a moved folder (:func:`follow_moved_folder`).

        Lightning calls every callback's ``on_load_checkpoint`` before any loads its state.
        """
        states = checkpoint.get("callbacks") or {}
        for callback in trainer.checkpoint_callbacks:
            state = states.get(callback.state_key)
            if not (isinstance(callback, ModelCheckpoint) and isinstance(state, dict)):
                continue
            recorded = state.get("dirpath")
            if follow_moved_folder(state, callback):
                rank_zero_info(f"The run moved from {recorded} to {callback.dirpath}: its chosen checkpoints are kept")

    def on_exception(self, trainer: Trainer, pl_module: LightningModule, exception: BaseException) -> None:
        """Save when SIGTERM stopped ``fit`` at the end of a step, so that the run resumes from the step it reached.

        Lightning raises ``SIGTERMException`` once the step in progress (and any validation it ran) has ended: the
        same state as this callback's other saves. Not when the signal stopped a validation before its last batch
        (the run then resumes from the save before that validation); not on other exceptions (a crash or Ctrl+C
        may stop in the middle of an update).
        """
        if isinstance(exception, SIGTERMException) and not trainer.validating:
            self._save(trainer)

    def on_train_epoch_end(self, trainer: Trainer, pl_module: LightningModule) -> None:
        """Save at the end of every complete training epoch not saved at its last batch (:meth:`on_train_batch_end`).

        That is, after the epoch's validation when a ``ModelCheckpoint`` or ``EarlyStopping`` takes it in at the
        epoch's end.

        An epoch cut short (``max_steps``) is not saved here: its last step was (a checkpoint here would resume at
        the next epoch).
        """
        if _epoch_complete(trainer):
            self._save(trainer)


def _validation_taken_in_at_epoch_end(trainer: Trainer) -> bool:
    """Whether a ``ModelCheckpoint`` or ``EarlyStopping`` callback takes a validation in at the epoch's end.

    Lightning's rule for one validation per epoch, unless the callback says otherwise (``save_on_train_epoch_end``,
    ``check_on_train_epoch_end``; lcreg's default ``ModelCheckpoint`` saves at the validation's end); it is read from
    the callbacks themselves.
    """
    checkpoints = [c for c in trainer.checkpoint_callbacks if isinstance(c, ModelCheckpoint)]
    stoppers = [c for c in trainer.callbacks if isinstance(c, EarlyStopping)]  # type: ignore[attr-defined]
    return any(c._should_save_on_train_epoch_end(trainer) for c in checkpoints) or any(
        bool(c._check_on_train_epoch_end) for c in stoppers
    )


def _epoch_complete(trainer: Trainer) -> bool:
    """Whether every training batch of the current epoch has run (its end-of-epoch hooks follow)."""
    return trainer.fit_loop.epoch_loop.batch_progress.current.ready >= trainer.num_training_batches


def _validation_follows(trainer: Trainer) -> bool:
    """Whether Lightning validates right after the current training batch.

    A checkpoint taken at that batch's end would resume after the validation (Lightning fast-forwards it), so the
    save waits for ``on_validation_end``. Uses the training loop's own decision (a private method of Lightning 2.6).
    """
    fetcher = trainer.fit_loop._data_fetcher
    return fetcher is not None and bool(trainer.fit_loop.epoch_loop._should_check_val_fx(fetcher))


def _rng_states() -> dict[str, Any]:
    """The torch (CPU and, when initialised, CUDA), NumPy and Python RNG states, as a weights-only load reads them."""
    key = np.random.get_state(legacy=False)
    state: dict[str, Any] = {
        "torch": torch.get_rng_state(),
        "numpy": {
            "key": torch.from_numpy(np.asarray(key["state"]["key"], dtype=np.int64)),
            "pos": int(key["state"]["pos"]),
            "has_gauss": int(key["has_gauss"]),
            "gauss": float(key["gauss"]),
        },
        "python": random.getstate(),
    }
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def _restore_rng_states(state: dict[str, Any]) -> None:
    """Set the RNG states saved by :func:`_rng_states`."""
    torch.set_rng_state(state["torch"])
    numpy = state["numpy"]
    np.random.set_state(
        ("MT19937", numpy["key"].numpy().astype(np.uint32), numpy["pos"], numpy["has_gauss"], numpy["gauss"])
    )
    version, internal, gauss = state["python"]
    random.setstate((version, tuple(internal), gauss))
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


class MinimumEarlyStopping(EarlyStopping):
    """Lightning's ``EarlyStopping`` whose patience stop does not latch before the trainer's ``min_steps``.

    Lightning 2.6 latches the stop (``trainer.should_stop = trainer.should_stop or should_stop``): when patience
    runs out before ``min_steps``/``min_epochs``, the run stops the moment the minimum is reached even if its metric
    has improved since (Lightning-AI/pytorch-lightning#19966). Here such a stop is provisional: the next check
    derives it again, so a run still improving at its minimum goes on until ``patience`` validations without an
    improvement (or the step cap), and a run that never recovered stops at the minimum as before. Stops for a
    non-finite metric or a threshold latch as in Lightning, as does a stop set by anything else. Under DDP the stop
    is provisional only when it is on every process (one whose own reason was not patience latches it for all), so
    that no process trains on after another stopped.

    Its state in a checkpoint is ``EarlyStopping``'s, under the same key, so runs started with Lightning's class
    resume with this one and the other way round.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._provisional = False

    @property
    def state_key(self) -> str:
        """``EarlyStopping``'s own key (the parent's class name, not this one's)."""
        return f"EarlyStopping{ ({'monitor': self.monitor, 'mode': self.mode})!r}"

    def _run_early_stopping_check(self, trainer: Trainer) -> None:
        if self._provisional:  # this callback's own stop under the minimum: derived again below
            trainer.should_stop, self._provisional = False, False
        stopped = trainer.should_stop
        super()._run_early_stopping_check(trainer)
        patience = self.stopping_reason == EarlyStoppingReason.PATIENCE_EXHAUSTED
        provisional = trainer.should_stop and not stopped and patience and not _minimum_met(trainer)
        # Under DDP every process must keep or drop the stop alike: provisional only where all of them say so
        self._provisional = trainer.strategy.reduce_boolean_decision(bool(provisional), all=True)


def _minimum_met(trainer: Trainer) -> bool:
    """Whether the fit loop may stop early: its ``min_steps`` and ``min_epochs`` (where set) are reached."""
    loop = trainer.fit_loop
    steps = loop.min_steps is None or trainer.global_step >= loop.min_steps
    epochs = not loop.min_epochs or trainer.current_epoch >= loop.min_epochs
    return steps and epochs


class RngState(Callback):
    """Save the torch (CPU and CUDA), NumPy and Python RNG states in checkpoints; a resumed ``fit`` restores them.

    Lightning checkpoints leave them out, so a resumed run would draw other random numbers than the uninterrupted
    one (LC's random subsets, dropout). The states are restored when training starts (after the sanity check),
    as tensors and plain numbers that a weights-only load reads.
    """

    def __init__(self) -> None:
        self._pending: dict[str, Any] | None = None

    def state_dict(self) -> dict[str, Any]:
        """The current RNG states."""
        return _rng_states()

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        """Keep the states until training starts."""
        self._pending = state_dict

    def on_train_start(self, trainer: Trainer, pl_module: LightningModule) -> None:
        """Restore the states of the checkpoint being resumed, if any."""
        state, self._pending = self._pending, None
        if not state:
            return
        _restore_rng_states(state)


class TrainingClock(Callback):
    """Wall-clock seconds of a run's training, carried through its checkpoints into resumed segments.

    A run cut off and resumed from ``last.ckpt`` trains in segments; each segment alone times only itself. The clock
    saves the time trained so far in every checkpoint and a resumed ``fit`` starts from it, so :meth:`seconds` is
    the time of all the training the run kept: the segments up to the checkpoint each one resumed from, plus the
    current one (time after a segment's last checkpoint was lost with its steps and is not counted).

    Args:
        clock: Clock in seconds (monotonic; a fake one in tests).
    """

    def __init__(self, clock: Callable[[], float] = time.perf_counter) -> None:
        self._clock = clock
        self._before = 0.0
        self._start: float | None = None

    def seconds(self) -> float:
        """Seconds trained: the checkpoint's earlier segments plus the current one since its ``fit`` started."""
        return self._before + (0.0 if self._start is None else self._clock() - self._start)

    def on_fit_start(self, trainer: Trainer, pl_module: LightningModule) -> None:
        """Start this segment's time."""
        self._start = self._clock()

    def state_dict(self) -> dict[str, Any]:
        """The seconds trained up to the checkpoint being written."""
        return {"seconds": self.seconds()}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        """Continue from the checkpoint's seconds."""
        self._before = float(state_dict.get("seconds", 0.0))


class TransformWriter(BasePredictionWriter):
    """Write ``lcreg predict`` results to ``<log_dir>/predictions.npz``.

    Arrays: ``index (P,)`` (dataset index when the batches carry it, else a running count),
    ``transform_ref_src (P, 4, 4)`` (maps source into reference), ``converged (P,)``, ``num_iters (P,)`` and, when
    the data has a ground truth, ``transform_gt (P, 4, 4)``.

    Args:
        filename: File name inside the logger's directory (or ``default_root_dir`` without a logger).
    """

    def __init__(self, filename: str = "predictions.npz") -> None:
        super().__init__(write_interval="epoch")
        self.filename = filename

    def write_on_epoch_end(
        self,
        trainer: Trainer,
        pl_module: LightningModule,
        predictions: Sequence[Any],
        batch_indices: Sequence[Any],
    ) -> None:
        """Concatenate the per-batch :class:`RegistrationResult` objects and save them."""
        results = [r for r in predictions if isinstance(r, RegistrationResult)]
        if not results:
            return
        out: dict[str, np.ndarray] = {
            "transform_ref_src": torch.cat([r.transform_ref_src for r in results]).cpu().numpy(),
            "converged": torch.cat([r.converged for r in results]).cpu().numpy(),
            "num_iters": torch.cat([r.num_iters for r in results]).cpu().numpy(),
        }
        for key in ("index", "transform_gt"):
            if all(isinstance(r.aux.get(key), torch.Tensor) for r in results):
                out[key] = torch.cat([r.aux[key] for r in results]).cpu().numpy()
        out.setdefault("index", np.arange(len(out["converged"])))
        directory = Path(trainer.log_dir or trainer.default_root_dir)
        directory.mkdir(parents=True, exist_ok=True)
        path = directory / self.filename
        np.savez(path, **out)  # type: ignore[arg-type]  # numpy stubs type **kwds as allow_pickle
        rank_zero_info(f"{len(out['index'])} predictions written to {path}")


class TimedProgressBar(TQDMProgressBar):
    """A TQDM bar that refreshes at the end of a batch once ``min_interval_s`` have passed since its last refresh.

    Lightning's ``refresh_rate`` counts batches: 20 keeps a CPU run (about 1 s a step) still for 20 s, 1 redraws the
    bar hundreds of times a second on a fast GPU. This bar is checked after every train/val/test/predict batch and
    redraws when ``min_interval_s`` have passed since its last redraw, and always at the last batch of a loop, so it
    moves at every step on the CPU and a few times a second on a GPU. ``refresh_rate`` stays 1 (the environment's
    ``TQDM_MINITERS`` still raises it).

    Args:
        min_interval_s: Least time between two redraws, in seconds (0: every batch).
        process_position: Forwarded to ``TQDMProgressBar`` (bar position, for several trainers at once).
        leave: Forwarded to ``TQDMProgressBar`` (keep each epoch's bar).

    Raises:
        ValueError: If ``min_interval_s`` is negative or not finite.
    """

    clock: Callable[[], float] = staticmethod(time.monotonic)
    """Seconds of a monotonic clock (replaced in tests)."""

    def __init__(self, min_interval_s: float = 0.5, process_position: int = 0, leave: bool = False) -> None:
        if not 0 <= min_interval_s < float("inf"):
            raise ValueError(f"`min_interval_s` must be a finite number >= 0, got {min_interval_s!r}")
        super().__init__(refresh_rate=1, process_position=process_position, leave=leave)
        self.min_interval_s = min_interval_s
        self._last_refresh = float("-inf")

    def _should_update(self, current: int, total: int) -> bool:
        """Whether the batch-end hook redraws the bar (Lightning 2.x calls this from all four batch-end hooks)."""
        if not super()._should_update(current, total):  # enabled, refresh_rate
            return False
        now = self.clock()
        if current != total and now - self._last_refresh < self.min_interval_s:
            return False
        self._last_refresh = now
        return True


def validate_starting_weights(
    trainer: Trainer, model: LightningModule, datamodule: LightningDataModule | None = None
) -> Path | None:
    """Validate the weights a run starts from and keep them as a candidate (:func:`keep_initial_weights_as_candidate`).

    The RNG states are put back afterwards (validation draws from them, e.g. a data loader's seed), so the training
    that follows draws the same random numbers as a run that did not validate first.

    Args:
        trainer: The trainer that will ``fit`` ``model``.
        model: The model, with the weights it starts from.
        datamodule: The run's data (validation split).

    Returns:
        The step-0 checkpoint written, or None when no callback took the weights.
    """
    state = _rng_states()
    trainer.validate(model, datamodule=datamodule, verbose=False)
    _restore_rng_states(state)
    return keep_initial_weights_as_candidate(trainer)


def keep_initial_weights_as_candidate(trainer: Trainer) -> Path | None:
    """Make the weights just validated (before ``fit``) a candidate of the run's selection, as a step-0 checkpoint.

    Lightning writes no checkpoint outside ``fit`` and starts its early stopping from no score, so without this a
    run started from given weights (a pretrained encoder, say) selects its best *trained* checkpoint even when
    validation never beat the starting point, and its patience counts from the first trained validation. Here
    each ``ModelCheckpoint`` that monitors a logged metric gets the weights as a checkpoint named by its own
    template (step 0) and scored with that metric, which a later checkpoint replaces only by beating it; each
    ``EarlyStopping`` takes the score as its best so far. Nothing changes where the metric was not logged or is
    not finite.

    Args:
        trainer: A trainer that has just run ``validate`` on the model it will ``fit``.

    Returns:
        The step-0 checkpoint written, or None when no callback took the weights.
    """
    metrics = dict(trainer.callback_metrics)
    written: Path | None = None
    for callback in getattr(trainer, "callbacks", []):
        score = metrics.get(getattr(callback, "monitor", None) or "")
        if score is None or not torch.isfinite(score):
            continue
        if isinstance(callback, EarlyStopping):
            callback.best_score = score.detach().clone()
            callback.wait_count = 0
        elif isinstance(callback, ModelCheckpoint) and callback.save_top_k != 0:
            name = callback.format_checkpoint_name({**metrics, "epoch": torch.tensor(0), "step": torch.tensor(0)})
            trainer.save_checkpoint(name)
            _add_candidate(callback, name, score.detach().clone())
            written = Path(name)
    return written


def _add_candidate(callback: Any, path: str, score: torch.Tensor) -> None:
    """Record checkpoint ``path`` with ``score`` in a ``ModelCheckpoint``'s top-k, as its own saves do."""
    callback.best_k_models[path] = score
    for name, value in _top_k_fields(callback.best_k_models, callback.mode, callback.save_top_k).items():
        setattr(callback, name, value)


def _top_k_fields(best_k_models: dict[str, Any], mode: str, save_top_k: int) -> dict[str, Any]:
    """A ``ModelCheckpoint``'s best and k-th entries for a non-empty top-k ``{path: score}``, as its saves set them.

    The k-th entry (the one the next better checkpoint replaces) is set only once the top-k is full.
    """
    k = len(best_k_models) if save_top_k == -1 else save_top_k
    worst, best = (max, min) if mode == "min" else (min, max)
    fields: dict[str, Any] = {}
    if len(best_k_models) >= k:
        fields["kth_best_model_path"] = worst(best_k_models, key=lambda path: best_k_models[path])
        fields["kth_value"] = best_k_models[fields["kth_best_model_path"]]
    fields["best_model_path"] = best(best_k_models, key=lambda path: best_k_models[path])
    fields["best_model_score"] = best_k_models[fields["best_model_path"]]
    return fields


def follow_moved_folder(state: dict[str, Any], callback: ModelCheckpoint) -> bool:
    """Point a ``ModelCheckpoint``'s saved ``state`` at its files in ``callback``'s folder, if the run was moved.

    Lightning keeps a resumed ``ModelCheckpoint``'s top-k only when the checkpoint records the same ``dirpath``:
    a run folder renamed, or copied to another machine or root, resumes with an empty top-k, so its first later
    validation is saved as the best however much worse it is, and the checkpoint chosen before the move is
    neither a candidate nor deleted. Here each recorded checkpoint that was in the recorded folder and is now in
    ``callback.dirpath`` (same file name) is renamed into it; recorded files absent there are dropped. Nothing
    changes when the folder is the same, when the recorded best checkpoint is not in the new folder (Lightning's
    own behaviour follows), or for files recorded outside the old folder.

    Args:
        state: The callback's entry of a checkpoint's ``callbacks`` (changed in place).
        callback: The ``ModelCheckpoint`` about to load it (its ``dirpath`` resolved by ``setup``).

    Returns:
        Whether ``state`` was changed.
    """
    old, new = state.get("dirpath"), callback.dirpath
    if not old or not new or Path(old) == Path(new):
        return False

    def moved(path: str) -> str:
        return str(Path(new) / Path(path).name) if path and Path(path).parent == Path(old) else path

    best = moved(str(state.get("best_model_path") or ""))
    if not best or best == state.get("best_model_path"):
        return False
    kept = {moved(path): score for path, score in (state.get("best_k_models") or {}).items()}
    kept = {path: score for path, score in kept.items() if Path(path).is_file()}
    if best not in kept:
        return False
    state.update(_top_k_fields(kept, callback.mode, callback.save_top_k))
    state.update(dirpath=new, best_k_models=kept, last_model_path=moved(str(state.get("last_model_path") or "")))
    return True
