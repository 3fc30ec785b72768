"""The paper's claims as comparisons of seed samples, judged against the seed spread.

A claim ("A > B > C > D in error", "|X1| = 64 is best", "LC + X beats X") is a list of comparisons, each
"``better`` has a lower error than ``worse``". One comparison is decided by the difference of the seed means
against the seed spread, the larger of the two sample standard deviations (the rule of ``docs/results/lc_plus_x.md``):

* ``holds``: the mean of ``better`` is lower by more than the spread;
* ``does not hold``: it is higher by more than the spread;
* ``within spread``: the difference is not larger than the spread;
* ``one seed``: a side has fewer than two seeds (no spread to compare with).

A claim holds when all of its comparisons hold, does not hold when any of them does not, and is otherwise
``within spread`` (or ``one seed``); ``not run`` when a side has no finished run.

"Within spread" decides nothing about the paper. A second judgement (:func:`against_paper`) therefore asks whether
our difference is as large as the paper's: the paper's relative difference (``paper_better / paper_worse - 1``) is
scaled to our level (times the mean of our ``worse`` side, since our errors need not be the paper's), and our
difference is compared with it against the same spread:

* ``smaller than the paper's``: our difference is above the paper's by more than the spread (for a claimed gain: the
  gain of the size the paper reports is refuted here);
* ``larger than the paper's``: below it by more than the spread;
* ``as the paper's``: within the spread of it;
* ``one seed`` / ``no paper value`` (a side without a paper row, or a paper value of 0).

A claim is ``smaller than the paper's`` when any comparison is, ``as the paper's or larger`` when all are as large
or larger, and otherwise ``one seed`` or ``no paper value``.

Example:
    >>> claim = Claim("B beats A", (Comparison("B", "A"),))
    >>> judge(claim, {"A": [4.0, 4.2, 4.1], "B": [2.0, 2.1, 2.2]}).verdict
    'holds'
    >>> judge(claim, {"A": [2.0, 4.2, 1.0], "B": [2.0, 2.1, 2.2]}).verdict
    'within spread'
"""

from __future__ import annotations

import statistics
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Literal

__all__ = [
    "VERDICTS",
    "Claim",
    "ClaimResult",
    "Comparison",
    "ComparisonResult",
    "SizeVerdict",
    "Verdict",
    "against_paper",
    "compare",
    "judge",
]

Verdict = Literal["holds", "does not hold", "within spread", "one seed", "not run"]
VERDICTS: tuple[Verdict, ...] = ("holds", "does not hold", "within spread", "one seed", "not run")
SizeVerdict = Literal[
    "smaller than the paper's",
    "as the paper's",
    "larger than the paper's",
    "as the paper's or larger",
    "one seed",
    "no paper value",
]


@dataclass(frozen=True)
class Comparison:
    """``better`` (a variant key) has a lower error than ``worse``."""

    better: str
    worse: str


@dataclass(frozen=True)
class Claim:
    """A claim of the paper: a sentence and the comparisons that make it true."""

    text: str
    comparisons: tuple[Comparison, ...]


@dataclass(frozen=True)
class ComparisonResult:
    """One comparison judged: the difference of the means (``better - worse``), the spread and the verdict."""

    comparison: Comparison
    difference: float
    spread: float
    verdict: Verdict
    paper_difference: float | None = None
    size: SizeVerdict = "no paper value"


@dataclass(frozen=True)
class ClaimResult:
    """A claim judged on one metric."""

    claim: Claim
    verdict: Verdict
    comparisons: tuple[ComparisonResult, ...]
    size: SizeVerdict = "no paper value"


def _std(values: Sequence[float]) -> float:
    return statistics.stdev(values) if len(values) > 1 else 0.0


def compare(better: Sequence[float], worse: Sequence[float]) -> tuple[float, float, Verdict]:
    """Difference of the means (``better - worse``), the larger seed standard deviation, and the verdict.

    Args:
        better: Per-seed errors of the side claimed lower.
        worse: Per-seed errors of the other side.

    Raises:
        ValueError: If a side is empty.
    """
    if not better or not worse:
        raise ValueError("compare needs at least one value on each side")
    difference = statistics.fmean(better) - statistics.fmean(worse)
    spread = max(_std(better), _std(worse))
    if min(len(better), len(worse)) < 2:
        return difference, spread, "one seed"
    if abs(difference) <= spread:
        return difference, spread, "within spread"
    return difference, spread, "holds" if difference < 0 else "does not hold"


def against_paper(
    better: Sequence[float], worse: Sequence[float], paper_better: float | None, paper_worse: float | None
) -> tuple[float | None, SizeVerdict]:
    """The paper's difference scaled to our level, and whether ours is as large (module docstring).

    Args:
        better: Per-seed errors of the side claimed lower.
        worse: Per-seed errors of the other side.
        paper_better: The paper's value of the ``better`` side (``None``: no paper row).
        paper_worse: The paper's value of the ``worse`` side.

    Returns:
        ``(paper_better / paper_worse - 1) * mean(worse)`` (``None`` without paper values) and the verdict.
    """
    return _against_paper(compare(better, worse), statistics.fmean(worse), paper_better, paper_worse)


def _against_paper(
    compared: tuple[float, float, Verdict], worse_mean: float, paper_better: float | None, paper_worse: float | None
) -> tuple[float | None, SizeVerdict]:
    """:func:`against_paper` from :func:`compare`'s result and the mean of the ``worse`` side."""
    if paper_better is None or paper_worse is None or paper_worse == 0:
        return None, "no paper value"
    paper_difference = (paper_better / paper_worse - 1.0) * worse_mean
    difference, spread, verdict = compared
    if verdict == "one seed":
        return paper_difference, "one seed"
    if abs(difference - paper_difference) <= spread:
        return paper_difference, "as the paper's"
    return paper_difference, "smaller than the paper's" if difference > paper_difference else "larger than the paper's"


def _claim_size(results: Sequence[ComparisonResult]) -> SizeVerdict:
    sizes = {r.size for r in results}
    if "smaller than the paper's" in sizes:
        return "smaller than the paper's"
    if sizes and sizes <= {"as the paper's", "larger than the paper's"}:
        return "as the paper's or larger"
    return "one seed" if "one seed" in sizes else "no paper value"


def judge(claim: Claim, values: Mapping[str, Sequence[float]], paper: Mapping[str, float] | None = None) -> ClaimResult:
    """Judge ``claim`` on per-seed values of one metric by variant key (missing or empty: ``not run``).

    ``paper``: the paper's value of the same metric by variant key, for :func:`against_paper` (``None``: none).
    """
    if any(not values.get(key) for c in claim.comparisons for key in (c.better, c.worse)):
        return ClaimResult(claim, "not run", ())
    paper = paper or {}
    results = []
    for c in claim.comparisons:
        compared = compare(values[c.better], values[c.worse])
        size = _against_paper(compared, statistics.fmean(values[c.worse]), paper.get(c.better), paper.get(c.worse))
        results.append(ComparisonResult(c, *compared, *size))
    verdicts = {r.verdict for r in results}
    verdict: Verdict
    if "does not hold" in verdicts:
        verdict = "does not hold"
    elif verdicts == {"holds"}:
        verdict = "holds"
    elif "one seed" in verdicts:
        verdict = "one seed"
    else:
        verdict = "within spread"
    return ClaimResult(claim, verdict, tuple(results), _claim_size(results))
