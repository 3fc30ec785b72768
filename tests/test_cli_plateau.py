"""A plateau scheduler with validation every N steps: steps after each validation, never stops the run."""

from __future__ import annotations

from pathlib import Path

import pytest

from lcreg.cli import main

from _cli_runs import CONFIGS  # type: ignore[import-not-found]

pytestmark = pytest.mark.usefixtures("isolated_cli")


def test_reduce_on_plateau_with_validation_every_n_steps_trains(tmp_path: Path) -> None:
    # Two training steps per epoch, validation every 3 steps: epoch 1 ends without a validation (no val/loss), which
    # stopped the run with a MisconfigurationException (DeepGMR's config uses ReduceLROnPlateau on val/loss).
    small = ["--data.init_args.num_train", "8", "--data.init_args.num_val", "4", "--data.init_args.batch_size", "4"]
    main([
        "fit", "--config", str(CONFIGS / "models" / "deepgmr.yaml"),
        "--config", str(CONFIGS / "data" / "embedded.yaml"),
        *small, "--data.init_args.num_points", "64", "--trainer.val_check_interval", "3",
        "--trainer.check_val_every_n_epoch", "null", "--trainer.max_steps", "7",
        "--trainer.default_root_dir", str(tmp_path), "--trainer.enable_progress_bar", "false",
    ])  # fmt: skip
    assert list(tmp_path.rglob("metrics.csv")) or list(Path("runs").rglob("metrics.csv"))
