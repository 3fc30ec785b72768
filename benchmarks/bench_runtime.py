"""The paper's runtime table (ms per pair at 500, 1000 and 2000 points) for every method, in one run.

    python benchmarks/bench_runtime.py [--device cpu|cuda] [--pairs 8] [--repeats 3] [--ckpt dvds=path ...]

Methods: DVDs, PointNetLK, FMR-Net, PCRNet, DCP-v2 (learned; ``--device``) and Open3D ICP (point-to-point), FPFH +
FGR, FPFH + RANSAC (always CPU, as in the paper), each built from its config in ``configs/`` at the original sizes.
Pairs: the deterministic ModelNet40 test pairs (``--root``, unseen objects) when the data is present, else the
embedded synthetic shapes; one pair at a time (batch 1), median over ``--repeats`` timed passes after a warm-up.
Weights: random unless ``--ckpt key=path`` is given; the LK models' iteration counts (and so their time) depend on
the weights, so the mean number of iterations is printed beside each figure. Ratios are against DVDs in the same
process. The paper's figures (Titan Xp + E5-2620): DVDs 66/68/69, ICP 7/16/35, DCP 6/9/20, PointNetLK 70/73/75,
FMR-Net 68/70/72, PCRNet 14/16/18, FGR 143/172/232, RANSAC 18/48/110.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time
from pathlib import Path
from typing import Any

import torch
from bench_dvds import pairs

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
METHODS = {
    "dvds": ("DVDs", "dvds_modelnet40.yaml", True),
    "pointnetlk": ("PointNetLK", "pointnetlk.yaml", True),
    "fmr": ("FMR-Net", "fmr.yaml", True),
    "pcrnet": ("PCRNet", "pcrnet.yaml", True),
    "dcp": ("DCP-v2", "dcp.yaml", True),
    "icp": ("ICP (Open3D, CPU)", "icp.yaml", False),
    "fgr": ("FGR (Open3D, CPU)", "fgr.yaml", False),
    "ransac": ("RANSAC (Open3D, CPU)", "ransac.yaml", False),
}
PAPER = {
    "dvds": (66, 68, 69),
    "icp": (7, 16, 35),
    "dcp": (6, 9, 20),
    "pointnetlk": (70, 73, 75),
    "fmr": (68, 70, 72),
    "pcrnet": (14, 16, 18),
    "fgr": (143, 172, 232),
    "ransac": (18, 48, 110),
}
SIZES = (500, 1000, 2000)


def build(key: str, ckpt: str | None, device: str) -> Any:
    """The model of ``configs/<method>.yaml`` (checkpoint weights if given) on ``device`` in eval mode."""
    from lcreg.cli import build_cli

    model = build_cli(["--config", str(CONFIGS / METHODS[key][1])], run=False).model
    if ckpt:
        model = model.load_weights(ckpt)
    return model.to(device if METHODS[key][2] else "cpu").eval()


def time_pairs(model: Any, src: torch.Tensor, ref: torch.Tensor, repeats: int) -> tuple[float, float]:
    """Median ms/pair over ``repeats`` passes (one pair at a time, after one warm-up pass) and mean iterations."""
    params = list(model.parameters())
    device = params[0].device if params else torch.device("cpu")
    src, ref = src.to(device), ref.to(device)
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    runs, iters = [], []
    for r in range(repeats + 1):
        sync()
        start = time.perf_counter()
        for i in range(len(src)):
            result = model.register(src[i : i + 1], ref[i : i + 1])
            if r == 0:
                iters.append(float(result.num_iters.float().mean()))
        sync()
        if r > 0:
            runs.append(1000 * (time.perf_counter() - start) / len(src))
    return statistics.median(runs), statistics.mean(iters)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--root", default="../shared/data/modelnet40_mini")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--pairs", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--methods", nargs="*", default=list(METHODS))
    parser.add_argument("--ckpt", nargs="*", default=[], help="key=path")
    args = parser.parse_args()
    ckpts = dict(item.split("=", 1) for item in args.ckpt)

    torch.manual_seed(0)
    data = {n: pairs(n, args.pairs, args.root) for n in SIZES}
    print(
        f"device {args.device} ({torch.cuda.get_device_name() if args.device == 'cuda' else platform.processor()}), "
        f"torch {torch.__version__}, {torch.get_num_threads()} threads, {args.pairs} pairs per size, batch 1, "
        f"median of {args.repeats} passes; pairs from {data[SIZES[0]][1]}"
    )
    results: dict[str, list[tuple[float, float]]] = {}
    for key in args.methods:
        model = build(key, ckpts.get(key), args.device)
        with torch.no_grad():
            results[key] = [time_pairs(model, b.points_src, b.points_ref, args.repeats) for b, _ in data.values()]
        print(f"{key}: " + ", ".join(f"{ms:.1f} ms ({it:.1f} it.)" for ms, it in results[key]), flush=True)
    head = " | ".join(f"{n} pts ms/pair" for n in SIZES)
    print(f"\n| method | {head} | ratio to DVDs ({'/'.join(map(str, SIZES))}) | mean iterations | paper (ms) |")
    print("|---" * 7 + "|")
    ref = results.get("dvds")
    for key, values in results.items():
        ms = " | ".join(f"{v[0]:.1f}" for v in values)
        ratio = "/".join(f"{v[0] / r[0]:.2f}" for v, r in zip(values, ref)) if ref else "n/a"
        iters = "/".join(f"{v[1]:.1f}" for v in values)
        paper = "/".join(map(str, PAPER[key])) if key in PAPER else ""
        print(f"| {METHODS[key][0]} | {ms} | {ratio} | {iters} | {paper} |")


if __name__ == "__main__":
    main()
