"""The paper's claims judged on hand-made seed values: holds, does not hold, within spread, one seed, not run."""

from __future__ import annotations

import pytest

from lcreg.experiments.reproduce.ablation import ABLATION
from lcreg.experiments.reproduce.claims import Claim, Comparison, against_paper, compare, judge
from lcreg.experiments.reproduce.lc import LC

ORDER = Claim("A > B > C in error", (Comparison("B", "A"), Comparison("C", "B")))


def test_compare_decides_on_the_larger_seed_std() -> None:
    difference, spread, verdict = compare([1.0, 1.2, 1.1], [2.0, 2.2, 2.1])
    assert verdict == "holds" and difference == pytest.approx(-1.0) and spread == pytest.approx(0.1)
    assert compare([3.0, 3.2, 3.1], [2.0, 2.2, 2.1])[2] == "does not hold"
    difference, spread, verdict = compare([1.0, 3.0], [2.5, 2.5])  # mean 2.0 vs 2.5, std 1.41 vs 0
    assert verdict == "within spread" and difference == pytest.approx(-0.5) and spread == pytest.approx(2**0.5)
    assert compare([1.0], [2.0, 2.1])[2] == "one seed"
    with pytest.raises(ValueError, match="at least one value"):
        compare([], [1.0])


def test_a_claim_holds_only_when_every_comparison_holds_beyond_the_spread() -> None:
    values = {"A": [4.0, 4.2, 4.1], "B": [2.0, 2.1, 2.2], "C": [1.0, 1.1, 0.9]}
    result = judge(ORDER, values)
    assert result.verdict == "holds" and [r.verdict for r in result.comparisons] == ["holds", "holds"]
    assert result.comparisons[0].difference == pytest.approx(-2.0)


def test_one_reversed_comparison_makes_the_claim_fail() -> None:
    values = {"A": [4.0, 4.2, 4.1], "B": [2.0, 2.1, 2.2], "C": [3.0, 3.1, 3.2]}  # C worse than B beyond spread
    assert judge(ORDER, values).verdict == "does not hold"


def test_a_difference_inside_the_spread_leaves_the_claim_open() -> None:
    values = {"A": [4.0, 4.2, 4.1], "B": [2.0, 2.1, 2.2], "C": [1.0, 3.0, 2.0]}  # C - B = -0.1, std 1
    result = judge(ORDER, values)
    assert result.verdict == "within spread" and [r.verdict for r in result.comparisons] == ["holds", "within spread"]


def test_against_the_paper_scales_its_relative_difference_to_our_level() -> None:
    """The paper: 4.0 -> 3.0 (-25 %); ours at twice its level: X 8.0, so a gain of the paper's size is -2.0."""
    x = [7.9, 8.0, 8.1]  # spread 0.1
    paper_difference, size = against_paper([7.9, 8.0, 8.1], x, 3.0, 4.0)  # no gain
    assert paper_difference == pytest.approx(-2.0) and size == "smaller than the paper's"
    assert against_paper([6.0, 6.05, 6.1], x, 3.0, 4.0)[1] == "as the paper's"  # -1.95, within 0.1 of -2.0
    assert against_paper([4.9, 5.0, 5.1], x, 3.0, 4.0)[1] == "larger than the paper's"  # -3.0
    noisy = [6.0, 8.0, 10.0]  # spread 2: no gain, yet within the spread of the paper's -2.0
    assert compare(noisy, x)[2] == "within spread" and against_paper(noisy, x, 3.0, 4.0)[1] == "as the paper's"
    assert against_paper([6.0], x, 3.0, 4.0)[1] == "one seed"
    assert against_paper(x, x, None, 4.0) == (None, "no paper value")
    assert against_paper(x, x, 0.0, 0.0) == (None, "no paper value")  # the paper prints 0.000


def test_a_claim_is_smaller_than_the_papers_when_any_comparison_is() -> None:
    values = {"A": [4.0, 4.2, 4.1], "B": [2.0, 2.1, 2.2], "C": [2.0, 2.1, 2.2]}
    paper = {"A": 4.0, "B": 2.0, "C": 1.0}  # paper: B halves A, C halves B
    result = judge(ORDER, values, paper)
    assert [r.size for r in result.comparisons] == ["as the paper's", "smaller than the paper's"]
    assert result.size == "smaller than the paper's" and result.verdict == "within spread"
    assert judge(ORDER, {**values, "C": [1.0, 1.05, 1.1]}, paper).size == "as the paper's or larger"
    assert judge(ORDER, values).size == "no paper value"  # no paper values given


def test_one_seed_and_missing_runs_are_named() -> None:
    assert judge(ORDER, {"A": [4.0], "B": [2.0], "C": [1.0]}).verdict == "one seed"
    missing = judge(ORDER, {"A": [4.0, 4.1], "B": [2.0, 2.1]})
    assert missing.verdict == "not run" and missing.comparisons == ()


def test_the_experiments_encode_the_papers_claims() -> None:
    claims = {c.text: c for c in ABLATION.claims}
    order = claims["A > B > C > D in error (paper objective)"].comparisons
    assert [(c.better, c.worse) for c in order] == [
        ("paper/model_B", "paper/model_A"),
        ("paper/model_C", "paper/model_B"),
        ("paper/model_D", "paper/model_C"),
    ]
    local = claims["|X1| = 64 is best (+ self-motion)"].comparisons
    assert {(c.better, c.worse) for c in local} == {
        ("recipe/model_D", "recipe/local_32"),
        ("recipe/model_D", "recipe/local_96"),
    }
    assert "(λ1, λ2) = (0.5, 0.1) is best (paper objective)" in claims and len(ABLATION.claims) == 6
    assert [(c.comparisons[0].better, c.comparisons[0].worse) for c in LC.claims] == [
        (f"{host}/{lc}", f"{host}/X") for host in ("dcp", "prnet", "idam", "deepgmr") for lc in ("LC", "LC-matched")
    ]
    assert all("not a claim of the paper" in c.text for c in LC.claims if "matched" in c.text)
