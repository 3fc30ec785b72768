"""Build a registered method from its configs (as ``lcreg test`` does), with weights by the library's one loader.

Settings travel as :data:`Values`: Python objects by dotted config key, applied after the config files by
:func:`lcreg.cli.instantiate` (no command-line strings are written and parsed again).
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, overload

import yaml

from lcreg.experiments.benchmarking.registry import Values, config_path, method

if TYPE_CHECKING:
    from lightning.pytorch import LightningDataModule

    from lcreg.cli import LcregCLI
    from lcreg.models.base import RegistrationModule
    from lcreg.weights import PretrainedWeights

__all__ = ["Values", "build", "build_cli_for", "method_layers"]


def method_layers(
    name: str, configs: Sequence[str | Path] = (), values: Mapping[str, Any] | None = None
) -> tuple[list[Path], Values]:
    """The config files and the values that build method ``name``, in the order :func:`lcreg.cli.instantiate` takes.

    The method's own configs, then ``configs``; then the method's values (:attr:`MethodSpec.overrides
    <lcreg.experiments.benchmarking.registry.MethodSpec>`, e.g. the original batch size) except those a file of
    ``configs`` sets (a data add-on brings its own batch size: it wins, as a later config does), then ``values``.

    Args:
        name: Registry name (:data:`lcreg.experiments.benchmarking.registry.METHODS`).
        configs: Further configs after the method's own (data add-ons, voxelisation), relative to the configs folder
            or absolute.
        values: Further values by dotted key (:data:`Values`), applied last.

    Returns:
        ``(files, values)``.

    Raises:
        KeyError: Unknown method. FileNotFoundError: A config is missing.
    """
    spec = method(name)
    further = [config_path(file) for file in configs]
    files = [*(config_path(file) for file in spec.config_files()), *further]
    later = _keys_set_by(further)
    own = {key: value for key, value in spec.overrides.items() if key not in later}
    return files, {**own, **(values or {})}


def build_cli_for(name: str, configs: Sequence[str | Path] = (), values: Mapping[str, Any] | None = None) -> LcregCLI:
    """:func:`lcreg.cli.instantiate` of method ``name`` (:func:`method_layers`): model, data and trainer, nothing run.

    Raises:
        lcreg.config.ConfigValueError: A malformed key or a value a constructor refuses.
    """
    from lcreg.cli import instantiate

    return instantiate(*method_layers(name, configs, values))


@overload
def build(
    name: str,
    checkpoint: str | Path | None = ...,
    configs: Sequence[str | Path] = ...,
    values: Mapping[str, Any] | None = ...,
    *,
    with_data: Literal[False] = ...,
) -> RegistrationModule: ...


@overload
def build(
    name: str,
    checkpoint: str | Path | None = ...,
    configs: Sequence[str | Path] = ...,
    values: Mapping[str, Any] | None = ...,
    *,
    with_data: Literal[True],
) -> tuple[RegistrationModule, LightningDataModule]: ...


def build(
    name: str,
    checkpoint: str | Path | None = None,
    configs: Sequence[str | Path] = (),
    values: Mapping[str, Any] | None = None,
    *,
    with_data: bool = False,
) -> RegistrationModule | tuple[RegistrationModule, LightningDataModule]:
    """Build a registered method exactly as ``lcreg test --config ... --weights ...`` does, then load the weights.

    Args:
        name: Registry name; its configs (and refinement config) come first.
        checkpoint: Weights loaded by :func:`lcreg.weights.load_into` (a ``.ckpt`` of ``lcreg fit``, an exported
            ``.pt``, a shipped name; ``None``: the config's initialisation, seeded by its ``seed_everything``). Their
            own model arguments replace the configs' (:func:`lcreg.weights.settings_of`: ``pointnetlk-modelnet40``
            runs with its analytic Jacobian and 40 iterations, not the config's finite differences and 20), except
            the ``model.init_args`` that ``values`` set.
        configs: Further configs (see :func:`method_layers`).
        values: Further values by dotted key, e.g. ``{"data.init_args.num_points": 512, "seed_everything": 3}``.
        with_data: Also return the config's DataModule (not set up).

    Returns:
        The model (CPU, mode untouched), or ``(model, datamodule)`` with ``with_data``.

    Raises:
        KeyError: Unknown method. FileNotFoundError: A config is missing.
        lcreg.config.ConfigValueError: A malformed key or a value a constructor refuses.
        lcreg.checkpoints.CheckpointError: Unusable weights (a subclass naming the file).
    """
    from lcreg.weights import CHECKPOINT_SUFFIX, load_into, read_weights

    cli = build_cli_for(name, configs, values)
    model = _registration_module(cli, name)
    if checkpoint is not None:
        weights = read_weights(checkpoint)  # a .ckpt: as exported; load_into reads its training-only tensors too
        settings = _settings_of_weights(model, weights, values or {})
        if settings:  # built again with them, as `lcreg test --weights` configures the model before building it
            cli = build_cli_for(name, configs, {**(values or {}), **settings})
            model = _registration_module(cli, name)
        load_into(model, checkpoint if weights.path.suffix == CHECKPOINT_SUFFIX else weights)
    return (model, cli.datamodule) if with_data else model


def _registration_module(cli: LcregCLI, name: str) -> RegistrationModule:
    from lcreg.models.base import RegistrationModule

    if not isinstance(cli.model, RegistrationModule):  # pragma: no cover - the CLI only builds RegistrationModules
        raise TypeError(f"{name} built a {type(cli.model).__name__}, not a RegistrationModule")
    return cli.model


def _settings_of_weights(model: RegistrationModule, weights: PretrainedWeights, values: Mapping[str, Any]) -> Values:
    """The weights' own model arguments (:func:`lcreg.weights.settings_of`) as values, but those ``values`` set.

    A file of another class gives none (:func:`lcreg.weights.load_into` then refuses it, naming the file).
    """
    from lightning.pytorch.utilities import rank_zero_info

    from lcreg.weights import class_path_of, settings_of

    if weights.class_path != class_path_of(model):
        return {}
    prefix = "model.init_args."
    given = {key.removeprefix(prefix) for key in values if key.startswith(prefix)}
    model_value = values.get("model")
    if isinstance(model_value, Mapping):
        given |= set(model_value.get("init_args") or {})
    settings = settings_of(weights, dict(model.hparams), given)
    if settings:
        told = ", ".join(f"{key}={value!r}" for key, value in settings.items())
        rank_zero_info(f"lcreg: the weights {weights.source} set the model's {told} (the file's; values given win)")
    return {f"{prefix}{key}": value for key, value in settings.items()}


def _keys_set_by(files: Sequence[Path]) -> set[str]:
    """Every dotted key the files set (their ``compose:`` files included), e.g. ``data.init_args.batch_size``."""
    from lcreg.config import composed

    keys: set[str] = set()
    for file in files:
        for part in composed(file):
            content = yaml.safe_load(part.read_text(encoding="utf-8"))
            keys.update(_dotted(content) if isinstance(content, dict) else ())
    return keys


def _dotted(tree: Mapping[str, Any], prefix: str = "") -> Iterator[str]:
    """The dotted keys of a nested mapping, inner keys included (``a``, ``a.b``, ``a.b.c`` of ``{a: {b: {c: 1}}}``)."""
    for key, value in tree.items():
        dotted = f"{prefix}{key}"
        yield dotted
        if isinstance(value, dict):
            yield from _dotted(value, f"{dotted}.")
