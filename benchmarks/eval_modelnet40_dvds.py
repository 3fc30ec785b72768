"""A trained LK model (several seeds) vs the same network untrained vs baselines, on the same ModelNet40 test pairs.

    python benchmarks/eval_modelnet40_dvds.py --ckpt runs/.../checkpoints/<best>.ckpt \
        --root ../shared/data/modelnet40_mini --out docs/results/modelnet40_dvds.md
    python benchmarks/eval_modelnet40_dvds.py --method dvds_selfsup --ckpt s0.ckpt s1.ckpt s2.ckpt \
        --extra "paper D=dvds=d.ckpt" "PointNetLK=pointnetlk=p.ckpt" --classical ransac_icp --refine \
        --noise-sigma 0 0.01 --out docs/results/test_table.md      # issue 12's test table
    python benchmarks/eval_modelnet40_dvds.py --smoke    # seconds, synthetic pairs, untrained weights saved as --ckpt

Models: registry method ``--method`` (default ``dvds``: ``configs/dvds_modelnet40.yaml``) with each ``--ckpt``'s
weights (the seeds of one recipe, each chosen on validation: reported one by one and as mean ± std), and with the
config's initialisation for each ``--init-seeds`` seed (mean ± std); ``--extra`` rows (any registry method with a
checkpoint); Open3D point-to-point ICP (``configs/icp.yaml`` with the gate set to each ``--icp-distances`` value, 50
iterations) and any ``--classical`` registry method (e.g. ``ransac_icp``: FPFH + RANSAC + ICP). ``--refine`` adds
every learned row again with ICP refinement (``configs/refine/icp.yaml``). ``--model-args NAME=VALUE ...`` sets
constructor arguments of every learned row that are not weights (e.g. ``eval_iterations=2``); ``--split val`` runs
the same table on the validation pairs, to choose such settings before the one test run.
``--same-points`` draws both clouds from one sampling (the originals' PCRNet and PointNetLK protocol).
``--from-truth`` first moves every source by its ground truth (the true pose becomes the identity, where every solve
then starts): a row's errors are then where its objective's minimum lies near the truth, not whether the solve
finds it. ICP starts exactly at the true pose; a centring solve (the IC-LK models, iPCRNet) at the true rotation with
the two centroids aligned (the pair's centroid offset away); ``benchmarks/lk_fixed_point.py`` starts the IC-LK solve
at the exact true pose.
``--choose-starts A [A ...]`` (with ``--split val``) applies the rule that sets an IC-LK model's test-time starts
(:func:`lcreg.experiments.evaluation.choose_start_angle`): each checkpoint with one start and with starts at ±A° about
x, y and z for each A, and the setting with the lowest mean RRE (ties: one start, then the smaller angle); the test is
then run once with ``--model-args "eval_start_angles_deg=[A]"``. Only the trained rows are evaluated in this mode.
``--pairs-csv PATH`` also writes every row's per-pair errors (e.g. for an original's success-conditional means) and
each pair's centroid offset (the translation error of aligning the two centroids under the true rotation: what the
two samplings alone leave; 0 with ``--same-points`` and no noise).
Pairs: ModelNet40DataModule(protocol) ``--split`` split (default test), seed 1234 (the configs' default), 1024
points, Euler U[0, 45°], t U[-0.5, 0.5], independent samplings (unless ``--same-points``); one table per
``--noise-sigma`` (Gaussian, clip 0.05).
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import io
from collections.abc import Mapping, Sequence
from pathlib import Path

from lcreg.experiments.benchmarking import (
    add_smoke_argument,
    build,
    cli_args,
    key_values,
    machine_line,
    mean_std_row,
    output_path,
    pair_batches_and_classes,
    report_table,
    write_text,
)
from lcreg.experiments.benchmarking.registry import REFINE_CONFIG
from lcreg.experiments.evaluation import EvaluationReport, choose_start_angle, evaluate
from lcreg.geometry.se3 import identity, transform_normals, transform_points
from lcreg.models.base import RegistrationModule
from lcreg.types import RegistrationBatch
from lcreg.weights.export import save

SMOKE = {"num_points": 64, "batch_size": 2, "pairs": 2, "init_seeds": [0, 1], "icp_distances": [0.2], "refine": True}
PairColumns = dict[str, list[str]]
"""Per-pair columns of ``--pairs-csv`` beside the errors, by name: ``centroid_offset`` and ``class``."""


def icp(distance: float) -> RegistrationModule:
    """ICP from the identity, max correspondence distance ``distance`` (voxel = gate, factor 1), 50 iterations."""
    return build(
        "icp", values=cli_args("model", {"voxel_size": distance, "distance_factor": 1.0, "max_iterations": 50})
    )


def parse(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--ckpt",
        nargs="+",
        default=None,
        help="trained checkpoints of --method (one per seed, each chosen on validation); required",
    )
    parser.add_argument("--method", default="dvds", help="registry method the checkpoints and untrained rows build")
    parser.add_argument("--extra", nargs="*", default=[], help="more rows: LABEL=METHOD=CHECKPOINT")
    parser.add_argument("--classical", nargs="*", default=[], help="registry methods without weights (ransac_icp)")
    parser.add_argument("--refine", action="store_true", help="every learned row also with ICP refinement")
    parser.add_argument("--root", default="../shared/data/modelnet40_mini")
    parser.add_argument("--protocol", default="unseen_objects", choices=["unseen_objects", "unseen_categories"])
    parser.add_argument("--split", default="test", choices=["val", "test"], help="val: choose settings; test: report")
    parser.add_argument(
        "--val-pairs",
        type=int,
        default=1,
        help="pairs per validation object with --split val (4: the 312 pairs the converge budget validates on)",
    )
    parser.add_argument(
        "--model-args",
        nargs="*",
        default=[],
        metavar="NAME=VALUE",
        help="constructor arguments of every learned row, e.g. eval_iterations=5 (YAML values)",
    )
    parser.add_argument("--num-points", type=int, default=1024)
    parser.add_argument(
        "--same-points",
        action="store_true",
        help="both clouds from the same sampling of each shape (as PCRNet's and PointNetLK's originals test); "
        "default: independent samplings",
    )
    parser.add_argument(
        "--from-truth",
        action="store_true",
        help="move each source by its ground truth first: every solve starts at the true pose (a centring solve: the "
        "true rotation, centroids aligned)",
    )
    parser.add_argument("--noise-sigma", type=float, nargs="+", default=[0.0], help="one table per sigma")
    parser.add_argument("--batch-size", type=int, default=16)
    parser.add_argument(
        "--icp-distances",
        type=float,
        nargs="*",
        default=[0.2, 1.0],
        help="ICP max correspondence distances, declared in advance (not tuned on test): a tight gate and a gate "
        "covering the largest displacement of the protocol (|t| <= 0.87 plus a 45-degree rotation of the unit sphere)",
    )
    parser.add_argument("--seed", type=int, default=1234, help="seed of the deterministic test pairs (configs: 1234)")
    parser.add_argument(
        "--init-seeds",
        type=int,
        nargs="*",
        default=[0, 1, 2, 3, 4],
        help="initialisation seeds of the untrained-weights baseline (reported as mean ± std)",
    )
    parser.add_argument(
        "--choose-starts",
        type=float,
        nargs="+",
        default=None,
        metavar="DEG",
        help="with --split val: each checkpoint with one start and with starts at ±DEG, and the setting with the "
        "lowest mean RRE (ties: one start, then the smaller angle); only the trained rows",
    )
    parser.add_argument("--out", default=None, help="Markdown file to write the table to")
    parser.add_argument(
        "--pairs-csv",
        default=None,
        help="also write every row's per-pair errors (sigma, row, pair, rre_deg, rte, centroid_offset, class: the "
        "pair's object class, empty without labels) to this CSV file, e.g. for an original's success-conditional "
        "means or failures by class",
    )
    add_smoke_argument(parser)
    args = parser.parse_args(argv)
    args.pairs = None
    if args.smoke:
        vars(args).update(SMOKE)
        args.root = None  # the embedded synthetic shapes
    args.out = output_path(args.out, "modelnet40_dvds.md", args.smoke)
    if args.smoke and not args.ckpt:
        args.ckpt = [str(save(build("dvds", values={"seed_everything": 99}), args.out.with_suffix(".pt")))]
    if not args.ckpt:
        parser.error("--ckpt is required (outside --smoke)")
    args.model_args = key_values(args.model_args, "--model-args")
    if args.choose_starts is not None and args.split != "val":
        parser.error("--choose-starts chooses on validation pairs: add --split val (then test once with the choice)")
    if args.choose_starts is not None and "eval_start_angles_deg" in args.model_args:
        parser.error("--choose-starts sets eval_start_angles_deg itself: leave it out of --model-args")
    return args


def learned(
    method: str, checkpoint: str | None, seed: int | None, refine: bool, model_args: Mapping[str, str] | None = None
) -> RegistrationModule:
    """``method`` with a checkpoint's weights (or seeded untrained), optionally with ICP refinement.

    ``model_args`` (``{name: YAML text}``, typed as ``lcreg`` types its command line) override constructor
    arguments that are not weights, e.g. ``eval_iterations``.
    """
    configs = [REFINE_CONFIG] if refine else []
    seeded = {} if seed is None else {"seed_everything": seed}
    return build(method, checkpoint, configs=configs, values={**seeded, **cli_args("model", model_args or {})})


def evaluation_pairs(args: argparse.Namespace, sigma: float) -> tuple[list[RegistrationBatch], str, list[str] | None]:
    """The deterministic ``--split`` pairs at noise ``sigma``, a description of their source and every pair's class
    (``None`` without labels)."""
    options = {"protocol": args.protocol, "noise_sigma": sigma, "seed": args.seed}
    if args.same_points:
        options["independent_sampling"] = False
    if args.root is not None:  # the synthetic shapes have no validation objects to draw from
        options["val_pairs_per_object"] = args.val_pairs
    batches, source, classes = pair_batches_and_classes(
        args.root, args.split, args.pairs, num_points=args.num_points, batch_size=args.batch_size, **options
    )
    if args.from_truth:
        return [at_truth(batch) for batch in batches], f"{source}, each source moved to its true pose", classes
    return batches, source, classes


def at_truth(batch: RegistrationBatch) -> RegistrationBatch:
    """``batch`` with every source (and its normals) moved by its ground truth, whose transforms become the identity."""
    if batch.transform_ref_src is None:
        raise ValueError("--from-truth needs the pairs' ground-truth transforms")
    truth = batch.transform_ref_src
    normals = None if batch.normals_src is None else transform_normals(truth, batch.normals_src)
    return dataclasses.replace(
        batch,
        points_src=transform_points(truth, batch.points_src),
        normals_src=normals,
        transform_ref_src=identity(len(batch), truth.device, truth.dtype),
    )


def centroid_offsets(batches: Sequence[RegistrationBatch]) -> list[float]:
    """Per pair ``‖c_ref − (R c_src + t)‖`` (cloud units): how far the true transform leaves the source's centroid from
    the reference's, i.e. the translation error of a solve that aligns centroids under the true rotation."""
    offsets: list[float] = []
    for batch in batches:
        if batch.transform_ref_src is None:
            raise ValueError("centroid offsets need the pairs' ground-truth transforms")
        moved = transform_points(batch.transform_ref_src, batch.points_src.mean(dim=1, keepdim=True))  # (B, 1, 3)
        offsets += (batch.points_ref.mean(dim=1, keepdim=True) - moved).norm(dim=-1)[:, 0].tolist()
    return offsets


def table(args: argparse.Namespace, sigma: float) -> tuple[str, list[EvaluationReport], PairColumns]:
    """The Markdown table (rows, then mean ± std rows) at noise ``sigma``, its rows' reports and the pairs' own
    columns: centroid offset (:func:`centroid_offsets`) and class."""
    batches, source, classes = evaluation_pairs(args, sigma)
    reports: list[EvaluationReport] = []
    groups: list[tuple[list[EvaluationReport], str]] = []
    for refine in (False, True) if args.refine else (False,):
        tag = " + ICP" if refine else ""
        trained = [
            evaluate(
                learned(args.method, c, None, refine, args.model_args),
                batches,
                f"{args.method} (trained, {Path(c).name}){tag}",
            )
            for c in args.ckpt
        ]
        untrained = [
            evaluate(
                learned(args.method, None, s, refine, args.model_args),
                batches,
                f"{args.method} (untrained, seed {s}){tag}",
            )
            for s in args.init_seeds
        ]
        for spec in args.extra:
            label, method, ckpt = spec.split("=", 2)
            reports.append(evaluate(learned(method, ckpt, None, refine, args.model_args), batches, f"{label}{tag}"))
        reports += [*trained, *untrained]
        seeds = ", ".join(str(s) for s in args.init_seeds)
        groups += [(trained, f"{args.method} trained{tag}, mean ± std over {len(trained)} checkpoint(s)")]
        groups += [(untrained, f"{args.method} untrained{tag}, mean ± std over seeds {seeds}")]
    reports += [
        evaluate(icp(d), batches, f"Open3D ICP p2p (identity init, dist {d}, 50 it.)") for d in args.icp_distances
    ]
    reports += [evaluate(build(name), batches, name) for name in args.classical]
    rows = report_table(reports) + "\n" + "\n".join(mean_std_row(g, label) for g, label in groups if g)
    return _header(args, source, reports, sigma) + "\n" + rows + "\n", reports, _pair_columns(batches, classes)


def starts_table(args: argparse.Namespace, sigma: float) -> tuple[str, list[EvaluationReport], PairColumns]:
    """``--choose-starts``: every checkpoint with one start and with each ``--choose-starts`` angle, and the setting
    :func:`~lcreg.experiments.evaluation.choose_start_angle` picks for it (as :func:`table` returns its results)."""
    batches, source, classes = evaluation_pairs(args, sigma)
    reports: list[EvaluationReport] = []
    chosen: list[str] = []
    for checkpoint in args.ckpt:
        mean_rre: dict[float | None, float] = {}
        for angle in (None, *args.choose_starts):
            starts = "one start" if angle is None else f"starts ±{angle:g}°"
            values = {**args.model_args, "eval_start_angles_deg": "[]" if angle is None else f"[{angle:g}]"}
            model = learned(args.method, checkpoint, None, False, values)
            reports.append(evaluate(model, batches, f"{args.method} ({Path(checkpoint).name}), {starts}"))
            mean_rre[angle] = reports[-1].metrics["rre_mean_deg"]
        best = choose_start_angle(mean_rre)
        setting = "one start" if best is None else f"`eval_start_angles_deg=[{best:g}]`"
        chosen.append(f"- {Path(checkpoint).name}: {setting} (mean RRE {mean_rre[best]:.4g}°)")
    rule = "Chosen by the lowest mean RRE (ties: one start, then the smaller angle):"
    text = f"{report_table(reports)}\n\n{rule}\n\n" + "\n".join(chosen) + "\n"
    return _header(args, source, reports, sigma) + "\n" + text, reports, _pair_columns(batches, classes)


def _header(args: argparse.Namespace, source: str, reports: Sequence[EvaluationReport], sigma: float) -> str:
    """The line above a table: the pairs and the machine; prints every row's mean solver iterations."""
    for r in reports:
        print(f"{r.name}: mean IC-LK/ICP iterations {r.extra['mean_iterations']:.2f}", flush=True)
    return (
        f"{source}, {reports[0].num_pairs} {args.split} pairs, {args.num_points} points, noise sigma {sigma}, "
        f"batch {args.batch_size}, {machine_line()}\n"
    )


def _pair_columns(batches: Sequence[RegistrationBatch], classes: list[str] | None) -> PairColumns:
    """The pairs' own columns of ``--pairs-csv``: centroid offset (:func:`centroid_offsets`) and class."""
    offsets = [f"{c:.6g}" for c in centroid_offsets(batches)]
    return {"centroid_offset": offsets, "class": classes or [""] * len(offsets)}


def write_pairs_csv(path: str | Path, tables: Sequence[tuple[float, list[EvaluationReport], PairColumns]]) -> Path:
    """Every report's per-pair rotation (degrees) and translation errors and the pair's own columns
    (:data:`PairColumns`), one line per pair, under ``sigma,row``."""
    text = io.StringIO()
    writer = csv.writer(text, lineterminator="\n")
    names = list(tables[0][2]) if tables else []
    writer.writerow(["sigma", "row", "pair", "rre_deg", "rte", *names])
    for sigma, reports, columns in tables:
        per_pair = list(zip(*(columns[name] for name in names), strict=True))
        for report in reports:
            errors = zip(report.rotation_error_deg.tolist(), report.translation_error.tolist(), per_pair, strict=True)
            writer.writerows(
                [sigma, report.name, i, f"{r:.6g}", f"{t:.6g}", *own] for i, (r, t, own) in enumerate(errors)
            )
    return write_text(path, text.getvalue())


def main(argv: Sequence[str] | None = None) -> None:
    args = parse(argv)
    make = table if args.choose_starts is None else starts_table
    tables = {sigma: make(args, sigma) for sigma in args.noise_sigma}
    text = "\n".join(markdown for markdown, _, _ in tables.values())
    print(text)
    if args.out:
        write_text(args.out, text)
    if args.pairs_csv:
        rows = [(sigma, reports, columns) for sigma, (_, reports, columns) in tables.items()]
        print(f"wrote {write_pairs_csv(args.pairs_csv, rows)}")


if __name__ == "__main__":
    main()
