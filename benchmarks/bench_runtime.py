"""The paper's runtime table (ms per pair at 500, 1000 and 2000 points) for every method, in one run.

    python benchmarks/bench_runtime.py [--device cpu|cuda] [--pairs 8] [--repeats 3] [--ckpt dvds=path ...]
    python benchmarks/bench_runtime.py --smoke       # seconds, embedded synthetic pairs (checks the script runs)

Methods: DVDs, PointNetLK, FMR-Net, PCRNet, DCP-v2 (learned; ``--device``) and Open3D ICP (point-to-point), FPFH +
FGR, FPFH + RANSAC (always CPU, as in the paper), each built from its config in ``configs/`` at the original sizes.
Pairs: the deterministic ModelNet40 test pairs (``--root``, unseen objects) when the data is present, else the
embedded synthetic shapes; one pair at a time (batch 1), median over ``--repeats`` timed passes after a warm-up
(synchronised on CUDA).
Weights: random unless ``--ckpt key=path`` is given; the LK models' iteration counts (and so their time) depend on
the weights, so the mean number of iterations is printed beside each figure. Ratios are against DVDs in the same
process. The paper's figures (Titan Xp + E5-2620) are ``lcreg.experiments.reproduce.paper.RUNTIME_MS``; ``lcreg
reproduce runtime`` runs the same measurement over seeds with a report and a figure.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence

import torch

from lcreg.experiments.benchmarking import (
    METHODS,
    RegistrationSpeed,
    add_smoke_argument,
    apply_smoke,
    build,
    key_values,
    machine_line,
    markdown_table,
    output_path,
    pair_batches,
    registration_speed,
    write_text,
)
from lcreg.experiments.reproduce.paper import RUNTIME_MS, RUNTIME_POINTS

DEFAULT_METHODS = ["dvds", "pointnetlk", "fmr", "pcrnet", "dcp", "icp", "fgr", "ransac"]
PAPER = RUNTIME_MS
SIZES = RUNTIME_POINTS
SMOKE = {"sizes": (64,), "pairs": 2, "repeats": 1}


def label(key: str) -> str:
    """The method's label; Open3D methods are marked as CPU."""
    return METHODS[key].label + ("" if METHODS[key].learned else " (Open3D, CPU)")


def measure(key: str, ckpt: str | None, data: dict[int, Sequence[torch.Tensor]], args: argparse.Namespace) -> list:
    """Speed of one method at every size (learned methods on ``--device``, Open3D ones on the CPU)."""
    model = build(key, ckpt).to(args.device if METHODS[key].learned else "cpu")
    return [registration_speed(model, src, ref, 1, args.repeats) for src, ref in data.values()]


def row(key: str, values: list[RegistrationSpeed], ref: list[RegistrationSpeed] | None) -> list[object]:
    """Table row: ms/pair per size, ratio to DVDs, mean iterations, the paper's figures."""
    ratio = "/".join(f"{v.ms_per_pair / r.ms_per_pair:.2f}" for v, r in zip(values, ref)) if ref else "n/a"
    return [
        label(key),
        *(f"{v.ms_per_pair:.1f}" for v in values),
        ratio,
        "/".join(f"{v.mean_iterations:.1f}" for v in values),
        "/".join(map(str, PAPER.get(key, ()))),
    ]


def parse(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--root", default="../shared/data/modelnet40_mini")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--pairs", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--methods", nargs="*", default=DEFAULT_METHODS, choices=list(METHODS))
    parser.add_argument("--ckpt", nargs="*", default=[], help="key=path")
    parser.add_argument("--out", default=None, help="also write the table (Markdown) here")
    add_smoke_argument(parser)
    args = parser.parse_args(argv)
    args.sizes = SIZES
    return apply_smoke(args, SMOKE)


def main(argv: Sequence[str] | None = None) -> None:
    args = parse(argv)
    ckpts = key_values(args.ckpt, "--ckpt")
    data, source = {}, ""
    for n in args.sizes:
        batches, source = pair_batches(args.root, pairs=args.pairs, num_points=n, batch_size=args.pairs)
        data[n] = (batches[0].points_src, batches[0].points_ref)
    head = (
        f"device {args.device}: {machine_line(args.device)}, {args.pairs} pairs per size, batch 1, median of "
        f"{args.repeats} passes; pairs from {source}"
    )
    print(head, flush=True)
    results = {}
    for key in args.methods:
        with torch.no_grad():
            results[key] = measure(key, ckpts.get(key), data, args)
        print(f"{key}: " + ", ".join(f"{v.ms_per_pair:.1f} ms ({v.mean_iterations:.1f} it.)" for v in results[key]))
    sizes = "/".join(map(str, args.sizes))
    header = ["method", *(f"{n} pts ms/pair" for n in args.sizes), f"ratio to DVDs ({sizes})", "mean iterations"]
    table = markdown_table([*header, "paper (ms)"], [row(k, v, results.get("dvds")) for k, v in results.items()])
    print(f"\n{table}")
    out = output_path(args.out, "bench_runtime.md", args.smoke)
    if out:
        write_text(out, f"{head}\n\n{table}\n")


if __name__ == "__main__":
    main()
