"""Short pilot runs of DVDs training variants, scored on the ModelNet40 *validation* pairs (never test).

    python benchmarks/pilot_dvds_variants.py --root ../shared/data/modelnet40_mini [--steps 40] [--variants ...]

Each variant trains from the same initialisation (seed 0) for ``--steps`` Adam steps (batch 16, 512 points,
gradient clipping 1.0) on the unseen-objects training split, then registers the validation pairs (78 objects in
modelnet40_mini). This is how the settings of configs/dvds_modelnet40.yaml were chosen.
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import torch

from lcreg.data.datamodule import ModelNet40DataModule
from lcreg.evaluation import evaluate
from lcreg.models.dvds import DVDs

VARIANTS: dict[str, dict[str, Any]] = {
    "untrained (BN)": {"steps": 0},
    "paper: BN, lr 1e-3": {},
    "paper: BN, lr 1e-4": {"lr": 1e-4},
    "BN running stats only (lr 0)": {"lr": 0.0},
    "no BN, lr 1e-3": {"batch_norm": False},
    "no BN, lr 1e-4": {"batch_norm": False, "lr": 1e-4},
    "no BN, lr 1e-4, LC not standardized": {"batch_norm": False, "lr": 1e-4, "lc_standardize": False},
    "no BN, lr 1e-4, normalized global": {"batch_norm": False, "lr": 1e-4, "global_loss": "normalized_l2"},
}


def run(dm: ModelNet40DataModule, name: str, steps: int, lr: float = 1e-3, **model_kwargs: Any) -> str:
    torch.manual_seed(0)
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
        last = {k: float(v) for k, v in losses.items()}
    report = evaluate(model, list(dm.val_dataloader()), name)
    m = report.metrics
    terms = ", ".join(f"{k} {v:.3g}" for k, v in last.items() if k != "loss")
    return (
        f"| {name} | {steps} | {m['rre_mean_deg']:.2f} | {m['rre_median_deg']:.2f} | {m['rte_mean']:.4f} | "
        f"{100 * m['recall_r2_t0p01']:.1f} % | {terms or '-'} | {time.perf_counter() - start:.0f} |"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--root", default="../shared/data/modelnet40_mini")
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--variants", nargs="*", default=list(VARIANTS), choices=list(VARIANTS))
    args = parser.parse_args()
    dm = ModelNet40DataModule(root=args.root, batch_size=16, num_points=512)
    dm.setup("fit")
    print(f"validation pairs: {len(dm.val_set)}; torch threads {torch.get_num_threads()}")
    print("| variant | steps | mean RRE ° | median RRE ° | mean RTE | recall (2°, 0.01) | last loss terms | s |")
    print("|---|---|---|---|---|---|---|---|")
    for name in args.variants:
        kwargs = dict(VARIANTS[name])
        print(run(dm, name, kwargs.pop("steps", args.steps), **kwargs), flush=True)


if __name__ == "__main__":
    main()
