"""Speed of the correspondence-based baselines and the cost of local consistency, in one process.

    python benchmarks/bench_baselines.py [--root ../shared/data/modelnet40_mini] [--device cpu|cuda]

* Inference ms/pair of DCP-v2, PRNet, IDAM and DeepGMR (default constructor arguments = the originals' sizes) at
  500/1000/2000 points, batch 1 and batch 8 (``--batch-sizes``), on real ModelNet40 test pairs (synthetic shapes
  without the data), with Open3D point-to-point ICP on the same pairs as the in-process peer;
* one training step (forward, loss, backward, Adam step) of each host without and with LC
  (``LocalConsistency(K, 64)``, weight 1), same weights and batch, steps alternated to cancel drift; reports the
  median step time and the LC overhead in % (target: at most 10 %).

The paper's runtime reference (Titan Xp) lists DCP at 6/9/20 ms for 500/1000/2000 points.
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable

import torch
from bench_dvds import pairs, time_model
from lightning.fabric.utilities.apply_func import move_data_to_device

from lcreg.baselines.classical import ICP
from lcreg.models.base import RegistrationModule
from lcreg.nn.local_consistency import LocalConsistency
from lcreg.types import RegistrationBatch


def hosts() -> dict[str, Callable[[LocalConsistency | None], RegistrationModule]]:
    """Factories of the hosts with their default sizes and an optional LC module."""
    from lcreg.baselines.dcp import DCP
    from lcreg.baselines.deepgmr import DeepGMR
    from lcreg.baselines.idam import IDAM
    from lcreg.baselines.prnet import PRNet

    return {
        "DCP-v2": lambda lc: DCP(local_consistency=lc),
        "PRNet": lambda lc: PRNet(local_consistency=lc),
        "IDAM": lambda lc: IDAM(local_consistency=lc),
        "DeepGMR": lambda lc: DeepGMR(local_consistency=lc),
    }


def feature_dim(model: RegistrationModule, batch: RegistrationBatch) -> int:
    """Output width of the host's encoder (what LC is built for)."""
    with torch.no_grad():
        return int(model.lc_encoder()(batch.points_src[:1, :64]).shape[-1])  # type: ignore[operator]


def step_seconds(model: RegistrationModule, batch: RegistrationBatch, opt: torch.optim.Optimizer, sync: bool) -> float:
    """Wall time of one optimisation step."""
    if sync:
        torch.cuda.synchronize()
    start = time.perf_counter()
    opt.zero_grad()
    model.training_losses(model.training_forward(batch), batch)["loss"].backward()
    opt.step()
    if sync:
        torch.cuda.synchronize()
    return time.perf_counter() - start


def lc_overhead(name: str, factory: Callable, batch: RegistrationBatch, device: str, repeats: int) -> str:
    """Median step time without/with LC (alternating) and the overhead."""
    torch.manual_seed(0)
    base = factory(None).to(device).train()
    k = feature_dim(base, batch)
    torch.manual_seed(0)
    with_lc = factory(LocalConsistency(k, num_local_points=64)).to(device).train()
    models = {"X": base, "LC + X": with_lc}
    opts = {v: torch.optim.Adam([p for p in m.parameters() if p.requires_grad], lr=1e-4) for v, m in models.items()}
    times: dict[str, list[float]] = {v: [] for v in models}
    for i in range(repeats + 1):
        for variant in models:
            seconds = step_seconds(models[variant], batch, opts[variant], device == "cuda")
            if i > 0:  # first round is warm-up
                times[variant].append(seconds)
    t_x, t_lc = (statistics.median(times[v]) for v in models)
    return f"| {name} | {k} | {1000 * t_x:.0f} | {1000 * t_lc:.0f} | {100 * (t_lc / t_x - 1):+.1f} % |"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--root", default="../shared/data/modelnet40_mini")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--pairs", type=int, default=8)
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=[1, 8])
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--train-batch", type=int, default=16)
    parser.add_argument("--train-points", type=int, default=1024)
    parser.add_argument("--skip-inference", action="store_true")
    args = parser.parse_args()
    factories = hosts()
    print(f"device {args.device}, torch threads {torch.get_num_threads()}, median of {args.repeats} runs")

    if not args.skip_inference:
        torch.manual_seed(0)
        models = {name: make(None).to(args.device) for name, make in factories.items()}
        icp = ICP(voxel_size=0.05, distance_factor=4.0, method="point_to_point")  # gate 0.2
        header = " | ".join(f"{n} b={b}" for n in models for b in args.batch_sizes)
        print(f"\n| points | {header} | ICP |")
        print("|---" * (len(args.batch_sizes) * len(models) + 2) + "|")
        for n in (500, 1000, 2000):
            batch, source = pairs(n, args.pairs, args.root)
            cells = []
            for model in models.values():
                cells += [f"{time_model(model, batch, b, args.device, args.repeats):.1f}" for b in args.batch_sizes]
            cells.append(f"{time_model(icp, batch, 1, 'cpu', args.repeats):.1f}")
            print(f"| {n} | " + " | ".join(cells) + " |")
        print(f"ms/pair; pairs from: {source}")

    batch, source = pairs(args.train_points, args.train_batch, args.root)
    batch = move_data_to_device(batch, args.device)
    print(f"\ntraining step, batch {args.train_batch} x {args.train_points} points ({source}):")
    print("| host | K | X ms/step | LC + X ms/step | LC overhead |\n|---|---|---|---|---|")
    for name, make in factories.items():
        print(lc_overhead(name, make, batch, args.device, args.repeats), flush=True)


if __name__ == "__main__":
    main()
