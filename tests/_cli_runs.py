"""Shared pieces of the tests that drive the ``lcreg`` CLI: config paths, compositions, YAML loading, a tiny budget.

Tests that call the CLI also request the ``isolated_cli`` fixture (``tests/conftest.py``).
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
import yaml
from lightning.pytorch import Trainer
from lightning.pytorch.callbacks import Callback

from lcreg.cli import main

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
TINY_RUN = [
    "--trainer.fast_dev_run=true",
    "--trainer.enable_progress_bar=false",
    "--trainer.enable_model_summary=false",
    "--data.init_args.num_points=96",
    "--data.init_args.batch_size=2",
]
# A tiny DVDs on the embedded shapes: one epoch of two batches (tests of fit/test end to end).
TINY_DVDS = [
    "--model.init_args.encoder_channels=[16,32]",
    "--model.init_args.decoder_grid_size=8",
    "--model.init_args.decoder_hidden=[32]",
    "--model.init_args.normal_hidden=[16]",
    "--data.init_args.num_points=128",
    "--data.init_args.points_per_shape=256",
    "--data.init_args.num_train=4",
    "--data.init_args.num_val=2",
    "--data.init_args.num_test=2",
    "--data.init_args.batch_size=2",
    "--trainer.max_epochs=1",
    "--trainer.limit_train_batches=2",
    "--trainer.enable_progress_bar=false",
    "--trainer.enable_model_summary=false",
]
SYNTHETIC = ["--data.init_args.num_train=2", "--data.init_args.num_val=2", "--data.init_args.num_test=2"]

# The hosts of the LC + X table train under the DCP-family protocol (data/dcp_protocol.yaml after the data file).
DCP_FAMILY = ("dcp", "prnet", "idam", "deepgmr")


def config_args(*names: str) -> list[str]:
    """``--config configs/<name>`` for each name, in order (later files override earlier ones)."""
    return [arg for name in names for arg in ("--config", str(CONFIGS / name))]


def host_composition(host: str, lc: bool = False, data: str = "embedded") -> list[str]:
    """The documented composition of a model: ``models/<host>.yaml`` [+ ``lc.yaml``] + ``data/<data>.yaml``.

    The DCP-family hosts get ``data/dcp_protocol.yaml`` after the data file (what the old ``configs/<host>.yaml`` and
    ``configs/embedded/<host>.yaml`` held).
    """
    names = [f"models/{host}.yaml", *(["lc.yaml"] if lc else []), f"data/{data}.yaml"]
    if host in DCP_FAMILY:
        names.append("data/dcp_protocol.yaml")
    return config_args(*names)


def load_yaml(path: Path) -> dict[str, Any]:
    """A config file as a dict."""
    return yaml.safe_load(path.read_text())


def fit_then_test_embedded(host: str, lc: bool = False) -> None:
    """``lcreg fit`` then ``lcreg test`` on the host's composition with the embedded data and the tiny budget."""
    config = host_composition(host, lc=lc, data="embedded")
    main(["fit", *config, *TINY_RUN, *SYNTHETIC])
    main(["test", *config, *TINY_RUN, *SYNTHETIC])


@contextmanager
def cli_isolation(root: Path) -> Iterator[None]:
    """The ``isolated_cli`` fixture for module-scoped fixtures: no wandb, program name `lcreg`, working dir ``root``."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("WANDB_MODE", "disabled")
        patch.setattr(sys, "argv", ["lcreg"])
        patch.chdir(root)
        yield


class SigtermAt(Callback):
    """Send this process SIGTERM at the end of optimiser step ``step`` (``--trainer.callbacks+=_cli_runs.SigtermAt``);
    Lightning's handler then stops ``fit`` at that step's end, as on a signal from outside."""

    def __init__(self, step: int) -> None:
        self.step = step

    def on_train_batch_end(self, trainer: Trainer, *args: Any) -> None:
        if trainer.global_step == self.step:
            os.kill(os.getpid(), signal.SIGTERM)


class CopyLastCheckpointAt(Callback):
    """Copy ``last.ckpt`` to ``dest`` when optimiser step ``step`` starts: the file a ``kill -9`` then would leave
    (``--trainer.callbacks+=_cli_runs.CopyLastCheckpointAt``)."""

    def __init__(self, step: int, dest: str) -> None:
        self.step, self.dest = step, Path(dest)

    def on_train_batch_start(self, trainer: Trainer, *args: Any) -> None:
        if trainer.global_step == self.step and not self.dest.exists():
            shutil.copy(Path(trainer.log_dir or trainer.default_root_dir) / "checkpoints" / "last.ckpt", self.dest)


class InterruptAt(Callback):
    """Raise ``KeyboardInterrupt`` when optimiser step ``step`` starts, as Ctrl+C would
    (``--trainer.callbacks+=_cli_runs.InterruptAt``): ``last.ckpt`` stays the latest save before that step."""

    def __init__(self, step: int) -> None:
        self.step = step

    def on_train_batch_start(self, trainer: Trainer, *args: Any) -> None:
        if trainer.global_step == self.step:
            raise KeyboardInterrupt


class RecordRates(Callback):
    """Write to ``dest`` (JSON) the rate each training step used, the steps after which ``fit`` validated and the
    steps its first scheduler took (``--trainer.callbacks+=_cli_runs.RecordRates``)."""

    def __init__(self, dest: str) -> None:
        self.dest = Path(dest)
        self.rates: list[float] = []
        self.validations: list[int] = []

    def on_train_batch_start(self, trainer: Trainer, *args: Any) -> None:
        self.rates.append(float(trainer.optimizers[0].param_groups[0]["lr"]))

    def on_validation_end(self, trainer: Trainer, *args: Any) -> None:
        if not trainer.sanity_checking:
            self.validations.append(trainer.global_step)

    def on_fit_end(self, trainer: Trainer, *args: Any) -> None:
        scheduler = trainer.lr_scheduler_configs[0].scheduler
        record = {"rates": self.rates, "validations": self.validations, "scheduler_steps": scheduler.last_epoch}
        self.dest.write_text(json.dumps(record))
