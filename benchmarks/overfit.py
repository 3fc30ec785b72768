"""Overfit probe: can a learned method fit a few fixed pairs? A defect check for a reimplementation far off its paper.

    python benchmarks/overfit.py --root ../shared/data/modelnet40_mini --methods dcp --pairs 8 --points 256 \
        --steps 300 --val-every 25 --run-dir runs/overfit --out docs/results/converge/overfit/overfit.md
    python benchmarks/overfit.py --smoke      # seconds, embedded shapes, 2 steps

Each method trains, exactly as ``lcreg fit`` trains it (its registry configs: for the LC hosts the DCP-family pairs of
``configs/data/dcp_protocol.yaml``; its own loss, optimiser, learning rate and gradient clipping), on the first
``--pairs`` **validation** pairs of ModelNet40, the same fixed batches every step (motions, samplings and noise drawn
once), and is validated on those same pairs every ``--val-every`` steps. A correct implementation drives the error of
pairs it trains on far below what it reaches on unseen pairs; one that cannot, at a step count where its converge runs
already plateau on unseen pairs, has a defect in its forward pass, loss or gradient path (or an optimiser setting
that cannot fit even these). ``--model-args NAME=VALUE`` changes constructor arguments (the run is named
``method[NAME=VALUE]``), e.g. ``batch_norm=false`` for DCP. The report sets the last training loss (training mode)
beside the last validation loss (eval mode) on the same pairs, and the final weights' errors in training mode: far
apart, the network evaluated is not the one trained (BatchNorm's batch statistics, dropout). Nothing here measures
generalisation, and test pairs are never read.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import DataLoader

from lcreg.experiments.benchmarking import (
    ResultLog,
    Series,
    Values,
    add_smoke_argument,
    apply_smoke,
    build_cli_for,
    cli_args,
    fit_overrides,
    key_values,
    load_runs,
    machine_line,
    markdown_table,
    output_path,
    plot_curves,
    read_metrics,
    split_batches,
    synthetic_overrides,
    write_text,
)
from lcreg.experiments.reproduce.stops import metrics_file
from lcreg.metrics.registration import registration_metrics
from lcreg.models.base import RegistrationModule
from lcreg.types import RegistrationBatch

SMOKE = {"steps": 2, "val_every": 1, "pairs": 2, "batch": 2, "points": 64, "methods": ["dcp"], "seeds": [0]}
KEY = ("label", "seed", "pairs", "points", "steps")
CURVE_KEYS = ("val/rre_mean_deg", "val/rre_median_deg", "val/rte_mean")


def data_overrides(args: argparse.Namespace) -> Values:
    """The pairs' source: ModelNet40 validation pairs at ``--points`` and ``--batch``, or embedded shapes (smoke)."""
    if args.root is None:
        return synthetic_overrides(pairs=args.pairs, num_points=args.points, batch_size=args.batch)
    values = {"root": args.root, "num_points": args.points, "batch_size": args.batch, "num_workers": 0}
    return cli_args("data", values)


def fixed_loader(batches: Sequence[Any], pairs: int) -> DataLoader[Any]:
    """The first ``pairs / batch size`` batches, served as they are (already collated), in the same order each epoch.

    Raises:
        ValueError: If the split has fewer pairs.
    """
    count = math.ceil(pairs / max(len(batches[0]), 1)) if batches else 0
    chosen = list(batches[:count])
    if sum(len(b) for b in chosen) < pairs:
        raise ValueError(f"--pairs {pairs}: the validation split has only {sum(len(b) for b in batches)} pairs")
    return DataLoader(chosen, batch_size=None, shuffle=False, collate_fn=lambda batch: batch)  # type: ignore[arg-type]


def label(method: str, model_args: dict[str, str]) -> str:
    """A run's name and folder: ``method``, or ``method[name=value,...]`` with ``--model-args``."""
    return method + (f"[{','.join(f'{k}={v}' for k, v in model_args.items())}]" if model_args else "")


def run(args: argparse.Namespace, method: str, seed: int, log: ResultLog) -> None:
    """Train ``method`` on the fixed pairs from seed ``seed`` unless ``log`` lists the run; append its row."""
    name = label(method, args.model_args)
    key = {"label": name, "seed": seed, "pairs": args.pairs, "points": args.points, "steps": args.steps}
    if log.done(**key):
        print(f"{name} seed {seed}: done before, skipped", flush=True)
        return
    values = {
        **data_overrides(args),
        **fit_overrides(args.steps, args.val_every, Path(args.run_dir) / name, seed=seed),
        "trainer.logger.init_args.version": f"seed{seed}",
        **cli_args("model", args.model_args),
    }
    cli = build_cli_for(method, values=values)
    loader = fixed_loader(split_batches(cli.datamodule, "val"), args.pairs)
    cli.trainer.validate(cli.model, dataloaders=loader, verbose=False)  # step 0: the untrained model
    cli.trainer.fit(cli.model, train_dataloaders=loader, val_dataloaders=loader)
    metrics = Path(cli.trainer.log_dir or args.run_dir) / "metrics.csv"
    row = {**key, "method": method, "metrics_csv": str(metrics), "stopped_step": cli.trainer.global_step}
    log.append({**row, "train_mode": train_mode_errors(cli.model, loader), "machine": machine_line()})
    print(f"{name} seed {seed}: stopped at step {cli.trainer.global_step}, {metrics}", flush=True)


def train_mode_errors(model: RegistrationModule, loader: Iterable[RegistrationBatch]) -> dict[str, float]:
    """Mean and median RRE (°), mean RTE and recall (2°, 0.01) of the final weights **in training mode** on the pairs.

    The forward the loss saw (BatchNorm on each batch's own statistics, no gradient), against the eval-mode validation:
    far apart, the network evaluated is not the one trained. The model's mode is restored; BatchNorm's running
    statistics take one more update per batch, as in a training step.
    """
    metrics = registration_metrics()
    was_training = model.training
    model.train()
    try:
        with torch.no_grad():
            for batch in loader:
                metrics.update(model(batch.points_src, batch.points_ref).transform_ref_src, batch.transform_ref_src)
    finally:
        model.train(was_training)
    keys = ("rre_mean_deg", "rre_median_deg", "rte_mean", "recall_r2_t0p01")
    return {key: round(float(value), 6) for key, value in metrics.compute().items() if key in keys}


def summary_rows(rows: Sequence[dict[str, Any]]) -> list[list[object]]:
    """Per run: the fitted pairs' errors at step 0, at the best mean RRE and at the last validation, and the loss of
    the last validation (eval mode) against the training loss logged last (training mode, the same pairs)."""
    table = []
    for row in rows:
        curves = read_metrics(row["metrics_csv"])
        rre = curves["val/rre_mean_deg"]
        cells: list[object] = [row["label"], row["seed"], row["pairs"], row["points"]]
        for at in (0, int(rre.values.argmin()), len(rre.steps) - 1):
            step = int(rre.steps[at])
            found = [value_at(curves[k], step) for k in CURVE_KEYS if k in curves]
            cells.append(f"{step}: " + " / ".join(f"{v:.3g}" for v in found if v is not None))
        train, val = curves.get("train/loss"), curves.get("val/loss")
        cells.append(f"{train.values[-1]:.3g} / {val.values[-1]:.3g}" if train and val else "–")
        fit = row.get("train_mode")
        cells.append(f"{fit['rre_mean_deg']:.3g} / {fit['rre_median_deg']:.3g} / {fit['rte_mean']:.3g}" if fit else "–")
        table.append(cells)
    return table


def value_at(series: Series, step: int) -> float | None:
    """The value logged at ``step``, or ``None``."""
    hits = np.flatnonzero(series.steps == step)
    return float(series.values[hits[0]]) if len(hits) else None


def report(args: argparse.Namespace, log: ResultLog, out: Path) -> None:
    """Write the summary table of the chosen methods' finished runs and their validation curves."""
    chosen = [r for r in log.rows if r.get("method") in args.methods]  # every finished run, whatever its steps
    # The recorded path, or the same run under --run-dir (a copied folder, e.g. the committed results).
    rows = [{**r, "metrics_csv": str(path)} for r in chosen if (path := metrics_file(r, args.run_dir)) is not None]
    header = ["run", "seed", "pairs", "points"]
    header += [f"{at}: step: mean RRE (°) / median RRE (°) / mean RTE" for at in ("start", "best", "last")]
    header += ["loss: training (train mode) / validation (eval mode), last"]
    header += ["last weights in train mode: mean RRE (°) / median RRE (°) / mean RTE"]
    lines = [
        "# Overfit probe: the error on the pairs each run trains on",
        "",
        "`benchmarks/overfit.py`: every finished run of the methods "
        f"{', '.join(args.methods)}, validated (eval mode) on the pairs it trains on; trained on "
        f"{'; '.join(sorted({str(r.get('machine', '?')) for r in rows}))}. Best: the validation with the lowest mean "
        "RRE; last: the run's last validation.",
        "",
        markdown_table(header, summary_rows(rows)),
        "",
    ]
    write_text(out, "\n".join(lines))
    by_method: dict[str, list[str]] = {}
    for row in rows:
        by_method.setdefault(row["label"], []).append(row["metrics_csv"])
    plot_curves(load_runs(by_method), out.parent, prefix=f"{out.stem}_")
    print(f"wrote {out}", flush=True)


def parse(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--root", default="../shared/data/modelnet40_mini")
    parser.add_argument("--methods", nargs="+", default=["dcp"], help="registry names of learned methods")
    parser.add_argument(
        "--model-args",
        nargs="*",
        default=[],
        help="NAME=VALUE constructor arguments (YAML text), e.g. batch_norm=false",
    )
    parser.add_argument("--pairs", type=int, default=8, help="fixed validation pairs trained and validated on")
    parser.add_argument("--points", type=int, default=256)
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--val-every", type=int, default=25)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--run-dir", default="runs/overfit")
    parser.add_argument("--out", default=None, help="the report (Markdown); its PNG is written beside it")
    parser.add_argument("--report-only", action="store_true", help="write the report from --run-dir, train nothing")
    add_smoke_argument(parser)
    args = apply_smoke(parser.parse_args(argv), SMOKE)
    args.model_args = key_values(args.model_args, "--model-args")
    if min(args.pairs, args.batch, args.steps, args.val_every) < 1:
        parser.error("--pairs, --batch, --steps and --val-every must be >= 1")
    if args.pairs % args.batch:
        parser.error(f"--pairs ({args.pairs}) must be a multiple of --batch ({args.batch}): whole batches are trained")
    return args


def main(argv: Sequence[str] | None = None) -> None:
    args = parse(argv)
    log = ResultLog(Path(args.run_dir) / "runs.jsonl", key=KEY)
    if not args.report_only:
        for method in args.methods:
            for seed in args.seeds:
                run(args, method, seed, log)
    out = output_path(args.out, "overfit.md", args.smoke)
    if out is not None:
        report(args, log, out)


if __name__ == "__main__":
    main()
