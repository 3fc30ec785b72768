"""Every registration method on the same deterministic ModelNet40 test pairs, clean and noisy: one table.

    python benchmarks/compare_methods.py --out docs/results/compare_methods.md \
        --ckpt dvds=runs/.../best.ckpt --ckpt dcp=runs/.../best.ckpt \
        --train pointnetlk=200,512,16 --train pcrnet=300,512,20 --train fmr=300,512,8
    python benchmarks/compare_methods.py --smoke     # seconds: trains DVDs 2 steps on synthetic pairs, 3 rows

* Learned methods (DVDs, PointNetLK, PCRNet, FMR-Net, DCP, PRNet, IDAM, DeepGMR) are built from their config in
  ``configs/`` and need weights: ``--ckpt key=path`` (a checkpoint chosen on validation), or ``--train
  key=steps,points,batch`` trains one here (``lcreg fit`` on the config with that budget, seed 0, validation
  every quarter of the run, the checkpoint with the lowest ``val/rre_mean_deg``: never the test set). A learned
  method with neither is listed as not evaluated.
* Classical methods (Open3D ICP point-to-point / point-to-plane, FPFH + RANSAC, FPFH + FGR) run with the parameters
  of their configs; ``+ ICP`` rows add ``configs/refine/icp.yaml`` (the same mechanism as ``lcreg test --config
  <x>.yaml --config configs/refine/icp.yaml``).
* Pairs: ``ModelNet40DataModule`` test split (``--protocol``, unseen objects by default), seed 1234, 1024 points, two
  independent samplings, Euler U[0, 45°], t U[-0.5, 0.5]; once clean and once with Gaussian noise sigma 0.01 clipped
  at 0.05 on both clouds. Every method sees the same pairs.
* Metrics: :func:`lcreg.experiments.evaluation.evaluate` (RMSE/MAE of the Euler angles and translations, recall at (2°,
  0.01) and (5°, 0.05)); ms/pair is the wall time of ``register`` per pair (batch ``--batch-size``; Open3D methods loop
  over pairs on the CPU).

Rows are appended to ``<out>.jsonl`` as they finish (a rerun skips them); the Markdown table is rewritten each time.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from lcreg.experiments.benchmarking import (
    METHODS,
    Budget,
    ResultLog,
    Values,
    add_smoke_argument,
    build,
    cli_args,
    fit,
    fit_overrides,
    key_values,
    machine_line,
    markdown_table,
    output_path,
    pair_batches,
    report_table,
    synthetic_overrides,
    write_text,
)
from lcreg.experiments.evaluation import EvaluationReport, evaluate

ROWS = [
    "dvds",
    "pointnetlk",
    "pcrnet",
    "fmr",
    "dcp",
    "prnet",
    "idam",
    "deepgmr",
    "icp",
    "icp_plane",
    "ransac",
    "fgr",
    "ransac_icp",
    "fgr_icp",
    "dvds_icp",
]
NOISE = {"clean": 0.0, "noise σ 0.01": 0.01}
NUM_POINTS = 1024
SMOKE = {"only": ["dvds", "dvds_icp", "icp"], "train": ["dvds=2,64,2"], "num_points": 64, "batch_size": 2}


def data_overrides(args: argparse.Namespace, budget: Budget) -> Values:
    """The training data of a ``--train`` run: ModelNet40 under ``--root`` (synthetic pairs in a smoke run)."""
    if args.smoke:
        return synthetic_overrides(num_points=budget.points, batch_size=budget.batch)
    values = {"root": args.root, "protocol": args.protocol, "num_points": budget.points, "batch_size": budget.batch}
    return cli_args("data", {**values, "seed": 1234})


def train(key: str, budget: Budget, args: argparse.Namespace) -> str:
    """``lcreg fit`` on the method's config with the budget; returns the best checkpoint (validation)."""
    run = fit_overrides(budget.steps, max(1, budget.steps // 4), args.run_dir, name=key, seed=0)
    return str(fit(key, {**run, **data_overrides(args, budget)}).best_checkpoint)


def test_sets(args: argparse.Namespace) -> tuple[dict[str, list[Any]], str]:
    """The test batches of every noise setting, and where they come from."""
    root, pairs = (None, 2) if args.smoke else (args.root, None)
    sets, source = {}, ""
    for setting, sigma in NOISE.items():
        options = {"protocol": args.protocol, "noise_sigma": sigma}
        sets[setting], source = pair_batches(
            root, pairs=pairs, num_points=args.num_points, batch_size=args.batch_size, **options
        )
    return sets, source


def evaluate_method(key: str, ckpts: dict[str, str], budgets: dict[str, str], sets: dict, log: ResultLog) -> None:
    """Every unfinished setting of one method, appended to the log."""
    source = METHODS[key].weights_from or key
    model = None
    for setting, batches in sets.items():
        if log.done(key=key, setting=setting):
            continue
        model = model or build(key, ckpts.get(source)).eval()
        torch.manual_seed(0)  # stochastic test-time choices (PRNet's Gumbel noise) are the same for every run
        report = evaluate(model, batches, METHODS[key].label)
        log.append(
            {
                "key": key,
                "label": report.name,
                "setting": setting,
                "metrics": report.metrics,
                "ms_per_pair": report.ms_per_pair,
                "pairs": report.num_pairs,
                "checkpoint": ckpts.get(source),
                "budget": budgets.get(source),
            }
        )
        print(f"{key} [{setting}] {report.metrics} {report.ms_per_pair:.1f} ms/pair", flush=True)


def table(log: ResultLog, args: argparse.Namespace) -> str:
    """The Markdown document from every finished row."""
    lines = [
        "# Every method on the same ModelNet40 test pairs",
        "",
        f"Command: `python benchmarks/compare_methods.py {' '.join(args.argv)}`",
        f"Machine: {machine_line()}.",
        f"Data: {args.source}, seed 1234, {args.num_points} points, two "
        "independent samplings, Euler U[0°, 45°] per axis, t U[-0.5, 0.5]; noisy: Gaussian sigma 0.01 clipped at 0.05 "
        "on both clouds.",
        "",
    ]
    for setting in NOISE:
        rows = [row for row in (log.find(key=key, setting=setting) for key in ROWS) if row is not None]
        reports = [
            EvaluationReport(r["label"], r["metrics"], torch.empty(0), torch.empty(0), r["ms_per_pair"], r["pairs"])
            for r in rows
        ]
        lines += [f"## {setting}", "", report_table(reports), ""]
    weights = [
        [row["label"], f"`{row['checkpoint']}`", row["budget"] or "given"]
        for row in (log.find(key=key, setting="clean") for key in ROWS if METHODS[key].learned)
        if row is not None
    ]
    header = ["method", "checkpoint", "budget trained here (steps, points, batch)"]
    return "\n".join([*lines, "## Weights", "", markdown_table(header, weights)]) + "\n"


def parse(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--root", default="../shared/data/modelnet40_mini")
    parser.add_argument("--protocol", default="unseen_objects", choices=["unseen_objects", "unseen_categories"])
    parser.add_argument("--ckpt", nargs="*", default=[], help="key=path of a trained checkpoint")
    parser.add_argument("--train", nargs="*", default=[], help="key=steps,points,batch: train here on CPU")
    parser.add_argument("--only", nargs="*", default=None, choices=ROWS, help="evaluate these keys only")
    parser.add_argument("--batch-size", type=int, default=16)
    parser.add_argument("--run-dir", default="runs/compare")
    parser.add_argument("--out", default=None, help="Markdown table (default docs/results/compare_methods.md)")
    add_smoke_argument(parser)
    args = parser.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    args.num_points = NUM_POINTS
    if args.smoke:
        vars(args).update(SMOKE)
    args.out = output_path(args.out, "compare_methods.md", args.smoke) or Path("docs/results/compare_methods.md")
    if args.smoke:
        args.run_dir = str(args.out.parent / "runs")
    return args


def main(argv: Sequence[str] | None = None) -> None:
    args = parse(argv)
    ckpts, budgets = key_values(args.ckpt, "--ckpt"), key_values(args.train, "--train")
    log = ResultLog(args.out.with_suffix(".jsonl"), key=("key", "setting"))
    sets, args.source = test_sets(args)
    for key in ROWS:
        if args.only is not None and key not in args.only:
            continue
        source = METHODS[key].weights_from or key
        if METHODS[key].learned and source not in ckpts and source in budgets:
            ckpts[source] = train(source, Budget.parse(budgets[source], "--train"), args)
            print(f"{key}: trained, best checkpoint {ckpts[source]}", flush=True)
        if METHODS[key].learned and source not in ckpts:
            print(f"{key}: no checkpoint, not evaluated", flush=True)
            continue
        evaluate_method(key, ckpts, budgets, sets, log)
        write_text(args.out, table(log, args))


if __name__ == "__main__":
    main()
