# Ad-hoc probe of session 15 (README.md of docs/results/converge, "PCRNet and FMR-Net on 8 fixed pairs"); run from the
# repository root: PYTHONPATH=src python docs/results/converge/overfit/probes/pcr_probe.py POINTS STEPS VARIANT, where
# VARIANT contains any of same (identical points in both clouds), sup (pose loss), idinit, it1, lr4 (Adam lr 1e-4).
"""PCRNet diagnostics on 8 fixed ModelNet40 val pairs: which losses/settings let it fit."""

import sys
import time

import torch

from lcreg.baselines.pcrnet import CHAMFER_SCALE, PCRNet
from lcreg.experiments.benchmarking import build_cli_for, cli_args, split_batches
from lcreg.geometry import se3
from lcreg.geometry.chamfer import chamfer_distance
from lcreg.metrics.registration import registration_metrics

torch.set_num_threads(1)
points = int(sys.argv[1])
steps = int(sys.argv[2])
variant = sys.argv[3]
cli = build_cli_for(
    "pcrnet",
    values={
        **cli_args(
            "data", {"root": "../shared/data/modelnet40_mini", "num_points": points, "batch_size": 8, "num_workers": 0}
        ),
        "trainer.max_steps": 1,
        "trainer.logger": False,
    },
)
batch = split_batches(cli.datamodule, "val")[0]
src, ref, gt = batch.points_src, batch.points_ref, batch.transform_ref_src
if "same" in variant:  # original protocol: the source is the reference's own points moved by gt^-1
    src = se3.transform_points(torch.linalg.inv(gt), ref)
torch.manual_seed(0)
model = PCRNet(identity_init="idinit" in variant, num_iterations=1 if "it1" in variant else 8)
lr = 1e-4 if "lr4" in variant else 1e-3
opt = torch.optim.Adam(model.parameters(), lr=lr)


def rre(T):
    """Mean RRE (deg) and mean RTE of the estimates ``T (B, 4, 4)`` against the pairs' ground truth."""
    m = registration_metrics()
    m.update(T, gt)
    d = m.compute()
    return float(d["rre_mean_deg"]), float(d["rte_mean"])


print(variant, "chamfer at gt", float(CHAMFER_SCALE * chamfer_distance(se3.transform_points(gt, src), ref).mean()))
t0 = time.time()
for s in range(steps + 1):
    res = model(src, ref)
    if "sup" in variant:
        loss = ((res.transform_ref_src @ torch.linalg.inv(gt) - torch.eye(4)) ** 2).mean() * 16
    else:
        loss = CHAMFER_SCALE * chamfer_distance(res.aux["transformed_src"], ref).mean()
    if s % max(steps // 10, 1) == 0:
        with torch.no_grad():
            cd = float(CHAMFER_SCALE * chamfer_distance(res.aux["transformed_src"], ref).mean())
        errors = rre(res.transform_ref_src.detach())
        print(f"step {s} loss {float(loss):.4f} chamfer {cd:.4f} rre/rte {errors} {time.time() - t0:.0f}s", flush=True)
    opt.zero_grad()
    loss.backward()
    opt.step()
