"""A plateau scheduler with validation every N steps: steps after each validation, never stops the run."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from lcreg.cli import main

from _cli_runs import CONFIGS, TINY_DVDS, config_args  # type: ignore[import-not-found]

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


# Every plateau step after the first halves the rate (an improvement would need val/loss to rise by 1e9).
HALVING = (
    '--model.init_args.lr_scheduler={"class_path": "torch.optim.lr_scheduler.ReduceLROnPlateau", "init_args": '
    '{"mode": "max", "patience": 0, "factor": 0.5, "threshold": 1e9, "threshold_mode": "abs"}}'
)
BY_STEPS = ["--trainer.check_val_every_n_epoch=null", "--trainer.max_epochs=-1"]
SCHEDULES = {  # epochs of 3 steps (6 training shapes in batches of 2)
    "every 4 steps": ["--trainer.val_check_interval=4", *BY_STEPS, "--trainer.max_steps=12"],
    "every 2 steps": ["--trainer.val_check_interval=2", *BY_STEPS, "--trainer.max_steps=6"],
    "every epoch's end, by steps": ["--trainer.val_check_interval=3", *BY_STEPS, "--trainer.max_steps=9"],
    "every 2nd epoch": ["--trainer.check_val_every_n_epoch=2", "--trainer.max_epochs=4"],
    "every epoch": ["--trainer.max_epochs=3"],
    "twice an epoch": ["--trainer.val_check_interval=0.5", "--trainer.max_epochs=2", "--data.init_args.num_train=8"],
}


@pytest.mark.parametrize("schedule", list(SCHEDULES))
def test_a_plateau_scheduler_steps_once_right_after_each_validation(tmp_path: Path, schedule: str) -> None:
    """Lightning counts a plateau scheduler's frequency in batches of the epoch (or in epochs), so before session 62
    a plateau on validations every 4 steps over epochs of 3 never stepped, one every 2 steps took a step between two
    validations on a stale metric, and one validated every 2nd epoch stepped every epoch: the rate halved without a
    validation, or never (DeepGMR's converge schedule on a training set whose epochs are not 88 steps)."""
    record = tmp_path / "rates.json"
    spec = {"class_path": "_cli_runs.RecordRates", "init_args": {"dest": str(record)}}
    main([
        "fit", *config_args("dvds.yaml"), *TINY_DVDS, "--data.init_args.num_train=6",
        "--trainer.limit_train_batches=1.0", "--validate_first=false", HALVING, *SCHEDULES[schedule],
        f"--trainer.callbacks+={json.dumps(spec)}", f"--trainer.default_root_dir={tmp_path}",
        f"--trainer.logger.init_args.save_dir={tmp_path}",
    ])  # fmt: skip
    seen = json.loads(record.read_text())
    validations, rates = seen["validations"], seen["rates"]
    assert len(validations) >= 2 and seen["scheduler_steps"] == len(validations)
    for step, rate in enumerate(rates):  # the first validation sets the best value; each later one halves the rate
        halvings = max(0, sum(v <= step for v in validations) - 1)
        assert rate == pytest.approx(rates[0] * 0.5**halvings, rel=1e-6), (step, rates, validations)
