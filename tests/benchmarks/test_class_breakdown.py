"""``benchmarks/class_breakdown.py``: a model's test figures by class, from its seeds' ``test_per_pair.csv`` files."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import pytest
from test_smoke import load  # type: ignore[import-not-found]

from lcreg.models.evaluation import COMPONENT_COLUMNS

class_breakdown = load("class_breakdown")
HEADER = ["index", "rotation_error_deg", "translation_error", "class", *COMPONENT_COLUMNS]


def _csv(path: Path, rows: list[list[object]], header: list[str] = HEADER) -> Path:
    with path.open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(header)
        writer.writerows(rows)
    return path


def _cells(text: str, group: str) -> list[str]:
    (line,) = [line for line in text.splitlines() if line.startswith(f"| {group} |")][:1]
    return [cell.strip() for cell in line.strip("|").split("|")]


def test_figures_per_group_follow_from_the_rows(tmp_path: Path) -> None:
    # Class a: Euler errors (3, 0, 0) and (0, 4, 0); class b: (0, 0, 12). Translations: (0.1, 0, 0) each.
    rows = [[0, 3.0, 0.1, "a", 3, 0, 0, 0.1, 0, 0], [1, 4.0, 0.1, "a", 0, 4, 0, 0.1, 0, 0]]
    rows.append([2, 12.0, 0.1, "b", 0, 0, 12, 0.1, 0, 0])
    path = _csv(tmp_path / "s0.csv", rows)
    text = class_breakdown.report([path], 1, [["b"]], [1.0, 1.0, 0.1, 0.1], "made up")
    everything = _cells(text, "all pairs")
    assert everything[1] == "3"
    assert float(everything[2].split(" ± ")[0]) == pytest.approx(math.sqrt((9 + 16 + 144) / 9), rel=1e-2)
    assert float(everything[3].split(" ± ")[0]) == pytest.approx(19 / 9, rel=1e-2)
    a = _cells(text, "a")
    assert float(a[2].split(" ± ")[0]) == pytest.approx(math.sqrt(25 / 6), rel=1e-2)  # RMSE(R) of class a alone
    assert float(a[8].split(" ± ")[0]) == pytest.approx(25 / 169, rel=1e-2)  # its share of the squared Euler error
    assert float(_cells(text, "b")[8].split(" ± ")[0]) == pytest.approx(144 / 169, rel=1e-2)
    assert _cells(text, "all but b")[2] == a[2]  # the same pairs as class a here
    assert "| all but b | RMSE(R) ° |" in text and "one file: no spread" in text


def test_a_failed_pair_counts_at_180_degrees_in_the_geodesic_figures(tmp_path: Path) -> None:
    rows = [[0, 2.0, 0.1, "a", 2, 0, 0, 0.1, 0, 0], [1, "nan", "nan", "a", 180, 180, 180, 0.3, 0.4, 0]]
    text = class_breakdown.report([_csv(tmp_path / "s0.csv", rows)], 1, [], None, "")
    assert _cells(text, "a")[6] == "91.0 ± 0"  # mean RRE (2 + 180) / 2, as the test's rre_mean_deg counts it


def test_seeds_give_mean_and_std_and_the_without_group_is_judged_against_all_pairs(tmp_path: Path) -> None:
    paths = []
    for seed, big in enumerate((10.0, 11.0, 12.0)):
        rows = [[k, 1.0, 0.01, "a", 1, 0, 0, 0.01, 0, 0] for k in range(9)]
        rows.append([9, big, 0.1, "b", big, 0, 0, 0.1, 0, 0])
        paths.append(_csv(tmp_path / f"s{seed}.csv", rows))
    text = class_breakdown.report(paths, 2, [["b"]], None, "")
    assert _cells(text, "a")[2] == "0.577 ± 0"  # sqrt(1 / 3) in every seed
    assert _cells(text, "the other 1 classes")[1] == "1"  # class b has 1 pair < --min-pairs 2: pooled
    verdicts = [line for line in text.splitlines() if line.startswith("| all but b | ")]
    assert len(verdicts) == 5 and "lower beyond the spread" in verdicts[1]  # the table's row, then 4 judgements
    assert "Ours / paper" not in text


def test_bad_files_are_named(tmp_path: Path) -> None:
    good = _csv(tmp_path / "good.csv", [[0, 1.0, 0.1, "a", 1, 0, 0, 0.1, 0, 0]])
    old = _csv(tmp_path / "old.csv", [[0, 1.0, 0.1, "a"]], HEADER[:4])
    other = _csv(tmp_path / "other.csv", [[1, 1.0, 0.1, "a", 1, 0, 0, 0.1, 0, 0]])
    bad = _csv(tmp_path / "bad.csv", [[0, 1.0, 0.1, "a", "x", 0, 0, 0.1, 0, 0]])
    cases = [
        ([tmp_path / "missing.csv"], "missing.csv: cannot be read"),
        ([old], "old.csv: no column euler_error_z_deg.*test its weights again"),
        ([good, other], "other.csv: other test pairs"),
        ([bad], "bad.csv, line 2: not a number"),
    ]
    for paths, message in cases:
        with pytest.raises(class_breakdown.PerPairFileError, match=message):
            class_breakdown.report(paths, 1, [], None, "")
    with pytest.raises(class_breakdown.PerPairFileError, match="no test pair of class z"):
        class_breakdown.report([good], 1, [["z"]], None, "")
    with pytest.raises(class_breakdown.PerPairFileError, match="leaves no test pair"):
        class_breakdown.report([good], 1, [["a"]], None, "")
    with pytest.raises(SystemExit, match=r"class_breakdown: .*old\.csv"):
        class_breakdown.main(["--per-pair", str(old)])
