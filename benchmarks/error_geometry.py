"""Do a model's test errors lie along motions the object's shape barely pins down? (issue 23, goal (d))

    python benchmarks/error_geometry.py \
        --runs runs/.../seed0/retest-32-true-noise_sigma-0/run runs/.../seed1/... runs/.../seed2/... \
        --out docs/results/converge/error_geometry/idam_partial.md
    python benchmarks/error_geometry.py --smoke      # seconds: embedded shapes, made-up estimates

Each run folder is one ``lcreg test`` (or ``lcreg reproduce ... --retest``) of one seed: its ``config.yaml`` rebuilds
the test pairs, its ``test_transforms.npz`` holds each pair's estimate and truth (:mod:`lcreg.models.evaluation`).
The pairs must be clean (no noise), so that every source point lies on its object.

Per pair, the error motion ``E = T_gt^-1 T_pred`` (the source moved in its own frame) is scored by its surface
residual (:func:`lcreg.geometry.surface.surface_residual`): the mean point-to-plane distance of the moved source
points to the whole object (all its points, PCA normals of ``--normal-k`` neighbours). The same is computed for
``--draws`` random motions of the same rotation angle and translation length
(:func:`lcreg.geometry.surface.random_motions_like`). Their ratio, the **residual ratio**, is about 1 for a
misalignment like any other of its size and well below 1 for an error along a near-symmetry of the shape (a flat
box slid along its faces, a round tub turned about its axis): an error the surface hardly shows. The **shape
freedom** is the 10th percentile of the random motions' residuals over their median: how much less the object's
easiest directions show than a typical one, at this pair's error size (1: no easy direction). The last column does
the same for the error's rotation alone, about the object's centroid, against random rotations of its angle: a turn
about an axis of symmetry through the centroid (a vase's) scores near 0 there even when the error also shifts.

Groups as ``benchmarks/class_breakdown.py``'s: all pairs, each class with ``--min-pairs`` pairs, the rest pooled.
Per group and seed the medians over its pairs (of the pairs with a rotation error above ``--large-deg`` too); each
cell is the mean ± sample std over the seeds. A failed pair (non-finite estimate) is counted, not scored.
"""

from __future__ import annotations

import argparse
import csv
import importlib
import math
import statistics
import sys
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml

from lcreg.data.datamodule import PairDataModule
from lcreg.experiments.benchmarking import ClassGroup, add_smoke_argument, class_groups, markdown_table, write_or_print
from lcreg.experiments.benchmarking.writers import format_mean_std
from lcreg.geometry import se3
from lcreg.geometry.neighbors import knn
from lcreg.geometry.normals import estimate_normals
from lcreg.geometry.surface import random_motions_like, surface_residual
from lcreg.metrics.functional import rotation_error_deg
from lcreg.models.evaluation import TRANSFORMS_FILE

ON_SURFACE = 1e-4
"""Largest distance (object units) of a clean source point to its object's nearest point: above it, refused."""
PLOT_MIN_DEG = 0.01
"""Pairs with a smaller rotation error are not drawn (rounding-level errors would stretch the log axis)."""
SAME_TRUTH = 1e-4
"""Largest difference of a ``transform_gt`` entry to the rebuilt pair's: above it, the files hold other pairs."""


class ErrorGeometryError(ValueError):
    """A run folder lacks a file, or its transforms are not the pairs its config builds, or its pairs are noisy."""


@dataclass(frozen=True)
class PairGeometry:
    """One scored test pair of one run.

    Attributes:
        index: Dataset index.
        cls: Object class (``"all"`` without labels).
        rre_deg: Geodesic rotation error, degrees.
        residual: Surface residual of the error motion (object units).
        random_median: Median surface residual of the random motions of the same size.
        random_p10: Their 10th percentile.
        turn_residual: Surface residual of the error's rotation alone, about the object's centroid (the origin of
            the pairs' normalized frame).
        turn_random_median: Median surface residual of random rotations of the same angle about the centroid.
    """

    index: int
    cls: str
    rre_deg: float
    residual: float
    random_median: float
    random_p10: float
    turn_residual: float
    turn_random_median: float

    @property
    def ratio(self) -> float:
        """Residual ratio: the error's residual over the median of random motions of its size."""
        return self.residual / self.random_median if self.random_median > 0 else float("nan")

    @property
    def turn_ratio(self) -> float:
        """Residual ratio of the error's rotation alone, against random rotations of its angle about the centroid."""
        return self.turn_residual / self.turn_random_median if self.turn_random_median > 0 else float("nan")

    @property
    def freedom(self) -> float:
        """Shape freedom at this size: 10th percentile over median of the random motions' residuals."""
        return self.random_p10 / self.random_median if self.random_median > 0 else float("nan")


def run_datamodule(config: Path) -> PairDataModule:
    """The DataModule of a run's ``config.yaml`` (its ``data`` block), set up for ``test``."""
    try:
        data = yaml.safe_load(config.read_text(encoding="utf-8"))["data"]
        module, _, name = data["class_path"].rpartition(".")
        dm = getattr(importlib.import_module(module), name)(**data.get("init_args", {}))
    except (OSError, yaml.YAMLError, KeyError, TypeError, AttributeError, ImportError) as err:
        raise ErrorGeometryError(f"{config}: no usable `data` block ({type(err).__name__}: {err})") from err
    if not isinstance(dm, PairDataModule):
        raise ErrorGeometryError(f"{config}: {type(dm).__name__} is not a PairDataModule (object pairs)")
    dm.setup("test")
    return dm


def read_transforms(run: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(index (P,), transform_pred (P, 4, 4), transform_gt (P, 4, 4))`` of a run's test."""
    path = run / TRANSFORMS_FILE
    try:
        with np.load(path) as data:
            index, pred, gt = (np.asarray(data[k]) for k in ("index", "transform_pred", "transform_gt"))
    except (OSError, KeyError, ValueError) as err:
        raise ErrorGeometryError(f"{path}: cannot be read ({err}); test the weights again to write it") from err
    if pred.shape != gt.shape or pred.shape != (len(index), 4, 4):
        raise ErrorGeometryError(f"{path}: shapes {index.shape}, {pred.shape}, {gt.shape} do not agree")
    return index, pred, gt


def score_pair(
    dm: PairDataModule, index: int, pred: np.ndarray, gt: np.ndarray, args: argparse.Namespace
) -> PairGeometry | None:
    """The :class:`PairGeometry` of test pair ``index`` (``None`` for a failed pair)."""
    test_set = dm.test_set
    assert test_set is not None  # set up by run_datamodule
    item = test_set[index]
    truth = item["transform_ref_src"].double()
    if not torch.allclose(truth, torch.from_numpy(gt), atol=SAME_TRUTH, rtol=0):
        raise ErrorGeometryError(f"pair {index}: its transform_gt is not the config's pair (other data options?)")
    if not np.isfinite(pred).all():
        return None
    source = item["points_src"].double()[None]  # (1, K, 3)
    surface = test_set.object_points(index)[None]  # (1, P, 3)
    off = float(knn(source, surface, 1)[0].max())
    if off > ON_SURFACE:
        raise ErrorGeometryError(f"pair {index}: a source point lies {off:.2g} off its object (noisy pairs?)")
    normals = estimate_normals(surface, k=args.normal_k)
    error = se3.compose(se3.inverse(truth[None]), torch.from_numpy(pred)[None])  # (1, 4, 4)
    turn = se3.make_transform(error[:, :3, :3], torch.zeros(1, 3, dtype=error.dtype))  # about the object's centroid
    seed = torch.Generator().manual_seed  # the same draws for both parts: equal when the error does not shift
    whole, rotation = (_residuals(source, surface, normals, m, args.draws, seed(index)) for m in (error, turn))
    classes = dm.pair_classes("test", torch.tensor([index]))
    return PairGeometry(
        index=index,
        cls=classes[0] if classes else "all",
        rre_deg=float(rotation_error_deg(torch.from_numpy(pred)[None], truth[None])[0]),
        residual=whole[0],
        random_median=whole[1],
        random_p10=whole[2],
        turn_residual=rotation[0],
        turn_random_median=rotation[1],
    )


def _residuals(
    source: torch.Tensor,
    surface: torch.Tensor,
    normals: torch.Tensor,
    motion: torch.Tensor,
    draws: int,
    generator: torch.Generator,
) -> tuple[float, float, float]:
    """Surface residual of ``motion (1, 4, 4)``, and the median and 10th percentile of ``draws`` of its size."""
    moved = random_motions_like(motion, draws, generator)[0]  # (D, 4, 4)
    expand = (draws, -1, -1)
    random = surface_residual(source.expand(expand), moved, surface.expand(expand), normals.expand(expand))
    own = float(surface_residual(source, motion, surface, normals)[0])
    return own, float(random.median()), float(torch.quantile(random, 0.1))


def score_run(run: Path, args: argparse.Namespace) -> tuple[list[PairGeometry], int]:
    """Every pair of one run folder, and the number of failed pairs."""
    dm = run_datamodule(run / "config.yaml")
    index, pred, gt = read_transforms(run)
    scored = [score_pair(dm, int(i), p, g, args) for i, p, g in zip(index, pred, gt, strict=True)]
    return [s for s in scored if s is not None], sum(s is None for s in scored)


def _median(values: Sequence[float]) -> float:
    """Median of the finite values (a perfect estimate has no ratio), NaN if none."""
    finite = [v for v in values if math.isfinite(v)]
    return statistics.median(finite) if finite else float("nan")


def summary(pairs: Sequence[PairGeometry], large_deg: float) -> dict[str, float]:
    """One seed's medians over ``pairs``."""
    large = [p for p in pairs if p.rre_deg > large_deg]
    return {
        "pairs": len(pairs),
        "rre_median": _median([p.rre_deg for p in pairs]),
        "ratio": _median([p.ratio for p in pairs]),
        "large": len(large),
        "ratio_large": _median([p.ratio for p in large]),
        "freedom": _median([p.freedom for p in pairs]),
        "turn_ratio": _median([p.turn_ratio for p in pairs]),
    }


COLUMNS = {
    "pairs": "pairs",
    "rre_median": "median RRE °",
    "ratio": "residual ratio, median",
    "large": "pairs above --large-deg",
    "ratio_large": "their residual ratio, median",
    "freedom": "shape freedom, median",
    "turn_ratio": "rotation part alone: residual ratio, median",
}


def _cell(values: Sequence[float]) -> str:
    """Mean ± std of one cell; a count that every run shares as a plain number."""
    if all(v == values[0] and float(v).is_integer() for v in values):
        return str(int(values[0]))
    return format_mean_std(values)


def report(runs: Sequence[Path], args: argparse.Namespace) -> tuple[str, list[list[PairGeometry]]]:
    """The Markdown report over ``runs`` (one per seed) and every run's scored pairs."""
    seeds, failed = zip(*(score_run(run, args) for run in runs), strict=True)
    first = sorted((p.index, p.cls) for p in seeds[0])
    for run, pairs in zip(runs[1:], seeds[1:], strict=True):
        if sorted((p.index, p.cls) for p in pairs) != first:
            raise ErrorGeometryError(f"{run}: other scored pairs than {runs[0]} (other pairs, or other failures)")
    lines = []
    for name, classes in class_groups([p.cls for p in seeds[0]], args.min_pairs):
        values = [summary([p for p in pairs if p.cls in classes], args.large_deg) for pairs in seeds]
        lines.append([name, *(_cell([v[k] for v in values]) for k in COLUMNS)])
    text = [
        "# Test errors against the shape: residual ratios",
        "",
        f"{len(runs)} run(s), one per seed, the same {len(first)} scored test pairs (failed pairs left out, per run:"
        f" {', '.join(map(str, failed))}); {args.draws} random motions per pair, normals from {args.normal_k}"
        f" neighbours, 'above --large-deg' = rotation error above {args.large_deg:g}°. Each cell: mean ± sample std"
        " over the runs of the group's median. Residual ratio about 1: a misalignment like a random one of its size;"
        " well below 1: an error along motions the object's surface hardly shows (`benchmarks/error_geometry.py`)."
        " Runs:",
        "",
        *(f"- `{run}`" for run in runs),
        "",
        markdown_table(["group", *COLUMNS.values()], lines),
    ]
    return "\n".join(text) + "\n", list(seeds)


def write_pairs(path: Path, runs: Sequence[Path], seeds: Sequence[Sequence[PairGeometry]]) -> None:
    """Every scored pair of every run, one CSV row each."""
    header = ["run", "index", "class", "rre_deg", "residual", "random_median", "random_p10", "ratio", "freedom"]
    header += ["turn_residual", "turn_random_median", "turn_ratio"]
    with path.open("w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh)
        writer.writerow(header)
        for run, pairs in zip(runs, seeds, strict=True):
            for p in pairs:
                values = [p.rre_deg, p.residual, p.random_median, p.random_p10, p.ratio, p.freedom, p.turn_residual]
                values += [p.turn_random_median, p.turn_ratio]
                writer.writerow([str(run), p.index, p.cls, *(f"{v:.6g}" for v in values)])


def plot(path: Path, seeds: Sequence[Sequence[PairGeometry]], groups: Sequence[ClassGroup]) -> Path:
    """Residual ratio against rotation error, every scored pair of every run, one colour per group."""
    from lcreg.figures import agg_figure, save_png

    fig = agg_figure(6.4, 4.2, 120, "error geometry")
    ax = fig.add_subplot()
    for name, classes in groups:
        chosen = [p for pairs in seeds for p in pairs if p.cls in classes and p.rre_deg >= PLOT_MIN_DEG]
        label = f"{name} ({len(chosen)})"
        ax.scatter([p.rre_deg for p in chosen], [p.ratio for p in chosen], s=10, alpha=0.6, label=label)
    ax.axhline(1.0, color="grey", lw=0.8, ls="--")
    ax.set(xscale="log", xlabel=f"rotation error (degrees, log scale; from {PLOT_MIN_DEG:g})", ylabel="residual ratio")
    ax.set_title("Error's surface residual / random motions' of its size (1: a typical motion)", fontsize=9)
    ax.legend(fontsize=8)
    return save_png(fig, path)


SMOKE_DATA = {"num_train": 2, "num_val": 2, "num_test": 6, "num_points": 256, "batch_size": 2, "seed": 7}
"""The embedded pairs of ``--smoke`` (``SyntheticDataModule`` arguments)."""


def synthetic_truths(init: dict[str, Any]) -> torch.Tensor:
    """The true transforms ``(P, 4, 4)`` float64 of the test pairs of ``SyntheticDataModule(**init)``."""
    from lcreg.data.datamodule import SyntheticDataModule

    dm = SyntheticDataModule(**init)
    dm.setup("test")
    assert dm.test_set is not None
    return torch.stack([dm.test_set[i]["transform_ref_src"].double() for i in range(len(dm.test_set))])


def write_run(folder: Path, init: dict[str, Any], pred: torch.Tensor, gt: torch.Tensor) -> Path:
    """A run folder as a test of the embedded pairs writes it: ``config.yaml`` and the transforms file."""
    folder.mkdir(parents=True, exist_ok=True)
    data = {"class_path": "lcreg.data.datamodule.SyntheticDataModule", "init_args": init}
    (folder / "config.yaml").write_text(yaml.safe_dump({"data": data}), encoding="utf-8")
    index = np.arange(len(gt))
    np.savez(folder / TRANSFORMS_FILE, index=index, transform_pred=pred.numpy(), transform_gt=gt.numpy())
    return folder


def smoke_run(folder: Path) -> Path:
    """A made-up test of the embedded pairs: every estimate the truth turned by 10° about a fixed axis."""
    from lcreg.geometry import so3

    gt = synthetic_truths(SMOKE_DATA)
    turn = se3.make_transform(so3.exp(torch.tensor([[0.0, 0.0, 0.17]], dtype=torch.float64)), torch.zeros(1, 3))
    return write_run(folder, SMOKE_DATA, se3.compose(gt, turn.expand(len(gt), 4, 4)), gt)


def parse(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", nargs="+", type=Path, default=[], help="test run folders, one per seed")
    parser.add_argument("--draws", type=int, default=32, help="random motions per pair (default 32)")
    parser.add_argument("--normal-k", type=int, default=16, help="neighbours per PCA normal (default 16)")
    parser.add_argument("--large-deg", type=float, default=5.0, help="a 'large' rotation error, degrees (default 5)")
    parser.add_argument("--min-pairs", type=int, default=10, help="a class with fewer pairs is pooled (default 10)")
    parser.add_argument("--pairs-out", type=Path, help="also write every scored pair to this CSV")
    parser.add_argument("--plot", type=Path, help="also draw residual ratio against rotation error to this PNG")
    parser.add_argument("--out", help="write the report here (default: print it)")
    add_smoke_argument(parser)
    args = parser.parse_args(argv)
    if args.draws < 2 or args.normal_k < 3 or args.min_pairs < 1:
        parser.error("--draws must be >= 2, --normal-k >= 3 and --min-pairs >= 1")
    return args


def main(argv: Sequence[str] | None = None) -> None:
    args = parse(argv)
    with tempfile.TemporaryDirectory(prefix="lcreg-error-geometry-") as scratch:
        runs = [smoke_run(Path(scratch))] if args.smoke else args.runs
        if not runs:
            sys.exit("error_geometry: give --runs FOLDER [FOLDER ...] (or --smoke)")
        try:
            text, seeds = report(runs, args)
        except ErrorGeometryError as err:
            sys.exit(f"error_geometry: {err}")
        if args.pairs_out:
            write_pairs(args.pairs_out, runs, seeds)
        if args.plot:
            groups = class_groups([p.cls for p in seeds[0]], args.min_pairs)
            print(f"wrote {plot(args.plot, seeds, groups[1:] or groups)}")
    write_or_print(text, args.out, "error_geometry.md", args.smoke)


if __name__ == "__main__":
    main()
