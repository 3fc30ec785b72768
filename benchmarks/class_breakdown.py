"""A model's test figures split by the class of the object in each pair, from its seeds' ``test_per_pair.csv`` files.

    python benchmarks/class_breakdown.py \
        --per-pair runs/.../seed0/retest-32-true/run/test_per_pair.csv runs/.../seed1/... runs/.../seed2/... \
        --without bathtub --paper 3.716 1.863 0.0229 0.0109 --paper-label "IDAM Tab. 1, noisy partial" \
        --out docs/results/converge/class_breakdown/idam_partial.md
    python benchmarks/class_breakdown.py --smoke      # seconds: three made-up files

The files (one per seed, the same test pairs: their ``index`` and ``class`` columns must agree) are the ones every
``lcreg test`` and ``lcreg reproduce`` test writes (:mod:`lcreg.models.evaluation`); their last columns are each
pair's Euler-angle and translation component errors as DCP's four figures count them, so RMSE(R), MAE(R), RMSE(t) and
MAE(t) of any subset of pairs follow from its rows. A file written before those columns existed is refused: test its
weights again (``lcreg reproduce <the job's flags> --retest 32-true``).

Groups: all pairs; each class with at least ``--min-pairs`` pairs; the other classes pooled; and for each
``--without`` list, all pairs but those classes. Per group and figure the mean ± sample std over the files, the
group's share of the squared Euler error of all pairs, and with ``--paper`` the ratio of the mean to the paper's
figure. Each ``--without`` group is judged against all pairs as the queue's rules judge two sets of runs
(:func:`lcreg.experiments.reproduce.claims.compare`: the difference of the means against the larger std).
"""

from __future__ import annotations

import argparse
import csv
import math
import statistics
import sys
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from lcreg.experiments.benchmarking import ClassGroup, add_smoke_argument, class_groups, markdown_table, write_or_print
from lcreg.experiments.benchmarking.writers import format_mean_std, significant
from lcreg.experiments.reproduce.claims import compare
from lcreg.metrics.registration import WORST_ROTATION_DEG
from lcreg.models.evaluation import COMPONENT_COLUMNS

PAPER_FIGURES = ("RMSE(R) °", "MAE(R) °", "RMSE(t)", "MAE(t)")
"""The figures ``--paper`` gives, in DCP's column order (rotation in degrees, translation in the clouds' units)."""
WORDS = {"holds": "lower beyond the spread", "does not hold": "higher beyond the spread"}


class PerPairFileError(ValueError):
    """A per-pair file is missing, damaged, lacks a column, or holds other pairs than the first file."""


@dataclass(frozen=True)
class Pair:
    """One test pair of one file: its class, geodesic rotation error (degrees) and DCP components."""

    index: int
    cls: str
    rre_deg: float
    euler_deg: tuple[float, float, float]
    translation: tuple[float, float, float]


def read_pairs(path: Path) -> list[Pair]:
    """The pairs of one ``test_per_pair.csv``, in file order.

    Raises:
        PerPairFileError: The file is missing or unreadable, lacks the ``class`` or component columns, or holds a
            value that is not a finite number.
    """
    try:
        with path.open(newline="", encoding="utf-8") as fh:
            reader = csv.DictReader(fh)
            rows = list(reader)
            columns = reader.fieldnames or []
    except (OSError, UnicodeDecodeError, csv.Error) as err:
        raise PerPairFileError(f"{path}: cannot be read ({err})") from err
    missing = [c for c in ("index", "rotation_error_deg", "class", *COMPONENT_COLUMNS) if c not in columns]
    if missing:
        hint = " (written before the component columns: test its weights again)" if "class" not in missing else ""
        raise PerPairFileError(f"{path}: no column {', '.join(missing)}{hint}")
    if not rows:
        raise PerPairFileError(f"{path}: no pairs")
    return [_pair(path, line, row) for line, row in enumerate(rows, start=2)]


def _pair(path: Path, line: int, row: dict[str, str]) -> Pair:
    try:
        values = [float(row[c]) for c in ("rotation_error_deg", *COMPONENT_COLUMNS)]
        index = int(row["index"])
    except (TypeError, ValueError) as err:
        raise PerPairFileError(f"{path}, line {line}: not a number ({err})") from err
    if not all(math.isfinite(v) for v in values[1:]):  # a failed pair's components are finite by construction
        raise PerPairFileError(f"{path}, line {line}: a component error is not finite")
    rre = values[0] if math.isfinite(values[0]) else WORST_ROTATION_DEG  # a failed pair, as the test figures count it
    return Pair(index, row["class"], rre, (values[1], values[2], values[3]), (values[4], values[5], values[6]))


def read_seeds(paths: Sequence[Path]) -> list[list[Pair]]:
    """Every file's pairs; each must hold the first file's pairs (index and class) in the same order."""
    seeds = [read_pairs(path) for path in paths]
    first = [(p.index, p.cls) for p in seeds[0]]
    for path, pairs in zip(paths[1:], seeds[1:], strict=True):
        if [(p.index, p.cls) for p in pairs] != first:
            raise PerPairFileError(f"{path}: other test pairs than {paths[0]} (index or class differs)")
    return seeds


def figures(pairs: Sequence[Pair], total_euler_sq: float) -> dict[str, float]:
    """DCP's four figures, the mean and median geodesic error and the share of ``total_euler_sq`` of ``pairs``."""
    euler = [v for p in pairs for v in p.euler_deg]
    trans = [v for p in pairs for v in p.translation]
    euler_sq = sum(v * v for v in euler)
    return {
        "rmse_r_deg": math.sqrt(euler_sq / len(euler)),
        "mae_r_deg": statistics.fmean(abs(v) for v in euler),
        "rmse_t": math.sqrt(statistics.fmean(v * v for v in trans)),
        "mae_t": statistics.fmean(abs(v) for v in trans),
        "rre_mean_deg": statistics.fmean(p.rre_deg for p in pairs),
        "rre_median_deg": statistics.median(p.rre_deg for p in pairs),
        "euler_sq_share": euler_sq / total_euler_sq if total_euler_sq > 0 else float("nan"),
    }


COLUMNS = {
    "rmse_r_deg": "RMSE(R) °",
    "mae_r_deg": "MAE(R) °",
    "rmse_t": "RMSE(t)",
    "mae_t": "MAE(t)",
    "rre_mean_deg": "mean RRE °",
    "rre_median_deg": "median RRE °",
    "euler_sq_share": "share of the squared Euler error",
}


def groups(pairs: Sequence[Pair], min_pairs: int, without: Sequence[Sequence[str]]) -> list[ClassGroup]:
    """The report's groups (:func:`~lcreg.experiments.benchmarking.class_groups`) of the first file's pairs."""
    try:
        return class_groups([pair.cls for pair in pairs], min_pairs, without)
    except ValueError as err:
        raise PerPairFileError(str(err)) from err


def per_seed(seeds: Sequence[Sequence[Pair]], group: ClassGroup) -> tuple[int, list[dict[str, float]]]:
    """The group's pair count and its figures in each file."""
    values = []
    for pairs in seeds:
        total = sum(v * v for p in pairs for v in p.euler_deg)
        values.append(figures([p for p in pairs if p.cls in group[1]], total))
    return sum(1 for p in seeds[0] if p.cls in group[1]), values


def report(
    paths: Sequence[Path],
    min_pairs: int,
    without: Sequence[Sequence[str]],
    paper: Sequence[float] | None,
    paper_label: str,
) -> str:
    """The Markdown report (module docstring)."""
    seeds = read_seeds(paths)
    found = {group[0]: per_seed(seeds, group) for group in groups(seeds[0], min_pairs, without)}
    header = ["group", "pairs", *COLUMNS.values()]
    lines = [
        [name, count, *(format_mean_std([v[key] for v in values]) for key in COLUMNS)]
        for name, (count, values) in found.items()
    ]
    parts = [
        "# Test figures by the class of each pair",
        "",
        f"{len(paths)} file(s) of per-pair errors (one per seed, the same {len(seeds[0])} test pairs); each cell is",
        "the mean ± sample std over them. RMSE/MAE(R) are DCP's, over the [z, y, x] Euler-angle errors; the share is",
        "the group's part of the sum of squared Euler errors of all pairs. Files:",
        "",
        *(f"- `{path}`" for path in paths),
        "",
        markdown_table(header, lines),
    ]
    if paper is not None:
        parts += ["", _ratios(found, paper, paper_label)]
    if without:
        parts += ["", _judgements(found, [name for name in found if name.startswith("all but ")])]
    return "\n".join(parts) + "\n"


def _ratios(found: dict[str, tuple[int, list[dict[str, float]]]], paper: Sequence[float], label: str) -> str:
    """Per group, the mean of each of DCP's figures over the paper's (above 1: ours is worse)."""
    keys = list(COLUMNS)[:4]
    lines = [
        [name, *(f"{statistics.fmean(v[k] for v in values) / p:.2f}" for k, p in zip(keys, paper, strict=True))]
        for name, (_, values) in found.items()
    ]
    paper_cells = ", ".join(f"{f} {p:g}" for f, p in zip(PAPER_FIGURES, paper, strict=True))
    return "\n".join([f"Ours / paper ({label}: {paper_cells}):", "", markdown_table(["group", *PAPER_FIGURES], lines)])


def _judgements(found: dict[str, tuple[int, list[dict[str, float]]]], names: Sequence[str]) -> str:
    """Each ``all but`` group against all pairs, per figure: the difference of the means against the larger std."""
    everything = found["all pairs"][1]
    lines = []
    for name in names:
        values = found[name][1]
        for key in list(COLUMNS)[:4]:
            difference, spread, verdict = compare([v[key] for v in values], [v[key] for v in everything])
            words = WORDS.get(verdict, "within the spread" if verdict == "within spread" else "one file: no spread")
            sign = "+" if difference > 0 else ""
            lines.append([name, COLUMNS[key], f"{sign}{significant(difference, 3)}", significant(spread), words])
    header = ["group", "figure", "difference to all pairs", "spread", "verdict"]
    return "\n".join(["Against all pairs (`claims.compare`):", "", markdown_table(header, lines)])


def smoke_files(folder: Path) -> list[Path]:
    """Three made-up files: 6 pairs of class ``a`` with small errors, 3 of ``b`` with large ones, 1 of ``c``."""
    paths = []
    for seed in range(3):
        path = folder / f"seed{seed}.csv"
        with path.open("w", newline="", encoding="utf-8") as fh:
            writer = csv.writer(fh)
            writer.writerow(["index", "rotation_error_deg", "translation_error", "class", *COMPONENT_COLUMNS])
            for k, cls in enumerate("aaaaaabbbc"):
                size = (10.0 if cls == "b" else 1.0) * (1 + 0.1 * seed)
                writer.writerow([k, size * 1.5, size / 100, cls, size, -size, size / 2, size / 100, 0, -size / 100])
        paths.append(path)
    return paths


def parse(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--per-pair", nargs="+", type=Path, default=[], help="test_per_pair.csv files, one per seed")
    parser.add_argument("--min-pairs", type=int, default=10, help="a class with fewer pairs is pooled (default 10)")
    parser.add_argument(
        "--without", nargs="+", action="append", default=[], metavar="CLASS", help="also all pairs but these classes"
    )
    parser.add_argument("--paper", nargs=4, type=float, metavar=("RMSE_R", "MAE_R", "RMSE_T", "MAE_T"))
    parser.add_argument("--paper-label", default="the paper", help="where --paper's figures come from")
    parser.add_argument("--out", help="write the report here (default: print it)")
    add_smoke_argument(parser)
    args = parser.parse_args(argv)
    if args.min_pairs < 1:
        parser.error(f"--min-pairs must be >= 1, got {args.min_pairs}")
    if args.paper is not None and not all(math.isfinite(p) and p > 0 for p in args.paper):
        parser.error(f"--paper figures must be finite and > 0, got {args.paper}")
    return args


def main(argv: Sequence[str] | None = None) -> None:
    args = parse(argv)
    with tempfile.TemporaryDirectory(prefix="lcreg-classes-") as scratch:
        paths = smoke_files(Path(scratch)) if args.smoke else args.per_pair
        without = [["b"]] if args.smoke else args.without
        if not paths:
            sys.exit("class_breakdown: give --per-pair FILE [FILE ...] (or --smoke)")
        try:
            text = report(paths, args.min_pairs if not args.smoke else 2, without, args.paper, args.paper_label)
        except PerPairFileError as err:
            sys.exit(f"class_breakdown: {err}")
    write_or_print(text, args.out, "class_breakdown.md", args.smoke)


if __name__ == "__main__":
    main()
