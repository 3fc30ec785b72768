"""Command line: ``lcreg fit|validate|test|predict --config configs/<x>.yaml`` (LightningCLI).

Models are any :class:`~lcreg.models.base.RegistrationModule` subclass (``model.class_path``), data any
LightningDataModule that yields :class:`~lcreg.types.RegistrationBatch` (``data.class_path``: the object
:class:`~lcreg.data.datamodule.PairDataModule` family or the scene :class:`~lcreg.data.scenes.ScenePairDataModule`
family); both are picked in YAML.
Shared trainer defaults live here, once: seed 1234, CSV logging under ``runs/<name>/version_<k>/`` (under
``<D>/<name>/version_<k>/`` with ``--trainer.default_root_dir D``), checkpoints
selected on the validation registration error ``val/rre_mean_deg`` (validation pairs carry a known pose; the
label-free ``val/loss`` of self-supervised models keeps falling while registration degrades) plus ``last.ckpt``, and a
TQDM bar redrawn by time (:class:`lcreg.callbacks.TimedProgressBar`). A config that lists its own ``ModelCheckpoint``
or progress bar replaces the default. Optimisers are model arguments (``model.init_args.optimizer``), so the top-level
``optimizer:`` key of LightningCLI is not used.

Configs compose: ``--config`` may be given several times (later files override earlier ones; ``loss_terms+:``
appends to a list), and a file may list the files it builds on under ``compose:`` (paths relative to that file),
which are read first, recursively. ``configs/dcp_lc.yaml`` is ``compose: [models/dcp.yaml, lc.yaml,
data/modelnet40.yaml, data/dcp_protocol.yaml]``. Test-time components are model arguments too:
``configs/refine/icp.yaml`` sets ``model.init_args.refiner`` (ICP after any model's estimate),
``configs/voxelize/lk27.yaml`` sets ``model.init_args.voxel_grid`` (voxelised IC-LK for the LK models).
``lcreg fit`` refuses models with nothing to train (classical methods) before anything runs.

``--weights NAME_OR_PATH`` (every subcommand) loads pretrained weights (:mod:`lcreg.weights`: a shipped name or an
exported ``.pt`` file) into the configured model once it is built: every tensor of the file must fit, and the
model's tensors the file lacks may only be training-only modules (decoder, normal head, loss terms), which keep their
initialisation. ``fit`` then fine-tunes from them; a ``--ckpt_path`` replaces them (they are not loaded).
``validate``, ``test`` and ``predict`` also take the model's arguments from the file, as from a checkpoint: the file's
``init_args`` (e.g. ``batch_norm``, ``jacobian``, ``eval_iterations``) replace the config's, so the model evaluated is
the one the weights were exported with, except ``recall_thresholds`` and the arguments given on the command line
(``--model.init_args.NAME``), which win. ``fit`` keeps the config's arguments (training settings are the run's).

Starting point: ``fit --validate_first true`` validates the starting weights (untrained, or ``--weights``) before
training and keeps them as a step-0 checkpoint that training must beat to be selected, and as the early-stopping
baseline (``configs/dvds.yaml`` sets it).

Resuming a run: ``lcreg fit --config X --ckpt_path last`` continues the latest run of that config where it stopped
(killed, crashed or finished): ``last`` is the ``last.ckpt`` of the highest ``runs/<name>/version_<k>`` that has
one (:mod:`lcreg.resume`), and the run keeps logging in that folder (the earlier ``metrics.csv`` is kept as
``metrics.segment<n>.csv``). ``last.ckpt`` is the latest state, written every 50 optimiser steps, after every
validation and every epoch (:class:`lcreg.callbacks.LatestCheckpoint`; list one in ``trainer.callbacks`` to change the
cadence) with the RNG states (:class:`lcreg.callbacks.RngState`), the training time so far
(:class:`lcreg.callbacks.TrainingClock`) and the position in the training stream, so the resumed run computes what
the uninterrupted one would have. An explicit ``--ckpt_path FILE`` works for every
subcommand; ``last`` with nothing to resume is an error. ``validate``/``test``/``predict --ckpt_path best`` take the
checkpoint that same run chose on validation (recorded in its ``last.ckpt``). ``fit`` prints its run folder.

Checkpoints are checked before Lightning reads them: read weights-only (no pickled code runs; Lightning also loads
them with ``weights_only=True``), refused with one line naming the file when missing, damaged, not a Lightning
checkpoint, of another model class than the config's, or with other ``state_dict`` keys.

Errors: from the command line, user errors print one or two lines on stderr: exit code 2 for arguments and configs,
1 for files, checkpoints, weights and a training stopped by non-finite losses. ``LCREG_DEBUG=1`` prints the full
report and traceback instead. Unexpected exceptions (bugs) keep their traceback.

A WandbLogger config works without an account: when one is requested, ``WANDB_MODE`` is unset and no
``WANDB_API_KEY`` is present, ``WANDB_MODE=offline`` is set (runs can be synced later with ``wandb sync``).
"""

from __future__ import annotations

import importlib
import os
import re
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NoReturn

from lightning.pytorch import LightningDataModule
from lightning.pytorch.cli import ArgsType, LightningArgumentParser, LightningCLI
from lightning.pytorch.utilities import rank_zero_info
from lightning.pytorch.utilities.exceptions import SIGTERMException

from lcreg.checkpoints import CheckpointError, check_class, check_keys, one_line, read_checkpoint
from lcreg.checks import DatasetLayoutError, DatasetNotFoundError, MissingDependencyError
from lcreg.config import ConfigFileError, ConfigValueError, UsageError, config_texts, expand_configs
from lcreg.models.base import EVALUATION_ARGS, NonFiniteTrainingError, RegistrationModule
from lcreg.resume import TERMINATED_EXIT_CODE

__all__ = [
    "ConfigFileError",
    "ConfigLayers",
    "ConfigValueError",
    "LcregArgumentParser",
    "LcregCLI",
    "NothingToTrainError",
    "UsageError",
    "build_cli",
    "expand_configs",
    "instantiate",
    "main",
]

INFERENCE_SUBCOMMANDS = ("validate", "test", "predict")
"""Subcommands where ``--weights`` also sets the model's arguments from the file (``fit`` keeps the config's)."""
DEBUG_ENV = "LCREG_DEBUG"
"""Set to 1 for full error reports and tracebacks from the command line."""

TRAINER_DEFAULTS: dict[str, Any] = {
    "logger": {"class_path": "lightning.pytorch.loggers.CSVLogger", "init_args": {"save_dir": "runs", "name": "lcreg"}},
    "log_every_n_steps": 10,
}


BATCH_LIMITS = tuple(f"trainer.limit_{stage}_batches" for stage in ("train", "val", "test", "predict"))
"""Trainer options where an int counts batches and a float is a fraction: ``1`` is one batch, ``1.0`` every batch."""


FILE_ERRORS = (
    CheckpointError,
    NonFiniteTrainingError,
    DatasetNotFoundError,
    DatasetLayoutError,
    MissingDependencyError,
)
"""Errors that end the command line with one line and exit code 1 (files, weights, data, optional packages)."""


class NothingToTrainError(UsageError, RuntimeError):
    """``lcreg fit`` on a method with nothing to train."""


def _debug() -> bool:
    return os.environ.get(DEBUG_ENV, "") not in ("", "0")


def condense_parser_error(message: str) -> str:
    r"""One line out of jsonargparse's multi-line report: the innermost key (dotted as on the command line) and why.

    Example:
        >>> condense_parser_error('Parser key "model":\n  - Problem with given class_path \'a.B\':\n'
        ...                       '    Parser key "depth":\n      Expected a <class \'int\'>. Got value: x')
        "--model.init_args.depth: Expected a <class 'int'>. Got value: x"
    """
    lines = [line.strip().lstrip("- ").strip() for line in message.splitlines() if line.strip()]
    key, detail = "", ""
    for i, line in enumerate(lines):
        found = re.match(r'Parser key "([^"]+)":\s*(.*)$', line)
        if found is None:
            continue
        joiner = ".init_args." if any("class_path" in ln for ln in lines[max(i - 1, 0) : i]) and key else "."
        key = f"{key}{joiner}{found.group(1)}" if key else found.group(1)
        detail = found.group(2) or (lines[i + 1] if i + 1 < len(lines) else "")
    if not key:
        return one_line(message)
    if "Union subtypes" in detail:  # the reason is under "Problem with given class_path 'x':", not in the summary
        detail = _class_path_problem(lines) or _union_problem(lines) or detail
    return one_line(f"--{key}: {detail}")


def _union_problem(lines: list[str]) -> str | None:
    """``expected int or None, got 'abc'`` from a plain union's report (``Expected a <class 'int'>`` lines)."""
    types = [m.group(1) for line in lines for m in [re.match(r"Expected a <class '(\w+)'>", line)] if m]
    given = next((line.partition(":")[2].strip() for line in lines if line.startswith("Given value:")), None)
    if not types or given is None:
        return None
    names = [{"NoneType": "None"}.get(t, t) for t in dict.fromkeys(types)]
    return f"expected {' or '.join(names)}, got {given!r}"


def _class_path_problem(lines: list[str]) -> str | None:
    """``<class path>: <first reason>`` of jsonargparse's ``Problem with given class_path`` block, if any."""
    for i, line in enumerate(lines[:-1]):
        found = re.match(r"Problem with given class_path '([^']+)':", line)
        if found:
            return f"{found.group(1)}: {lines[i + 1]}"
    return None


class LcregArgumentParser(LightningArgumentParser):
    """The parser of ``lcreg``: an invalid argument or config is reported in two lines (exit code 2).

    ``LCREG_DEBUG=1`` (or jsonargparse's own debug mode) keeps jsonargparse's full report. With ``raise_errors``
    (:func:`instantiate`, a Python call) the same line is raised as :class:`ConfigValueError` instead.
    """

    raise_errors: bool = False

    def error(self, message: str, ex: Exception | None = None) -> NoReturn:
        """Print ``lcreg: error: <key>: <why>`` and a hint, then exit with code 2 (or raise, see the class)."""
        if self.raise_errors:
            raise ConfigValueError(condense_parser_error(message)) from ex
        if not self.exit_on_error or _debug():
            super().error(message, ex)
        parser = getattr(ex, "subcommand_parser", None) or self
        prog = " ".join(["lcreg", *parser.prog.replace(" [options]", "").split()[1:]])
        sys.stderr.write(f"lcreg: error: {condense_parser_error(message)}\n")
        sys.stderr.write(f"hint: `{prog} --help` lists the options; {DEBUG_ENV}=1 prints the full report\n")
        self.exit(2)


@dataclass(frozen=True)
class ConfigLayers:
    """What :func:`instantiate` builds from: config files, then typed values (no command-line strings).

    Attributes:
        files: Config files in order (later ones override earlier ones; ``compose:`` lists already expanded).
        values: Python values by dotted key (``{"data.init_args.num_points": 512, "trainer.max_steps": 10}``),
            applied after the files, in order, as jsonargparse merges configs (a ``class_path`` value replaces the
            class, keeping the arguments it shares with the previous one); a list replaces the config's list, as on
            the command line.
    """

    files: tuple[str, ...] = ()
    values: Mapping[str, Any] = field(default_factory=dict)


def nested(values: Mapping[str, Any]) -> dict[str, Any]:
    """``{"a.b.c": 1}`` as ``{"a": {"b": {"c": 1}}}`` (a dotted key under another key's dict value is merged in).

    Raises:
        ConfigValueError: If a key is empty, or one key sets a value that another key descends into.
    """
    out: dict[str, Any] = {}
    for key, value in values.items():
        parts = key.split(".")
        if not all(parts):
            raise ConfigValueError(f"config value key {key!r}: expected dotted names such as 'data.init_args.x'")
        node = out
        for part in parts[:-1]:
            child = node.setdefault(part, {})
            if not isinstance(child, dict):
                raise ConfigValueError(f"config value key {key!r}: {part!r} is already set to {child!r}")
            node = child
        node[parts[-1]] = value
    return out


class LcregCLI(LightningCLI):
    """LightningCLI with lcreg's base classes in subclass mode, the shared trainer defaults and ``compose``.

    Unless the trainer config lists its own, adds ``ModelCheckpoint(monitor="val/rre_mean_deg")`` (the best; saved
    when each validation ends),
    :class:`~lcreg.callbacks.LatestCheckpoint` (``last.ckpt``: the latest state) and a
    :class:`~lcreg.callbacks.TimedProgressBar` (a TQDM bar redrawn at most every 0.5 s, at every step on a CPU); always
    adds :class:`~lcreg.callbacks.RngState` and :class:`~lcreg.callbacks.TrainingClock` (training seconds carried
    through checkpoints). ``lcreg predict`` writes ``predictions.npz`` (:class:`lcreg.callbacks.TransformWriter`) to
    the run's log directory. ``--ckpt_path`` is resolved (``last``,
    ``best``) and checked before anything is built (see the module docstring).
    """

    _checkpoint_keys: list[str] | None = None
    _explicit_model_args: frozenset[str] = frozenset()
    _pretrained: Any = None  # the --weights file read by _configure_from_weights (a PretrainedWeights)
    _kept_metrics: Path | None = None  # the earlier metrics.csv of a resumed run (keep_previous_metrics)

    def before_fit(self) -> None:
        """Say where the run logs and checkpoints (the folder changes with every run: ``version_<k>``).

        With ``--validate_first true`` (and no ``--ckpt_path``: a resumed run did it when it started) validate the
        starting weights and make them a candidate of the checkpoint selection and the early-stopping baseline
        (:func:`lcreg.callbacks.validate_starting_weights`): the learning curve starts at step 0, and a run
        that never beats its starting point (untrained or ``--weights``) selects it.
        """
        rank_zero_info(f"lcreg: this run logs to {self.trainer.log_dir}")
        if self._get(self.config, "validate_first") and not self._get(self.config, "ckpt_path"):
            from lcreg.callbacks import validate_starting_weights

            written = validate_starting_weights(self.trainer, self.model, self.datamodule)
            if written is not None:
                rank_zero_info(f"lcreg: the starting weights are a candidate of the selection: {written}")

    def after_fit(self) -> None:
        """A resumed run that logged nothing (resumed at its step cap) keeps its ``metrics.csv`` as it was."""
        from lcreg.resume import restore_unlogged_metrics

        restore_unlogged_metrics(self._kept_metrics, self.trainer.loggers)

    def parse_arguments(self, parser: LightningArgumentParser, args: ArgsType) -> None:
        """Parse ``args``: arguments, a dict, or :class:`ConfigLayers` (:func:`instantiate`).

        :func:`build_cli` reads ``sys.argv`` only when ``args`` is ``None``, so Lightning's warning about both does not
        apply.
        """
        self._explicit_model_args = explicit_model_args(args)
        if isinstance(args, ConfigLayers):
            parser.raise_errors = True  # an LcregArgumentParser (parser_class)
            self.config = parser.parse_args([arg for file in args.files for arg in ("--config", file)])
            for key, value in args.values.items():  # one at a time, in order: each merges like another --config
                if isinstance(value, list) and key in self.config:
                    del self.config[key]  # a list replaces the config's (jsonargparse would merge it item by item)
                self.config = parser.parse_object(nested({key: value}), self.config)
        elif isinstance(args, dict):
            self.config = parser.parse_object(args)
        else:
            self.config = parser.parse_args(args)  # type: ignore[arg-type]  # a list of strings here

    def _parse_ckpt_path(self) -> None:
        """Check the files named on the command line before anything is built (or seeded).

        ``--weights`` must name known weights (for validate/test/predict its ``init_args`` then configure the model,
        :meth:`_configure_from_weights`); ``--ckpt_path last`` is resolved, the checkpoint is read weights-only
        and its model class checked against the config's, then its hyper-parameters override the config's model
        arguments (LightningCLI's behaviour).

        Raises:
            lcreg.checkpoints.CheckpointError: One line naming the file: nothing to resume, missing, unreadable,
                not a Lightning checkpoint, or a checkpoint of another model class.
            lcreg.weights.PretrainedError: Unknown weights name or missing weights file (a CheckpointError too).
        """
        subcommand = self.config.get("subcommand")
        _logger_under_root_dir(self.config[subcommand] if subcommand else self.config)
        if not subcommand:
            return
        config = self.config[subcommand]
        if config.get("weights_only") is False:
            raise ConfigValueError("lcreg reads checkpoints weights-only: `--weights_only false` is not supported")
        model = config.get("model")
        class_path = model.get("class_path") if model is not None else None
        if subcommand == "fit" and isinstance(class_path, str):
            _refuse_nothing_to_train(class_path)
        path = config.get("ckpt_path")
        if config.get("weights") and not path:
            from lcreg.weights import resolve

            resolve(config["weights"])
            if subcommand in INFERENCE_SUBCOMMANDS and isinstance(class_path, str):
                self._configure_from_weights(subcommand, config["weights"], class_path)
        if not path or path in ("hpc", "registry") or str(path).startswith("registry:"):
            return
        if path == "last":
            path = self._resolve_last(subcommand)
            config["ckpt_path"] = path
        elif path == "best" and subcommand != "fit":
            path = self._resolve_best(subcommand)
            config["ckpt_path"] = path
        elif path == "best":
            raise ConfigValueError("`--ckpt_path best` is for validate/test/predict; `fit` resumes with `last`")
        checkpoint = read_checkpoint(path)
        if isinstance(class_path, str):
            check_class(path, checkpoint, class_path)
        self._checkpoint_keys = list(checkpoint["state_dict"])
        self._merge_hparams(subcommand, checkpoint)

    def _resolve_last(self, subcommand: str) -> str:
        """The file ``last`` means (:func:`lcreg.resume.find_last_checkpoint`); ``fit`` logs to its version again."""
        from lcreg.resume import find_last_checkpoint, keep_previous_metrics

        trainer = self.config[subcommand]["trainer"]
        last = find_last_checkpoint(trainer)
        rank_zero_info(f"lcreg: resuming from {last.path}")
        if subcommand == "fit" and last.version is not None:
            trainer["logger"]["init_args"]["version"] = last.version
            kept = self._kept_metrics = keep_previous_metrics(last.path.parent.parent)
            if kept is not None:
                rank_zero_info(f"lcreg: the earlier metrics of this run are kept in {kept}")
        return str(last.path)

    def _resolve_best(self, subcommand: str) -> str:
        """The checkpoint chosen on validation by the run ``last`` means (:func:`lcreg.resume.best_checkpoint_of`)."""
        from lcreg.resume import best_checkpoint_of, find_last_checkpoint

        best = best_checkpoint_of(find_last_checkpoint(self.config[subcommand]["trainer"]).path)
        rank_zero_info(f"lcreg: --ckpt_path best is {best} (chosen on validation)")
        return str(best)

    def _merge_hparams(self, subcommand: str, checkpoint: dict[str, Any]) -> None:
        """The model arguments saved in the checkpoint override the config's (LightningCLI's behaviour).

        Except the evaluation settings (:data:`~lcreg.models.base.EVALUATION_ARGS`, ``recall_thresholds``): what a
        run reports is the run's choice, so ``lcreg test --ckpt_path X --model.init_args.recall_thresholds ...``
        logs the recalls asked for, whatever the training run had.
        """
        hparams = dict(checkpoint.get("hyper_parameters") or {})
        hparams.pop("_instantiator", None)
        for key in EVALUATION_ARGS:
            hparams.pop(key, None)
        if not hparams:
            return
        if "_class_path" in hparams:
            hparams = {"class_path": hparams.pop("_class_path"), "dict_kwargs": hparams}
        self.config = self.parser.parse_object({subcommand: {"model": hparams}}, self.config)

    def _configure_from_weights(self, subcommand: str, source: str, class_path: str) -> None:
        """The ``--weights`` file's model arguments replace the config's, as a checkpoint's do (validate/test/predict).

        :func:`lcreg.weights.settings_of` chooses them: all but :data:`~lcreg.models.base.EVALUATION_ARGS` and the
        arguments given on the command line; for a Lightning checkpoint (``--weights run.ckpt``) also all but the
        class's ``inference_hparams`` (the export's settings: the run's decoder is built and loaded, as with
        ``--ckpt_path``). A file of another class changes nothing here (:func:`lcreg.weights.load_into` refuses it
        once the model is built).

        Raises:
            lcreg.weights.PretrainedError: The file is damaged, or the class refuses its arguments
                (:class:`~lcreg.weights.PretrainedBuildError`).
        """
        from lcreg.weights import CHECKPOINT_SUFFIX, PretrainedBuildError, read_weights, settings_of

        weights = read_weights(source)  # a .ckpt: as the export would write it (its constructor arguments)
        if weights.path.suffix != CHECKPOINT_SUFFIX:
            self._pretrained = weights  # read once; a .ckpt is read again by load_into, training-only tensors too
        if weights.class_path != class_path:
            return
        configured = self.config[subcommand]["model"].get("init_args") or {}
        changed = settings_of(weights, configured, self._explicit_model_args)
        if not changed:
            return
        model = {"class_path": class_path, "init_args": changed}
        parser = self.parser
        if not isinstance(parser, LcregArgumentParser):  # pragma: no cover - build_cli always passes parser_class
            raise TypeError(f"lcreg's CLI needs an LcregArgumentParser, got {type(parser).__name__}")
        raising, parser.raise_errors = parser.raise_errors, True  # raise ConfigValueError instead of exiting
        try:
            self.config = parser.parse_object({subcommand: {"model": model}}, self.config)
        except ConfigValueError as err:  # an argument the class no longer has (another lcreg version), a bad value
            message = f"{class_path} refuses the file's init_args {sorted(changed)}: {one_line(str(err))}"
            raise PretrainedBuildError(weights.source, message, weights.path) from err
        finally:
            parser.raise_errors = raising
        values = ", ".join(f"{k}={v!r}" for k, v in changed.items())
        rank_zero_info(f"lcreg: --weights {source} sets the model's {values} (the file's; --model.init_args.NAME wins)")

    def _prepare_subcommand_kwargs(self, subcommand: str) -> dict[str, Any]:
        """Lightning loads ``--ckpt_path`` weights-only (its default is a full unpickle for local files)."""
        kwargs = super()._prepare_subcommand_kwargs(subcommand)
        if "weights_only" in self._subcommand_method_arguments[subcommand]:
            kwargs["weights_only"] = True
        return kwargs

    def add_arguments_to_parser(self, parser: LightningArgumentParser) -> None:
        """Accept ``--weights`` and ``compose`` (expanded by :func:`expand_configs`); read batch limits' ints as ints.

        ``--trainer.limit_*_batches 1`` is one batch, ``1.0`` every batch (:func:`_int_before_float`).
        """
        _int_before_float(parser, BATCH_LIMITS)
        parser.add_argument(
            "--compose",
            type=list[str] | None,
            default=None,
            help="config files this config builds on (read first, relative to it); expanded before parsing",
        )
        parser.add_argument(
            "--weights",
            type=str | None,
            default=None,
            help="pretrained weights loaded into the built model: a name of lcreg.pretrained_names() or the path of a "
            ".pt file of `python -m lcreg.weights.export`; strict for the inference modules, training-only modules "
            "(decoder, normal head, loss terms) keep their initialisation; `fit` fine-tunes from them; a --ckpt_path "
            "replaces them",
        )
        parser.add_argument(
            "--validate_first",
            type=bool,
            default=False,
            help="fit: validate the starting weights before training (a step-0 row in metrics.csv) and keep them as a "
            "checkpoint that training must beat to be selected (and the early-stopping baseline); not repeated when "
            "resuming with --ckpt_path; ignored by the other subcommands",
        )

    def instantiate_classes(self) -> None:
        """Build model, data and trainer; refuse ``fit`` without a loss; check the checkpoint's keys; load weights.

        Raises:
            ConfigValueError: A constructor refused its arguments (one line: the class and its reasons).
        """
        try:
            super().instantiate_classes()
        except (ValueError, TypeError) as err:  # a constructor's own check, wrapped by jsonargparse in many lines
            raise ConfigValueError(_constructor_error(err)) from err
        if self.subcommand == "fit" and not getattr(self.model, "has_loss", True):
            _refuse_nothing_to_train(type(self.model).__name__)
        if self._checkpoint_keys is not None and getattr(self.model, "strict_loading", True):
            check_keys(self._get(self.config, "ckpt_path"), self._checkpoint_keys, self.model)
        self._load_pretrained_weights()

    def _load_pretrained_weights(self) -> None:
        """Load ``--weights`` into the model (:func:`lcreg.weights.load_into`), unless ``--ckpt_path`` replaces them.

        Raises:
            lcreg.weights.PretrainedError: One line naming the weights: unknown name, missing or damaged file,
                another model class, tensors that do not fit.
        """
        source = self._get(self.config, "weights")
        if not source:
            return
        checkpoint = self._get(self.config, "ckpt_path")
        if checkpoint:
            rank_zero_info(f"lcreg: --weights {source} not loaded, --ckpt_path {checkpoint} sets the model's weights")
            return
        from lcreg.weights import load_into

        weights = load_into(self.model, self._pretrained or source)
        rank_zero_info(f"lcreg: loaded pretrained weights {source!r} ({weights.path}) into {type(self.model).__name__}")

    def _instantiate_trainer(self, config: dict[str, Any], callbacks: list[Any]) -> Any:
        from lightning.pytorch.callbacks import ModelCheckpoint, TQDMProgressBar

        from lcreg.callbacks import LatestCheckpoint, RngState, TimedProgressBar, TrainingClock

        listed = config.get("callbacks") or []
        # A listed LatestCheckpoint goes after every ModelCheckpoint (below), so last.ckpt records their update.
        latest = [c for c in listed if isinstance(c, LatestCheckpoint)]
        listed = config["callbacks"] = [c for c in listed if not isinstance(c, LatestCheckpoint)]
        checkpointing = config.get("enable_checkpointing") is not False
        if checkpointing and not any(isinstance(c, ModelCheckpoint) for c in listed):
            callbacks.append(
                ModelCheckpoint(
                    monitor="val/rre_mean_deg",
                    mode="min",
                    filename="epoch{epoch:03d}-rre{val/rre_mean_deg:.3f}",
                    auto_insert_metric_name=False,
                    # Saved when each validation ends, also one at an epoch's end: last.ckpt can then be written
                    # after it at the epoch's last batch, which a max_steps run resumes exactly (LatestCheckpoint).
                    save_on_train_epoch_end=False,
                )
            )
        callbacks.extend(latest or ([LatestCheckpoint()] if checkpointing else []))
        for checkpoint in (c for c in listed if isinstance(c, ModelCheckpoint) and c.save_last):
            rank_zero_info("lcreg: a listed ModelCheckpoint's save_last is off: LatestCheckpoint writes last.ckpt")
            checkpoint.save_last = False
        callbacks.extend([RngState(), TrainingClock()])
        if self.subcommand == "predict":
            from lcreg.callbacks import TransformWriter

            callbacks.append(TransformWriter())
        if config.get("enable_progress_bar") is not False and not any(isinstance(c, TQDMProgressBar) for c in listed):
            callbacks.append(TimedProgressBar())
        return super()._instantiate_trainer(config, callbacks)


def _int_before_float(parser: LightningArgumentParser, keys: Sequence[str]) -> None:
    """Parse the options ``keys`` as ``int | float | None``, trying int first.

    The Trainer annotates ``limit_*_batches`` as ``Optional[Union[int, float]]``, which ``typing`` may hand back as
    ``Union[float, int, None]`` (its cache treats unions in any order as equal); jsonargparse then reads ``1`` as
    ``1.0``, which Lightning takes as "every batch". A PEP 604 union keeps its order.
    """
    for action in parser._actions:
        if action.dest in keys and hasattr(action, "_typehint"):
            action._typehint = int | float | None  # jsonargparse's ActionTypeHint: the type it parses with


def explicit_model_args(args: ArgsType | ConfigLayers) -> frozenset[str]:
    """Names of the model arguments set on the command line or as :class:`ConfigLayers` values (not in files).

    ``--model.init_args.NAME[=V]`` and ``--model.NAME[=V]`` give ``NAME`` (``--model.init_args.optimizer.init_args.lr``
    gives ``optimizer``); ``ConfigLayers`` values ``model.init_args.NAME...`` the same.
    """
    if isinstance(args, ConfigLayers):
        keys: Sequence[Any] = [f"--{key}" for key in args.values]
    elif isinstance(args, (list, tuple)):
        keys = args
    else:
        return frozenset()
    names = set()
    for arg in keys:
        match = re.fullmatch(r"--model\.(?:init_args\.)?([A-Za-z_]\w*)(?:[.=].*)?", str(arg), flags=re.DOTALL)
        if match and match.group(1) not in ("class_path", "init_args", "dict_kwargs"):
            names.add(match.group(1))
    return frozenset(names)


def _logger_under_root_dir(config: Any) -> None:
    """``--trainer.default_root_dir D`` moves the default logger too: its ``save_dir`` ``runs`` becomes ``D``.

    A logger ``save_dir`` set to anything other than the default stays as set.
    """
    trainer = config.get("trainer")
    root = trainer.get("default_root_dir") if trainer is not None else None
    logger = trainer.get("logger") if root else None
    default = TRAINER_DEFAULTS["logger"]
    if logger is None or isinstance(logger, bool) or logger.get("class_path") != default["class_path"]:
        return
    if logger.get("init_args") is not None and logger.init_args.get("save_dir") == default["init_args"]["save_dir"]:
        logger.init_args.save_dir = str(root)


def _refuse_nothing_to_train(class_path: str) -> None:
    """Refuse ``lcreg fit`` for a model class without a training loss (``has_loss = False``).

    Raises:
        NothingToTrainError: Naming the class and what to run instead.
    """
    module, _, name = class_path.rpartition(".")
    try:
        cls = getattr(importlib.import_module(module), name) if module else None
    except (ImportError, AttributeError):  # jsonargparse reports unknown classes itself
        return
    if cls is not None and not getattr(cls, "has_loss", True):
        raise NothingToTrainError(
            f"{name} is a classical method with nothing to train: `lcreg fit` does not apply, evaluate it with "
            "`lcreg test` (or `lcreg validate`)"
        )


def _wandb_offline_if_no_account(argv: list[str]) -> None:
    """Default ``WANDB_MODE=offline`` when a WandbLogger is requested without credentials."""
    wants_wandb = any("WandbLogger" in a or "wandb" in os.path.basename(a) for a in argv)
    if wants_wandb and "WANDB_MODE" not in os.environ and "WANDB_API_KEY" not in os.environ:
        os.environ["WANDB_MODE"] = "offline"
        print("lcreg: no WANDB_API_KEY found, logging to wandb in offline mode (sync later with `wandb sync`)")


def build_cli(args: ArgsType | ConfigLayers = None, run: bool = True) -> LcregCLI:
    """The ``lcreg`` CLI; ``run=False`` only instantiates model, data and trainer (scripts and tests use it).

    Args:
        args: Command-line arguments (``None`` reads ``sys.argv``); with ``run=False`` no subcommand is given.
        run: Run the subcommand.
    """
    if args is None:
        args = sys.argv[1:]
    if isinstance(args, (list, tuple)):
        args = expand_configs([str(a) for a in args])
    return LcregCLI(
        RegistrationModule,
        LightningDataModule,
        subclass_mode_model=True,
        subclass_mode_data=True,
        auto_configure_optimizers=False,
        parser_class=LcregArgumentParser,
        save_config_kwargs={"overwrite": True},
        parser_kwargs={
            "description": "lcreg: train, test and compare registration networks (fit, validate, test, predict). "
            "To register your own clouds: `lcreg register SRC REF` (`lcreg register --help`). To deploy a learned "
            "registrar: `lcreg export NAME --format onnx|torchscript --out FILE`. To rerun the paper's "
            "tables: `lcreg reproduce EXPERIMENT --budget smoke|cpu|converge|paper` (`lcreg reproduce --help`).",
        },
        trainer_defaults=TRAINER_DEFAULTS,
        seed_everything_default=1234,
        args=args,  # type: ignore[arg-type]  # ConfigLayers: parse_arguments above reads them
        run=run,
    )


def instantiate(configs: Sequence[str | Path] = (), values: Mapping[str, Any] | None = None) -> LcregCLI:
    """Model, data and trainer of config files and typed values, as ``lcreg fit`` builds them; nothing runs.

    The experiments and scripts build methods with it: the YAML files are read as ``--config`` would read them, and
    ``values`` are Python objects merged after them (no command-line strings written and parsed again).

    Args:
        configs: Config files, later ones overriding earlier ones (a ``configs/...`` path is found in the package's
            configs, ``compose:`` lists are expanded: :func:`lcreg.config.expand_configs`).
        values: Dotted keys and their values, applied after the files in order, e.g.
            ``{"data.init_args.num_points": 512, "trainer.max_steps": 10, "seed_everything": 0}``.

    Returns:
        The :class:`LcregCLI` with ``model``, ``datamodule`` and ``trainer`` built (seeded by ``seed_everything``).

    Raises:
        ConfigFileError: A config file is missing. ConfigValueError: A malformed or unknown key, a value of the wrong
            type, or a value a constructor refuses (one line naming the key or the class).
    """
    from lcreg.config import find_config

    for file in configs:
        if find_config(file) is None:
            raise ConfigFileError(f"config file {str(file)!r} not found")
    args = expand_configs([arg for file in configs for arg in ("--config", str(file))])
    files = tuple(args[i + 1] for i, arg in enumerate(args) if arg == "--config")
    extra = {"compose": None} if "--compose=null" in args else {}
    return build_cli(ConfigLayers(files, {**extra, **dict(values or {})}), run=False)


def main(args: ArgsType = None) -> None:
    """Entry point of the ``lcreg`` console script (``args=None`` reads ``sys.argv``; tests pass a list).

    From the command line (``args=None``), user errors end the program with one line on stderr (:func:`_exit_on`);
    with ``args`` given, they are raised (typed) to the caller.
    """
    argv = list(args) if isinstance(args, (list, tuple)) else sys.argv[1:]
    if argv[:1] == ["register"]:  # not a Lightning subcommand: no trainer, no config
        from lcreg.registration.command import main as register_main

        register_main([str(a) for a in argv[1:]])
        return
    if argv[:1] == ["export"]:  # not a Lightning subcommand either
        from lcreg.deploy import main as export_main

        export_main([str(a) for a in argv[1:]])
        return
    if argv[:1] == ["reproduce"]:  # the experiments' command: the library does not import them
        raise UsageError(
            "`reproduce` is not a command of lcreg.cli.main: run `lcreg reproduce` (the console script, "
            "lcreg.__main__.main) or lcreg.experiments.reproduce.command.main"
        )
    _wandb_offline_if_no_account(config_texts([str(a) for a in argv]))
    try:
        if args is not None or _debug():
            build_cli(args)
            return
        try:
            build_cli(argv)
        except Exception as err:
            _exit_on(err)
    except SIGTERMException as stop:  # a SystemExit of code None: the process would exit 0, as if training ended
        sys.stderr.write("lcreg: training stopped by SIGTERM; `--ckpt_path last` resumes it from its last.ckpt\n")
        raise SystemExit(TERMINATED_EXIT_CODE) from stop


def _constructor_error(err: Exception) -> str:
    """One line from jsonargparse's report of a refused constructor: the class and the constructor's reasons."""
    text = str(err)
    reasons = [
        line.strip()[2:]
        for line in text.splitlines()
        if line.strip().startswith("- ") and not line.strip().startswith("- Expected a <class 'NoneType'>")
    ]
    found = re.findall(r"class_path='([\w.]+)'", text)
    where = f"{found[0].rpartition('.')[2]}: " if found else ""
    return where + ("; ".join(reasons) if reasons else one_line(text))


def _exit_on(err: Exception) -> NoReturn:
    """Exit with one line for a user error; re-raise anything else (a bug: its traceback is shown).

    Exit codes: 2 for arguments and configs; 1 for dataset folders, files, checkpoints, weights and training stopped
    on non-finite losses.
    """
    if isinstance(err, UsageError):
        code = 2
    elif isinstance(err, FILE_ERRORS):
        code = 1
    else:
        raise err
    sys.stderr.write(f"lcreg: error: {one_line(str(err), 1000)}\n")
    sys.stderr.write(f"hint: {DEBUG_ENV}=1 shows the traceback\n")
    raise SystemExit(code)


if __name__ == "__main__":  # pragma: no cover
    main()
