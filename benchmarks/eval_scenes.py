"""ModelNet40-trained models on real scenes: DVDs, DVDs voxelised and Open3D RANSAC + ICP on the same pairs.

    python benchmarks/eval_scenes.py --dataset sevenscenes --ckpt runs/.../best.ckpt --out docs/results/scenes.md
    python benchmarks/eval_scenes.py --dataset kitti --ckpt runs/.../best.ckpt --out docs/results/scenes.md
    python benchmarks/eval_scenes.py --tune --ckpt runs/.../best.ckpt --out docs/results/scenes_tuning.md
    python benchmarks/eval_scenes.py --smoke [--tune]    # seconds, synthetic pairs, untrained weights

* Every method is built from the same configs ``lcreg test`` uses: the model config (``configs/dvds_modelnet40.yaml``
  with ``--ckpt``), the data add-on ``configs/data/<dataset>.yaml``, ``configs/voxelize/lk27.yaml`` for the voxelised
  row and ``configs/pipelines/ransac_icp_<dataset>.yaml`` for RANSAC + ICP. The DataModule of the data config makes the
  pairs once; every method sees the same batches.
* Metrics: :func:`lcreg.experiments.evaluation.evaluate` (RMSE/MAE of the Euler angles in degrees and of the
  translation in metres, mean/median RRE) plus the scene recall of the usual benchmarks: RRE < 15° and RTE < 0.3 m on
  3DMatch / 7-Scenes (FCGF, DGR), RRE < 5° and RTE < 2 m on KITTI (DGR, GeoTransformer). The thresholds are the
  DataModules' ``recall_thresholds``, the same that ``lcreg test`` logs as ``test/recall_r15_t0p3`` /
  ``test/recall_r5_t2``. ms/pair is the wall time of ``register``.
* ``--tune`` picks the voxelisation settings on validation scenes only (3DMatch SUN3D scenes, never redkitchen or
  KITTI): each candidate (``configs/voxelize/lk27.yaml`` with other ``normalize`` / ``coarse_iterations`` /
  ``reassign_every``) is run with DVDs and ranked by mean RRE.

Rows are appended to ``<out>.jsonl``; the Markdown file is rewritten from all rows each time.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from lcreg.data.kitti import KITTIOdometryDataModule
from lcreg.data.threedmatch import SevenScenesDataModule
from lcreg.experiments.benchmarking import (
    METHODS,
    VOXELIZE_CONFIG,
    ResultLog,
    Values,
    add_smoke_argument,
    build,
    config_values,
    data_config,
    machine_line,
    markdown_table,
    output_path,
    split_batches,
    synthetic_overrides,
    voxelize_overrides,
    write_text,
)
from lcreg.experiments.evaluation import EvaluationReport, evaluate
from lcreg.metrics.functional import registration_recall

# (degrees, metres) of each dataset's standard recall: the one its DataModule gives `lcreg test` (single source).
RECALL = {
    "sevenscenes": SevenScenesDataModule.recall_thresholds[0],
    "kitti": KITTIOdometryDataModule.recall_thresholds[0],
}
VALIDATION_SCENES = ["sun3d-home_md-home_md_scan9_2012_sep_30", "sun3d-mit_76_studyroom-76-1studyroom2"]
METHOD_KEYS = ("dvds", "dvds_voxel", "ransac_icp")
SCENE_METRICS = {
    "rmse_r_deg": "RMSE(R) °",
    "mae_r_deg": "MAE(R) °",
    "rmse_t": "RMSE(t) m",
    "mae_t": "MAE(t) m",
    "rre_mean_deg": "mean RRE °",
    "rre_median_deg": "median RRE °",
    "rte_mean": "mean RTE m",
}
SMOKE_DATA = synthetic_overrides(pairs=2, num_points=64, batch_size=1)
SMOKE_VOXELS = voxelize_overrides(points_per_voxel=16, min_points=4)  # 64-point clouds: small voxels


def registry_name(key: str, dataset: str) -> str:
    """The registered method of a row key (RANSAC + ICP has one config per dataset scale)."""
    return f"{key}_{dataset}" if key == "ransac_icp" else key


def scene_data(name: str, dataset: str, args: argparse.Namespace) -> tuple[list[str], Values]:
    """Configs and values of method ``name``'s pairs: the dataset's data add-on, or tiny synthetic pairs (smoke)."""
    extra = config_values(args.data_args)
    if not args.smoke:
        return [data_config(dataset)], extra
    voxels = SMOKE_VOXELS if VOXELIZE_CONFIG in METHODS[name].configs else {}
    return [], {**SMOKE_DATA, **voxels, **extra}


def row(report: EvaluationReport, dataset: str, key: str, extra: dict[str, Any]) -> dict[str, Any]:
    """A JSON row: metrics, scene recall, timing and provenance."""
    rot_thr, trans_thr = RECALL[dataset.removesuffix("-val")]
    recall = registration_recall(report.rotation_error_deg, report.translation_error, rot_thr, trans_thr)
    return {
        "dataset": dataset,
        "key": key,
        "label": report.name,
        "pairs": report.num_pairs,
        "metrics": report.metrics,
        "scene_recall": float(recall),
        "ms_per_pair": report.ms_per_pair,
        "mean_iterations": report.extra.get("mean_iterations"),
        **extra,
    }


def evaluate_methods(args: argparse.Namespace) -> list[dict[str, Any]]:
    """Every method of ``--methods`` on the dataset's test pairs."""
    rows, batches = [], None
    for key in args.methods:
        name = registry_name(key, args.dataset)
        configs, values = scene_data(name, args.dataset, args)
        ckpt = args.ckpt if METHODS[name].learned else None
        model, datamodule = build(name, ckpt, configs, values, with_data=True)
        batches = batches if batches is not None else split_batches(datamodule, "test")
        torch.manual_seed(0)
        report = evaluate(model, batches, METHODS[name].label)
        extra = {"checkpoint": ckpt, "data_args": args.data_args, "section": args.section or args.dataset}
        rows.append(row(report, args.dataset, key, extra))
        print(json.dumps(rows[-1]), flush=True)
    return rows


def candidates() -> list[dict[str, Any] | None]:
    """Voxelisation settings tried by ``--tune`` (``None``: no voxelisation)."""
    grid = itertools.product([False, True], [0, 10], [1, 5])
    return [None, *({"normalize": n, "coarse_iterations": c, "reassign_every": r} for n, c, r in grid)]


def tune(args: argparse.Namespace) -> list[dict[str, Any]]:
    """Voxel settings for DVDs on the validation scenes (mean RRE, lower is better)."""
    scenes = {} if args.smoke else {"data.init_args.test_scenes": VALIDATION_SCENES}
    section = f"validation: {', '.join(VALIDATION_SCENES)} (3DMatch, overlap > 0.7)"
    rows, batches = [], None
    for params in candidates():
        name, voxel = ("dvds", {}) if params is None else ("dvds_voxel", voxelize_overrides(**params))
        configs, values = scene_data(name, "sevenscenes", args)
        model, datamodule = build(name, args.ckpt, configs, {**values, **scenes, **voxel}, with_data=True)
        batches = batches if batches is not None else split_batches(datamodule, "test")
        label = (
            "no voxelisation" if params is None else f"lk27 voxels, {', '.join(f'{k}={v}' for k, v in params.items())}"
        )
        report = evaluate(model, batches, label)
        rows.append(row(report, "sevenscenes-val", "tune", {"scenes": VALIDATION_SCENES, "section": section}))
        print(json.dumps(rows[-1]), flush=True)
    return rows


def section_table(subset: list[dict[str, Any]]) -> str:
    """One Markdown table of rows of the same section."""
    rot_thr, trans_thr = RECALL[subset[0]["dataset"].removesuffix("-val")]
    recall = f"recall (RRE < {rot_thr:g}°, RTE < {trans_thr:g} m)"
    header = ["method", "pairs", *SCENE_METRICS.values(), recall, "ms/pair"]
    rows = []
    for r in subset:
        m = r["metrics"]
        metrics = [f"{m[k]:.2f}" if k.endswith("deg") else f"{m[k]:.3f}" for k in SCENE_METRICS]
        rows.append([r["label"], r["pairs"], *metrics, f"{100 * r['scene_recall']:.1f} %", f"{r['ms_per_pair']:.0f}"])
    return markdown_table(header, rows)


def markdown(rows: list[dict[str, Any]]) -> str:
    """The results file from every row (one table per section)."""
    lines = [
        "# ModelNet40-trained registration on real scenes",
        "",
        f"Machine: {machine_line()}. Commands: see each section.",
        "",
    ]
    for section in dict.fromkeys(r.get("section", r["dataset"]) for r in rows):
        subset = [r for r in rows if r.get("section", r["dataset"]) == section]
        commands = dict.fromkeys(f"`python benchmarks/eval_scenes.py {r.get('command', '')}`" for r in subset)
        lines += [f"## {section}", "", "Command: " + "; ".join(commands), "", section_table(subset), ""]
    return "\n".join(lines)


def parse(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dataset", choices=sorted(RECALL), default="sevenscenes")
    parser.add_argument(
        "--ckpt", default=None, help="DVDs checkpoint trained on ModelNet40 (chosen on validation); required"
    )
    parser.add_argument("--methods", nargs="*", default=list(METHOD_KEYS), choices=list(METHOD_KEYS))
    parser.add_argument("--tune", action="store_true", help="choose the voxel settings on the validation scenes")
    parser.add_argument("--section", default=None, help="title of this run's table (default: the dataset)")
    parser.add_argument("--out", default=None, help="Markdown file (default docs/results/scenes.md)")
    add_smoke_argument(parser)
    # Every other argument is a config value, e.g. --data.init_args.test_split=train (typed as `lcreg` types it)
    args, args.data_args = parser.parse_known_args(argv)
    config_values(args.data_args)  # a malformed one fails here, before anything runs
    args.command = " ".join(sys.argv[1:] if argv is None else argv)
    if not args.ckpt and not args.smoke:
        parser.error("--ckpt is required (outside --smoke, where untrained weights are used)")
    args.out = output_path(args.out, "scenes.md", args.smoke) or Path("docs/results/scenes.md")
    return args


def main(argv: Sequence[str] | None = None) -> None:
    args = parse(argv)
    print(f"command: python benchmarks/eval_scenes.py {args.command}", flush=True)
    log = ResultLog(args.out.with_suffix(".jsonl"))
    for r in tune(args) if args.tune else evaluate_methods(args):
        log.append({**r, "command": args.command})
    write_text(args.out, markdown(log.rows))


if __name__ == "__main__":
    main()
