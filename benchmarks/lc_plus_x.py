"""The paper's "LC + X" experiment: train each host X with and without local consistency, same seeds and budget.

    python benchmarks/lc_plus_x.py --hosts dcp prnet idam deepgmr --seeds 0 1 2 --max-steps 120 \
        --out docs/results/lc_plus_x.md

For every host, variant (``configs/<host>.yaml`` = X, ``configs/<host>_lc.yaml`` = LC + X) and seed, the run
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
import json
import platform
import statistics
import time
from pathlib import Path
from typing import Any

import torch

NAMES = {"dcp": "DCP", "prnet": "PRNet", "idam": "IDAM", "deepgmr": "DeepGMR"}
METRICS = {
    "rmse_r_deg": "RMSE(R) °",
    "mae_r_deg": "MAE(R) °",
    "rmse_t": "RMSE(t)",
    "mae_t": "MAE(t)",
    "recall_r2_t0p01": "recall (2°, 0.01)",
}


def budget(host: str, args: argparse.Namespace) -> dict[str, int | None]:
    """Steps, points and batch size of a host: ``--host-budget host=steps,points,batch`` or the global options."""
    for item in args.host_budget:
        name, values = item.split("=")
        if name == host:
            steps, points, batch = (int(v) for v in values.split(","))
            return {"max_steps": steps, "num_points": points, "batch_size": batch, "val_every": max(1, steps // 3)}
    return {
        "max_steps": args.max_steps,
        "num_points": args.num_points,
        "batch_size": args.batch_size,
        "val_every": args.val_every,
    }


def run_one(config: Path, seed: int, args: argparse.Namespace, run_dir: Path, plan: dict) -> dict[str, Any]:
    """Train and test one (config, seed); returns the test metrics and bookkeeping."""
    from lcreg.cli import build_cli

    overrides = [
        f"--seed_everything={seed}",
        f"--trainer.max_steps={plan['max_steps']}",
        "--trainer.max_epochs=-1",
        f"--trainer.val_check_interval={plan['val_every']}",
        "--trainer.check_val_every_n_epoch=null",
        "--trainer.enable_progress_bar=false",
        "--trainer.enable_model_summary=false",
        f"--trainer.logger.init_args.save_dir={run_dir}",
        "--trainer.logger.init_args.name=",
        f"--trainer.default_root_dir={run_dir}",
        f"--data.init_args.root={args.root}",
        f"--data.init_args.protocol={args.protocol}",
        "--data.init_args.seed=1234",
        f"--data.init_args.num_workers={args.num_workers}",
    ]
    if plan["batch_size"]:
        overrides.append(f"--data.init_args.batch_size={plan['batch_size']}")
    if plan["num_points"]:
        overrides.append(f"--data.init_args.num_points={plan['num_points']}")
    cli = build_cli(["--config", str(config), *overrides], run=False)
    start = time.perf_counter()
    cli.trainer.fit(cli.model, datamodule=cli.datamodule)
    train_s = time.perf_counter() - start
    best = cli.trainer.checkpoint_callback.best_model_path if cli.trainer.checkpoint_callback else ""
    lc_final = _last_logged(cli.trainer, "train/lc")  # before testing, which resets the logged metrics
    tested = cli.trainer.test(cli.model, datamodule=cli.datamodule, ckpt_path=best or None, verbose=False)[0]
    return {
        "config": str(config),
        "seed": seed,
        "train_s": round(train_s, 1),
        "steps": int(cli.trainer.global_step),
        "best_ckpt": best,
        "num_test_pairs": len(cli.datamodule.test_set),
        "num_points": cli.datamodule.hparams.num_points,
        "batch_size": cli.datamodule.hparams.batch_size,
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


def _mean_std(values: list[float], digits: int) -> str:
    std = statistics.stdev(values) if len(values) > 1 else 0.0
    return f"{statistics.fmean(values):.{digits}f} ± {std:.{digits}f}"


def table(rows: list[dict[str, Any]], args: argparse.Namespace) -> str:
    """Markdown: one line per (host, variant) with mean ± std, then the LC - X differences."""
    lines = [
        "| method | " + " | ".join(METRICS.values()) + " | seeds | test pairs | budget | train s/run |",
        "|---" * (len(METRICS) + 5) + "|",
    ]
    verdicts = []
    for host in args.hosts:
        by_variant = {}
        for variant, suffix in (("X", ""), ("LC + X", "_lc")):
            config = str(Path(args.config_dir) / f"{host}{suffix}.yaml")
            runs = [r for r in rows if r["config"] == config and r["seed"] in args.seeds]
            if not runs:
                continue
            by_variant[variant] = runs
            name = NAMES.get(host, host) if variant == "X" else f"LC + {NAMES.get(host, host)}"
            cells = [_mean_std([r[k] for r in runs], 2 if k.endswith("deg") else 4) for k in METRICS]
            cells[-1] = _mean_std([100 * r["recall_r2_t0p01"] for r in runs], 1) + " %"
            train_s = statistics.fmean(r["train_s"] for r in runs)
            r0 = runs[0]
            plan = f"{r0['steps']} steps x {r0['batch_size']} pairs x {r0['num_points']} pts"
            tail = f" | {len(runs)} | {r0['num_test_pairs']} | {plan} | {train_s:.0f} |"
            lines.append(f"| {name} | " + " | ".join(cells) + tail)
        if len(by_variant) == 2:
            verdicts.append(_verdict(NAMES.get(host, host), by_variant["X"], by_variant["LC + X"]))
            verdicts.append(_lc_share(NAMES.get(host, host), by_variant["LC + X"]))
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--hosts", nargs="+", default=["dcp", "prnet", "idam", "deepgmr"])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--config-dir", default="configs")
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
    parser.add_argument("--out", default="docs/results/lc_plus_x.md")
    args = parser.parse_args()

    out = Path(args.out)
    jsonl = out.with_suffix(".jsonl")
    rows = [json.loads(line) for line in jsonl.read_text().splitlines()] if jsonl.exists() else []
    for host in args.hosts:
        for suffix in ("", "_lc"):
            config = Path(args.config_dir) / f"{host}{suffix}.yaml"
            for seed in args.seeds:
                if any(r["config"] == str(config) and r["seed"] == seed for r in rows):
                    continue
                run_dir = Path(args.run_dir) / f"{host}{suffix}" / f"seed{seed}"
                row = run_one(config, seed, args, run_dir, budget(host, args))
                rows.append(row)
                jsonl.parent.mkdir(parents=True, exist_ok=True)
                with jsonl.open("a") as fh:
                    fh.write(json.dumps(row) + "\n")
                print(json.dumps(row), flush=True)

    header = (
        f"# LC + X on ModelNet40 ({Path(args.root).name}, {args.protocol})\n\n"
        f"Command: `python benchmarks/lc_plus_x.py --hosts {' '.join(args.hosts)} "
        f"--seeds {' '.join(map(str, args.seeds))} --max-steps {args.max_steps} --val-every {args.val_every}"
        + (f" --batch-size {args.batch_size}" if args.batch_size else "")
        + (f" --num-points {args.num_points}" if args.num_points else "")
        + (f" --host-budget {' '.join(args.host_budget)}" if args.host_budget else "")
        + f"`\n\nMachine: {platform.processor() or platform.machine()}, torch {torch.__version__}, "
        f"{torch.get_num_threads()} threads. Budget per run: the optimiser steps, pairs per batch and points per "
        "cloud in the table (the same for X and LC + X), validation three times per run, checkpoint chosen on "
        "val/rre_mean_deg, tested once on the same test pairs.\n\n"
    )
    out.write_text(header + table(rows, args))
    print(out.read_text())


if __name__ == "__main__":
    main()
