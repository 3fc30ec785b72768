"""Speed of the correspondence-based baselines and the cost of local consistency, in one process.

    python benchmarks/bench_baselines.py [--root ../shared/data/modelnet40_mini] [--device cpu|cuda]
    python benchmarks/bench_baselines.py --smoke     # seconds, embedded synthetic pairs (checks the script runs)

* Inference ms/pair of DCP-v2, PRNet, IDAM and DeepGMR (their configs in ``configs/``: the originals' sizes) at
  500/1000/2000 points, batch 1 and batch 8 (``--batch-sizes``), on real ModelNet40 test pairs (synthetic shapes
  without the data), with Open3D point-to-point ICP (``configs/icp.yaml``, gate 0.2) on the same pairs as the
  in-process peer;
* one training step (forward, full training loss, backward, Adam step) of each host without and with LC (the
  ``<host>_lc`` config: ``LocalConsistency(K, 64)``, weight 1), same seed (so the same host weights) and batch, steps
  alternated to cancel drift; reports the median step time and the LC overhead in % (target: at most 10 %).

The paper's runtime reference (Titan Xp) lists DCP at 6/9/20 ms for 500/1000/2000 points.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from functools import partial

import torch
from lightning.fabric.utilities.apply_func import move_data_to_device

from lcreg.experiments.benchmarking import (
    METHODS,
    add_smoke_argument,
    apply_smoke,
    build,
    cli_args,
    machine_line,
    markdown_table,
    output_path,
    pair_batches,
    registration_speed,
    time_calls,
    training_loss,
    write_text,
)
from lcreg.models.base import RegistrationModule
from lcreg.types import RegistrationBatch

HOSTS = ("dcp", "prnet", "idam", "deepgmr")
SIZES = (500, 1000, 2000)
SMOKE = {"sizes": (64,), "pairs": 2, "batch_sizes": [1, 2], "repeats": 1, "train_batch": 2, "train_points": 64}
SEED = {"seed_everything": 0}  # X and LC + X start from the same host weights


def train_step(model: RegistrationModule, batch: RegistrationBatch, opt: torch.optim.Optimizer) -> None:
    """One optimisation step on the full training loss."""
    opt.zero_grad()
    training_loss(model, batch)["loss"].backward()
    opt.step()


def lc_overhead(host: str, batch: RegistrationBatch, device: str, repeats: int) -> list[object]:
    """Median step time without/with LC (alternating rounds after a warm-up round) and the overhead."""
    names = {"X": host, "LC + X": METHODS[host].lc_variant or host}
    models = {v: build(name, values=SEED).to(device).train() for v, name in names.items()}
    opts = {v: torch.optim.Adam([p for p in m.parameters() if p.requires_grad], lr=1e-4) for v, m in models.items()}
    steps = {v: partial(train_step, models[v], batch, opts[v]) for v in models}
    t_x, t_lc = (t.median_s for t in time_calls(steps, repeats, warmup=1, device=device).values())
    k = models["X"].descriptor_dim  # the width LC is bound to
    return [METHODS[host].label, k, f"{1000 * t_x:.0f}", f"{1000 * t_lc:.0f}", f"{100 * (t_lc / t_x - 1):+.1f} %"]


def inference_table(args: argparse.Namespace) -> str:
    """ms/pair of every host at every size and batch size, and of ICP."""
    models = {host: build(host, values=SEED).to(args.device) for host in HOSTS}
    icp = build("icp", values=cli_args("model", {"distance_factor": 4.0}))  # voxel 0.05: gate 0.2
    header = ["points", *(f"{METHODS[h].label} b={b}" for h in models for b in args.batch_sizes), "ICP"]
    rows, source = [], ""
    for n in args.sizes:
        batches, source = pair_batches(args.root, pairs=args.pairs, num_points=n, batch_size=args.pairs)
        src, ref = batches[0].points_src, batches[0].points_ref
        cells = [
            registration_speed(m, src, ref, b, args.repeats).ms_per_pair
            for m in models.values()
            for b in args.batch_sizes
        ]
        cells.append(registration_speed(icp, src, ref, 1, args.repeats).ms_per_pair)
        rows.append([n, *(f"{ms:.1f}" for ms in cells)])
    return markdown_table(header, rows) + f"\nms/pair; pairs from: {source}"


def training_table(args: argparse.Namespace) -> str:
    """The LC overhead of one training step, per host."""
    batches, source = pair_batches(
        args.root, pairs=args.train_batch, num_points=args.train_points, batch_size=args.train_batch
    )
    batch = move_data_to_device(batches[0], args.device)
    header = ["host", "K", "X ms/step", "LC + X ms/step", "LC overhead"]
    rows = [lc_overhead(host, batch, args.device, args.repeats) for host in HOSTS]
    return f"training step, batch {args.train_batch} x {args.train_points} points ({source}):\n" + markdown_table(
        header, rows
    )


def parse(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--root", default="../shared/data/modelnet40_mini")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--pairs", type=int, default=8)
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=[1, 8])
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--train-batch", type=int, default=16)
    parser.add_argument("--train-points", type=int, default=1024)
    parser.add_argument("--skip-inference", action="store_true")
    parser.add_argument("--out", default=None, help="also write the report (Markdown) here")
    add_smoke_argument(parser)
    args = parser.parse_args(argv)
    args.sizes = SIZES
    return apply_smoke(args, SMOKE)


def main(argv: Sequence[str] | None = None) -> None:
    args = parse(argv)
    parts = [f"device {args.device}: {machine_line(args.device)}, median of {args.repeats} runs"]
    print(parts[0], flush=True)
    if not args.skip_inference:
        parts.append(inference_table(args))
        print(parts[-1], flush=True)
    parts.append(training_table(args))
    print(parts[-1], flush=True)
    out = output_path(args.out, "bench_baselines.md", args.smoke)
    if out:
        write_text(out, "\n\n".join(parts) + "\n")


if __name__ == "__main__":
    main()
