"""Command line: ``lcreg fit|validate|test|predict --config configs/<x>.yaml`` (LightningCLI).

Models are any :class:`~lcreg.models.base.RegistrationModule` subclass (``model.class_path``), data any
LightningDataModule that yields :class:`~lcreg.types.RegistrationBatch` (``data.class_path``: the object
:class:`~lcreg.data.datamodule.PairDataModule` family or the scene :class:`~lcreg.data.scenes.ScenePairDataModule`
family); both are picked in YAML.
Defaults: CSV logging under ``runs/``, checkpoints selected on ``val/loss`` (label-free, as in the DVDs paper; a
config that lists its own ``ModelCheckpoint`` replaces it, as the DVDs configs do) plus ``last.ckpt``, and a TQDM
bar refreshed every 20 steps (readable in CI logs). Optimisers are model arguments (``model.init_args.optimizer``),
so the top-level ``optimizer:`` key of LightningCLI is not used.

Any model can be followed by ICP refinement at validation/test/predict time: a top-level ``refine:`` block
(``class_path: lcreg.baselines.classical.ICP`` with its ``init_args``), or ``--refine lcreg.baselines.classical.ICP
--refine.voxel_size 0.02`` on the command line; it starts from the model's estimate
(:meth:`~lcreg.models.base.RegistrationModule.set_refiner`). ``lcreg fit`` refuses models with nothing to train
(classical methods) before anything runs.

LK models (DVDs, PointNetLK, FMR-Net) can register large clouds with voxelised IC-LK at validation/test/predict
time: a top-level ``voxelize:`` block (``class_path: lcreg.nn.voxel_lk.VoxelGrid``; configs/voxelize/lk27.yaml)
calls :meth:`~lcreg.models.lucas_kanade.LucasKanadeModule.set_voxel_grid`; other models refuse it.

A WandbLogger config works without an account: when one is requested, ``WANDB_MODE`` is unset and no
``WANDB_API_KEY`` is present, ``WANDB_MODE=offline`` is set (runs can be synced later with ``wandb sync``).
"""

from __future__ import annotations

import os
import sys
from typing import Any

from lightning.pytorch import LightningDataModule
from lightning.pytorch.cli import ArgsType, LightningArgumentParser, LightningCLI

from lcreg.models.base import RegistrationModule

__all__ = ["LcregCLI", "build_cli", "main"]

TRAINER_DEFAULTS: dict[str, Any] = {
    "logger": {"class_path": "lightning.pytorch.loggers.CSVLogger", "init_args": {"save_dir": "runs", "name": "lcreg"}},
}


class LcregCLI(LightningCLI):
    """LightningCLI with lcreg's base classes in subclass mode, default callbacks, ``refine`` and ``voxelize``.

    Unless disabled in the trainer config, adds ``ModelCheckpoint(monitor="val/loss", save_last=True)`` and a
    ``TQDMProgressBar(refresh_rate=20)``; callbacks listed in a config are kept as well. ``lcreg predict`` writes
    ``predictions.npz`` (:class:`lcreg.callbacks.TransformWriter`) to the run's log directory.
    """

    def add_arguments_to_parser(self, parser: LightningArgumentParser) -> None:
        """Add ``refine`` (ICP after the model's estimate) and ``voxelize`` (voxelised IC-LK), both test-time."""
        from lcreg.baselines.classical import ICP
        from lcreg.nn.voxel_lk import VoxelGrid

        parser.add_argument(
            "--refine",
            type=ICP | None,
            default=None,
            help="ICP refinement after the model's estimate (lcreg.baselines.classical.ICP), none by default",
        )
        parser.add_argument(
            "--voxelize",
            type=VoxelGrid | None,
            default=None,
            help="voxelised IC-LK for LK models outside training (lcreg.nn.voxel_lk.VoxelGrid), none by default",
        )

    def instantiate_classes(self) -> None:
        """Build model, data and trainer; attach the refiner; refuse ``fit`` for models without a loss."""
        super().instantiate_classes()
        config = self.config_init[self.subcommand] if self.subcommand else self.config_init
        if config.get("refine") is not None:
            self.model.set_refiner(config["refine"])
        if config.get("voxelize") is not None:
            if not hasattr(self.model, "set_voxel_grid"):
                raise ValueError(
                    "`voxelize` applies to IC-LK models (DVDs, PointNetLK, FMR-Net), not to "
                    f"{type(self.model).__name__}"
                )
            self.model.set_voxel_grid(config["voxelize"])
        if self.subcommand == "fit" and not getattr(self.model, "has_loss", True):
            raise RuntimeError(
                f"{type(self.model).__name__} is a classical method with nothing to train: `lcreg fit` does not "
                "apply, evaluate it with `lcreg test` (or `lcreg validate`)"
            )

    def _instantiate_trainer(self, config: dict[str, Any], callbacks: list[Any]) -> Any:
        from lightning.pytorch.callbacks import ModelCheckpoint, TQDMProgressBar

        listed = config.get("callbacks") or []
        if config.get("enable_checkpointing") is not False and not any(isinstance(c, ModelCheckpoint) for c in listed):
            callbacks.append(
                ModelCheckpoint(
                    monitor="val/loss",
                    mode="min",
                    save_last=True,
                    filename="epoch{epoch:03d}-val_loss{val/loss:.4f}",
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


def build_cli(args: ArgsType = None, run: bool = True) -> LcregCLI:
    """The ``lcreg`` CLI; ``run=False`` only instantiates model, data and trainer (scripts and tests use it).

    Args:
        args: Command-line arguments (``None`` reads ``sys.argv``); with ``run=False`` no subcommand is given.
        run: Run the subcommand.
    """
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
