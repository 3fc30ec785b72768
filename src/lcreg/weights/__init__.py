"""Pretrained weights shipped inside the package, loaded by name: ``lcreg.pretrained("dvds-modelnet40")``.

A weights file ``src/lcreg/weights/<name>.pt`` (written by ``python -m lcreg.weights.export``, next to its model card
``<name>.md``) is a ``torch.save`` dict of plain data, read with ``torch.load(weights_only=True)`` (no code runs):

* ``format``: :data:`FORMAT` (1);
* ``name``: the name it was exported under (a :data:`REGISTRY` name for shipped files);
* ``class_path``: the model class, e.g. ``"lcreg.models.dvds.DVDs"``; only
  :class:`~lcreg.models.base.RegistrationModule` subclasses inside ``lcreg`` are ever imported;
* ``init_args``: the constructor's hyper-parameters (plain values; components such as optimisers, loss terms or a
  refiner are never saved, :data:`~lcreg.models.base.COMPONENT_ARGS`);
* ``state_dict``: the tensors inference needs (the model's ``training_only_modules`` are left out);
* ``lcreg_version``: the version that exported it;
* ``metadata``: provenance, plain ``str``/``int``/``float``/``bool`` values (data, steps, command, machine, ...).

Files are at most :data:`MAX_FILE_BYTES`. Loading builds ``class_path(**init_args, **overrides)`` on the CPU and
loads the tensors strictly: every tensor of the file must fit the model (same keys, same shapes) and the model's
tensors the file lacks may only belong to its ``training_only_modules`` (a decoder an override asked for, loss
terms). ``import lcreg.weights`` needs torch only; Lightning is imported when a model is built.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from datetime import datetime, timezone
from importlib import import_module
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from lcreg import __version__
from lcreg.checkpoints import (
    PACKAGE_WEIGHTS,
    CheckpointError,
    CheckpointFormatError,
    CheckpointMismatchError,
    CheckpointNotFoundError,
    CheckpointReadError,
    check_class,
    first_non_finite,
    read_checkpoint,
    read_torch_file,
    state_problems,
)
from lcreg.checkpoints import few_items as _few
from lcreg.methods import pretrained_weights

if TYPE_CHECKING:
    from lcreg.models.base import RegistrationModule

__all__ = [
    "CHECKPOINT_SUFFIX",
    "FORMAT",
    "KEYS",
    "MAX_FILE_BYTES",
    "NAME_PATTERN",
    "REGISTRY",
    "Metadata",
    "PretrainedBuildError",
    "PretrainedClassError",
    "PretrainedError",
    "PretrainedFormatError",
    "PretrainedMismatchError",
    "PretrainedNotFoundError",
    "PretrainedReadError",
    "PretrainedSizeError",
    "PretrainedSpec",
    "PretrainedWeights",
    "UnknownPretrainedError",
    "class_path_of",
    "is_plain_mapping",
    "load_into",
    "model_payload",
    "pretrained",
    "pretrained_names",
    "read_weights",
    "registered_names",
    "resolve",
    "resolve_class",
    "settings_of",
    "shipped_names",
    "slim_payload",
    "training_only",
    "validated",
    "weights_dir",
]

FORMAT = 1
"""Version of the file layout this lcreg writes and reads."""
KEYS = ("format", "name", "class_path", "init_args", "state_dict", "lcreg_version", "metadata")
"""The keys of a weights file, all required, no others."""
MAX_FILE_BYTES = 5_000_000
"""Size limit of one weights file: 5 MB (5,000,000 bytes)."""
NAME_PATTERN = re.compile(r"[a-z0-9][a-z0-9._-]*")
"""Names of weights files: lower case letters, digits, ``.``, ``_`` and ``-`` (the file is ``<name>.pt``)."""
CHECKPOINT_SUFFIX = ".ckpt"
"""Files read as Lightning checkpoints (everything else is read as an exported weights file)."""
_PLAIN_SCALARS = (str, int, float, bool, type(None))
Metadata = dict[str, str | int | float | bool]
"""Provenance entries of a weights file."""


@dataclass(frozen=True)
class PretrainedSpec:
    """One shippable set of weights.

    Attributes:
        class_path: The model class the file must hold.
        description: One line for listings and error messages.
    """

    class_path: str
    description: str


REGISTRY: dict[str, PretrainedSpec] = {
    name: PretrainedSpec(info.class_path, text) for name, (info, text) in pretrained_weights().items()
}
"""Every name :func:`pretrained` accepts (from :data:`lcreg.methods.METHODS`); a name's file ships as ``<name>.pt`` in
:func:`weights_dir` (or not yet)."""


# --- errors --------------------------------------------------------------------------------------------------------
class PretrainedError(CheckpointError):
    """Pretrained weights could not be used; ``source`` is the name or path asked for, ``path`` the file (if any).

    Part of the one family of weights and checkpoint errors (:class:`lcreg.checkpoints.CheckpointError` is its
    root). The message is one line, starting with ``pretrained weights '<source>'``.
    """

    def __init__(self, source: str | Path, message: str, path: Path | None = None) -> None:
        where = f" ({path})" if path is not None and str(path) != str(source) else ""
        Exception.__init__(self, f"pretrained weights {str(source)!r}{where}: {message}")
        self.source = str(source)
        self.path = path
        self.reason = message

    def __str__(self) -> str:  # KeyError (a base of UnknownPretrainedError) would quote the message
        return str(self.args[0])


class UnknownPretrainedError(PretrainedError, KeyError):
    """The name is neither a registered name nor a path to a ``.pt`` file (the message lists the known names)."""


class PretrainedNotFoundError(PretrainedError, CheckpointNotFoundError):
    """The file does not exist (a registered name whose file is not shipped, or a missing path)."""


class PretrainedReadError(PretrainedError, CheckpointReadError):
    """The file is empty, damaged or not a weights-only ``torch.save`` file."""


class PretrainedFormatError(PretrainedError, CheckpointFormatError):
    """The file loads but is not a format-1 lcreg weights file (wrong keys, types, format or name)."""


class PretrainedClassError(PretrainedError, TypeError):
    """``class_path`` is not an lcreg ``RegistrationModule`` subclass, or not the class the name or model expects."""


class PretrainedBuildError(PretrainedError, TypeError):
    """The class refuses ``init_args`` plus the overrides (an unknown or invalid argument)."""


class PretrainedMismatchError(PretrainedError, CheckpointMismatchError):
    """The tensors do not fit the model: unexpected or missing keys, or other shapes (another architecture)."""


class PretrainedSizeError(PretrainedError, ValueError):
    """An exported file would exceed :data:`MAX_FILE_BYTES`."""


# --- the file ------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class PretrainedWeights:
    """The validated content of a weights file.

    Attributes:
        source: The name or path asked for.
        path: The file read.
        name: The name stored in the file.
        class_path: The model class.
        init_args: Constructor hyper-parameters (plain values).
        state_dict: Tensors on the CPU.
        lcreg_version: Version that exported the file.
        metadata: Provenance (plain values).
    """

    source: str
    path: Path
    name: str
    class_path: str
    init_args: dict[str, Any]
    state_dict: dict[str, torch.Tensor]
    lcreg_version: str
    metadata: dict[str, str | int | float | bool]


def weights_dir() -> Path:
    """The package folder holding the shipped ``<name>.pt`` files and their ``<name>.md`` model cards."""
    return PACKAGE_WEIGHTS


def registered_names() -> list[str]:
    """Every registered name (:data:`REGISTRY`), shipped or not yet; :func:`pretrained_names` lists the loadable."""
    return sorted(REGISTRY)


def shipped_names() -> list[str]:
    """The registered names whose ``<name>.pt`` file is in this installation (what :func:`pretrained` loads)."""
    return [name for name in registered_names() if (weights_dir() / f"{name}.pt").is_file()]


def pretrained_names() -> list[str]:
    """The names :func:`pretrained` loads here: :func:`shipped_names` (a registered name not shipped is left out)."""
    return shipped_names()


def resolve(name_or_path: str | Path) -> Path:
    """The file of a registered name, or ``name_or_path`` itself when it names a file (``.pt``, ``.ckpt``, a path).

    Raises:
        UnknownPretrainedError: Neither a registered name nor a path (lists the known and shipped names).
        PretrainedNotFoundError: A registered name whose file is not shipped, or a path that does not exist.
    """
    text = str(name_or_path)
    if isinstance(name_or_path, str) and text in REGISTRY:
        path = weights_dir() / f"{text}.pt"
        if not path.is_file():
            present = ", ".join(shipped_names()) or "none yet"
            raise PretrainedNotFoundError(text, f"registered but not shipped in this installation; shipped: {present}")
        return path
    if isinstance(name_or_path, Path) or text.endswith((".pt", CHECKPOINT_SUFFIX)) or "/" in text or "\\" in text:
        path = Path(name_or_path)
        if not path.is_file():
            raise PretrainedNotFoundError(text, "no such file")
        return path
    shipped = shipped_names()
    known = ", ".join(f"{n} ({'shipped' if n in shipped else 'not shipped'})" for n in registered_names())
    raise UnknownPretrainedError(text, f"unknown name; known: {known}; or pass the path of an exported .pt file")


def read_weights(name_or_path: str | Path) -> PretrainedWeights:
    """Read and validate a weights file (registered name or path), tensors on the CPU.

    A Lightning checkpoint (``.ckpt`` of ``lcreg fit``) is read as the file :mod:`lcreg.weights.export` would write
    from it (its inference tensors and constructor arguments), so every reader takes all three sources.

    Raises:
        UnknownPretrainedError, PretrainedNotFoundError: See :func:`resolve`.
        PretrainedReadError: The file is empty, damaged or not weights-only loadable.
        PretrainedFormatError: Not a format-1 weights file, or a registered name's file holds another name.
        PretrainedClassError: A registered name's file holds another class than :data:`REGISTRY` says.
    """
    source = str(name_or_path)
    path = resolve(name_or_path)
    if path.suffix == CHECKPOINT_SUFFIX:
        return validated(slim_payload(path, "checkpoint"), source, path)
    try:
        content = read_torch_file(path)
    except CheckpointError as err:  # same reasons, named after the weights
        error = PretrainedNotFoundError if isinstance(err, CheckpointNotFoundError) else PretrainedReadError
        raise error(source, err.reason, path) from err
    weights = validated(content, source, path)
    spec = REGISTRY.get(source) if isinstance(name_or_path, str) else None
    if spec is not None and weights.name != source:
        raise PretrainedFormatError(source, f"the file holds weights named {weights.name!r}", path)
    if spec is not None and weights.class_path != spec.class_path:
        raise PretrainedClassError(source, f"holds {weights.class_path}, the registry expects {spec.class_path}", path)
    return weights


def validated(content: Any, source: str, path: Path) -> PretrainedWeights:
    """``content`` (a loaded file) as :class:`PretrainedWeights` after checking keys, format and types.

    Raises:
        PretrainedFormatError: Not a dict with exactly :data:`KEYS`, another format, values of other types, or a
            tensor holding NaN/Inf.
    """

    def fail(message: str) -> PretrainedFormatError:
        return PretrainedFormatError(source, message, path)

    if not isinstance(content, dict):
        raise fail(f"not an lcreg weights file (holds a {type(content).__name__}, not a dict)")
    missing, extra = [k for k in KEYS if k not in content], sorted(str(k) for k in content if k not in KEYS)
    if missing or extra:
        raise fail(
            f"not an lcreg weights file (missing keys {missing}, unexpected keys {extra}; expected {list(KEYS)})"
        )
    if content["format"] != FORMAT:
        raise fail(f"format {content['format']!r} is not supported (this lcreg reads format {FORMAT})")
    for key in ("name", "class_path", "lcreg_version"):
        if not isinstance(content[key], str):
            raise fail(f"{key!r} must be a string, got {type(content[key]).__name__}")
    if not is_plain_mapping(content["init_args"]):
        raise fail("'init_args' must be a dict of plain values (str keys; str/int/float/bool/None, lists, dicts)")
    metadata = content["metadata"]
    if not isinstance(metadata, dict) or not all(
        isinstance(k, str) and isinstance(v, (str, int, float, bool)) for k, v in metadata.items()
    ):
        raise fail("'metadata' must be a dict of str keys and str/int/float/bool values")
    state = content["state_dict"]
    if not isinstance(state, dict) or not all(isinstance(k, str) and torch.is_tensor(v) for k, v in state.items()):
        raise fail("'state_dict' must be a dict of str keys and tensors")
    bad = first_non_finite(state)
    if bad is not None:
        raise fail(f"tensor `{bad[0]}` holds {bad[1]} NaN/Inf value(s)")
    return PretrainedWeights(
        source, path, content["name"], content["class_path"], dict(content["init_args"]), state,
        content["lcreg_version"], dict(metadata),
    )  # fmt: skip


def _is_plain(value: Any) -> bool:
    """Whether ``value`` is JSON-like plain data (no tensors, no objects)."""
    if isinstance(value, _PLAIN_SCALARS):
        return True
    if isinstance(value, (list, tuple)):
        return all(_is_plain(v) for v in value)
    return is_plain_mapping(value)


def is_plain_mapping(value: Any) -> bool:
    """Whether ``value`` is a dict of ``str`` keys and plain values (what ``init_args`` may hold)."""
    return isinstance(value, dict) and all(isinstance(k, str) and _is_plain(v) for k, v in value.items())


# --- the model -----------------------------------------------------------------------------------------------------
def class_path_of(model: torch.nn.Module) -> str:
    """``"<module>.<class>"`` of ``model``, as stored in ``class_path``."""
    cls = type(model)
    return f"{cls.__module__}.{cls.__qualname__}"


def resolve_class(class_path: str, source: str | Path = "", path: Path | None = None) -> type[RegistrationModule]:
    """Import ``class_path`` and check that it is a :class:`~lcreg.models.base.RegistrationModule` subclass.

    Only modules inside ``lcreg`` are imported (a file cannot make the loader import other code).

    Raises:
        PretrainedClassError: Outside ``lcreg``, not importable, or not a ``RegistrationModule`` subclass.
    """
    from lcreg.models.base import RegistrationModule

    module_name, _, class_name = class_path.rpartition(".")
    if not module_name.startswith("lcreg.") or not class_name.isidentifier():
        raise PretrainedClassError(source or class_path, f"class_path {class_path!r} is not a class of lcreg", path)
    try:
        cls = getattr(import_module(module_name), class_name)
    except (ImportError, AttributeError) as err:
        raise PretrainedClassError(source or class_path, f"class_path {class_path!r} cannot be imported", path) from err
    if not (isinstance(cls, type) and issubclass(cls, RegistrationModule)):
        raise PretrainedClassError(source or class_path, f"{class_path} is not a RegistrationModule subclass", path)
    return cls


def training_only(model: torch.nn.Module, key: str) -> bool:
    """Whether state-dict ``key`` belongs to one of ``model.training_only_modules``."""
    prefixes = getattr(model, "training_only_modules", ("loss_terms",))
    return any(key == prefix or key.startswith(f"{prefix}.") for prefix in prefixes)


def settings_of(weights: PretrainedWeights, configured: Mapping[str, Any], keep: Iterable[str] = ()) -> dict[str, Any]:
    """The file's constructor arguments that a configured model has other values of: what makes it the file's model.

    ``lcreg test --weights`` and :func:`lcreg.experiments.benchmarking.build` set them before the model is built, so
    that weights run with the settings they were exported with (a shipped file's ``jacobian``, ``eval_iterations``),
    not a config's. Left out: :data:`~lcreg.models.base.EVALUATION_ARGS`, ``keep`` and, for a Lightning checkpoint,
    the class's ``inference_hparams`` (the export's settings, not the run's: the run's decoder is built and loaded).

    Args:
        weights: Weights read by :func:`read_weights` (a name, an exported ``.pt`` or a ``.ckpt``).
        configured: The model's constructor arguments as configured (a config's ``init_args``, a model's
            ``hparams``); an argument it lacks counts as differing.
        keep: Names whose configured value stays (the caller set them itself).

    Returns:
        ``{name: the file's value}``; tuples and lists of the same items count as equal.
    """
    from lcreg.models.base import EVALUATION_ARGS

    skip = {*EVALUATION_ARGS, *keep}
    if weights.path.suffix == CHECKPOINT_SUFFIX:
        skip |= set(resolve_class(weights.class_path, weights.source, weights.path).inference_hparams)
    return {
        key: value
        for key, value in weights.init_args.items()
        if key not in skip and (key not in configured or _as_lists(configured[key]) != _as_lists(value))
    }


def _as_lists(value: Any) -> Any:
    """``value`` with every tuple a list (a config's ``[64, 128]`` and a model's ``(64, 128)`` are one setting)."""
    if isinstance(value, (list, tuple)):
        return [_as_lists(item) for item in value]
    if isinstance(value, Mapping):
        return {key: _as_lists(item) for key, item in value.items()}
    return value


def pretrained(name: str | Path, **overrides: Any) -> RegistrationModule:
    """A model with pretrained weights, in eval mode on the CPU.

    Args:
        name: A registered name (:func:`pretrained_names`, e.g. ``"dvds-modelnet40"``) or the path of a ``.pt`` file
            written by ``python -m lcreg.weights.export``.
        **overrides: Constructor arguments replacing the file's ``init_args`` or adding components, e.g.
            ``eval_iterations=30``, ``refiner=ICP()``, ``voxel_grid=VoxelGrid()``. An override that builds a
            training-only module (DVDs ``lambda_recon=0.5``) leaves it initialised, not loaded.

    Returns:
        The model (``register(points_src (B, N, 3), points_ref (B, M, 3))`` estimates ``(B, 4, 4)`` transforms);
        move it with ``.to(device)``.

    Raises:
        PretrainedError: A subclass naming the name and file: :class:`UnknownPretrainedError`,
            :class:`PretrainedNotFoundError`, :class:`PretrainedReadError`, :class:`PretrainedFormatError`,
            :class:`PretrainedClassError`, :class:`PretrainedBuildError`, :class:`PretrainedMismatchError`.
    """
    weights = read_weights(name)
    cls = resolve_class(weights.class_path, weights.source, weights.path)
    try:
        model = cls(**{**weights.init_args, **overrides})
    except (TypeError, ValueError) as err:
        message = f"{weights.class_path} refuses init_args + overrides {sorted(overrides)}: {err}"
        raise PretrainedBuildError(weights.source, message, weights.path) from err
    _load_state(model, weights)
    return model.eval()


def load_into(model: torch.nn.Module, weights: str | Path | PretrainedWeights) -> PretrainedWeights:
    """Load pretrained weights into an already configured model (``lcreg <subcommand> --weights``).

    Args:
        model: A model of exactly the file's class (e.g. built from a config, with its decoder and loss terms).
        weights: A registered name, the path of an exported ``.pt`` file, a Lightning checkpoint (``.ckpt``: all its
            tensors the model has are loaded, training-only ones included), or weights already read.

    Returns:
        The weights loaded (provenance in ``metadata``).

    Raises:
        CheckpointError: A subclass naming the file: as :func:`pretrained`; a class mismatch when ``model`` is of
            another class (:class:`PretrainedClassError`; a checkpoint's: :class:`CheckpointMismatchError`).
    """
    if not isinstance(weights, PretrainedWeights):
        is_checkpoint = str(weights).endswith(CHECKPOINT_SUFFIX)
        weights = _checkpoint_weights(Path(weights), model) if is_checkpoint else read_weights(weights)
    if weights.class_path != class_path_of(model):
        message = f"holds {weights.class_path} weights, the configured model is {class_path_of(model)}"
        raise PretrainedClassError(weights.source, message, weights.path)
    _load_state(model, weights)
    return weights


def _checkpoint_weights(path: Path, model: torch.nn.Module) -> PretrainedWeights:
    """A Lightning checkpoint's tensors for ``model``: all it has, less training-only ones ``model`` was built without.

    Raises:
        CheckpointError: Missing, unreadable, no ``state_dict``, or of another class than ``model``.
    """
    content = read_checkpoint(path)
    check_class(path, content, class_path_of(model))
    own = model.state_dict()
    state = {k: v for k, v in content["state_dict"].items() if k in own or not training_only(model, k)}
    return PretrainedWeights(str(path), path, path.stem, class_path_of(model), {}, state, "", {})


def _load_state(model: torch.nn.Module, weights: PretrainedWeights) -> None:
    """Strict loading of the inference modules; ``model``'s training-only tensors absent from the file are kept.

    Raises:
        PretrainedMismatchError: A file tensor the model lacks or of another shape, or a missing inference tensor.
    """
    own = model.state_dict()
    missing = [k for k in own if k not in weights.state_dict]
    problems = state_problems(own, weights.state_dict, [k for k in missing if not training_only(model, k)])
    if problems:
        problems += _differing_args(model, weights.init_args)
        message = f"does not fit {class_path_of(model)} (another architecture?): {'; '.join(problems)}"
        raise PretrainedMismatchError(weights.source, message, weights.path)
    model.load_state_dict(weights.state_dict, strict=not missing)


def _differing_args(model: torch.nn.Module, init_args: Mapping[str, Any]) -> list[str]:
    """A hint for a mismatch: the file's constructor arguments that ``model`` was built with other values of.

    The model's ``inference_hparams`` are left out (the export sets those itself).
    """
    hparams = getattr(model, "hparams", {})
    skip = set(getattr(type(model), "inference_hparams", {}))
    differ = [
        f"{k}={v!r} (model: {hparams[k]!r})"
        for k, v in init_args.items()
        if k in hparams and k not in skip and hparams[k] != v
    ]
    if not differ:
        return []
    return [f"the file was built with {_few(differ)}: configure these (e.g. --model.init_args.<name>)"]


# --- the file's content from a checkpoint or a model in memory ----------------------------------------------------
def slim_payload(
    checkpoint: str | Path,
    name: str,
    metadata: Mapping[str, str | int | float | bool] | None = None,
    class_path: str | None = None,
    init_args: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """The content of the weights file for a Lightning checkpoint or an exported weights file (nothing written).

    Args:
        checkpoint: A checkpoint of ``lcreg fit`` (``.ckpt``: any Lightning checkpoint with ``hyper_parameters``), or
            an exported weights file (any other suffix), re-exported: its class, tensors and metadata are kept.
        name: The name stored in the file (:data:`~lcreg.weights.NAME_PATTERN`).
        metadata: Entries added to (or replacing) the default metadata (a re-export: the source file's metadata,
            ``source_weights``, the export time).
        class_path: The model class when the checkpoint does not name it (``hyper_parameters["_class_path"]``); a
            weights file's class must be this one when given.
        init_args: Constructor arguments replacing the source's, e.g. ``{"eval_iterations": 20}``: inference
            settings chosen after training (an architecture argument no longer fits the tensors and is refused).

    Returns:
        The dict :func:`torch.save` writes: ``format``, ``name``, ``class_path``, ``init_args``, ``state_dict``
        (inference tensors only, CPU, contiguous copies), ``lcreg_version``, ``metadata``.

    Raises:
        ValueError: A name outside :data:`~lcreg.weights.NAME_PATTERN`.
        CheckpointError: The checkpoint is missing, unreadable, has no hyper-parameters or class, or its tensors do
            not fit the class (:class:`~lcreg.checkpoints.CheckpointMismatchError`).
        PretrainedError: The class is not an lcreg ``RegistrationModule`` or refuses the hyper-parameters.
    """
    _check_name(name)
    if Path(checkpoint).suffix != CHECKPOINT_SUFFIX:
        return _reexport_payload(Path(checkpoint), name, metadata, class_path, init_args)
    content = read_checkpoint(checkpoint)
    hparams = content.get("hyper_parameters")
    if not isinstance(hparams, dict):
        raise CheckpointFormatError(checkpoint, "no 'hyper_parameters' (the model's constructor arguments)")
    class_path = class_path or hparams.get("_class_path")
    if not isinstance(class_path, str):
        raise CheckpointFormatError(checkpoint, "no model class in hyper_parameters['_class_path']; pass --class-path")
    meta = {**_default_metadata(checkpoint, content), **(metadata or {})}
    hparams = {**hparams, **(init_args or {})}
    return _payload(class_path, hparams, content["state_dict"], name, meta, Path(checkpoint))


def _reexport_payload(
    path: Path,
    name: str,
    metadata: Mapping[str, str | int | float | bool] | None,
    class_path: str | None,
    init_args: Mapping[str, Any] | None,
) -> dict[str, Any]:
    """:func:`slim_payload` of an exported weights file: its tensors and class, ``init_args`` replaced.

    Raises:
        PretrainedError: The file cannot be read (see :func:`read_weights`), or holds another class than
            ``class_path``.
    """
    weights = read_weights(path)
    if class_path is not None and class_path != weights.class_path:
        raise PretrainedClassError(str(path), f"holds {weights.class_path}, not {class_path}", path)
    meta = {**weights.metadata, "source_weights": path.name, **_time_metadata(), **(metadata or {})}
    hparams = {**weights.init_args, **(init_args or {})}
    return _payload(weights.class_path, hparams, weights.state_dict, name, meta, path)


def model_payload(
    model: torch.nn.Module, name: str, metadata: Mapping[str, str | int | float | bool] | None = None
) -> dict[str, Any]:
    """The content of the weights file for a model in memory (its ``hparams`` and inference tensors; nothing written).

    Raises:
        ValueError: A name outside :data:`~lcreg.weights.NAME_PATTERN`.
        PretrainedError: The model is not an lcreg ``RegistrationModule``, or its tensors or hyper-parameters do not
            rebuild it.
    """
    _check_name(name)
    hparams = dict(getattr(model, "hparams", {}))
    meta = {**_time_metadata(), **(metadata or {})}
    return _payload(class_path_of(model), hparams, model.state_dict(), name, meta, Path(f"{name}.pt"))


def _check_name(name: str) -> None:
    if not NAME_PATTERN.fullmatch(name):
        raise ValueError(f"weights name {name!r} must match {NAME_PATTERN.pattern} (it becomes <name>.pt)")


def _payload(
    class_path: str,
    hparams: Mapping[str, Any],
    state: Mapping[str, torch.Tensor],
    name: str,
    metadata: Metadata,
    source: Path,
) -> dict[str, Any]:
    """Build the inference model of ``class_path`` from ``hparams``, take its tensors from ``state``, check it loads.

    Raises:
        CheckpointFormatError: Hyper-parameters that are not plain data.
        CheckpointMismatchError: ``state`` does not fit the class (see :func:`_inference_state`).
        PretrainedError: Not an lcreg ``RegistrationModule`` class, or it refuses the hyper-parameters.
    """
    cls = resolve_class(class_path, name)
    init_args = {k: v for k, v in hparams.items() if not k.startswith("_")}
    if not is_plain_mapping(init_args):
        raise CheckpointFormatError(source, "hyper_parameters hold values other than plain data")
    init_args.update(cls.inference_hparams)
    try:
        model = cls(**init_args)
    except (TypeError, ValueError) as err:
        raise PretrainedBuildError(name, f"{class_path} refuses the hyper-parameters: {err}") from err
    inference = _inference_state(model, state, source)
    payload = {
        "format": FORMAT,
        "name": name,
        "class_path": class_path,
        "init_args": init_args,
        "state_dict": inference,
        "lcreg_version": __version__,
        "metadata": dict(metadata),
    }
    check = PretrainedWeights(name, source, name, class_path, init_args, inference, __version__, {})
    load_into(model, check)  # the file loads back exactly as lcreg.pretrained will load it
    return payload


def _inference_state(
    model: torch.nn.Module, checkpoint_state: Mapping[str, torch.Tensor], checkpoint: str | Path
) -> dict[str, torch.Tensor]:
    """The checkpoint's tensors of ``model``'s inference modules (CPU, contiguous copies: no shared storage).

    Raises:
        CheckpointMismatchError: The checkpoint lacks an inference tensor, or holds tensors that are neither the
            model's nor training-only (another architecture).
    """
    wanted = [k for k in model.state_dict() if not training_only(model, k)]
    missing = [k for k in wanted if k not in checkpoint_state]
    foreign = [k for k in checkpoint_state if k not in wanted and not training_only(model, k)]
    if missing or foreign:
        raise CheckpointMismatchError(
            checkpoint,
            f"does not fit {type(model).__name__}: missing {missing[:5]} ({len(missing)}), "
            f"unexpected {foreign[:5]} ({len(foreign)})",
        )
    return {k: checkpoint_state[k].detach().to("cpu", copy=True).contiguous() for k in wanted}


def _time_metadata() -> Metadata:
    """The export time and torch version."""
    return {
        "exported_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "torch_version": str(torch.__version__),  # a str subclass torch.load(weights_only) refuses
    }


def _default_metadata(checkpoint: str | Path, content: Mapping[str, Any]) -> Metadata:
    """Provenance the checkpoint itself records (no absolute paths)."""
    meta: Metadata = {"source_checkpoint": Path(checkpoint).name, **_time_metadata()}
    for key in ("global_step", "epoch"):
        if isinstance(content.get(key), int):
            meta[key] = content[key]
    if isinstance(content.get("pytorch-lightning_version"), str):
        meta["lightning_version"] = content["pytorch-lightning_version"]
    data = content.get("datamodule_hyper_parameters")
    if isinstance(data, dict):
        meta["data"] = _data_summary(data)
    return meta


def _data_summary(hparams: Mapping[str, Any]) -> str:
    """``"ModelNet40DataModule(root=modelnet40_mini, num_points=1024, ...)"`` (folders by their last part)."""
    cls = str(hparams.get("_class_path", "data")).rpartition(".")[2]
    items = [
        f"{k}={Path(v).name if k == 'root' and isinstance(v, str) else v}"
        for k, v in hparams.items()
        if not k.startswith("_")
    ]
    return f"{cls}({', '.join(items)})"
