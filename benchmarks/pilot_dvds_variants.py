"""Short pilot runs of DVDs training variants, scored on the ModelNet40 *validation* pairs (never test).

    python benchmarks/pilot_dvds_variants.py --root ../shared/data/modelnet40_mini [--steps 40] [--variants ...]

Each variant trains from the same initialisations (``--seeds``, reported as mean ± std) for ``--steps`` Adam
steps (batch 16, 512 points, gradient clipping 1.0) on the unseen-objects training split, then registers the
validation pairs (78 objects in modelnet40_mini). This is how the settings of configs/dvds_modelnet40.yaml were
chosen.
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import torch

from lcreg.data.datamodule import ModelNet40DataModule
from lcreg.evaluation import EvaluationReport, evaluate, format_mean_std
from lcreg.models.dvds import DVDs

VARIANTS: dict[str, dict[str, Any]] = {
    "untrained (BN)": {"steps": 0},
    "untrained (no BN)": {"steps": 0, "batch_norm": False},
    "paper: BN, lr 1e-3": {},
    "BN running stats only (lr 0)": {"lr": 0.0},
    "no BN, lr 1e-3": {"batch_norm": False},
    "no BN, lr 1e-4": {"batch_norm": False, "lr": 1e-4},
    "no BN, lr 1e-4, LC not standardized": {"batch_norm": False, "lr": 1e-4, "lc_standardize": False},
}


def run(dm: ModelNet40DataModule, seed: int, steps: int, lr: float = 1e-3, **model_kwargs: Any) -> EvaluationReport:
    """Train one variant from initialisation ``seed`` and evaluate it on the validation pairs."""
    torch.manual_seed(seed)
    model = DVDs(diagnostics_every_n_steps=0, **model_kwargs)
    opt = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=lr)
    loader, start, last = iter(dm.train_dataloader()), time.perf_counter(), {}
    for _ in range(steps):
        try:
            batch = next(loader)
        except StopIteration:
            loader = iter(dm.train_dataloader())
            batch = next(loader)
        model.train()
        losses = model.compute_loss(model(batch.points_src, batch.points_ref), batch)
        losses["loss"].backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        opt.zero_grad()
        last = {k: float(v.detach()) for k, v in losses.items()}
    report = evaluate(model, list(dm.val_dataloader()), f"seed {seed}")
    report.extra.update({f"last_{k}": v for k, v in last.items()})
    report.extra["seconds"] = time.perf_counter() - start
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
    return f"| {name} | {steps} | " + " | ".join(cols) + f" | {terms} | {seconds:.0f} |"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--root", default="../shared/data/modelnet40_mini")
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--variants", nargs="*", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    args = parser.parse_args()
    dm = ModelNet40DataModule(root=args.root, batch_size=16, num_points=512)
    dm.setup("fit")
    num_val = len(dm.val_set) if dm.val_set is not None else 0
    print(f"validation pairs: {num_val}; seeds {args.seeds}; torch threads {torch.get_num_threads()}")
    head = ["variant", "steps", "mean RRE °", "median RRE °", "mean RTE", "recall (2°, 0.01)", "last loss terms", "s"]
    print("| " + " | ".join(head) + " |")
    print("|---|---|---|---|---|---|---|---|")
    for name in args.variants:
        kwargs = dict(VARIANTS[name])
        steps = kwargs.pop("steps", args.steps)
        print(row(name, steps, [run(dm, seed, steps, **kwargs) for seed in args.seeds]), flush=True)


if __name__ == "__main__":
    main()
