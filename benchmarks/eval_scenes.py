"""ModelNet40-trained models on real scenes: DVDs, DVDs voxelised and Open3D RANSAC + ICP on the same pairs.

    python benchmarks/eval_scenes.py --dataset sevenscenes --ckpt runs/.../best.ckpt --out docs/results/scenes.md
    python benchmarks/eval_scenes.py --dataset kitti --ckpt runs/.../best.ckpt --out docs/results/scenes.md
    python benchmarks/eval_scenes.py --tune --ckpt runs/.../best.ckpt --out docs/results/scenes_tuning.md

* Every method is built from the same configs ``lcreg test`` uses: the model config (``configs/dvds_modelnet40.yaml``
  with ``--ckpt``), the data add-on ``configs/real/<dataset>.yaml``, ``configs/voxelize/lk27.yaml`` for the voxelised
  row and ``configs/real/ransac_icp_<dataset>.yaml`` for RANSAC + ICP. The DataModule of the data config makes the
  pairs once; every method sees the same batches.
* Metrics: :func:`lcreg.evaluation.evaluate` (RMSE/MAE of the Euler angles in degrees and of the translation in
  metres, mean/median RRE) plus the scene recall of the usual benchmarks: RRE < 15° and RTE < 0.3 m on 3DMatch /
  7-Scenes (FCGF, DGR), RRE < 5° and RTE < 2 m on KITTI (DGR, GeoTransformer). ms/pair is the wall time of
  ``register``.
* ``--tune`` picks the voxelisation settings on validation scenes only (3DMatch SUN3D scenes, never redkitchen or
  KITTI): each candidate :class:`~lcreg.nn.voxel_lk.VoxelGrid` is run with DVDs and ranked by mean RRE.

Rows are appended to ``<out>.jsonl``; the Markdown file is rewritten from all rows each time.
"""

from __future__ import annotations

import argparse
import itertools
import json
import platform
import sys
from pathlib import Path
from typing import Any

import torch

from lcreg.evaluation import EvaluationReport, evaluate
from lcreg.metrics.functional import registration_recall

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
RECALL = {"sevenscenes": (15.0, 0.3), "kitti": (5.0, 2.0)}
VALIDATION_SCENES = ["sun3d-home_md-home_md_scan9_2012_sep_30", "sun3d-mit_76_studyroom-76-1studyroom2"]
METHODS = {
    "dvds": ("DVDs", ["dvds_modelnet40.yaml"]),
    "dvds_voxel": ("DVDs voxelised (27 voxels)", ["dvds_modelnet40.yaml", "voxelize/lk27.yaml"]),
    "ransac_icp": ("FPFH + RANSAC + ICP", ["real/ransac_icp_{dataset}.yaml"]),
}


def build(configs: list[str], dataset: str, ckpt: str | None, extra: list[str]) -> tuple[Any, Any]:
    """Model (with checkpoint weights, refiner and voxel grid of the configs) and DataModule of a config list."""
    from lcreg.cli import build_cli

    args = []
    for name in [*configs, f"real/{dataset}.yaml"]:
        args += ["--config", str(CONFIGS / name.format(dataset=dataset))]
    cli = build_cli(args + extra, run=False)
    model = cli.model if ckpt is None else cli.model.load_weights(ckpt)
    return model.eval(), cli.datamodule


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
    rows = []
    batches = None
    for key in args.methods:
        label, configs = METHODS[key]
        ckpt = args.ckpt if configs[0].startswith("dvds") else None
        model, datamodule = build(configs, args.dataset, ckpt, args.data_args)
        if batches is None:
            datamodule.setup("test")
            batches = list(datamodule.test_dataloader())
        torch.manual_seed(0)
        report = evaluate(model, batches, label)
        extra = {"checkpoint": ckpt, "data_args": args.data_args, "section": args.section or args.dataset}
        rows.append(row(report, args.dataset, key, extra))
        print(json.dumps(rows[-1]), flush=True)
    return rows


def tune(args: argparse.Namespace) -> list[dict[str, Any]]:
    """Voxel settings for DVDs on the validation scenes (mean RRE, lower is better)."""
    extra = ["--data.init_args.test_scenes", json.dumps(VALIDATION_SCENES)]
    model, datamodule = build(["dvds_modelnet40.yaml"], "sevenscenes", args.ckpt, extra)
    datamodule.setup("test")
    batches = list(datamodule.test_dataloader())
    from lcreg.nn.voxel_lk import VoxelGrid

    rows = []
    candidates: list[VoxelGrid | None] = [None]
    for normalize, coarse, reassign in itertools.product([False, True], [0, 10], [1, 5]):
        candidates.append(VoxelGrid(3, 512, 32, normalize, coarse_iterations=coarse, reassign_every=reassign))
    for grid in candidates:
        model.set_voxel_grid(grid)
        report = evaluate(model, batches, repr(grid) if grid else "no voxelisation")
        section = f"validation: {', '.join(VALIDATION_SCENES)} (3DMatch, overlap > 0.7)"
        rows.append(row(report, "sevenscenes-val", "tune", {"scenes": VALIDATION_SCENES, "section": section}))
        print(json.dumps(rows[-1]), flush=True)
    return rows


def write_markdown(rows: list[dict[str, Any]], out: Path) -> None:
    """Rewrite the results file from every row (one table per dataset)."""
    lines = [
        "# ModelNet40-trained registration on real scenes",
        "",
        f"Machine: {platform.processor() or platform.machine()}, torch {torch.__version__}, "
        f"{torch.get_num_threads()} threads, CPU. Commands: see each section.",
        "",
    ]
    for section in dict.fromkeys(r.get("section", r["dataset"]) for r in rows):
        subset = [r for r in rows if r.get("section", r["dataset"]) == section]
        rot_thr, trans_thr = RECALL[subset[0]["dataset"].removesuffix("-val")]
        commands = dict.fromkeys(f"`python benchmarks/eval_scenes.py {r.get('command', '')}`" for r in subset)
        lines += [
            f"## {section}",
            "",
            "Command: " + "; ".join(commands),
            "",
            "| method | pairs | RMSE(R) ° | MAE(R) ° | RMSE(t) m | MAE(t) m | mean RRE ° | median RRE ° | mean RTE m | "
            f"recall (RRE < {rot_thr:g}°, RTE < {trans_thr:g} m) | ms/pair |",
            "|---" * 11 + "|",
        ]
        for r in subset:
            m = r["metrics"]
            lines.append(
                f"| {r['label']} | {r['pairs']} | {m['rmse_r_deg']:.2f} | {m['mae_r_deg']:.2f} | {m['rmse_t']:.3f} | "
                f"{m['mae_t']:.3f} | {m['rre_mean_deg']:.2f} | {m['rre_median_deg']:.2f} | {m['rte_mean']:.3f} | "
                f"{100 * r['scene_recall']:.1f} % | {r['ms_per_pair']:.0f} |"
            )
        lines.append("")
    out.write_text("\n".join(lines))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dataset", choices=sorted(RECALL), default="sevenscenes")
    parser.add_argument("--ckpt", required=True, help="DVDs checkpoint trained on ModelNet40 (chosen on validation)")
    parser.add_argument("--methods", nargs="*", default=list(METHODS), choices=list(METHODS))
    parser.add_argument("--tune", action="store_true", help="choose the voxel settings on the validation scenes")
    parser.add_argument("--section", default=None, help="title of this run's table (default: the dataset)")
    parser.add_argument("--out", default="docs/results/scenes.md")
    # Every other argument is a LightningCLI override, e.g. --data.init_args.test_split=train
    args, args.data_args = parser.parse_known_args()
    torch.set_num_threads(max(1, torch.get_num_threads()))
    print(f"command: python benchmarks/eval_scenes.py {' '.join(sys.argv[1:])}", flush=True)
    out = Path(args.out)
    jsonl = out.with_suffix(".jsonl")
    new = tune(args) if args.tune else evaluate_methods(args)
    with jsonl.open("a") as fh:
        for r in new:
            fh.write(json.dumps({**r, "command": " ".join(sys.argv[1:])}) + "\n")
    write_markdown([json.loads(line) for line in jsonl.read_text().splitlines()], out)


if __name__ == "__main__":
    main()
