"""Peak memory and time of registering one full KITTI scan pair (about 120k points each) on the CPU.

    python benchmarks/kitti_full_pair.py --ckpt runs/.../best.ckpt [--pair 0] [--out docs/results/kitti_full_pair.md]
    python benchmarks/kitti_full_pair.py --smoke     # seconds, a synthetic pair, untrained weights

Each method runs in its own subprocess, so its peak resident memory (``ru_maxrss``) is its own: loading torch,
Lightning and the model, reading the two ``.bin`` scans at full resolution (``voxel_size: null``,
``num_points: null`` over ``configs/data/kitti.yaml``) and one ``register`` call. The resident memory just before
``register`` is printed too, so the registration's own share is visible. Methods: DVDs on every point, DVDs
voxelised (``configs/voxelize/lk27.yaml``), and FPFH + RANSAC + ICP (``configs/pipelines/ransac_icp_kitti.yaml``, which
voxel-downsamples at 0.3 m inside the method).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from functools import partial
from typing import Any

from lcreg.experiments.benchmarking import (
    METHODS,
    VOXELIZE_CONFIG,
    Values,
    add_smoke_argument,
    build,
    config_values,
    data_config,
    device_of,
    machine_line,
    markdown_table,
    output_path,
    peak_rss_mib,
    run_fresh_process,
    synthetic_overrides,
    timed,
    voxelize_overrides,
    write_text,
)
from lcreg.metrics.functional import rotation_error_deg, translation_error

METHOD_KEYS = {"dvds": "dvds", "dvds_voxel": "dvds_voxel", "ransac_icp": "ransac_icp_kitti"}
FULL = {"data.init_args.voxel_size": None, "data.init_args.num_points": None, "data.init_args.batch_size": 1}
SMOKE_DATA = synthetic_overrides(pairs=1, num_points=64, batch_size=1)
SMOKE_METHODS = ["dvds_voxel"]  # one fresh process (~5 s of imports); the others differ only by their config
SMOKE_VOXELS = voxelize_overrides(points_per_voxel=16, min_points=4)  # 64-point clouds: small voxels


def data(name: str, smoke: bool) -> tuple[list[str], Values]:
    """Configs and values of the pair: full KITTI scans, or one tiny synthetic pair in a smoke run."""
    if not smoke:
        return [data_config("kitti")], FULL
    return [], {**SMOKE_DATA, **(SMOKE_VOXELS if VOXELIZE_CONFIG in METHODS[name].configs else {})}


def child(key: str, ckpt: str | None, pair: int, smoke: bool, extra: list[str]) -> dict[str, Any]:
    """Register one full pair with one method (in this process) and return its measurements.

    ``extra``: the command line's config options (``--data.init_args.test_split=train``), applied last.
    """
    name = METHOD_KEYS[key]
    configs, values = data(name, smoke)
    weights = ckpt if METHODS[name].learned else None
    model, datamodule = build(name, weights, configs, {**values, **config_values(extra)}, with_data=True)
    datamodule.setup("test")
    dataset = datamodule.test_dataloader().dataset
    item = dataset[pair]
    src, ref, gt = item["points_src"][None], item["points_ref"][None], item["transform_ref_src"][None]
    before = peak_rss_mib()
    result, seconds = timed(partial(model.register, src, ref), device_of(model))
    pred = result.transform_ref_src.float()
    return {
        "method": METHODS[name].label,
        "pair": dataset.pairs[pair].name if hasattr(dataset, "pairs") else f"test pair {pair}",
        "points": [src.shape[1], ref.shape[1]],
        "seconds": seconds,
        "peak_rss_mib": peak_rss_mib(),
        "rss_before_register_mib": before,
        "rre_deg": float(rotation_error_deg(pred, gt)[0]),
        "rte_m": float(translation_error(pred, gt)[0]),
    }


def measurements(r: dict[str, Any]) -> list[str]:
    """Time, memory and errors of one row, formatted."""
    memory = [f"{r['peak_rss_mib']:.0f}", f"{r['rss_before_register_mib']:.0f}"]
    return [f"{r['seconds']:.2f}", *memory, f"{r['rre_deg']:.2f}", f"{r['rte_m']:.3f}"]


def table(rows: list[dict[str, Any]], command: str) -> str:
    """The Markdown report."""
    header = [
        "method",
        "pair",
        "points (src, ref)",
        "time s",
        "peak RSS MiB",
        "RSS before register MiB",
        "RRE °",
        "RTE m",
    ]
    cells = [[r["method"], r["pair"], f"{r['points'][0]}, {r['points'][1]}", *measurements(r)] for r in rows]
    machine = f"{machine_line()}, one process per method."
    return f"Command: `python benchmarks/kitti_full_pair.py {command}`; {machine}\n\n" + markdown_table(header, cells)


def parse(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ckpt", default=None, help="DVDs checkpoint trained on ModelNet40; required")
    parser.add_argument("--pair", type=int, default=0, help="index of the test pair")
    parser.add_argument("--methods", nargs="*", default=None, choices=list(METHOD_KEYS), help="default: all")
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--out", default=None, help="write a Markdown table here")
    add_smoke_argument(parser)
    # Every other argument is a config value, e.g. --data.init_args.test_split=train (typed as `lcreg` types it)
    args, args.data_args = parser.parse_known_args(argv)
    config_values(args.data_args)  # a malformed one fails here, before any process starts
    args.command = " ".join(sys.argv[1:] if argv is None else argv)
    if not args.ckpt and not args.smoke:
        parser.error("--ckpt is required (outside --smoke, where untrained weights are used)")
    if args.methods is None:
        args.methods = SMOKE_METHODS if args.smoke else list(METHOD_KEYS)
    return args


def main(argv: Sequence[str] | None = None) -> None:
    args = parse(argv)
    if args.child:
        print(json.dumps(child(args.child, args.ckpt, args.pair, args.smoke, args.data_args)), flush=True)
        return
    rows = []
    for key in args.methods:
        cmd = [__file__, "--child", key, "--pair", str(args.pair), *(["--ckpt", args.ckpt] if args.ckpt else [])]
        rows.append(run_fresh_process([*cmd, *(["--smoke"] if args.smoke else []), *args.data_args]))
        print(json.dumps(rows[-1]), flush=True)
    report = table(rows, args.command)
    print(report)
    out = output_path(args.out, "kitti_full_pair.md", args.smoke)
    if out:
        write_text(out, "# One full KITTI scan pair: peak memory and time\n\n" + report + "\n")


if __name__ == "__main__":
    main()
