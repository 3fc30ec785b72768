"""Peak memory and time of registering one full KITTI scan pair (about 120k points each) on the CPU.

    python benchmarks/kitti_full_pair.py --ckpt runs/.../best.ckpt [--pair 0] [--out docs/results/kitti_full_pair.md]

Each method runs in its own subprocess, so its peak resident memory (``ru_maxrss``) is its own: loading torch,
Lightning and the model, reading the two ``.bin`` scans at full resolution (``voxel_size: null``,
``num_points: null`` over ``configs/real/kitti.yaml``) and one ``register`` call. The resident memory just before
``register`` is printed too, so the registration's own share is visible. Methods: DVDs on every point, DVDs
voxelised (``configs/voxelize/lk27.yaml``), and FPFH + RANSAC + ICP (``configs/real/ransac_icp_kitti.yaml``, which
voxel-downsamples at 0.3 m inside the method).
"""

from __future__ import annotations

import argparse
import json
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

import torch

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from eval_scenes import METHODS, build  # noqa: E402

FULL = ["--data.init_args.voxel_size=null", "--data.init_args.num_points=null", "--data.init_args.batch_size=1"]


def _rss_mib() -> float:
    """Peak resident set size of this process so far, MiB (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def child(method: str, ckpt: str, pair: int, extra: list[str]) -> None:
    """Register one full pair with one method and print a JSON line."""
    from lcreg.metrics.functional import rotation_error_deg, translation_error

    label, configs = METHODS[method]
    model, datamodule = build(configs, "kitti", ckpt if configs[0].startswith("dvds") else None, FULL + extra)
    datamodule.setup("test")
    item = datamodule.datasets["test"][pair]
    src, ref, gt = item["points_src"][None], item["points_ref"][None], item["transform_ref_src"][None]
    before = _rss_mib()
    start = time.perf_counter()
    result = model.register(src, ref)
    seconds = time.perf_counter() - start
    pred = result.transform_ref_src.float()
    print(
        json.dumps(
            {
                "method": label,
                "pair": datamodule.datasets["test"].pairs[pair].name,
                "points": [src.shape[1], ref.shape[1]],
                "seconds": seconds,
                "peak_rss_mib": _rss_mib(),
                "rss_before_register_mib": before,
                "rre_deg": float(rotation_error_deg(pred, gt)[0]),
                "rte_m": float(translation_error(pred, gt)[0]),
            }
        ),
        flush=True,
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ckpt", required=True, help="DVDs checkpoint trained on ModelNet40")
    parser.add_argument("--pair", type=int, default=0, help="index of the test pair")
    parser.add_argument("--methods", nargs="*", default=list(METHODS), choices=list(METHODS))
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--out", default=None, help="write a Markdown table here")
    # Every other argument is a LightningCLI override, e.g. --data.init_args.test_split=train
    args, args.data_args = parser.parse_known_args()
    if args.child:
        child(args.child, args.ckpt, args.pair, args.data_args)
        return
    rows = []
    for method in args.methods:
        cmd = [sys.executable, __file__, "--child", method, "--ckpt", args.ckpt, "--pair", str(args.pair)]
        cmd += args.data_args
        done = subprocess.run(cmd, capture_output=True, text=True, check=False)
        lines = [line for line in done.stdout.splitlines() if line.startswith("{")]
        if done.returncode != 0 or not lines:
            raise SystemExit(f"{method} failed:\n{done.stderr[-3000:]}")
        rows.append(json.loads(lines[-1]))
        print(lines[-1], flush=True)
    table = [
        f"Command: `python benchmarks/kitti_full_pair.py {' '.join(sys.argv[1:])}`; "
        f"{platform.processor() or platform.machine()}, torch {torch.__version__}, CPU, one process per method.",
        "",
        "| method | pair | points (src, ref) | time s | peak RSS MiB | RSS before register MiB | RRE ° | RTE m |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        table.append(
            f"| {r['method']} | {r['pair']} | {r['points'][0]}, {r['points'][1]} | {r['seconds']:.2f} | "
            f"{r['peak_rss_mib']:.0f} | {r['rss_before_register_mib']:.0f} | {r['rre_deg']:.2f} | {r['rte_m']:.3f} |"
        )
    print("\n".join(table))
    if args.out:
        Path(args.out).write_text("# One full KITTI scan pair: peak memory and time\n\n" + "\n".join(table) + "\n")


if __name__ == "__main__":
    main()
