# Ad-hoc probe of session 17 (goal (d)): is PRNet's translation spoilt by BatchNorm's eval mode at batch 8, as
# DCP-v2's is (docs/results/converge/overfit/, gpu_dcp_bn_256)? Validation pairs only:
#   PYTHONPATH=src python docs/results/converge/prnet_lr_256/probes/bn_mode_probe.py [CHECKPOINT ...] > out.md
# (no checkpoint: the untrained network, seed 0). Each network is evaluated twice on the 312 validation pairs of the
# converge budget (256 points, batches of 8, the DCP-family pairs, σ 0.01): in eval mode (BatchNorm's running
# statistics; what validation and test use) and in eval mode with only the BatchNorm layers on each batch's own
# statistics (what training saw; a copy of the network, so its running statistics stay as saved). Everything else
# (the Gumbel sampler, no gradient) is the same in both. A third row: eval mode with ``deterministic_eval`` (the argmax
# instead of a Gumbel sample; upstream samples at test time too).
"""PRNet: eval-mode BatchNorm against batch-statistics BatchNorm on the validation pairs."""

import copy
import sys

import torch

from lcreg.experiments.benchmarking import build, cli_args, split_batches
from lcreg.metrics.registration import registration_metrics

ROOT = "../shared/data/modelnet40_mini"
KEYS = ("rre_mean_deg", "rre_median_deg", "rte_mean", "rmse_t", "recall_r5_t0p05", "recall_r2_t0p01")


def errors(model: torch.nn.Module, batches: list, batch_stats: bool, argmax: bool = False) -> dict[str, float]:
    """Validation errors of a copy of ``model`` in eval mode, its BatchNorm layers on batch statistics if asked."""
    net = copy.deepcopy(model).eval()
    net.deterministic_eval = argmax
    torch.manual_seed(0)  # the Gumbel samples
    if batch_stats:
        for module in net.modules():
            if isinstance(module, torch.nn.modules.batchnorm._BatchNorm):
                module.train()
    metrics = registration_metrics()
    with torch.no_grad():
        for b in batches:
            metrics.update(net(b.points_src, b.points_ref).transform_ref_src, b.transform_ref_src)
    return {k: float(v) for k, v in metrics.compute().items() if k in KEYS}


def main(checkpoints: list[str]) -> None:
    """Print one Markdown row per network and mode."""
    torch.set_num_threads(1)
    data = {"root": ROOT, "num_points": 256, "batch_size": 8, "num_workers": 0, "val_pairs_per_object": 4}
    values = {**cli_args("data", data), "seed_everything": 0}
    print("| network | BatchNorm | " + " | ".join(KEYS) + " |")
    print("|---|---|" + "---|" * len(KEYS))
    for checkpoint in checkpoints or [None]:
        model, dm = build("prnet", checkpoint, values=values, with_data=True)
        batches = split_batches(dm, "val")
        for batch_stats, argmax in ((False, False), (True, False), (False, True)):
            row = errors(model, batches, batch_stats, argmax)
            mode = "batch statistics" if batch_stats else "running (eval)"
            mode += ", argmax sampler" if argmax else ""
            cells = " | ".join(f"{row[k]:.4g}" for k in KEYS)
            print(f"| {checkpoint or 'untrained (seed 0)'} | {mode} | {cells} |", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
