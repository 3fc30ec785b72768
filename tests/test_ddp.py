"""Distributed training on the CPU: Lightning DDP with the gloo backend, two processes (issue 14, "Also").

A short ``lcreg fit`` under DDP, then ``lcreg test`` of its checkpoint with one process and with two: the metrics
and the per-pair errors must be equal, every test pair counted once (``DistributedSampler`` pads 5 pairs to 6 on two
processes; the metrics drop the repeat by dataset index).
"""

from __future__ import annotations

import csv
import os
import subprocess
import sys
from pathlib import Path

import pytest

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
TINY = [
    "--config",
    str(CONFIGS / "models" / "pointnetlk.yaml"),
    "--config",
    str(CONFIGS / "data" / "embedded.yaml"),
    "--model.init_args.encoder_channels=[16,32]",
    "--data.init_args.num_points=64",
    "--data.init_args.points_per_shape=128",
    "--data.init_args.num_train=8",
    "--data.init_args.num_val=3",
    "--data.init_args.num_test=5",
    "--data.init_args.batch_size=2",
    "--trainer.enable_progress_bar=false",
    "--trainer.enable_model_summary=false",
    "--seed_everything=0",
]
DDP = ["--trainer.strategy=ddp", "--trainer.devices=2", "--trainer.accelerator=cpu"]


def _lcreg(tmp_path: Path, *args: str) -> None:
    env = {**os.environ, "WANDB_MODE": "disabled", "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "lcreg.cli", *args]
    proc = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]


def _test_rows(tmp_path: Path, name: str) -> tuple[dict[str, float], list[list[str]]]:
    run = tmp_path / "runs" / name / "version_0"
    with (run / "metrics.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    metrics = {k: float(v) for row in rows for k, v in row.items() if k.startswith("test/") and v}
    with (run / "test_per_pair.csv").open() as fh:
        pairs = list(csv.reader(fh))[1:]
    return metrics, pairs


@pytest.mark.timeout(900)
def test_ddp_fit_then_test_equals_one_process(tmp_path: Path) -> None:
    _lcreg(tmp_path, "fit", *TINY, *DDP, "--trainer.max_steps=2", "--trainer.logger.init_args.name=fit")
    ckpt = tmp_path / "runs" / "fit" / "version_0" / "checkpoints" / "last.ckpt"
    assert ckpt.is_file()
    for name, extra in (("single", []), ("ddp", DDP)):
        _lcreg(tmp_path, "test", *TINY, *extra, f"--ckpt_path={ckpt}", f"--trainer.logger.init_args.name={name}")
    single, single_pairs = _test_rows(tmp_path, "single")
    ddp, ddp_pairs = _test_rows(tmp_path, "ddp")
    assert [row[0] for row in ddp_pairs] == ["0", "1", "2", "3", "4"]  # every pair once, none dropped
    flat = [[float(v) for row in rows for v in row[:3] + row[4:]] for rows in (ddp_pairs, single_pairs)]
    assert len(ddp_pairs[0]) == 10 and flat[0] == pytest.approx(flat[1], rel=1e-5, abs=1e-6)  # + the components
    assert [row[3] for row in ddp_pairs] == [row[3] for row in single_pairs]  # each pair's class, gathered
    assert set(ddp) == set(single) and "test/rre_mean_deg" in ddp
    assert ddp == pytest.approx(single, rel=1e-5)


# Early stopping under real DDP (two gloo processes): the stop decisions of ``MinimumEarlyStopping`` are collective
# (``reduce_boolean_decision``), so a process that disagrees would hang the other one. Each process scores its own
# scripted validations (``val/score`` unsynced, so the processes may differ) and writes the step it stopped at.
EARLY_STOPPING_SCRIPT = """
import sys
from pathlib import Path

import torch
from lightning.pytorch import LightningModule, Trainer
from torch.utils.data import DataLoader

from lcreg.callbacks import MinimumEarlyStopping

SCORES = {"recovers": [5.0, 4.0, 4.5, 4.6, 4.7, 3.0, 2.0, 1.5, 1.4, 1.6, 1.7, 1.8, 1.9, 2.0],
          "nan": [5.0, float("nan"), 1.0, 0.5, 0.4, 0.3, 0.2, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1]}


class Scripted(LightningModule):
    def __init__(self, scores):
        super().__init__()
        self.weight = torch.nn.Parameter(torch.zeros(1))
        self.scores = scores

    def training_step(self, batch, batch_idx):
        return (self.weight - batch).square().mean()

    def validation_step(self, batch, batch_idx):
        self.log("val/score", self.scores[self.trainer.global_step - 1])

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.1)

    def train_dataloader(self):
        return DataLoader(torch.zeros(2), batch_size=1)

    val_dataloader = train_dataloader


out, per_rank = Path(sys.argv[1]), sys.argv[2:]
trainer = Trainer(accelerator="cpu", strategy="ddp", devices=2, max_steps=14, min_steps=8, num_sanity_val_steps=0,
                  logger=False, enable_checkpointing=False, enable_model_summary=False, enable_progress_bar=False,
                  callbacks=[MinimumEarlyStopping("val/score", patience=2)], default_root_dir=out)
trainer.fit(Scripted(SCORES[per_rank[trainer.global_rank]]))
(out / f"rank{trainer.global_rank}").write_text(str(trainer.global_step))
# Lightning destroys only NCCL groups at exit; a gloo group left to the interpreter's teardown aborts the process now
# and then ("terminate called without an active exception", exit -6) after everything above has run.
torch.distributed.destroy_process_group()
"""


@pytest.mark.timeout(600)
@pytest.mark.parametrize(
    ("per_rank", "stop"),
    [
        (("recovers", "recovers"), 11),  # both provisional below min_steps 8: the best at step 9, patience 2
        (("recovers", "nan"), 8),  # rank 1 latches a non-finite stop at step 2: both stop at the minimum
    ],
)
def test_minimum_early_stopping_decides_alike_on_two_ddp_processes(
    tmp_path: Path, per_rank: tuple[str, str], stop: int
) -> None:
    script = tmp_path / "scripted_ddp.py"
    script.write_text(EARLY_STOPPING_SCRIPT)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONWARNINGS": "ignore"}
    proc = subprocess.run(
        [sys.executable, str(script), str(tmp_path), *per_rank],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert [int((tmp_path / f"rank{r}").read_text()) for r in (0, 1)] == [stop, stop]
