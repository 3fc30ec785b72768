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

__all__ = ["VERDICTS", "Claim", "ClaimResult", "Comparison", "ComparisonResult", "Verdict", "compare", "judge"]

Verdict = Literal["holds", "does not hold", "within spread", "one seed", "not run"]
VERDICTS: tuple[Verdict, ...] = ("holds", "does not hold", "within spread", "one seed", "not run")


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


@dataclass(frozen=True)
class ClaimResult:
    """A claim judged on one metric."""

    claim: Claim
    verdict: Verdict
    comparisons: tuple[ComparisonResult, ...]


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


def judge(claim: Claim, values: Mapping[str, Sequence[float]]) -> ClaimResult:
    """Judge ``claim`` on per-seed values of one metric by variant key (missing or empty: ``not run``)."""
    if any(not values.get(key) for c in claim.comparisons for key in (c.better, c.worse)):
        return ClaimResult(claim, "not run", ())
    results = tuple(ComparisonResult(c, *compare(values[c.better], values[c.worse])) for c in claim.comparisons)
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
    return ClaimResult(claim, verdict, results)
