"""DVDs inference speed and training-step memory, beside Open3D ICP in the same process.

    python benchmarks/bench_dvds.py [--ckpt CKPT] [--root ../shared/data/modelnet40_mini] [--device cpu|cuda]

* ms/pair of DVDs registration (IC-LK, T = 10, analytic Jacobian) at 500/1000/2000 points, batch 1 and batch 16,
  on real ModelNet40 test objects (the unseen-objects pairs) when the data is present, otherwise on the embedded
  synthetic shapes; Open3D point-to-point ICP (CPU, one pair at a time) on the same pairs;
* ratio DVDs / ICP at batch 1;
* peak memory of one DVDs training step (batch 32, 1024 points): peak RSS increase on CPU (a fresh subprocess),
  ``torch.cuda.max_memory_allocated`` on a GPU.

The paper's reference (Titan Xp): DVDs 66/68/69 ms and ICP 7/16/35 ms at 500/1000/2000 points.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import torch
from lightning.fabric.utilities.apply_func import move_data_to_device

from lcreg.baselines.classical import ICP
from lcreg.data.datamodule import ModelNet40DataModule, SyntheticDataModule
from lcreg.models.dvds import DVDs
from lcreg.types import RegistrationBatch


def pairs(num_points: int, count: int, root: str | None) -> tuple[RegistrationBatch, str]:
    """``count`` deterministic test pairs with ``num_points`` points."""
    if root and Path(root).is_dir():
        dm: ModelNet40DataModule | SyntheticDataModule = ModelNet40DataModule(
            root=root, num_points=num_points, batch_size=count
        )
        source = f"ModelNet40 {root} (unseen objects test pairs)"
    else:
        dm = SyntheticDataModule(num_points=num_points, batch_size=count, num_test=count)
        source = "embedded synthetic shapes"
    dm.setup("test")
    return next(iter(dm.test_dataloader())), source


def time_model(model: torch.nn.Module, batch: RegistrationBatch, batch_size: int, device: str, repeats: int) -> float:
    """Median over ``repeats`` of the ms/pair to register all pairs in chunks of ``batch_size``."""
    src, ref = batch.points_src.to(device), batch.points_ref.to(device)
    runs = []
    for _ in range(repeats + 1):  # first run is warm-up
        if device == "cuda":
            torch.cuda.synchronize()
        start = time.perf_counter()
        for i in range(0, len(src), batch_size):
            model.register(src[i : i + batch_size], ref[i : i + batch_size])
        if device == "cuda":
            torch.cuda.synchronize()
        runs.append(1000 * (time.perf_counter() - start) / len(src))
    return sorted(runs[1:])[len(runs[1:]) // 2]


def train_step_memory(device: str, batch_size: int = 32, num_points: int = 1024) -> dict[str, float]:
    """Peak memory of one forward+backward DVDs training step (run in this process)."""
    model = DVDs().to(device).train()
    dm = SyntheticDataModule(num_points=num_points, batch_size=batch_size, num_train=batch_size)
    dm.setup("fit")
    batch = move_data_to_device(next(iter(dm.train_dataloader())), device)
    batch.transform_ref_src = None  # self-supervised: the training step never sees the pose
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    if device == "cuda":
        torch.cuda.reset_peak_memory_stats()
    start = time.perf_counter()
    loss = model.compute_loss(model(batch.points_src, batch.points_ref), batch)["loss"]
    loss.backward()
    seconds = time.perf_counter() - start
    out = {
        "step_s": seconds,
        "rss_before_mb": before,
        "rss_peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }
    if device == "cuda":
        out["cuda_peak_mb"] = torch.cuda.max_memory_allocated() / 2**20
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ckpt", default=None, help="DVDs checkpoint (speed does not depend on the weights)")
    parser.add_argument("--root", default="../shared/data/modelnet40_mini")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--pairs", type=int, default=32)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--memory-only", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.memory_only:
        print(json.dumps(train_step_memory(args.device)))
        return

    torch.manual_seed(0)
    dvds = (DVDs.load_from_checkpoint(args.ckpt, map_location=args.device) if args.ckpt else DVDs()).to(args.device)
    icp = ICP(voxel_size=0.05, distance_factor=4.0, method="point_to_point")  # gate 0.2
    print(
        f"device {args.device}, torch threads {torch.get_num_threads()}, {args.pairs} pairs per size, "
        f"median of {args.repeats} runs"
    )
    print("| points | DVDs b=1 ms/pair | DVDs b=16 ms/pair | ICP ms/pair | DVDs/ICP (b=1) |")
    print("|---|---|---|---|---|")
    for n in (500, 1000, 2000):
        batch, source = pairs(n, args.pairs, args.root)
        d1 = time_model(dvds, batch, 1, args.device, args.repeats)
        d16 = time_model(dvds, batch, 16, args.device, args.repeats)
        ti = time_model(icp, batch, 1, "cpu", args.repeats)
        print(f"| {n} | {d1:.1f} | {d16:.1f} | {ti:.1f} | {d1 / ti:.2f} |")
    print(f"pairs from: {source}")
    # Memory in a fresh process so the peak RSS belongs to the training step alone.
    cmd = [sys.executable, __file__, "--memory-only", "--device", args.device]
    mem = json.loads(subprocess.run(cmd, check=True, capture_output=True, text=True).stdout.strip().splitlines()[-1])
    line = (
        f"training step, batch 32 x 1024 points: {mem['step_s']:.2f} s, peak RSS {mem['rss_peak_mb']:.0f} MB "
        f"(+{mem['rss_peak_mb'] - mem['rss_before_mb']:.0f} MB over the process before the step)"
    )
    if "cuda_peak_mb" in mem:
        line += f", CUDA peak allocated {mem['cuda_peak_mb']:.0f} MB"
    print(line)


if __name__ == "__main__":
    main()
