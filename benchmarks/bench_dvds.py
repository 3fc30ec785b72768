"""DVDs inference speed and training-step memory, beside Open3D ICP in the same process.

    python benchmarks/bench_dvds.py [--ckpt CKPT] [--root ../shared/data/modelnet40_mini] [--device cpu|cuda]
    python benchmarks/bench_dvds.py --smoke          # seconds, embedded synthetic pairs (checks the script runs)

* ms/pair of DVDs registration (``configs/dvds_modelnet40.yaml``: IC-LK, T = 10, analytic Jacobian) at 500/1000/2000
  points, batch 1 and batch 16, on real ModelNet40 test objects (the unseen-objects pairs) when the data is present,
  otherwise on the embedded synthetic shapes; Open3D point-to-point ICP (``configs/icp.yaml`` with gate 0.2; CPU, one
  pair at a time) on the same pairs; median of ``--repeats`` passes after a warm-up pass;
* ratio DVDs / ICP at batch 1;
* peak memory of one DVDs training step (batch 32, 1024 points; the full training loss, local consistency included):
  peak RSS increase on CPU (a fresh subprocess), ``torch.cuda.max_memory_allocated`` on a GPU.

The paper's reference (Titan Xp): DVDs 66/68/69 ms and ICP 7/16/35 ms at 500/1000/2000 points.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from typing import Any

import torch
from lightning.fabric.utilities.apply_func import move_data_to_device

from lcreg.experiments.benchmarking import (
    add_smoke_argument,
    apply_smoke,
    build,
    cli_args,
    machine_line,
    markdown_table,
    output_path,
    pair_batches,
    peak_rss_mib,
    registration_speed,
    run_fresh_process,
    timed,
    training_loss,
    write_text,
)

SIZES = (500, 1000, 2000)
BATCH_SIZES = (1, 16)
SMOKE = {"sizes": (64,), "batch_sizes": (1, 2), "pairs": 2, "repeats": 1, "train_batch": 2, "train_points": 64}
ICP_GATE_0P2 = {"distance_factor": 4.0}  # voxel_size 0.05 in configs/icp.yaml: gate 0.2


def train_step_memory(device: str, batch_size: int, num_points: int) -> dict[str, float]:
    """Peak memory and time of one forward + backward DVDs training step (run in this process)."""
    model = build("dvds", values=cli_args("model", {"diagnostics_every_n_steps": 0})).to(device).train()
    batches, _ = pair_batches(None, pairs=batch_size, num_points=num_points, batch_size=batch_size)
    batch = move_data_to_device(batches[0], device)
    batch.transform_ref_src = None  # self-supervised: the training step never sees the pose
    before = peak_rss_mib()
    if device == "cuda":
        torch.cuda.reset_peak_memory_stats()
    _, seconds = timed(lambda: training_loss(model, batch)["loss"].backward(), device)
    out = {"step_s": seconds, "rss_before_mb": before, "rss_peak_mb": peak_rss_mib()}
    if device == "cuda":
        out["cuda_peak_mb"] = torch.cuda.max_memory_allocated() / 2**20
    return out


def speed_table(args: argparse.Namespace) -> str:
    """ms/pair of DVDs (each batch size) and ICP at every size, and the DVDs/ICP ratio at batch 1."""
    dvds = build("dvds", args.ckpt).to(args.device)
    icp = build("icp", values=cli_args("model", ICP_GATE_0P2))
    header = ["points", *(f"DVDs b={b} ms/pair" for b in args.batch_sizes), "ICP ms/pair", "DVDs/ICP (b=1)"]
    rows, source = [], ""
    for n in args.sizes:
        batches, source = pair_batches(args.root, pairs=args.pairs, num_points=n, batch_size=args.pairs)
        src, ref = batches[0].points_src, batches[0].points_ref
        dvds_ms = [registration_speed(dvds, src, ref, b, args.repeats).ms_per_pair for b in args.batch_sizes]
        icp_ms = registration_speed(icp, src, ref, 1, args.repeats).ms_per_pair
        rows.append([n, *(f"{ms:.1f}" for ms in dvds_ms), f"{icp_ms:.1f}", f"{dvds_ms[0] / icp_ms:.2f}"])
    return markdown_table(header, rows) + f"\npairs from: {source}"


def memory_line(args: argparse.Namespace) -> str:
    """The training step's memory, measured in a fresh process so its peak RSS belongs to the step alone."""
    sizes = ["--train-batch", str(args.train_batch), "--train-points", str(args.train_points)]
    mem: dict[str, Any] = run_fresh_process([__file__, "--memory-only", "--device", args.device, *sizes])
    line = (
        f"training step, batch {args.train_batch} x {args.train_points} points: {mem['step_s']:.2f} s, peak RSS "
        f"{mem['rss_peak_mb']:.0f} MB (+{mem['rss_peak_mb'] - mem['rss_before_mb']:.0f} MB over the process before "
        "the step)"
    )
    if "cuda_peak_mb" in mem:
        line += f", CUDA peak allocated {mem['cuda_peak_mb']:.0f} MB"
    return line


def parse(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ckpt", default=None, help="DVDs checkpoint (speed does not depend on the weights)")
    parser.add_argument("--root", default="../shared/data/modelnet40_mini")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--pairs", type=int, default=32)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", default=None, help="also write the report (Markdown) here")
    parser.add_argument("--memory-only", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--train-batch", type=int, default=32, help=argparse.SUPPRESS)
    parser.add_argument("--train-points", type=int, default=1024, help=argparse.SUPPRESS)
    add_smoke_argument(parser)
    args = parser.parse_args(argv)
    args.sizes, args.batch_sizes = SIZES, BATCH_SIZES
    return apply_smoke(args, SMOKE)


def main(argv: Sequence[str] | None = None) -> None:
    args = parse(argv)
    if args.memory_only:
        print(json.dumps(train_step_memory(args.device, args.train_batch, args.train_points)))
        return
    head = f"device {args.device}: {machine_line(args.device)}, {args.pairs} pairs per size, median of {args.repeats}"
    print(head, flush=True)
    report = "\n\n".join([head, speed_table(args), memory_line(args)])
    print(report.removeprefix(head).strip())
    out = output_path(args.out, "bench_dvds.md", args.smoke)
    if out:
        write_text(out, report + "\n")


if __name__ == "__main__":
    main()
