"""Build a registered method from its configs (as ``lcreg test`` does), with weights by the library's one loader."""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Literal, overload

from lcreg.experiments.benchmarking.registry import config_path, method

if TYPE_CHECKING:
    from lightning.pytorch import LightningDataModule

    from lcreg.cli import LcregCLI
    from lcreg.models.base import RegistrationModule

__all__ = ["build", "build_cli_for", "cli_arguments"]


def cli_arguments(name: str, configs: Sequence[str | Path] = (), overrides: Sequence[str] = ()) -> list[str]:
    """The ``lcreg`` arguments (after the subcommand) that build method ``name``.

    Args:
        name: Registry name (:data:`lcreg.experiments.benchmarking.registry.METHODS`).
        configs: Further configs after the method's own (data add-ons, voxelisation), relative to the configs folder
            or absolute.
        overrides: Further command-line arguments, e.g. ``--data.init_args.num_points=512``.

    Returns:
        ``["--config", <path>, ..., *overrides]``.
    """
    spec = method(name)
    args = [arg for file in spec.config_files() for arg in ("--config", str(config_path(file)))]
    args += spec.overrides  # before further configs: a data add-on brings its own batch size
    args += [arg for file in configs for arg in ("--config", str(config_path(file)))]
    return args + list(overrides)


def build_cli_for(name: str, configs: Sequence[str | Path] = (), overrides: Sequence[str] = ()) -> LcregCLI:
    """``lcreg.cli.build_cli(<method's arguments>, run=False)``: model, data and trainer, nothing run.

    LightningCLI's warning about a script's own ``sys.argv`` next to ``args`` is silenced: the arguments are exactly
    ``args``, the script's options are not read.
    """
    from lcreg.cli import build_cli

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="LightningCLI's args parameter is intended")
        return build_cli(cli_arguments(name, configs, overrides), run=False)


@overload
def build(
    name: str,
    checkpoint: str | Path | None = ...,
    configs: Sequence[str | Path] = ...,
    overrides: Sequence[str] = ...,
    *,
    with_data: Literal[False] = ...,
) -> RegistrationModule: ...


@overload
def build(
    name: str,
    checkpoint: str | Path | None = ...,
    configs: Sequence[str | Path] = ...,
    overrides: Sequence[str] = ...,
    *,
    with_data: Literal[True],
) -> tuple[RegistrationModule, LightningDataModule]: ...


def build(
    name: str,
    checkpoint: str | Path | None = None,
    configs: Sequence[str | Path] = (),
    overrides: Sequence[str] = (),
    *,
    with_data: bool = False,
) -> RegistrationModule | tuple[RegistrationModule, LightningDataModule]:
    """Build a registered method exactly as ``lcreg test --config ...`` does, then load checkpoint weights.

    Args:
        name: Registry name; its configs (and refinement config) come first.
        checkpoint: Weights loaded by :func:`lcreg.weights.load_into` (a ``.ckpt`` of ``lcreg fit``, an exported
            ``.pt``, a shipped name; ``None``: the config's initialisation, seeded by its ``seed_everything``).
        configs: Further configs (see :func:`cli_arguments`).
        overrides: Further command-line arguments.
        with_data: Also return the config's DataModule (not set up).

    Returns:
        The model (CPU, mode untouched), or ``(model, datamodule)`` with ``with_data``.

    Raises:
        KeyError: Unknown method. FileNotFoundError: A config is missing.
        lcreg.checkpoints.CheckpointError: Unusable weights (a subclass naming the file).
    """
    from lcreg.models.base import RegistrationModule
    from lcreg.weights import load_into

    cli = build_cli_for(name, configs, overrides)
    model = cli.model
    if not isinstance(model, RegistrationModule):  # pragma: no cover - the CLI only builds RegistrationModules
        raise TypeError(f"{name} built a {type(model).__name__}, not a RegistrationModule")
    if checkpoint is not None:
        load_into(model, checkpoint)
    return (model, cli.datamodule) if with_data else model
