"""Every ``lcreg register`` method on real pairs through ``lcreg register --pairs``; validation picks the default.

    python benchmarks/register_scenes.py --set validation --out docs/results/register_validation.md
    python benchmarks/register_scenes.py --set test --out docs/results/register_test.md    # 3DMatch + KITTI
    python benchmarks/register_scenes.py --smoke                                             # seconds, synthetic

Sets (``../shared/data``):

* ``validation``: ModelNet40 validation pairs (78 pairs of the object protocol: 1,024 points, Euler U[0,45]° per axis,
  t U[-0.5,0.5]; written as ``.npy`` files + a CSV under ``--out``), the two 3DMatch SUN3D scenes used as validation
  scenes since the voxelised-LK tuning (home_md scan9, mit_76_studyroom; all their ``gt.log`` pairs) and the KITTI
  sequence 00 pairs (frames 0-15 at least 10 m apart, ICP-refined ground truth; sequence 00 is in KITTI's training
  split). The default method is the one with the best recall averaged over the three kinds.
* ``test``: all 8 scenes of the 3DMatch benchmark and of 3DLoMatch (its low-overlap pairs, 10-30 %; every
  ``gt.log`` pair, official recall on the scored pairs) and the KITTI pairs.

Each (set, method) writes ``<results>/<set>/<data>__<method>.csv`` (resumable: a rerun continues it) and its
``.summary.json``; the Markdown table (``--out``) is rebuilt from all summaries found.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from lcreg.experiments.benchmarking import add_smoke_argument, machine_line, markdown_table, write_text
from lcreg.registration.command import run

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
VALIDATION_SCENES = ["sun3d-home_md-home_md_scan9_2012_sep_30", "sun3d-mit_76_studyroom-76-1studyroom2"]
METHODS = ["ransac+icp", "fgr+icp", "dvds+icp", "icp"]
"""Pipelines and ICP: each pipeline's results CSV also scores its coarse step alone (``ransac``, ``fgr``, ``dvds``:
the same computation, timed up to its end), so every method and pipeline is measured with one run per pipeline."""


def modelnet40_val_csv(folder: Path, smoke: bool = False) -> Path:
    """Write the ModelNet40 validation pairs (or 2 synthetic pairs with ``smoke``) as ``.npy`` + ``pairs.csv``."""
    folder.mkdir(parents=True, exist_ok=True)
    csv = folder / "pairs.csv"
    if csv.is_file():
        return csv
    if smoke:
        sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
        from _register_pairs import make_pair  # type: ignore[import-not-found]

        batches = [(make_pair()[0][None], make_pair()[1][None], make_pair()[2][None])] * 2
    else:
        from lcreg.data.datamodule import ModelNet40DataModule

        dm = ModelNet40DataModule(root=str(DATA / "modelnet40_mini"), num_points=1024, batch_size=32, seed=1234)
        dm.setup("fit")
        batches = [
            (b.points_src.numpy(), b.points_ref.numpy(), b.transform_ref_src.numpy()) for b in dm.val_dataloader()
        ]
    lines, k = ["src,ref,gt"], 0
    for src, ref, gt in batches:
        for i in range(len(src)):
            np.save(folder / f"src_{k:03d}.npy", src[i].astype(np.float32))
            np.save(folder / f"ref_{k:03d}.npy", ref[i].astype(np.float32))
            lines.append(f"src_{k:03d}.npy,ref_{k:03d}.npy," + " ".join(f"{x:.10g}" for x in gt[i].reshape(-1)))
            k += 1
    csv.write_text("\n".join(lines) + "\n")
    return csv


def kitti_csv(folder: Path) -> Path:
    """The KITTI sequence 00 pairs (frames >= 10 m apart among those with scans; ICP-refined ground truth) as a CSV."""
    folder.mkdir(parents=True, exist_ok=True)
    csv = folder / "kitti_pairs.csv"
    if csv.is_file():
        return csv
    from lcreg.data.kitti import kitti_pairs

    pairs = kitti_pairs(DATA / "kitti", "train", selection="all")
    lines = ["src,ref,gt"] + [
        f"{p.path_src},{p.path_ref}," + " ".join(f"{x:.10g}" for x in p.transform_ref_src.reshape(-1)) for p in pairs
    ]
    csv.write_text("\n".join(lines) + "\n")
    return csv


def datasets(kind: str, out: Path, smoke: bool) -> dict[str, list[str]]:
    """``name -> --pairs`` arguments (one or more lists, registered into one results file each)."""
    if smoke:
        return {"synthetic": [str(modelnet40_val_csv(out / "synthetic", smoke=True))]}
    bench = DATA / "3dmatch" / "benchmarks" / "3DMatch"
    if kind == "validation":
        return {
            "modelnet40_val": [str(modelnet40_val_csv(out / "modelnet40_val"))],
            "3dmatch_val": [str(bench / s) for s in VALIDATION_SCENES],
            "kitti00": [str(kitti_csv(out))],
        }
    low = DATA / "3dmatch" / "benchmarks" / "3DLoMatch"
    return {"3dmatch": [str(bench)], "3dlomatch": [str(low)], "kitti00": [str(kitti_csv(out))]}


def run_one(pairs: list[str], method: str, results: Path, extra: Sequence[str]) -> None:
    """``lcreg register --pairs`` for each list into ``results`` (resumed; one file per list, then merged)."""
    for i, path in enumerate(pairs):
        part = results.with_name(f"{results.stem}.part{i}.csv") if len(pairs) > 1 else results
        print(f"== {method}: {path} -> {part}", flush=True)
        run(["--pairs", path, "--method", method, "--results", str(part), "--resume", "--no-progress", *extra])


def _summaries(folder: Path) -> list[dict[str, Any]]:
    rows = []
    for path in sorted(folder.glob("*.summary.json")):
        data, _, label = path.name.removesuffix(".summary.json").partition("__")
        summary = json.loads(path.read_text())
        name, _, tag = label.split(".part")[0].partition("@")
        method = name.replace("-", "+") + (f" ({tag})" if tag else "")  # as asked ("default"), from the file name
        rows.append({**summary, "data": data.split(".part")[0], "part": path.name, "method": method})
    return rows


def _cell(value: float | None, percent: bool = False, digits: str = ".3g") -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    return f"{100 * value:.1f} %" if percent else format(value, digits)


def table(folder: Path) -> str:
    """Markdown: one row per (data, method, group) from the summaries in ``folder``."""
    header = [
        "data",
        "group",
        "method",
        "pairs",
        "recall (RRE, RTE)",
        "3DMatch recall (scored)",
        "median RRE °",
        "median RTE",
        "ms/pair",
    ]
    rows = []
    for s in _summaries(folder):
        for method, scores in _variants(s):
            rows += _rows(s["data"], method, scores)
    return markdown_table(header, rows)


def _variants(summary: dict[str, Any]) -> list[tuple[str, dict[str, Any]]]:
    """``(method label, scores)``: the method, then its coarse step when it is a pipeline."""
    out = [(summary["method"], summary)]
    if "coarse" in summary and summary["method"] != "default":
        coarse = summary["method"].partition("+")[0]
        out.append((f"{coarse} (coarse step of {summary['method']})", summary["coarse"]))
    return out


def _rows(data: str, method: str, s: dict[str, Any]) -> list[list[Any]]:
    """Table rows of one summary: each scene (when several), then all pairs, then the mean of the scenes' recalls."""
    groups = s["groups"] if len(s["groups"]) > 1 else {}
    only = next(iter(s["groups"]), "") if len(s["groups"]) == 1 else ""
    rows = []
    for name, g in [*groups.items(), (only or "all", s["overall"])]:
        recall = g.get("threedmatch_recall")
        scored = "-" if recall is None else f"{_cell(recall, True)} ({g.get('scored_pairs', 0)})"
        rre, rte = _cell(g.get("rre_median_deg")), _cell(g.get("rte_median"))
        rows.append([data, name, method, g["pairs"], _cell(g.get("recall"), True), scored, rre, rte,
                     f"{g['ms_per_pair']:.0f}"])  # fmt: skip
    if "threedmatch_recall_scene_mean" in s["overall"]:
        mean = _cell(s["overall"]["threedmatch_recall_scene_mean"], True)
        rows.append([data, "mean of scenes", method, "", "", mean, "", "", ""])
    return rows


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--set", choices=("validation", "test"), default="validation")
    parser.add_argument("--methods", nargs="+", default=METHODS)
    parser.add_argument("--data", nargs="+", help="only these data names (e.g. 3dmatch kitti00)")
    parser.add_argument("--out", help="write the Markdown table here")
    parser.add_argument("--results", help="results folder (default: runs/register_bench; a temporary one with --smoke)")
    parser.add_argument("--table-only", action="store_true", help="only rebuild the table from the results found")
    parser.add_argument("--tag", default="", help="suffix of the results files and method labels (with --extra)")
    parser.add_argument("--extra", nargs=argparse.REMAINDER, default=[], help="more lcreg register options")
    add_smoke_argument(parser)
    args = parser.parse_args(argv)
    out = Path(args.results or (tempfile.mkdtemp(prefix="lcreg_register_") if args.smoke else "runs/register_bench"))
    folder = out / ("smoke" if args.smoke else args.set)
    folder.mkdir(parents=True, exist_ok=True)
    methods = ["icp", "ransac+icp"] if args.smoke else args.methods
    for data, pairs in ({} if args.table_only else datasets(args.set, out, args.smoke)).items():
        if args.data and data not in args.data:
            continue
        for method in methods:
            run_one(pairs, method, folder / f"{data}__{method.replace('+', '-')}{args.tag}.csv", args.extra)
    text = f"Machine: {machine_line()}\n\n{table(folder)}\n"
    print(text)
    if args.out:
        write_text(args.out, text)


if __name__ == "__main__":
    main()
