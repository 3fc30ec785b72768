"""DVDs (trained) vs DVDs (untrained weights) vs Open3D ICP on the same deterministic ModelNet40 test pairs.

    python benchmarks/eval_modelnet40_dvds.py --ckpt runs/.../checkpoints/<best>.ckpt \
        --root ../shared/data/modelnet40_mini --out docs/results/modelnet40_dvds.md
    python benchmarks/eval_modelnet40_dvds.py --smoke    # seconds, synthetic pairs, untrained weights saved as --ckpt

Models: ``configs/dvds_modelnet40.yaml`` with the checkpoint's weights, and with the config's initialisation for each
``--init-seeds`` seed; Open3D point-to-point ICP (``configs/icp.yaml`` with the gate set to each ``--icp-distances``
value, 50 iterations).
Pairs: ModelNet40DataModule(protocol) test split, seed 1234 (the configs' default), 1024 points, Euler U[0, 45°],
t U[-0.5, 0.5], independent samplings; optional Gaussian noise (--noise-sigma, clip 0.05).
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

from lcreg.benchmarking import (
    add_smoke_argument,
    build,
    cli_args,
    machine_line,
    mean_std_row,
    output_path,
    pair_batches,
    report_table,
    save_weights,
    write_text,
)
from lcreg.evaluation import EvaluationReport, evaluate
from lcreg.models.base import RegistrationModule

SMOKE = {"num_points": 64, "batch_size": 2, "pairs": 2, "init_seeds": [0, 1], "icp_distances": [0.2]}


def icp(distance: float) -> RegistrationModule:
    """ICP from the identity, max correspondence distance ``distance`` (voxel = gate, factor 1), 50 iterations."""
    return build(
        "icp", overrides=cli_args("model", {"voxel_size": distance, "distance_factor": 1.0, "max_iterations": 50})
    )


def parse(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ckpt", default=None, help="trained DVDs checkpoint (chosen on validation); required")
    parser.add_argument("--root", default="../shared/data/modelnet40_mini")
    parser.add_argument("--protocol", default="unseen_objects", choices=["unseen_objects", "unseen_categories"])
    parser.add_argument("--num-points", type=int, default=1024)
    parser.add_argument("--noise-sigma", type=float, default=0.0)
    parser.add_argument("--batch-size", type=int, default=16)
    parser.add_argument(
        "--icp-distances",
        type=float,
        nargs="+",
        default=[0.2, 1.0],
        help="ICP max correspondence distances, declared in advance (not tuned on test): a tight gate and a gate "
        "covering the largest displacement of the protocol (|t| <= 0.87 plus a 45-degree rotation of the unit sphere)",
    )
    parser.add_argument("--seed", type=int, default=1234, help="seed of the deterministic test pairs (configs: 1234)")
    parser.add_argument(
        "--init-seeds",
        type=int,
        nargs="+",
        default=[0, 1, 2, 3, 4],
        help="initialisation seeds of the untrained-weights baseline (reported as mean ± std)",
    )
    parser.add_argument("--out", default=None, help="Markdown file to write the table to")
    add_smoke_argument(parser)
    args = parser.parse_args(argv)
    args.pairs = None
    if args.smoke:
        vars(args).update(SMOKE)
        args.root = None  # the embedded synthetic shapes
    args.out = output_path(args.out, "modelnet40_dvds.md", args.smoke)
    if args.smoke and not args.ckpt:
        args.ckpt = str(save_weights(build("dvds", overrides=["--seed_everything=99"]), args.out.with_suffix(".ckpt")))
    if not args.ckpt:
        parser.error("--ckpt is required (outside --smoke)")
    return args


def main(argv: Sequence[str] | None = None) -> None:
    args = parse(argv)
    options = {"protocol": args.protocol, "noise_sigma": args.noise_sigma, "seed": args.seed}
    batches, source = pair_batches(
        args.root, pairs=args.pairs, num_points=args.num_points, batch_size=args.batch_size, **options
    )
    untrained = [
        evaluate(build("dvds", overrides=[f"--seed_everything={s}"]), batches, f"DVDs (untrained weights, seed {s})")
        for s in args.init_seeds
    ]
    reports: list[EvaluationReport] = [
        evaluate(build("dvds", args.ckpt), batches, f"DVDs (trained, {Path(args.ckpt).name})"),
        *untrained,
        *(evaluate(icp(d), batches, f"Open3D ICP p2p (identity init, dist {d}, 50 it.)") for d in args.icp_distances),
    ]
    seeds = ", ".join(str(s) for s in args.init_seeds)
    table = report_table(reports) + "\n" + mean_std_row(untrained, f"DVDs untrained, mean ± std over seeds {seeds}")
    header = (
        f"{source}, {reports[0].num_pairs} test pairs, {args.num_points} points, noise sigma {args.noise_sigma}, "
        f"batch {args.batch_size}, {machine_line()}\n"
    )
    for r in reports:
        print(f"{r.name}: mean IC-LK/ICP iterations {r.extra['mean_iterations']:.2f}")
    print(header)
    print(table)
    if args.out:
        write_text(args.out, header + "\n" + table + "\n")


if __name__ == "__main__":
    main()
