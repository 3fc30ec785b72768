"""The error floor of the correspondence protocols: a rigid fit on the exact matches of every test pair (issue 23).

    python benchmarks/oracle_floor.py --root ../shared/data/modelnet40_mini \
        --out docs/results/converge/oracle_floor.md
    python benchmarks/oracle_floor.py --smoke      # seconds: embedded shapes, a few pairs

DCP-v2, PRNet and IDAM are trained and tested on same-points pairs (the DCP-family protocol: both clouds are one
sampling, shuffled), where every point of the source has its partner in the reference before noise. This script
fits the least-squares rigid transform (:func:`lcreg.geometry.procrustes.weighted_kabsch`, float64) to those exact
matches (:func:`lcreg.data.pairs.true_correspondences`) of every test pair, noise and crop included, for the
settings of the queue's runs and of the papers: what a method that found every correspondence would score. It
separates what the pairs themselves cost (independent noise on both clouds, where DCP's code adds one and the same
noise to both; a partial crop) from what a network's matching costs. Nothing is trained; the pairs are the runs'
(``lcreg reproduce``'s data: seed 1234, the same constructor values).
"""

from __future__ import annotations

import argparse
import statistics
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from lcreg.data.pairs import true_correspondences
from lcreg.experiments.benchmarking import (
    add_smoke_argument,
    apply_smoke,
    machine_line,
    markdown_table,
    output_path,
    pair_datamodule,
)
from lcreg.experiments.benchmarking.writers import write_text
from lcreg.experiments.reproduce.budgets import DEFAULT_ROOT, PAIR_SEED, SMOKE_PAIRS
from lcreg.geometry.procrustes import weighted_kabsch
from lcreg.metrics.registration import registration_metrics

METRICS = (
    ("rmse_r_deg", "RMSE(R) °", ".3g"),
    ("mae_r_deg", "MAE(R) °", ".3g"),
    ("rmse_t", "RMSE(t)", ".2g"),
    ("mae_t", "MAE(t)", ".2g"),
    ("rre_median_deg", "median RRE °", ".3g"),
    ("recall_r2_t0p01", "recall (2°, 0.01)", ".1%"),
)
"""The metrics of the table: key of :func:`~lcreg.metrics.registration.registration_metrics`, header, format."""


@dataclass(frozen=True)
class Setting:
    """One pair protocol of the table (same-points pairs, noise clipped at 0.05).

    Attributes:
        name: What it is.
        used_by: The runs or the paper's table that use it.
        points: Points sampled per cloud.
        noise_sigma: Gaussian noise on each cloud, drawn independently.
        partial: ``"none"`` or ``"prnet"`` (PRNet's and IDAM's shared far anchor).
        keep: Fraction of the points a crop keeps.
    """

    name: str
    used_by: str
    points: int
    noise_sigma: float
    partial: str = "none"
    keep: float = 0.75

    def options(self) -> dict[str, Any]:
        """The DataModule values of the DCP-family pairs in this setting (``configs/data/dcp_protocol.yaml``'s)."""
        crop = {} if self.partial == "none" else {"partial": self.partial, "partial_keep": self.keep}
        noise = {"noise_sigma": self.noise_sigma, "noise_clip": 0.05}
        return {"independent_sampling": False, "seed": PAIR_SEED, "num_workers": 0, **noise, **crop}


SETTINGS = (
    Setting("full clouds, clean", "DCP Tab. 1 (1024 points); a check: the floor is 0", 1024, 0.0),
    Setting("full clouds, σ 0.01", "`lc_dcp_prnet_converge` (DCP-v2, PRNet), `dcp_data_256`, `dcp_lr_256`", 256, 0.01),
    Setting(
        "full clouds, σ 0.01",
        "DCP Tab. 3's size (its code adds one and the same noise to both clouds: a floor of 0 there)",
        1024,
        0.01,
    ),
    Setting("PRNet crop 0.75, σ 0.01", "`gpu_prnet_partial` (PRNet)", 256, 0.01, "prnet"),
    Setting("PRNet crop 0.75, σ 0.01", "`idam_partial_converge` and its probes (IDAM)", 512, 0.01, "prnet"),
    Setting("PRNet crop 0.75, σ 0.01", "`idam_partial_1024`; IDAM Tab. 1 and PRNet's size", 1024, 0.01, "prnet"),
)
SMOKE = {"points": 64}


@dataclass(frozen=True)
class Floor:
    """The oracle fit's metrics on one setting's test pairs, and how many exact matches each pair had."""

    pairs: int
    matches: list[int]
    metrics: dict[str, float]


def oracle_floor(root: str | None, setting: Setting, points: int | None = None) -> Floor:
    """Fit every test pair of ``setting`` on its exact matches.

    Args:
        root: ModelNet40 folder, or ``None`` for the embedded synthetic shapes.
        setting: The pair protocol.
        points: Points per cloud instead of ``setting.points`` (smoke runs).

    Raises:
        ValueError: If a pair has fewer than 3 exact matches (no rigid fit).
    """
    pairs = SMOKE_PAIRS if root is None else None
    dm, _ = pair_datamodule(root, "test", pairs, points or setting.points, **setting.options())
    dm.setup("test")
    assert dm.test_set is not None
    metrics = registration_metrics()
    matches = []
    for index in range(len(dm.test_set)):
        pair = dm.test_set.item_with_indices(index)
        rows_src, rows_ref = true_correspondences(pair["point_index_src"], pair["point_index_ref"])
        if len(rows_src) < 3:
            raise ValueError(f"test pair {index} of {setting.name} has {len(rows_src)} exact matches (< 3)")
        src = pair["points_src"].double()[rows_src][None]
        ref = pair["points_ref"].double()[rows_ref][None]
        estimate = weighted_kabsch(src, ref).float()
        metrics.update(transform_pred=estimate, transform_gt=pair["transform_ref_src"][None])
        matches.append(len(rows_src))
    values = {key: float(value) for key, value in metrics.compute().items()}
    return Floor(len(dm.test_set), matches, values)


def table(root: str | None, points: int | None = None) -> str:
    """The Markdown table of every setting of :data:`SETTINGS`."""
    header = ["setting", "used by", "points (kept)", "test pairs", "exact matches per pair (mean, min)"]
    rows = []
    for setting in SETTINGS:
        floor = oracle_floor(root, setting, points)
        size = points or setting.points
        kept = f"{size} ({round(setting.keep * size)})" if setting.partial != "none" else f"{size}"
        matched = f"{statistics.fmean(floor.matches):.0f}, {min(floor.matches)}"
        cells = [format(floor.metrics[key], fmt) for key, _, fmt in METRICS]
        rows.append([setting.name, setting.used_by, kept, floor.pairs, matched, *cells])
    return markdown_table(header + [label for _, label, _ in METRICS], rows)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--root", default=DEFAULT_ROOT, help="ModelNet40 folder (default: %(default)s)")
    parser.add_argument("--points", type=int, help="every setting at this many points instead of its own")
    parser.add_argument("--out", help="write the report here (Markdown) as well as printing it")
    add_smoke_argument(parser)
    args = apply_smoke(parser.parse_args(argv), SMOKE)
    source = "embedded synthetic shapes (smoke: the numbers mean nothing)" if args.root is None else args.root
    command = "--smoke" if args.smoke else f"--root {args.root}" + (f" --points {args.points}" if args.points else "")
    text = "\n".join(
        [
            "# Oracle floor: the rigid fit on the exact matches of every test pair",
            "",
            f"`python benchmarks/oracle_floor.py {command}`; data: {source}, the test pairs of the runs "
            f"(pair seed {PAIR_SEED}); {machine_line()}. Same-points pairs, Gaussian noise clipped at 0.05 drawn "
            "independently on each cloud, Euler angles U[0°, 45°], t U[-0.5, 0.5]. Nothing is trained: this is "
            "what a method that found every correspondence would score.",
            "",
            table(args.root, args.points),
            "",
        ]
    )
    print(text)
    if (path := output_path(args.out, "oracle_floor.md", args.smoke)) is not None:
        write_text(path, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
