"""Command line: ``lcreg fit|validate|test|predict --config configs/<x>.yaml`` (LightningCLI).

Models are any :class:`~lcreg.models.base.RegistrationModule` subclass (``model.class_path``), data any
LightningDataModule that yields :class:`~lcreg.types.RegistrationBatch` (``data.class_path``: the object
:class:`~lcreg.data.datamodule.PairDataModule` family or the scene :class:`~lcreg.data.scenes.ScenePairDataModule`
family); both are picked in YAML.
Shared trainer defaults live here, once: seed 1234, CSV logging under ``runs/<name>/version_<k>/``, checkpoints
selected on the validation registration error ``val/rre_mean_deg`` (validation pairs carry a known pose; the
label-free ``val/loss`` of self-supervised models keeps falling while registration degrades) plus ``last.ckpt``, and a
TQDM bar. A config that lists its own ``ModelCheckpoint`` or progress bar replaces the default. Optimisers are model
arguments (``model.init_args.optimizer``), so the top-level ``optimizer:`` key of LightningCLI is not used.

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

A WandbLogger config works without an account: when one is requested, ``WANDB_MODE`` is unset and no
``WANDB_API_KEY`` is present, ``WANDB_MODE=offline`` is set (runs can be synced later with ``wandb sync``).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Any

import yaml
from lightning.pytorch import LightningDataModule
from lightning.pytorch.cli import ArgsType, LightningArgumentParser, LightningCLI
from lightning.pytorch.utilities import rank_zero_info

from lcreg.models.base import RegistrationModule

__all__ = ["LcregCLI", "build_cli", "expand_configs", "main"]

TRAINER_DEFAULTS: dict[str, Any] = {
    "logger": {"class_path": "lightning.pytorch.loggers.CSVLogger", "init_args": {"save_dir": "runs", "name": "lcreg"}},
    "log_every_n_steps": 10,
}


class LcregCLI(LightningCLI):
    """LightningCLI with lcreg's base classes in subclass mode, the shared trainer defaults and ``compose``.

    Unless the trainer config lists its own, adds ``ModelCheckpoint(monitor="val/rre_mean_deg", save_last=True)`` and
    a ``TQDMProgressBar``. ``lcreg predict`` writes ``predictions.npz`` (:class:`lcreg.callbacks.TransformWriter`) to
    the run's log directory.
    """

    def add_arguments_to_parser(self, parser: LightningArgumentParser) -> None:
        """Accept ``--weights`` and the ``compose`` key of configs (already expanded by :func:`expand_configs`)."""
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

    def instantiate_classes(self) -> None:
        """Build model, data and trainer; refuse ``fit`` for models without a loss; load ``--weights``."""
        super().instantiate_classes()
        if self.subcommand == "fit" and not getattr(self.model, "has_loss", True):
            raise RuntimeError(
                f"{type(self.model).__name__} is a classical method with nothing to train: `lcreg fit` does not "
                "apply, evaluate it with `lcreg test` (or `lcreg validate`)"
            )
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

        weights = load_into(self.model, source)
        rank_zero_info(f"lcreg: loaded pretrained weights {source!r} ({weights.path}) into {type(self.model).__name__}")

    def _instantiate_trainer(self, config: dict[str, Any], callbacks: list[Any]) -> Any:
        from lightning.pytorch.callbacks import ModelCheckpoint, TQDMProgressBar

        listed = config.get("callbacks") or []
        if config.get("enable_checkpointing") is not False and not any(isinstance(c, ModelCheckpoint) for c in listed):
            callbacks.append(
                ModelCheckpoint(
                    monitor="val/rre_mean_deg",
                    mode="min",
                    save_last=True,
                    filename="epoch{epoch:03d}-rre{val/rre_mean_deg:.3f}",
                    auto_insert_metric_name=False,
                )
            )
        if self.subcommand == "predict":
            from lcreg.callbacks import TransformWriter

            callbacks.append(TransformWriter())
        if config.get("enable_progress_bar") is not False and not any(isinstance(c, TQDMProgressBar) for c in listed):
            callbacks.append(TQDMProgressBar(refresh_rate=20))
        return super()._instantiate_trainer(config, callbacks)


def _wandb_offline_if_no_account(argv: list[str]) -> None:
    """Default ``WANDB_MODE=offline`` when a WandbLogger is requested without credentials."""
    wants_wandb = any("WandbLogger" in a or "wandb" in os.path.basename(a) for a in argv)
    if wants_wandb and "WANDB_MODE" not in os.environ and "WANDB_API_KEY" not in os.environ:
        os.environ["WANDB_MODE"] = "offline"
        print("lcreg: no WANDB_API_KEY found, logging to wandb in offline mode (sync later with `wandb sync`)")


def _config_mentions_wandb(argv: list[str]) -> list[str]:
    """Arguments plus the text of any ``--config`` files (to detect a WandbLogger)."""
    texts = list(argv)
    for i, arg in enumerate(argv):
        path = None
        if arg.startswith("--config="):
            path = arg.split("=", 1)[1]
        elif arg == "--config" and i + 1 < len(argv):
            path = argv[i + 1]
        if path and os.path.isfile(path):
            with open(path, encoding="utf-8") as fh:
                texts.append(fh.read())
    return texts


def _config_path(arg: str, following: str | None) -> str | None:
    """The file named by ``--config=F`` or ``--config F`` (``None`` for other arguments)."""
    if arg.startswith("--config="):
        return arg.split("=", 1)[1]
    return following if arg == "--config" else None


def _composed(path: Path, seen: tuple[Path, ...] = ()) -> list[Path]:
    """``path``'s ``compose:`` files (recursively, in order), then ``path`` itself.

    Raises:
        FileNotFoundError: If a composed file does not exist (names the file that lists it).
        ValueError: On a ``compose`` cycle or a ``compose`` value that is not a list of paths.
    """
    path = path.resolve()
    if path in seen:
        raise ValueError(f"config compose cycle: {' -> '.join(str(p) for p in (*seen, path))}")
    with path.open(encoding="utf-8") as fh:
        content = yaml.safe_load(fh)
    parts = content.get("compose") if isinstance(content, dict) else None
    if parts is None:
        return [path]
    if not isinstance(parts, list) or not all(isinstance(p, str) for p in parts):
        raise ValueError(f"{path}: `compose` must be a list of config paths, got {parts!r}")
    files: list[Path] = []
    for part in parts:
        child = path.parent / part
        if not child.is_file():
            raise FileNotFoundError(f"{path}: composed config {part!r} not found ({child})")
        files += _composed(child, (*seen, path))
    return [*files, path]


def expand_configs(args: list[str]) -> list[str]:
    """Replace each ``--config F`` whose YAML has ``compose: [...]`` by ``--config`` of every composed file, then F.

    Args:
        args: Command-line arguments.

    Returns:
        The arguments with composed configs spelled out (other arguments unchanged, in order), and
        ``--compose=null`` at the end when any file composed others, so the saved ``config.yaml`` (already complete)
        does not compose them again.
    """
    out: list[str] = []
    composed = False
    i = 0
    while i < len(args):
        path = _config_path(args[i], args[i + 1] if i + 1 < len(args) else None)
        step = 2 if args[i] == "--config" else 1
        if path is None or not Path(path).is_file():
            out += args[i : i + step] if path is not None else [args[i]]
            i += step if path is not None else 1
            continue
        files = _composed(Path(path))
        composed = composed or len(files) > 1
        for file in files:
            out += ["--config", str(file)]
        i += step
    return [*out, "--compose=null"] if composed else out


def build_cli(args: ArgsType = None, run: bool = True) -> LcregCLI:
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
        save_config_kwargs={"overwrite": True},
        trainer_defaults=TRAINER_DEFAULTS,
        seed_everything_default=1234,
        args=args,
        run=run,
    )


def main(args: ArgsType = None) -> None:
    """Entry point of the ``lcreg`` console script (``args=None`` reads ``sys.argv``; tests pass a list)."""
    argv = list(args) if isinstance(args, (list, tuple)) else sys.argv[1:]
    _wandb_offline_if_no_account(_config_mentions_wandb([str(a) for a in argv]))
    build_cli(args)


if __name__ == "__main__":  # pragma: no cover
    main()
