"""What ``--trainer.precision bf16-mixed`` buys each learned model: its training step in float32 and under bfloat16
autocast, in one process.

    python benchmarks/bench_precision.py [--root ../shared/data/modelnet40_mini] [--device cpu|cuda] [--threads 1]
    python benchmarks/bench_precision.py --skip-steps --eval-weights W.pt [--eval-method idam] [--eval-partial prnet]
    python benchmarks/bench_precision.py --smoke     # seconds, embedded synthetic pairs (checks the script runs)

For every learned method at the size the ``converge`` budget trains it (``SIZES``; DVDs: the self-motion recipe),
two copies of the same initial weights train on the same batch of real ModelNet40 test pairs (synthetic shapes
without the data), one step in float32 and one under autocast, alternated after a warm-up round so that drifts
cancel; the table gives the median step times, their ratio, and the two copies' first training losses (the same
weights and batch: how far bfloat16 moves the objective before any training diverges them). Under autocast the
networks run in bfloat16 and the geometry, the IC-LK solves and the metrics in float32
(:mod:`lcreg.geometry.precision`), so the IC-LK models gain only in their passes outside the solve. Whether
training in bfloat16 reaches the same accuracy is a question of whole runs, not of this script.

``--eval-weights``: inference only. Weights trained in float32 register the test pairs of the DCP-family protocol
(the same points in both clouds, independent noise sigma 0.01 clipped at 0.05; ``--eval-partial prnet`` crops both
clouds to ``--eval-keep`` of their points as PRNet and IDAM do) in float32 and under bfloat16 autocast, with the same
weights, pairs and seed; the table gives the errors of both and how many pairs moved by more than 1 degree.
"""

from __future__ import annotations

import argparse
import copy
from collections.abc import Callable, Sequence

import torch
from lightning.fabric.utilities.apply_func import move_data_to_device

from lcreg.experiments.benchmarking import (
    METHODS,
    add_smoke_argument,
    apply_smoke,
    build,
    machine_line,
    markdown_table,
    output_path,
    pair_batches,
    time_calls,
    training_loss,
    write_text,
)
from lcreg.metrics.functional import euler_errors_deg, rotation_error_deg, translation_error
from lcreg.models.base import RegistrationModule
from lcreg.types import RegistrationBatch

# (method, pairs per batch, points per cloud) as the converge budget trains them (docs/reproducing.md, "converge")
SIZES: tuple[tuple[str, int, int], ...] = (
    ("dcp", 8, 256),
    ("prnet", 8, 256),
    ("idam", 8, 512),
    ("deepgmr", 8, 512),
    ("dvds_selfsup", 16, 512),
    ("pointnetlk", 16, 1024),
    ("fmr", 16, 1024),
    ("pcrnet", 16, 1024),
)
SMOKE = {"methods": ["dcp", "dvds_selfsup"], "batch": 2, "points": 64, "repeats": 1, "eval_points": 64, "eval_pairs": 4}
DCP_FAMILY_PAIRS: dict[str, object] = {"independent_sampling": False, "noise_sigma": 0.01, "noise_clip": 0.05}


def step_function(
    model: RegistrationModule, batch: RegistrationBatch, device: str, autocast: bool, losses: list[float]
) -> Callable[[], None]:
    """One Adam step of ``model`` on ``batch`` (under bfloat16 autocast when asked), recording each loss."""
    opt = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=1e-4)

    def step() -> None:
        opt.zero_grad()
        with torch.autocast(torch.device(device).type, dtype=torch.bfloat16, enabled=autocast):
            loss = training_loss(model, batch)["loss"]
        loss.backward()
        opt.step()
        losses.append(loss.item())

    return step


def method_row(name: str, batch_size: int, points: int, args: argparse.Namespace) -> list[object]:
    """Median float32 and bfloat16 step times of one method, their ratio and the first losses."""
    batches, _ = pair_batches(args.root, pairs=batch_size, num_points=points, batch_size=batch_size)
    batch = move_data_to_device(batches[0], args.device)
    model = build(name, values={"seed_everything": 0}).to(args.device).train()
    losses: dict[str, list[float]] = {"float32": [], "bf16": []}
    steps = {
        "float32": step_function(model, batch, args.device, False, losses["float32"]),
        "bf16": step_function(copy.deepcopy(model), batch, args.device, True, losses["bf16"]),
    }
    timings = time_calls(steps, args.repeats, warmup=1, device=args.device)
    t32, t16 = timings["float32"].median_s, timings["bf16"].median_s
    first32, first16 = losses["float32"][0], losses["bf16"][0]
    return [
        METHODS[name].label,
        f"{batch_size} x {points}",
        f"{t32:.2f}",
        f"{t16:.2f}",
        f"{t32 / t16:.2f}x",
        f"{first32:.5g} / {first16:.5g} ({100 * (first16 / first32 - 1):+.2f} %)",
    ]


def registration_errors(
    model: RegistrationModule, batches: Sequence[RegistrationBatch], autocast: bool
) -> dict[str, torch.Tensor]:
    """Per-pair RRE (degrees), RTE and Euler errors ``(P, 3)`` of ``model`` on ``batches``, with or without autocast."""
    parts: dict[str, list[torch.Tensor]] = {"rre": [], "rte": [], "euler": []}
    torch.manual_seed(0)  # models that sample (PRNet's Gumbel) draw the same numbers in both precisions
    device = next(iter(model.parameters())).device
    with torch.no_grad(), torch.autocast(device.type, dtype=torch.bfloat16, enabled=autocast):
        for batch in batches:
            batch = move_data_to_device(batch, device)
            pred, gt = model.register(batch.points_src, batch.points_ref).transform_ref_src, batch.transform_ref_src
            parts["rre"].append(rotation_error_deg(pred, gt).cpu())
            parts["rte"].append(translation_error(pred, gt).cpu())
            parts["euler"].append(euler_errors_deg(pred, gt).cpu())
    return {k: torch.cat(v) for k, v in parts.items()}


def inference_table(args: argparse.Namespace) -> str:
    """The same float32-trained weights on the same test pairs in float32 and under bfloat16 autocast."""
    weights = None if args.smoke else args.eval_weights
    model = build(args.eval_method, checkpoint=weights, values={"seed_everything": 0}).to(args.device).eval()
    crop: dict[str, object] = {}
    if args.eval_partial != "none":
        crop = {"partial": args.eval_partial, "partial_keep": args.eval_keep}
    batches, source = pair_batches(
        args.root, "test", args.eval_pairs, args.eval_points, 41, "unseen_objects", **DCP_FAMILY_PAIRS, **crop
    )  # the DCP-family pairs of data/dcp_protocol.yaml
    errors = {name: registration_errors(model, batches, name == "bf16") for name in ("float32", "bf16")}
    rows = [
        [
            name,
            len(e["rre"]),
            f"{e['euler'].square().mean().sqrt():.3f}",
            f"{e['euler'].abs().mean():.3f}",
            f"{e['rre'].mean():.3f}",
            f"{e['rre'].median():.3f}",
            f"{e['rte'].mean():.4f}",
        ]
        for name, e in errors.items()
    ]
    moved = int(((errors["bf16"]["rre"] - errors["float32"]["rre"]).abs() > 1.0).sum())
    header = ["precision", "pairs", "RMSE(R) deg", "MAE(R) deg", "mean RRE deg", "median RRE deg", "mean RTE"]
    title = f"inference of {args.eval_method} weights {weights} ({source}, {args.eval_points} points"
    title += f", crop {crop or 'none'})"
    return f"{title}:\n\n{markdown_table(header, rows)}\n\npairs whose RRE moved by more than 1 deg: {moved}\n"


def parse(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--root", default="../shared/data/modelnet40_mini")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (the queue's runs use one)")
    parser.add_argument("--methods", nargs="+", default=[name for name, _, _ in SIZES], choices=[n for n, *_ in SIZES])
    parser.add_argument("--repeats", type=int, default=3, help="timed rounds per method (after one warm-up round)")
    parser.add_argument("--skip-steps", action="store_true", help="only the inference part (--eval-weights)")
    parser.add_argument("--eval-weights", default=None, help="float32-trained weights to test in both precisions")
    parser.add_argument("--eval-method", default="idam", help="the method the weights belong to")
    parser.add_argument("--eval-points", type=int, default=512)
    parser.add_argument("--eval-partial", default="none", choices=["none", "prnet"])
    parser.add_argument("--eval-keep", type=float, default=0.75, help="fraction of the points a crop keeps")
    parser.add_argument("--eval-pairs", type=int, default=None, help="first pairs only (default: all 164)")
    parser.add_argument("--out", default=None, help="also write the report (Markdown) here")
    add_smoke_argument(parser)
    args = parser.parse_args(argv)
    args.batch = args.points = None
    return apply_smoke(args, SMOKE)


def main(argv: Sequence[str] | None = None) -> None:
    args = parse(argv)
    torch.set_num_threads(args.threads)
    head = f"device {args.device}: {machine_line(args.device)}, median of {args.repeats} alternated steps"
    print(head, flush=True)
    header = ["method", "batch x points", "float32 s/step", "bf16 s/step", "speed-up", "first loss float32 / bf16"]
    rows = []
    for name, batch_size, points in SIZES:
        if name in args.methods and not args.skip_steps:
            rows.append(method_row(name, args.batch or batch_size, args.points or points, args))
            print(" | ".join(str(c) for c in rows[-1]), flush=True)
    source = "embedded synthetic shapes" if args.root is None else f"{args.root}, test split"
    report = f"{head}; pairs from {source}\n\n{markdown_table(header, rows)}\n"
    if args.eval_weights or args.smoke:
        table = inference_table(args)
        print(table, flush=True)
        report += "\n" + table
    out = output_path(args.out, "bench_precision.md", args.smoke)
    if out:
        write_text(out, report)


if __name__ == "__main__":
    main()
