"""``lcreg.experiments.benchmarking.data.class_groups``: the groups of the per-class reports."""

from __future__ import annotations

import pytest

from lcreg.experiments.benchmarking import class_groups


def test_groups_are_all_pairs_the_large_classes_largest_first_the_rest_pooled_and_each_without_list() -> None:
    classes = ["b"] * 3 + ["a"] * 5 + ["c", "d"]
    assert class_groups(classes, 3, [["a"], ["c", "d"]]) == [
        ("all pairs", frozenset("abcd")),
        ("a", frozenset("a")),
        ("b", frozenset("b")),
        ("the other 2 classes", frozenset("cd")),
        ("all but a", frozenset("bcd")),
        ("all but c, d", frozenset("ab")),
    ]
    assert class_groups(["a", "a"], 1) == [("all pairs", frozenset("a")), ("a", frozenset("a"))]


def test_a_without_list_naming_an_absent_class_or_leaving_nothing_is_refused() -> None:
    with pytest.raises(ValueError, match="no test pair of class z"):
        class_groups(["a", "b"], 1, [["z"]])
    with pytest.raises(ValueError, match="leaves no test pair"):
        class_groups(["a", "b"], 1, [["a", "b"]])
