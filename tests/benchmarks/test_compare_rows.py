"""``benchmarks/compare_rows.py``: runs of several jobs judged by the queue's rule, each run's newest row."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from test_smoke import load  # type: ignore[import-not-found]

compare_rows = load("compare_rows")
FIGURES = ["--figures", "rmse_r_deg", "mae_r_deg"]


def _jsonl(path: Path, *rows: dict[str, Any]) -> Path:
    path.write_text("".join(json.dumps(row) + "\n" for row in rows), encoding="utf-8")
    return path


def _row(seed: int, rmse: float, **more: Any) -> dict[str, Any]:
    return {"variant": "dcp/X", "seed": seed, "rmse_r_deg": rmse, "mae_r_deg": rmse / 2, **more}


def _verdicts(text: str) -> dict[str, str]:
    lines = [line.split(" | ") for line in text.splitlines() if line.startswith(("| rmse", "| mae"))]
    return {cells[0].strip("| "): cells[-1].strip(" |") for cells in lines}


def test_each_figure_is_judged_by_the_difference_of_the_means_against_the_larger_std(tmp_path: Path) -> None:
    low = _jsonl(tmp_path / "low.jsonl", _row(0, 9.0), _row(0, 4.0), _row(1, 4.2), _row(2, 4.4))  # seed 0 rerun
    high = _jsonl(tmp_path / "high.jsonl", _row(0, 5.0), _row(1, 5.6), _row(2, 6.2, mae_r_deg=1.9))
    out = tmp_path / "rule.md"
    sides = [("low", [f"{low}:dcp/X:{s}" for s in range(3)]), ("high", [f"{high}:dcp/X:{s}" for s in range(3)])]
    compare_rows.main(
        ["--side", *sides[0][0:1], *sides[0][1], "--side", sides[1][0], *sides[1][1], "--out", str(out), *FIGURES]
    )
    text = out.read_text()
    # RMSE(R): means 4.2 (the rerun of seed 0 counts, not its first row) and 5.6, stds 0.2 and 0.6: -1.4 beyond 0.6
    assert "| rmse_r_deg | 4.20 ± 0.20 | 5.60 ± 0.60 | -1.40 | 0.60 |" in text
    # MAE(R): 2.1 ± 0.1 against (2.5, 2.8, 1.9) = 2.4 ± 0.46: -0.3 within 0.46
    assert _verdicts(text) == {"rmse_r_deg": "low: better beyond the spread", "mae_r_deg": "low: within the spread"}
    reverse = compare_rows.report([sides[1], sides[0]], ["rmse_r_deg"])
    assert _verdicts(reverse) == {"rmse_r_deg": "high: worse beyond the spread"}
    one = compare_rows.report([("probe", [f"{high}:dcp/X:0"]), sides[0]], ["rmse_r_deg", "mae_r_deg"])
    assert _verdicts(one) == {  # 5.0 against 4.2 ± 0.2; 2.5 against 2.1 ± 0.1: both beyond the three seeds' std
        "rmse_r_deg": "probe: worse beyond the spread (one run against the other side's std)",
        "mae_r_deg": "probe: worse beyond the spread (one run against the other side's std)",
    }
    alone = compare_rows.report([("probe", [f"{high}:dcp/X:0"]), ("other", [f"{low}:dcp/X:1"])], ["rmse_r_deg"])
    assert _verdicts(alone) == {"rmse_r_deg": "probe: one seed: no spread"}


@pytest.mark.parametrize(
    ("spec", "rows", "message"),
    [
        ("{missing}:dcp/X:0", [], r"missing\.jsonl: no such file"),
        ("{file}:dcp/X:1", [_row(0, 4.0)], r"no row of dcp/X seed 1 \(rows: dcp/X:0\)"),
        ("{file}:dcp/X:0", [_row(0, 4.0), {"variant": "dcp/X", "seed": 0, "failed": "loss is NaN"}], "failed: loss"),
        ("{file}:dcp/X:0", [_row(0, float("nan"))], "its rmse_r_deg is nan, not a finite number"),
        ("{file}:dcp/X:0", [{"variant": "dcp/X", "seed": 0, "mae_r_deg": 1.0}], "no figure 'rmse_r_deg'"),
        ("{file}:dcp/X", [_row(0, 4.0)], "expected FILE:VARIANT:SEED"),
        ("{file}:dcp/X:first", [_row(0, 4.0)], "the seed 'first' is not an integer"),
    ],
)
def test_a_run_without_a_usable_row_is_refused_naming_it(
    tmp_path: Path, spec: str, rows: list[dict[str, Any]], message: str
) -> None:
    file = _jsonl(tmp_path / "rows.jsonl", *rows)
    named = spec.format(file=file, missing=tmp_path / "missing.jsonl")
    good = f"{_jsonl(tmp_path / 'good.jsonl', _row(0, 4.0))}:dcp/X:0"
    with pytest.raises(SystemExit, match=message):
        compare_rows.main(["--side", "a", named, "--side", "b", good, "--figures", "rmse_r_deg"])


def test_a_damaged_file_is_refused_naming_its_line(tmp_path: Path) -> None:
    damaged = tmp_path / "rows.jsonl"
    damaged.write_text(json.dumps(_row(0, 4.0)) + "\n{not json\n", encoding="utf-8")
    with pytest.raises(SystemExit, match=r"rows\.jsonl, line 2: not a JSON row"):
        compare_rows.main(["--side", "a", f"{damaged}:dcp/X:0", "--side", "b", f"{damaged}:dcp/X:0"])
    with pytest.raises(SystemExit, match="exactly two --side options, got 1"):
        compare_rows.main(["--side", "a", f"{_jsonl(tmp_path / 'ok.jsonl', _row(0, 4.0))}:dcp/X:0"])


def test_a_seed_under_several_budgets_must_be_named_by_a_piece_of_its_budget(tmp_path: Path) -> None:
    # a sweep's rows of an older budget key stay beside the newer ones (e.g. DCP-v2 at lr 1e-3, then at 2.5e-4)
    both = _jsonl(
        tmp_path / "lc.jsonl", _row(0, 6.0, budget="3000 steps"), _row(0, 4.0, budget="3000 steps, lr 0.00025")
    )
    other = f"{_jsonl(tmp_path / 'other.jsonl', _row(0, 5.0))}:dcp/X:0"
    with pytest.raises(SystemExit, match=r"dcp/X seed 0 has rows of 2 runs .*Name one with FILE:VARIANT:SEED:BUDGET"):
        compare_rows.main(["--side", "a", f"{both}:dcp/X:0", "--side", "b", other, *FIGURES])
    text = compare_rows.report([("a", [f"{both}:dcp/X:0:lr 0.00025"]), ("b", [other])], ["rmse_r_deg"])
    assert "| rmse_r_deg | 4.00 ± 0 | 5.00 ± 0 | -1.00 |" in text
    with pytest.raises(compare_rows.RowNotFoundError, match="with 'lr 1e-3' in its budget"):
        compare_rows.report([("a", [f"{both}:dcp/X:0:lr 1e-3"]), ("b", [other])], ["rmse_r_deg"])
