# Ad-hoc probe of session 15: a trained FMR-Net checkpoint (the overfit run, not kept) solved with other Jacobians
# and iteration counts. PYTHONPATH=src python .../fmrjac_probe.py CHECKPOINT
import sys

import torch

from lcreg.baselines.fmr import FMRNet
from lcreg.experiments.benchmarking import build_cli_for, cli_args, split_batches
from lcreg.metrics.registration import registration_metrics

torch.set_num_threads(1)
cli = build_cli_for(
    "fmr",
    values={
        **cli_args(
            "data", {"root": "../shared/data/modelnet40_mini", "num_points": 1024, "batch_size": 8, "num_workers": 0}
        ),
        "trainer.max_steps": 1,
        "trainer.logger": False,
    },
)
batch = split_batches(cli.datamodule, "val")[0]
ck = torch.load(sys.argv[1], map_location="cpu", weights_only=False)
for jac, fd, iters in (
    ("finite_difference", 1e-2, 10),
    ("finite_difference", 1e-3, 10),
    ("analytic", 1e-2, 10),
    ("analytic", 1e-2, 50),
):
    m = FMRNet(jacobian=jac, fd_step=fd, max_iterations=iters)
    m.load_state_dict(ck["state_dict"])
    m.eval()
    with torch.no_grad():
        r = m(batch.points_src, batch.points_ref)
    mt = registration_metrics()
    mt.update(r.transform_ref_src, batch.transform_ref_src)
    d = mt.compute()
    print(
        jac,
        fd,
        iters,
        round(float(d["rre_mean_deg"]), 2),
        round(float(d["rre_median_deg"]), 2),
        [round(float(x), 1) for x in r.residual_history[0]],
    )
