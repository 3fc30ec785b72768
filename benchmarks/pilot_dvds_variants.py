"""Short pilot runs of DVDs training variants, scored on the ModelNet40 *validation* pairs (never test).

    python benchmarks/pilot_dvds_variants.py --root ../shared/data/modelnet40_mini [--steps 40] [--variants ...]
    python benchmarks/pilot_dvds_variants.py --smoke     # seconds, synthetic pairs, one step per variant

Each variant is ``configs/dvds_modelnet40.yaml`` with the variant's model arguments, trained from the same
initialisations (``--seeds``, reported as mean ± std) for ``--steps`` Adam steps (batch 16, 512 points, gradient
clipping 1.0) on the full training loss (local consistency included) on the unseen-objects training split, then
registers the validation pairs (78 objects in modelnet40_mini). This is how the settings of
configs/dvds_modelnet40.yaml were chosen.
"""

from __future__ import annotations

import argparse
import itertools
from collections.abc import Iterator, Sequence
from functools import partial
from typing import Any

import torch
from lightning.pytorch import LightningDataModule

from lcreg.experiments.benchmarking import (
    add_smoke_argument,
    build,
    cli_args,
    format_mean_std,
    machine_line,
    markdown_row,
    markdown_table,
    output_path,
    split_batches,
    synthetic_overrides,
    timed,
    training_loss,
    write_text,
)
from lcreg.experiments.evaluation import EvaluationReport, evaluate
from lcreg.types import RegistrationBatch

# Model arguments of each variant over configs/dvds_modelnet40.yaml ("steps" and "lr" are the training loop's).
UNSTANDARDIZED_LC = [  # configs/lc.yaml's term with standardize: false
    {
        "class_path": "lcreg.models.loss_terms.LocalConsistencyLoss",
        "init_args": {
            "local_consistency": {
                "class_path": "lcreg.nn.local_consistency.LocalConsistency",
                "init_args": {"num_local_points": 64, "standardize": False},
            }
        },
    }
]
VARIANTS: dict[str, dict[str, Any]] = {
    "untrained (BN)": {"steps": 0, "batch_norm": True},
    "untrained (no BN)": {"steps": 0, "batch_norm": False},
    "paper: BN, lr 1e-3": {"batch_norm": True},
    "BN running stats only (lr 0)": {"batch_norm": True, "lr": 0.0},
    "no BN, lr 1e-3": {"batch_norm": False},
    "no BN, lr 1e-4": {"batch_norm": False, "lr": 1e-4},
    "no BN, lr 1e-4, LC not standardized": {"batch_norm": False, "lr": 1e-4, "loss_terms": UNSTANDARDIZED_LC},
}
HEADER = ["variant", "steps", "mean RRE °", "median RRE °", "mean RTE", "recall (2°, 0.01)", "last loss terms", "s"]
SMOKE = {"steps": 1, "seeds": [0]}


def training_batches(dm: LightningDataModule) -> Iterator[RegistrationBatch]:
    """Training batches without end (a new epoch of random pairs whenever one runs out)."""
    return itertools.chain.from_iterable(dm.train_dataloader() for _ in itertools.count())


def train(model: Any, batches: Iterator[RegistrationBatch], steps: int, lr: float) -> dict[str, float]:
    """``steps`` Adam steps with gradient clipping 1.0; returns the last step's loss terms."""
    opt = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=lr)
    last: dict[str, float] = {}
    for batch in itertools.islice(batches, steps):
        model.train()
        losses = training_loss(model, batch)
        losses["loss"].backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        opt.zero_grad()
        last = {k: float(v.detach()) for k, v in losses.items()}
    return last


def train_and_evaluate(model: Any, data: tuple[LightningDataModule, list], steps: int, lr: float) -> EvaluationReport:
    """Train ``model`` on the training pairs, then evaluate it on the validation pairs."""
    dm, val = data
    last = train(model, training_batches(dm), steps, lr)
    report = evaluate(model, val, "validation")
    report.extra.update({f"last_{k}": v for k, v in last.items()})
    return report


def run(
    data: tuple[LightningDataModule, list], seed: int, steps: int, lr: float = 1e-3, **kwargs: Any
) -> EvaluationReport:
    """One variant from initialisation ``seed``: its validation report, with the training loss terms and time."""
    model_args = cli_args("model", {"diagnostics_every_n_steps": 0, **kwargs})
    model = build("dvds", values={"seed_everything": seed, **model_args})
    report, seconds = timed(partial(train_and_evaluate, model, data, steps, lr))
    report.extra["seconds"] = seconds
    return report


def row(name: str, steps: int, reports: list[EvaluationReport]) -> str:
    """Markdown row: mean ± std over seeds of the validation metrics and the last training-loss terms."""
    cols = [
        format_mean_std([r.metrics["rre_mean_deg"] for r in reports], ".2f", ".2f"),
        format_mean_std([r.metrics["rre_median_deg"] for r in reports], ".2f", ".2f"),
        format_mean_std([r.metrics["rte_mean"] for r in reports], ".4f", ".4f"),
        format_mean_std([r.metrics["recall_r2_t0p01"] for r in reports], ".1f", ".1f", scale=100.0) + " %",
    ]
    keys = sorted({k for r in reports for k in r.extra if k.startswith("last_") and k != "last_loss"})
    terms = ", ".join(f"{k[5:]} {format_mean_std([r.extra[k] for r in reports], '.2g', '.2g')}" for k in keys) or "-"
    seconds = sum(r.extra["seconds"] for r in reports)
    return markdown_row([name, steps, *cols, terms, f"{seconds:.0f}"])


def parse(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--root", default="../shared/data/modelnet40_mini")
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--variants", nargs="*", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--out", default=None, help="also write the table (Markdown) here")
    add_smoke_argument(parser)
    args = parser.parse_args(argv)
    if args.smoke:
        vars(args).update(SMOKE)
    return args


def main(argv: Sequence[str] | None = None) -> None:
    args = parse(argv)
    if args.smoke:
        data_args = synthetic_overrides(pairs=2, num_points=64, batch_size=2)
    else:
        data_args = cli_args("data", {"root": args.root, "batch_size": 16, "num_points": 512, "num_workers": 0})
    dm = build("dvds", values=data_args, with_data=True)[1]
    data = (dm, split_batches(dm, "val"))
    head = f"validation pairs: {sum(len(b) for b in data[1])}; seeds {args.seeds}; {machine_line()}"
    lines = [head, "", markdown_table(HEADER)]
    print("\n".join(lines), flush=True)
    for name in args.variants:
        kwargs = dict(VARIANTS[name])
        steps = kwargs.pop("steps", args.steps)
        lines.append(row(name, steps, [run(data, seed, steps, **kwargs) for seed in args.seeds]))
        print(lines[-1], flush=True)
    out = output_path(args.out, "pilot_dvds_variants.md", args.smoke)
    if out:
        write_text(out, "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
