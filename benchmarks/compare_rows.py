"""Two sets of finished runs, judged by the queue's rules: the difference of the seed means against the spread.

    python benchmarks/compare_rows.py \
        --side "cap 9,000" docs/results/converge/dcp_bf16_lr_256/runs/lc.jsonl:dcp/X:0 \
            docs/results/converge/dcp_bf16_lr_cap_seed1_256/runs/lc.jsonl:dcp/X:1 \
            docs/results/converge/dcp_bf16_lr_cap_256/runs/lc.jsonl:dcp/X:2 \
        --side "cap 3,000" docs/results/converge/dcp_bf16_lr_256/runs/lc.jsonl:dcp/X:0 \
            docs/results/converge/dcp_bf16_lr_256/runs/lc.jsonl:dcp/X:1 \
            docs/results/converge/dcp_bf16_lr_seed2_256/runs/lc.jsonl:dcp/X:2 \
        --out docs/results/converge/dcp_bf16_lr_cap_seed1_256/cap_rule_table.md
    python benchmarks/compare_rows.py --smoke     # seconds: two made-up JSONL files

A rule of ``benchmarks/train_queue.toml`` compares runs that one report does not hold together: rows of several
jobs, under different budget keys (a raised cap, another rate). Each run is named ``FILE:VARIANT:SEED``: the newest
row of that variant and seed in the sweep's JSONL (as ``lcreg reproduce`` counts a rerun); where the file holds the
seed under several budgets, ``FILE:VARIANT:SEED:BUDGET`` names one by a piece of its budget text. Per figure the first
side is judged against the second by :func:`lcreg.experiments.reproduce.claims.compare` (the difference of the means
against the larger of the two sample standard deviations), the rule every report and queue job uses; one run against
several seeds (a probe's seed 0) is judged against their std, as the queue's rules do.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lcreg.experiments.benchmarking import add_smoke_argument, markdown_table, write_or_print
from lcreg.experiments.benchmarking.writers import format_mean_std, significant
from lcreg.experiments.reproduce.claims import compare
from lcreg.experiments.reproduce.stops import stopped_early

FIGURES = ("rmse_r_deg", "mae_r_deg", "rmse_t", "mae_t")
"""The test figures of the rules (DCP's Tab. 3 columns): rotation in degrees, translation in the clouds' units."""
VERDICT_TEXT = {
    "holds": "better beyond the spread",
    "does not hold": "worse beyond the spread",
    "within spread": "within the spread",
    "one seed": "one seed: no spread",
}


class RowNotFoundError(ValueError):
    """A run named on the command line has no usable row: a missing or damaged file, no such variant and seed, a
    failed run, a missing or non-finite figure."""


@dataclass(frozen=True)
class Run:
    """One finished run: where its row was found and the row itself."""

    side: str
    source: str
    row: Mapping[str, Any]


def parse_run(spec: str) -> tuple[Path, str, int, str]:
    """``FILE:VARIANT:SEED`` or ``FILE:VARIANT:SEED:BUDGET`` (e.g. ``runs/lc.jsonl:dcp/X:1``) as its parts; ``BUDGET``,
    a piece of the rows' ``budget`` text (``""``: any), picks one run where the file holds the seed under several.

    Raises:
        RowNotFoundError: Not of that form, or the seed is not an integer.
    """
    parts = spec.rsplit(":", 3)
    if len(parts) == 4 and parts[3].strip().isdigit():  # a FILE with a colon in it, no BUDGET
        parts = [f"{parts[0]}:{parts[1]}", *parts[2:]]
    if len(parts) == 3:
        parts.append("")
    if len(parts) != 4 or not all(parts[:3]):
        raise RowNotFoundError(f"{spec!r}: expected FILE:VARIANT:SEED[:BUDGET], e.g. runs/lc.jsonl:dcp/X:1")
    try:
        return Path(parts[0]), parts[1], int(parts[2]), parts[3]
    except ValueError:
        raise RowNotFoundError(f"{spec!r}: the seed {parts[2]!r} is not an integer") from None


def find_row(path: Path, variant: str, seed: int, budget: str = "") -> dict[str, Any]:
    """The newest row of ``variant`` and ``seed`` (whose ``budget`` contains ``budget``) in the JSONL ``path``.

    Raises:
        RowNotFoundError: No such file, a line that is not JSON, no such row, rows of the run under several budgets
            or data (a sweep's older key kept beside its newer one: which is meant must be said), or the run failed.
    """
    if not path.is_file():
        raise RowNotFoundError(f"{path}: no such file")
    rows = []
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        if not line.strip():
            continue
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError as err:
            raise RowNotFoundError(f"{path}, line {number}: not a JSON row ({err})") from None
    ours = [row for row in rows if row.get("variant") == variant and row.get("seed") == seed]
    matches = [row for row in ours if budget in str(row.get("budget", ""))]
    if not matches:
        found = sorted({f"{row.get('variant')}:{row.get('seed')}" for row in rows})
        within = f" with {budget!r} in its budget" if budget else ""
        raise RowNotFoundError(f"{path}: no row of {variant} seed {seed}{within} (rows: {', '.join(found) or 'none'})")
    keys = {(row.get("budget"), row.get("data")) for row in matches}
    if len(keys) > 1:
        budgets = "; ".join(sorted(f"{b!r} ({d})" for b, d in keys))
        raise RowNotFoundError(
            f"{path}: {variant} seed {seed} has rows of {len(keys)} runs (budget, data): {budgets}. "
            "Name one with FILE:VARIANT:SEED:BUDGET, BUDGET a piece of its budget text"
        )
    if matches[-1].get("failed"):
        raise RowNotFoundError(f"{path}: {variant} seed {seed} failed: {matches[-1]['failed']}")
    return dict(matches[-1])


def figure(run: Run, name: str) -> float:
    """``run``'s test figure ``name``.

    Raises:
        RowNotFoundError: The row has no such figure (names the run and the figures it has).
    """
    value = run.row.get(name)
    if isinstance(value, bool) or not isinstance(value, int | float):
        known = sorted(key for key, v in run.row.items() if isinstance(v, float))
        raise RowNotFoundError(f"{run.source}: no figure {name!r} (it has {', '.join(known)})")
    if not math.isfinite(value):
        raise RowNotFoundError(f"{run.source}: its {name} is {value}, not a finite number")
    return float(value)


def _or_dash(value: object) -> object:
    """A table cell: ``–`` for an unknown value, yes/no for a flag."""
    if isinstance(value, bool):
        return "yes" if value else "no"
    return "–" if value is None else value


def runs_table(runs: Sequence[Run], figures: Sequence[str]) -> str:
    """One line per run: its side, where it was found, its steps, whether it stopped before its cap
    (:func:`~lcreg.experiments.reproduce.stops.stopped_early`), its selected checkpoint and its figures."""
    header = ["side", "run", "steps", "stopped early", "selected", *figures]
    lines = [
        [run.side, f"`{run.source}`", _or_dash(run.row.get("steps")), _or_dash(stopped_early(run.row))]
        + [_or_dash(run.row.get("selected"))]
        + [f"{figure(run, name):.4g}" for name in figures]
        for run in runs
    ]
    return markdown_table(header, lines)


def judge(first: Sequence[float], second: Sequence[float]) -> tuple[float, float, str]:
    """:func:`~lcreg.experiments.reproduce.claims.compare`, and one run against several seeds as the queue's rules
    judge it (e.g. a probe's seed 0 against the 3 seeds it is compared with): against the other side's std.

    Returns:
        The difference of the means (first − second), the spread, and the verdict's words.
    """
    difference, spread, verdict = compare(first, second)
    if verdict != "one seed" or max(len(first), len(second)) < 2:
        return difference, spread, VERDICT_TEXT[verdict]
    beyond = "better" if difference < 0 else "worse"
    words = "within the spread" if abs(difference) <= spread else f"{beyond} beyond the spread"
    return difference, spread, f"{words} (one run against the other side's std)"


def judgement_table(first: Sequence[Run], second: Sequence[Run], figures: Sequence[str]) -> str:
    """Per figure: each side's mean ± std (seeds), the difference first − second, the spread and the verdict."""
    names = (first[0].side, second[0].side)
    header = ["figure", f"{names[0]} (n={len(first)})", f"{names[1]} (n={len(second)})", "difference", "spread"]
    lines = []
    for name in figures:
        a, b = [figure(run, name) for run in first], [figure(run, name) for run in second]
        difference, spread, verdict = judge(a, b)
        sign = "+" if difference > 0 else ""
        cells = [format_mean_std(a), format_mean_std(b), sign + significant(difference, 3), significant(spread)]
        lines.append([name, *cells, f"{names[0]}: {verdict}"])
    return markdown_table([*header, "verdict"], lines)


def report(sides: Sequence[tuple[str, Sequence[str]]], figures: Sequence[str]) -> str:
    """The Markdown report of two sides, each a name and its ``FILE:VARIANT:SEED`` runs."""
    if len(sides) != 2:
        raise RowNotFoundError(f"give exactly two --side options, got {len(sides)}")
    runs = [[Run(name, spec, find_row(*parse_run(spec))) for spec in specs] for name, specs in sides]
    lines = [
        f"# {sides[0][0]} against {sides[1][0]}",
        "",
        "Each side's mean ± sample std over its runs; the verdict is the first side's: its mean against the second's,",
        "beyond or within the larger std (`lcreg.experiments.reproduce.claims.compare`).",
        "",
        judgement_table(runs[0], runs[1], figures),
        "",
        runs_table([*runs[0], *runs[1]], figures),
    ]
    return "\n".join(lines) + "\n"


def smoke_sides(folder: Path) -> list[tuple[str, list[str]]]:
    """Two made-up JSONL files, three seeds on each side (``--smoke``)."""
    sides = []
    for name, level in (("lower", 4.0), ("higher", 6.0)):
        path = folder / f"{name}.jsonl"
        rows = [
            {"variant": "m/X", "seed": s, "steps": 100, **dict.fromkeys(FIGURES, level + 0.1 * s)} for s in range(3)
        ]
        path.write_text("".join(json.dumps(row) + "\n" for row in rows), encoding="utf-8")
        sides.append((name, [f"{path}:m/X:{s}" for s in range(3)]))
    return sides


def parse(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--side",
        nargs="+",
        action="append",
        metavar=("NAME", "FILE:VARIANT:SEED"),
        default=[],
        help="a side's name, then its runs (twice: the first side is judged against the second)",
    )
    parser.add_argument("--figures", nargs="+", default=list(FIGURES), help="row fields to compare (test figures)")
    parser.add_argument("--out", help="write the report here (default: print it)")
    add_smoke_argument(parser)
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> None:
    args = parse(argv)
    with tempfile.TemporaryDirectory(prefix="lcreg-compare-") as scratch:
        sides = smoke_sides(Path(scratch)) if args.smoke else [(side[0], side[1:]) for side in args.side]
        if any(not specs for _, specs in sides):
            sys.exit("compare_rows: each --side needs a name and at least one FILE:VARIANT:SEED")
        try:
            text = report(sides, args.figures)
        except RowNotFoundError as err:
            sys.exit(f"compare_rows: {err}")
    write_or_print(text, args.out, "compare_rows.md", args.smoke)


if __name__ == "__main__":
    main()
