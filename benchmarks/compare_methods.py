"""Every registration method on the same deterministic ModelNet40 test pairs, clean and noisy: one table.

    python benchmarks/compare_methods.py --out docs/results/compare_methods.md \
        --ckpt dvds=runs/.../best.ckpt --ckpt dcp=runs/.../best.ckpt \
        --train pointnetlk=200,512,16 --train pcrnet=300,512,20 --train fmr=300,512,8

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
* Metrics: :func:`lcreg.evaluation.evaluate` (RMSE/MAE of the Euler angles and translations, recall at (2°, 0.01) and
  (5°, 0.05)); ms/pair is the wall time of ``register`` per pair (batch ``--batch-size``; Open3D methods loop over
  pairs on the CPU).

Rows are appended to ``<out>.jsonl`` as they finish (a rerun skips them); the Markdown table is rewritten each time.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from lcreg.evaluation import EvaluationReport, evaluate, markdown_table

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
REFINE = CONFIGS / "refine" / "icp.yaml"
NOISE = {"clean": 0.0, "noise σ 0.01": 0.01}


@dataclass(frozen=True)
class Method:
    """One row: a config, whether it needs weights, and an optional ICP refinement."""

    key: str
    label: str
    config: str
    learned: bool
    refine: bool = False
    weights_from: str | None = None  # the learned method whose checkpoint a "+ ICP" row reuses


METHODS = [
    Method("dvds", "DVDs", "dvds_modelnet40.yaml", True),
    Method("pointnetlk", "PointNetLK", "pointnetlk.yaml", True),
    Method("pcrnet", "PCRNet", "pcrnet.yaml", True),
    Method("fmr", "FMR-Net", "fmr.yaml", True),
    Method("dcp", "DCP-v2", "dcp.yaml", True),
    Method("prnet", "PRNet", "prnet.yaml", True),
    Method("idam", "IDAM", "idam.yaml", True),
    Method("deepgmr", "DeepGMR", "deepgmr.yaml", True),
    Method("icp", "ICP point-to-point", "icp.yaml", False),
    Method("icp_plane", "ICP point-to-plane", "icp_plane.yaml", False),
    Method("ransac", "FPFH + RANSAC", "ransac.yaml", False),
    Method("fgr", "FPFH + FGR", "fgr.yaml", False),
    Method("ransac_icp", "FPFH + RANSAC + ICP", "ransac.yaml", False, refine=True),
    Method("fgr_icp", "FPFH + FGR + ICP", "fgr.yaml", False, refine=True),
    Method("dvds_icp", "DVDs + ICP", "dvds_modelnet40.yaml", True, refine=True, weights_from="dvds"),
]


def _pairs(key: str, items: list[str]) -> dict[str, str]:
    out = {}
    for item in items:
        name, _, value = item.partition("=")
        if not value:
            raise SystemExit(f"{key} expects key=value, got {item!r}")
        out[name] = value
    return out


def train(method: Method, budget: str, args: argparse.Namespace) -> str:
    """``lcreg fit`` on the method's config with ``steps,points,batch``; returns the best checkpoint (validation)."""
    from lcreg.cli import build_cli

    steps, points, batch = (int(v) for v in budget.split(","))
    run_dir = Path(args.run_dir)
    cli = build_cli(
        [
            "fit",
            "--config",
            str(CONFIGS / method.config),
            "--seed_everything=0",
            f"--trainer.max_steps={steps}",
            "--trainer.max_epochs=-1",
            f"--trainer.val_check_interval={max(1, steps // 4)}",
            "--trainer.check_val_every_n_epoch=null",
            "--trainer.enable_progress_bar=false",
            "--trainer.enable_model_summary=false",
            f"--trainer.logger.init_args.save_dir={run_dir}",
            f"--trainer.logger.init_args.name={method.key}",
            f"--trainer.default_root_dir={run_dir}",
            f"--data.init_args.root={args.root}",
            f"--data.init_args.protocol={args.protocol}",
            f"--data.init_args.num_points={points}",
            f"--data.init_args.batch_size={batch}",
            "--data.init_args.seed=1234",
        ]
    )
    callback = cli.trainer.checkpoint_callback
    best = getattr(callback, "best_model_path", "")
    if not best:
        raise RuntimeError(f"training {method.key} produced no checkpoint")
    return str(best)


def build(method: Method, ckpt: str | None) -> Any:
    """The model of a config (weights from ``ckpt`` for learned methods), with the ICP refiner if asked."""
    from lcreg.cli import build_cli

    configs = ["--config", str(CONFIGS / method.config)]
    if method.refine:
        configs += ["--config", str(REFINE)]
    model = build_cli(configs, run=False).model
    return (model if ckpt is None else model.load_weights(ckpt)).eval()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--root", default="../shared/data/modelnet40_mini")
    parser.add_argument("--protocol", default="unseen_objects", choices=["unseen_objects", "unseen_categories"])
    parser.add_argument("--ckpt", nargs="*", default=[], help="key=path of a trained checkpoint")
    parser.add_argument("--train", nargs="*", default=[], help="key=steps,points,batch: train here on CPU")
    parser.add_argument("--only", nargs="*", default=None, help="evaluate these keys only")
    parser.add_argument("--batch-size", type=int, default=16)
    parser.add_argument("--run-dir", default="runs/compare")
    parser.add_argument("--out", default="docs/results/compare_methods.md")
    args = parser.parse_args()

    from lcreg.data.datamodule import ModelNet40DataModule

    ckpts, budgets = _pairs("--ckpt", args.ckpt), _pairs("--train", args.train)
    jsonl = Path(args.out).with_suffix(".jsonl")
    done = (
        {(r["key"], r["setting"]): r for r in map(json.loads, jsonl.read_text().splitlines())} if jsonl.exists() else {}
    )
    sets = {}
    for setting, sigma in NOISE.items():
        dm = ModelNet40DataModule(
            root=args.root, protocol=args.protocol, num_points=1024, batch_size=args.batch_size, noise_sigma=sigma
        )
        dm.setup("test")
        sets[setting] = list(dm.test_dataloader())
    for method in METHODS:
        if args.only is not None and method.key not in args.only:
            continue
        source = method.weights_from or method.key
        if method.learned and source not in ckpts and source in budgets:
            ckpts[source] = train(method, budgets[source], args)
            print(f"{method.key}: trained, best checkpoint {ckpts[source]}", flush=True)
        if method.learned and source not in ckpts:
            print(f"{method.key}: no checkpoint, not evaluated", flush=True)
            continue
        model = None
        for setting, batches in sets.items():
            if (method.key, setting) in done:
                continue
            model = model or build(method, ckpts.get(source))
            torch.manual_seed(0)  # stochastic test-time choices (PRNet's Gumbel noise) are the same for every run
            report = evaluate(model, batches, method.label)
            row = {
                "key": method.key,
                "label": method.label,
                "setting": setting,
                "metrics": report.metrics,
                "ms_per_pair": report.ms_per_pair,
                "pairs": report.num_pairs,
                "checkpoint": ckpts.get(source),
                "budget": budgets.get(source),
            }
            done[(method.key, setting)] = row
            with jsonl.open("a") as fh:
                fh.write(json.dumps(row) + "\n")
            print(f"{method.key} [{setting}] {json.dumps(report.metrics)} {report.ms_per_pair:.1f} ms/pair", flush=True)
        write_table(done, args)


def write_table(rows: dict[tuple[str, str], dict[str, Any]], args: argparse.Namespace) -> None:
    """Rewrite the Markdown table from every finished row."""
    lines = [
        "# Every method on the same ModelNet40 test pairs",
        "",
        f"Command: `python benchmarks/compare_methods.py {' '.join(sys.argv[1:])}`",
        f"Machine: {platform.processor() or platform.machine()}, torch {torch.__version__}, "
        f"{torch.get_num_threads()} threads, CPU.",
        f"Data: `{args.root}`, protocol {args.protocol}, test split, seed 1234, 1024 points, two independent "
        "samplings, Euler U[0°, 45°] per axis, t U[-0.5, 0.5]; noisy: Gaussian sigma 0.01 clipped at 0.05 on both "
        "clouds.",
        "",
    ]
    for setting in NOISE:
        reports = [
            EvaluationReport(r["label"], r["metrics"], torch.empty(0), torch.empty(0), r["ms_per_pair"], r["pairs"])
            for r in (rows.get((method.key, setting)) for method in METHODS)
            if r is not None
        ]
        lines += [f"## {setting}", "", markdown_table(reports), ""]
    lines += ["## Weights", "", "| method | checkpoint | budget trained here (steps, points, batch) |", "|---|---|---|"]
    for method in METHODS:
        row = rows.get((method.key, "clean"))
        if row is not None and method.learned:
            lines.append(f"| {row['label']} | `{row['checkpoint']}` | {row['budget'] or 'given'} |")
    Path(args.out).write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
