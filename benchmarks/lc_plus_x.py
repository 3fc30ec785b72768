"""The paper's "LC + X" experiment: train each host X with and without local consistency, same seeds and budget.

    python benchmarks/lc_plus_x.py --hosts dcp prnet idam deepgmr --seeds 0 1 2 --max-steps 120 \
        --out docs/results/lc_plus_x.md
    python benchmarks/lc_plus_x.py --smoke           # seconds: DCP and LC + DCP, 2 steps on synthetic pairs

For every host, variant (the registered method X, ``configs/models/<host>.yaml``, and LC + X, the same plus
``configs/lc.yaml``) and seed, the run
1. builds model and data from the config through the CLI (the configs are what is measured), with
   ``seed_everything = seed`` (initialisation and training order; the LC metric has its own seed, so X and LC + X
   start from the same host weights) and the data's pair seed fixed at 1234 (the same validation and test pairs
   for every run);
2. trains ``--max-steps`` optimiser steps, validating every ``--val-every`` steps on the validation split carved
   out of the training objects, keeping the checkpoint with the lowest ``val/rre_mean_deg`` (never the test set);
3. tests that checkpoint on the deterministic test pairs (ModelNet40 unseen objects by default).

Rows are appended to ``<out>.jsonl`` as runs finish (a rerun skips finished runs), then the table (mean ± std over
seeds, the number of test pairs, the budget, and whether the LC - X difference exceeds the seed spread) is written
to ``--out``. The budget arguments override the configs (batch size, points, steps); they are printed in the table.
"""

from __future__ import annotations

import argparse
import csv
import statistics
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from lcreg.benchmarking import (
    METHODS,
    Budget,
    ResultLog,
    add_smoke_argument,
    cli_args,
    fit,
    fit_overrides,
    format_mean_std,
    key_values,
    load_weights,
    machine_line,
    markdown_row,
    markdown_table,
    output_path,
    synthetic_overrides,
    write_text,
)

HOSTS = ["dcp", "prnet", "idam", "deepgmr"]
METRICS = {
    "rmse_r_deg": "RMSE(R) °",
    "mae_r_deg": "MAE(R) °",
    "rmse_t": "RMSE(t)",
    "mae_t": "MAE(t)",
    "recall_r2_t0p01": "recall (2°, 0.01)",
}
SMOKE = {"hosts": ["dcp"], "seeds": [0], "max_steps": 2, "val_every": 1, "batch_size": 2, "num_points": 64}


def variants(host: str) -> dict[str, str]:
    """The registered methods of X and LC + X."""
    lc = METHODS[host].lc_variant
    if lc is None:
        raise SystemExit(f"{host} has no LC + X variant in the registry")
    return {"X": host, "LC + X": lc}


def plan(host: str, args: argparse.Namespace) -> dict[str, int | None]:
    """Steps, points, batch size and validation interval of a host: ``--host-budget`` or the global options."""
    budgets = key_values(args.host_budget, "--host-budget")
    if host in budgets:
        b = Budget.parse(budgets[host], "--host-budget")
        return {"max_steps": b.steps, "num_points": b.points, "batch_size": b.batch, "val_every": max(1, b.steps // 3)}
    return {
        "max_steps": args.max_steps,
        "num_points": args.num_points,
        "batch_size": args.batch_size,
        "val_every": args.val_every,
    }


def data_overrides(args: argparse.Namespace, p: dict[str, int | None]) -> list[str]:
    """ModelNet40 under ``--root`` with the pair seed 1234 and the plan's sizes (synthetic pairs in a smoke run)."""
    if args.smoke:
        return synthetic_overrides(num_points=p["num_points"] or 64, batch_size=p["batch_size"] or 2)
    values = {"root": args.root, "protocol": args.protocol, "seed": 1234, "num_workers": args.num_workers}
    return cli_args("data", {**values, "batch_size": p["batch_size"], "num_points": p["num_points"]})


def run_one(name: str, seed: int, args: argparse.Namespace, run_dir: Path, p: dict[str, Any]) -> dict[str, Any]:
    """Train and test one (method, seed); returns the test metrics and bookkeeping."""
    run = fit_overrides(p["max_steps"], p["val_every"], run_dir, seed=seed)
    result = fit(name, [*run, *data_overrides(args, p)])
    lc_final = _last_logged(result.trainer, "train/lc")  # before testing, which resets the logged metrics
    load_weights(result.model, result.best_checkpoint)
    tested = result.trainer.test(result.model, datamodule=result.datamodule, verbose=False)[0]
    dm: Any = result.datamodule
    return {
        "method": name,
        "configs": list(METHODS[name].config_files()),
        "seed": seed,
        "train_s": round(result.seconds, 1),
        "steps": int(result.trainer.global_step),
        "best_ckpt": str(result.best_checkpoint),
        "num_test_pairs": len(dm.test_set),
        "num_points": dm.hparams.num_points,
        "batch_size": dm.hparams.batch_size,
        "lc_final": lc_final,
        **{k: float(tested[f"test/{k}"]) for k in METRICS},
    }


def _last_logged(trainer: Any, key: str) -> float | None:
    """Last value of a logged training metric (``None`` when the run did not log it)."""
    value = trainer.callback_metrics.get(f"{key}_epoch", trainer.callback_metrics.get(f"{key}_step"))
    return None if value is None else float(value)


def lc_trajectory(row: dict[str, Any]) -> tuple[float, float, float] | None:
    """First and last logged ``train/lc`` and the last ``train/loss`` of a run (from its ``metrics.csv``)."""
    if not row.get("best_ckpt"):
        return None
    path = Path(row["best_ckpt"]).parents[1] / "metrics.csv"
    if not path.is_file():
        return None
    with path.open() as fh:
        steps = [r for r in csv.DictReader(fh) if r.get("train/lc_step")]
    if not steps:
        return None
    return float(steps[0]["train/lc_step"]), float(steps[-1]["train/lc_step"]), float(steps[-1]["train/loss_step"])


def _cells(runs: list[dict[str, Any]]) -> list[str]:
    """mean ± std over seeds of every metric (recall in %)."""
    cells = []
    for key in METRICS:
        if key.startswith("recall"):
            cells.append(format_mean_std([r[key] for r in runs], ".1f", ".1f", scale=100.0) + " %")
        else:
            digits = ".2f" if key.endswith("deg") else ".4f"
            cells.append(format_mean_std([r[key] for r in runs], digits, digits))
    return cells


def table(log: ResultLog, args: argparse.Namespace) -> str:
    """Markdown: one line per (host, variant) with mean ± std, then the LC - X differences."""
    header = ["method", *METRICS.values(), "seeds", "test pairs", "budget", "train s/run"]
    lines, verdicts = [markdown_table(header)], []
    for host in args.hosts:
        by_variant = {}
        for variant, name in variants(host).items():
            runs = [r for seed in args.seeds if (r := log.find(method=name, seed=seed)) is not None]
            if not runs:
                continue
            by_variant[variant] = runs
            r0 = runs[0]
            budget = f"{r0['steps']} steps x {r0['batch_size']} pairs x {r0['num_points']} pts"
            train_s = f"{statistics.fmean(r['train_s'] for r in runs):.0f}"
            lines.append(
                markdown_row([METHODS[name].label, *_cells(runs), len(runs), r0["num_test_pairs"], budget, train_s])
            )
        if len(by_variant) == 2:
            verdicts.append(_verdict(METHODS[host].label, by_variant["X"], by_variant["LC + X"]))
            verdicts.append(_lc_share(METHODS[host].label, by_variant["LC + X"]))
    return "\n".join(lines) + "\n\n" + "\n".join(verdicts) + "\n"


def _verdict(name: str, base: list[dict[str, Any]], lc: list[dict[str, Any]]) -> str:
    """Relative change of RMSE(R) and MAE(R), and whether it exceeds the larger seed std."""
    parts = []
    for key in ("rmse_r_deg", "mae_r_deg"):
        b, c = [r[key] for r in base], [r[key] for r in lc]
        diff = statistics.fmean(c) - statistics.fmean(b)
        spread = max(statistics.stdev(b) if len(b) > 1 else 0.0, statistics.stdev(c) if len(c) > 1 else 0.0)
        rel = 100 * diff / statistics.fmean(b)
        label = METRICS[key].removesuffix(" °")
        if min(len(b), len(c)) < 2:
            parts.append(f"{label} {diff:+.2f}° ({rel:+.1f} %, one seed: no spread to compare with)")
            continue
        beyond = "exceeds" if abs(diff) > spread else "within"
        parts.append(f"{label} {diff:+.2f}° ({rel:+.1f} %, {beyond} the larger seed std {spread:.2f}°)")
    return f"- LC + {name} vs {name}: " + "; ".join(parts)


def _lc_share(name: str, runs: list[dict[str, Any]]) -> str:
    """How large the LC term was during training (first and last logged step, mean over seeds)."""
    traj = [t for t in (lc_trajectory(r) for r in runs) if t is not None]
    if not traj:
        return f"  - LC + {name}: no logged LC values found"
    first, last, loss = (statistics.fmean(v) for v in zip(*traj))
    return (
        f"  - LC + {name}: LC term {first:.3g} at the first logged step, {last:.3g} at the last "
        f"({100 * last / loss:.2g} % of the total training loss {loss:.3g}; weight 1)"
    )


def header(args: argparse.Namespace) -> str:
    """Title, command and budget description."""
    data = "embedded synthetic shapes, smoke run" if args.smoke else f"{Path(args.root).name}, {args.protocol}"
    return (
        f"# LC + X on ModelNet40 ({data})\n\n"
        f"Command: `python benchmarks/lc_plus_x.py {args.command}`\n\n"
        f"Machine: {machine_line()}. Budget per run: the optimiser steps, pairs per batch and points per cloud in the "
        "table (the same for X and LC + X), validation three times per run, checkpoint chosen on val/rre_mean_deg, "
        "tested once on the same test pairs.\n\n"
    )


def parse(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--hosts", nargs="+", default=HOSTS, choices=HOSTS)
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--root", default="../shared/data/modelnet40_mini")
    parser.add_argument("--protocol", default="unseen_objects", choices=["unseen_objects", "unseen_categories"])
    parser.add_argument("--max-steps", type=int, default=120)
    parser.add_argument("--val-every", type=int, default=40)
    parser.add_argument("--batch-size", type=int, default=None, help="override the configs' batch size")
    parser.add_argument("--num-points", type=int, default=None, help="override the configs' points per cloud")
    parser.add_argument(
        "--host-budget",
        nargs="*",
        default=[],
        help="per-host budget overriding the global one: host=steps,points,batch (validation every steps/3)",
    )
    parser.add_argument("--num-workers", type=int, default=0)
    parser.add_argument("--run-dir", default="runs/lc_plus_x")
    parser.add_argument("--out", default=None, help="Markdown table (default docs/results/lc_plus_x.md)")
    add_smoke_argument(parser)
    args = parser.parse_args(argv)
    args.command = " ".join(sys.argv[1:] if argv is None else argv)
    if args.smoke:
        vars(args).update(SMOKE)
    args.out = output_path(args.out, "lc_plus_x.md", args.smoke) or Path("docs/results/lc_plus_x.md")
    if args.smoke:
        args.run_dir = str(args.out.parent / "runs")
    return args


def read_log(path: Path) -> ResultLog:
    """Finished runs; rows written before the registry (keyed by ``config``) get their method from the file name."""
    log = ResultLog(path, key=("method", "seed"))
    for row in log.rows:
        row.setdefault("method", Path(row.get("config", "")).stem)
    return log


def main(argv: Sequence[str] | None = None) -> None:
    args = parse(argv)
    log = read_log(args.out.with_suffix(".jsonl"))
    for host in args.hosts:
        for name in variants(host).values():
            for seed in args.seeds:
                if log.done(method=name, seed=seed):
                    continue
                row = run_one(name, seed, args, Path(args.run_dir) / name / f"seed{seed}", plan(host, args))
                print(log.append(row), flush=True)
    write_text(args.out, header(args) + table(log, args))
    print(args.out.read_text())


if __name__ == "__main__":
    main()
