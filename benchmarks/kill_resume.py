"""A run killed with ``kill -9`` at a random step and resumed with ``lcreg fit --ckpt_path last`` against an
uninterrupted run with the same seed: final weights, validation and test metrics.

    python benchmarks/kill_resume.py [--out runs/kill_resume/report.md] [--seed N] [--epochs 3] [--train 48]
                                     [--points 256]
    python benchmarks/kill_resume.py --smoke     # a tiny run (seconds of training; checks the script runs)

Three ``lcreg fit`` processes of ``configs/dvds.yaml`` (DVDs + LC on the embedded shapes, reduced sizes) with
``last.ckpt`` written after every step (``lcreg.callbacks.LatestCheckpoint(every_n_train_steps=1)``):

* ``whole``: uninterrupted;
* ``killed``: started, then ``SIGKILL``-ed as soon as its ``last.ckpt`` holds a step drawn uniformly from
  ``1 .. total - 1`` (``--seed``; the kill lands while the run computes a later step, so the steps it did after its
  last checkpoint are lost), then resumed by ``lcreg fit --config ... --ckpt_path last`` (one command);
* each final ``last.ckpt`` is tested with ``lcreg test --ckpt_path``.

Printed and written to ``--out`` (a Markdown table; the runs go to ``<out folder>/runs``): the step of the kill and of
the checkpoint resumed, the largest absolute difference of the final weights, ``val/rre_mean_deg`` per epoch and the
test metrics of both runs. Exit code 1 when they differ (beyond 1e-6 for the metrics; the weights are expected to be
bitwise equal on one machine).
"""

from __future__ import annotations

import argparse
import csv
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import torch

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "dvds.yaml"
TEST_KEYS = ("test/rre_mean_deg", "test/rre_median_deg", "test/rte_mean", "test/recall_r2_t0p01")


def _args(options: argparse.Namespace) -> list[str]:
    """The shared ``lcreg fit``/``test`` arguments: the reduced DVDs and data, checkpoints after every step."""
    return [
        "--config",
        str(CONFIG),
        "--model.init_args.encoder_channels=[32,64]",
        "--model.init_args.decoder_grid_size=8",
        "--model.init_args.decoder_hidden=[64]",
        "--model.init_args.normal_hidden=[32]",
        f"--data.init_args.num_points={options.points}",
        f"--data.init_args.points_per_shape={2 * options.points}",
        f"--data.init_args.num_train={options.train}",
        "--data.init_args.num_val=4",
        "--data.init_args.num_test=8",
        "--data.init_args.batch_size=4",
        f"--trainer.max_epochs={options.epochs}",
        "--trainer.enable_progress_bar=false",
        "--trainer.enable_model_summary=false",
        "--trainer.log_every_n_steps=1",
        "--trainer.callbacks=[{class_path: lcreg.callbacks.LatestCheckpoint, init_args: {every_n_train_steps: 1}}]",
    ]


def _lcreg(subcommand: str, args: list[str], out: Path, wait: bool = True) -> subprocess.Popen[bytes]:
    """``python -m lcreg.cli <subcommand>`` logging under ``out``; its output goes to ``out/<subcommand>.log``."""
    out.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT / "src"), os.environ.get("PYTHONPATH", "")])}
    env.setdefault("WANDB_MODE", "disabled")
    log = (out / f"{subcommand}.log").open("ab")
    command = [sys.executable, "-m", "lcreg.cli", subcommand, *args, f"--trainer.logger.init_args.save_dir={out}"]
    process = subprocess.Popen([*command, f"--trainer.default_root_dir={out}"], stdout=log, stderr=log, env=env)
    if wait and process.wait() != 0:
        raise RuntimeError(f"`lcreg {subcommand}` failed (exit {process.returncode}); see {out / f'{subcommand}.log'}")
    return process


def _checkpoint_step(path: Path) -> int:
    """The ``global_step`` of a checkpoint (-1 while it does not exist or is being replaced)."""
    try:
        return int(torch.load(path, map_location="cpu", weights_only=True)["global_step"])
    except (OSError, RuntimeError, EOFError, KeyError):
        return -1


def _kill_at(process: subprocess.Popen[bytes], last: Path, step: int) -> int:
    """SIGKILL ``process`` once ``last`` holds ``step`` or later; the step it held."""
    while (held := _checkpoint_step(last)) < step:
        if process.poll() is not None:
            raise RuntimeError(f"the run ended (exit {process.returncode}) before step {step} was checkpointed")
        time.sleep(0.05)
    os.kill(process.pid, signal.SIGKILL)
    process.wait()
    return held


def _metrics(run: Path) -> list[dict[str, str]]:
    return [row for path in sorted(run.glob("metrics*.csv")) for row in csv.DictReader(path.open())]


def _val_errors(run: Path) -> dict[int, float]:
    return {int(r["epoch"]): float(r["val/rre_mean_deg"]) for r in _metrics(run) if r.get("val/rre_mean_deg")}


def _test(args: list[str], checkpoint: Path, out: Path) -> dict[str, float]:
    _lcreg("test", [*args, "--ckpt_path", str(checkpoint)], out)
    rows = _metrics(out / "lcreg" / "version_0")
    return {key: float(row[key]) for row in rows for key in TEST_KEYS if row.get(key)}


def _largest_weight_difference(a: Path, b: Path) -> float:
    left, right = (torch.load(p, map_location="cpu", weights_only=True)["state_dict"] for p in (a, b))
    if left.keys() != right.keys():
        return float("inf")
    return max((float((left[k].double() - right[k].double()).abs().max()) for k in left if left[k].numel()), default=0)


def main(argv: list[str] | None = None) -> int:
    """Run the comparison; 0 when the resumed run ends like the uninterrupted one."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("runs/kill_resume/report.md"), help="Markdown report")
    parser.add_argument("--seed", type=int, default=None, help="seed of the kill step (default: random)")
    parser.add_argument("--epochs", type=int, default=3)
    parser.add_argument("--train", type=int, default=48, help="training shapes (batches of 4)")
    parser.add_argument("--points", type=int, default=256)
    parser.add_argument("--smoke", action="store_true", help="2 epochs of 3 steps at 128 points")
    options = parser.parse_args(argv)
    if options.smoke:
        options.epochs, options.train, options.points = 2, 12, 128
    args = _args(options)
    total = options.epochs * (options.train // 4)
    kill_step = random.Random(options.seed).randint(1, total - 1)
    out = options.out.resolve().parent / "runs"

    start = time.perf_counter()
    _lcreg("fit", args, out / "whole")
    killed_dir = out / "killed"
    last = killed_dir / "lcreg" / "version_0" / "checkpoints" / "last.ckpt"
    held = _kill_at(_lcreg("fit", args, killed_dir, wait=False), last, kill_step)
    _lcreg("fit", [*args, "--ckpt_path", "last"], killed_dir)
    whole_run, resumed_run = out / "whole" / "lcreg" / "version_0", killed_dir / "lcreg" / "version_0"
    whole_last = whole_run / "checkpoints" / "last.ckpt"
    tests = {name: _test(args, ckpt, out / f"test_{name}") for name, ckpt in (("whole", whole_last), ("resumed", last))}

    weights = _largest_weight_difference(whole_last, last)
    vals = {"whole": _val_errors(whole_run), "resumed": _val_errors(resumed_run)}
    rows = [
        ("kill -9 once checkpointed (step)", str(kill_step), f"killed holding step {held} of {total}"),
        ("final step", str(_checkpoint_step(whole_last)), str(_checkpoint_step(last))),
        ("largest abs weight difference", "", f"{weights:.3g}"),
        *(
            (f"val/rre_mean_deg epoch {e}", f"{v:.6f}", f"{vals['resumed'].get(e, float('nan')):.6f}")
            for e, v in sorted(vals["whole"].items())
        ),
        *(
            (key, f"{tests['whole'].get(key, float('nan')):.6g}", f"{tests['resumed'].get(key, float('nan')):.6g}")
            for key in TEST_KEYS
        ),
    ]
    same = weights == 0 and _close(vals["whole"], vals["resumed"]) and _close(tests["whole"], tests["resumed"])
    report = "\n".join(
        [
            f"# kill -9 and resume ({'SAME' if same else 'DIFFERENT'}; {time.perf_counter() - start:.0f} s)",
            "",
            "| | uninterrupted | killed + resumed |",
            "|---|---|---|",
            *(f"| {a} | {b} | {c} |" for a, b, c in rows),
            "",
        ]
    )
    options.out.parent.mkdir(parents=True, exist_ok=True)
    options.out.write_text(report)
    print(report)
    return 0 if same else 1


def _close(a: dict[Any, float], b: dict[Any, float]) -> bool:
    return a.keys() == b.keys() and all(abs(a[k] - b[k]) <= 1e-6 for k in a)


if __name__ == "__main__":
    sys.exit(main())
