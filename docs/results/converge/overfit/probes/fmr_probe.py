# Ad-hoc probe of session 15: FMR-Net on the 8 fixed pairs. PYTHONPATH=src python .../fmr_probe.py POINTS STEPS VARIANT
# (VARIANT contains any of same, nobn, pose, lr4).
"""FMR-Net on 8 fixed ModelNet40 val pairs: recon training vs registration error, BN on/off, pose term."""

import sys
import time

import torch

from lcreg.baselines.fmr import FMRNet
from lcreg.experiments.benchmarking import build_cli_for, cli_args, split_batches
from lcreg.metrics.registration import registration_metrics

torch.set_num_threads(1)
points = int(sys.argv[1])
steps = int(sys.argv[2])
variant = sys.argv[3]
cli = build_cli_for(
    "fmr",
    values={
        **cli_args(
            "data", {"root": "../shared/data/modelnet40_mini", "num_points": points, "batch_size": 8, "num_workers": 0}
        ),
        "trainer.max_steps": 1,
        "trainer.logger": False,
    },
)
batch = split_batches(cli.datamodule, "val")[0]
if "same" in variant:
    import dataclasses

    from lcreg.geometry import se3

    batch = dataclasses.replace(
        batch, points_src=se3.transform_points(torch.linalg.inv(batch.transform_ref_src), batch.points_ref)
    )
torch.manual_seed(0)
model = FMRNet(batch_norm="nobn" not in variant, pose_weight=1.0 if "pose" in variant else 0.0, decoder_points=points)
opt = torch.optim.Adam(model.parameters(), lr=1e-4 if "lr4" in variant else 1e-3)


def evaluate():
    """Eval-mode mean/median RRE (deg), mean RTE and reconstruction loss on the pairs; back to training mode."""
    model.eval()
    with torch.no_grad():
        res = model(batch.points_src, batch.points_ref)
        m = registration_metrics()
        m.update(res.transform_ref_src, batch.transform_ref_src)
        d = m.compute()
        rl = model._compute_loss(res, batch)["recon"]
    model.train()
    return (
        round(float(d["rre_mean_deg"]), 2),
        round(float(d["rre_median_deg"]), 2),
        round(float(d["rte_mean"]), 4),
        round(float(rl), 4),
    )


t0 = time.time()
model.train()
for s in range(steps + 1):
    if s % max(steps // 6, 1) == 0:
        print(f"step {s} eval rre mean/median/rte/recon {evaluate()} {time.time() - t0:.0f}s", flush=True)
    res = model.training_forward(batch)
    losses = model._compute_loss(res, batch)
    if s % max(steps // 6, 1) == 0:
        print(f"   train losses { {k: round(float(v), 4) for k, v in losses.items()} }", flush=True)
    opt.zero_grad()
    losses["loss"].backward()
    opt.step()
