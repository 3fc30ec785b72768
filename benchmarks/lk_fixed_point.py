"""Where an IC-LK model's solve settles when it starts exactly at the true pose (issue 23, goal (c)).

    python benchmarks/lk_fixed_point.py --ckpt src/lcreg/weights/dvds-modelnet40.pt \
        --out docs/results/converge/dvds_tw100_1024/test_fixed_point.md
    python benchmarks/lk_fixed_point.py --split val --val-pairs 4 --ckpt a.pt b.pt    # compare candidates
    python benchmarks/lk_fixed_point.py --smoke      # seconds, embedded shapes, untrained weights

For every checkpoint of ``--method`` (an IC-LK model: DVDs, PointNetLK) and every pair of the deterministic
ModelNet40 ``--split`` pairs (clean, independent samplings, ``--num-points``), two rows:

* *from the identity*: the model's own solve (``forward``, ``eval_iterations`` updates at most);
* *from the exact truth*: ``--iterations`` updates of the same solve started at each pair's ground-truth pose
  (:meth:`lcreg.nn.lk.InverseCompositionalLK.step_from`, the centring and Jacobian of the solve; no stopping rule).

Were the true pose a fixed point of the solve, the second row would stay at zero error. With two samplings of one
surface the descriptors differ at the true pose, so the solve walks away from it to the minimum of its residual: the
second row is that bias, which no start, iteration count or damping removes (only training moves it). The
``eval_modelnet40_dvds.py --from-truth`` rows differ in one respect: a centring solve started from a moved source
begins at the true rotation with the two centroids aligned, not at the exact true translation.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence

import numpy as np
import torch

from lcreg.experiments.benchmarking import (
    add_smoke_argument,
    apply_smoke,
    build,
    cli_args,
    key_values,
    machine_line,
    markdown_table,
    pair_batches,
)
from lcreg.experiments.benchmarking.writers import write_text
from lcreg.metrics.functional import rotation_error_deg, translation_error
from lcreg.models.base import RegistrationModule
from lcreg.types import RegistrationBatch

SMOKE = {"pairs": 4, "num_points": 64, "iterations": 3}


def from_truth(model: RegistrationModule, batch: RegistrationBatch, iterations: int) -> torch.Tensor:
    """``iterations`` updates of ``model``'s solve started at the batch's true poses, ``(B, 4, 4)``.

    Raises:
        TypeError: If ``model`` has no IC-LK ``step_from``.
        ValueError: If the batch has no ground truth.
    """
    step = getattr(model, "step_from", None)
    if step is None:
        raise TypeError(f"{type(model).__name__} has no IC-LK solve to step (`step_from`)")
    if batch.transform_ref_src is None:
        raise ValueError("the pairs have no ground truth")
    pose = batch.transform_ref_src
    for _ in range(iterations):
        pose = step(batch.points_src, batch.points_ref, pose)
    return pose


def errors(model: RegistrationModule, batches: Sequence[RegistrationBatch], iterations: int | None) -> np.ndarray:
    """Per pair ``(RRE °, RTE)`` ``(P, 2)``: the model's own solve (``iterations=None``) or from the exact truth."""
    rows = []
    with torch.no_grad():
        for batch in batches:
            if batch.transform_ref_src is None:
                raise ValueError("the pairs have no ground truth")
            if iterations is None:
                pose = model(batch.points_src, batch.points_ref).transform_ref_src
            else:
                pose = from_truth(model, batch, iterations)
            truth = batch.transform_ref_src
            rows.append(torch.stack([rotation_error_deg(pose, truth), translation_error(pose, truth)], dim=-1))
    return torch.cat(rows).double().numpy()


def row(label: str, start: str, found: np.ndarray) -> list[str]:
    """One table row: median and mean RRE, median RTE, recall (2°, 0.01)."""
    rre, rte = found[:, 0], found[:, 1]
    recall = 100 * float(((rre <= 2) & (rte <= 0.01)).mean())
    return [label, start, f"{np.median(rre):.4g}", f"{rre.mean():.4g}", f"{np.median(rte):.4g}", f"{recall:.1f} %"]


def parse(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ckpt", nargs="*", default=[], help="checkpoints of --method (none: --init-seeds only)")
    parser.add_argument("--method", default="dvds_selfsup", help="an IC-LK registry method (dvds_selfsup, pointnetlk)")
    parser.add_argument("--init-seeds", type=int, nargs="*", default=[], help="untrained rows, one per seed")
    parser.add_argument("--root", default="../shared/data/modelnet40_mini")
    parser.add_argument("--split", default="test", choices=["val", "test"])
    parser.add_argument("--val-pairs", type=int, default=1, help="validation pairs per validation object")
    parser.add_argument("--pairs", type=int, default=None, help="the first this many pairs (default: all)")
    parser.add_argument("--num-points", type=int, default=1024)
    parser.add_argument("--eval-iterations", type=int, default=40, help="the solve's iterations (shipped: 40)")
    parser.add_argument("--iterations", type=int, default=40, help="updates from the exact truth")
    parser.add_argument(
        "--model-args",
        nargs="*",
        default=[],
        metavar="NAME=VALUE",
        help="constructor arguments of --method that are not weights (pointnetlk's file: batch_norm=false "
        "jacobian=analytic)",
    )
    parser.add_argument("--out", default=None, help="Markdown file to write the table to")
    add_smoke_argument(parser)
    args = apply_smoke(parser.parse_args(argv), SMOKE)
    if args.smoke and not args.ckpt and not args.init_seeds:
        args.init_seeds = [0]
    if not args.ckpt and not args.init_seeds:
        parser.error("give --ckpt or --init-seeds")
    if min(args.iterations, args.eval_iterations) < 1:
        parser.error("--iterations and --eval-iterations must be >= 1")
    args.model_args = key_values(args.model_args, "--model-args")
    return args


def main(argv: Sequence[str] | None = None) -> str:
    args = parse(argv)
    options = {"protocol": "unseen_objects", "noise_sigma": 0.0, "seed": 1234}
    if args.root is not None:
        options["val_pairs_per_object"] = args.val_pairs
    batches, source = pair_batches(args.root, args.split, args.pairs, num_points=args.num_points, **options)
    settings = cli_args("model", {**args.model_args, "eval_iterations": args.eval_iterations})
    models = [(c.rsplit("/", 1)[-1], build(args.method, c, values=settings)) for c in args.ckpt]
    models += [
        (f"untrained, seed {s}", build(args.method, None, values={**settings, "seed_everything": s}))
        for s in args.init_seeds
    ]
    rows = []
    for label, model in models:
        model.eval()
        rows.append(row(label, f"identity ({args.eval_iterations} it. at most)", errors(model, batches, None)))
        rows.append(row(label, f"exact truth ({args.iterations} updates)", errors(model, batches, args.iterations)))
    header = ["weights", "start", "median RRE °", "mean RRE °", "median RTE", "recall (2°, 0.01)"]
    pairs = sum(len(b) for b in batches)
    head = f"{source}, {pairs} {args.split} pairs, {args.num_points} points, clean, {machine_line()}"
    text = f"{head}\n\n{markdown_table(header, rows)}\n"
    print(text)
    if args.out:
        write_text(args.out, text)
    return text


if __name__ == "__main__":
    main()
