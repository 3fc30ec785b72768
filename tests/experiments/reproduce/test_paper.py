"""The paper's numbers in lcreg.experiments.reproduce.paper match the LaTeX tables, and the experiments cover every
row."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from lcreg.experiments.benchmarking import config_dir
from lcreg.experiments.reproduce.ablation import ABLATION, ROWS
from lcreg.experiments.reproduce.lc import LC
from lcreg.experiments.reproduce.paper import ABLATION as PAPER_ABLATION
from lcreg.experiments.reproduce.paper import LC_PLUS_X, PAPER_METRICS

PAPER = Path(__file__).resolve().parents[4] / "shared" / "paper" / "dvds-paper.tex"
NUMBER_ROW = re.compile(r"&\s*([\d.]+)\s*&\s*([\d.]+)\s*&\s*([\d.]+)\s*&\s*([\d.]+)\s*\\\\")


def _table_rows(tex: str, label: str) -> list[tuple[float, ...]]:
    """The four numbers of every row of the table environment holding ``\\label{label}``, in order."""
    table = next(t for t in tex.split("\\begin{table") if f"\\label{{{label}}}" in t)
    return [tuple(float(v) for v in m.groups()) for m in NUMBER_ROW.finditer(table)]


@pytest.mark.skipif(not PAPER.is_file(), reason=f"the paper's source is not at {PAPER}")
@pytest.mark.parametrize(("label", "table"), [("ablation_all", PAPER_ABLATION), ("table4", LC_PLUS_X)])
def test_paper_numbers_are_the_tables_rows_in_order(label: str, table: dict) -> None:
    ours = [tuple(row[m] for m in PAPER_METRICS) for row in table.values()]
    assert ours == _table_rows(PAPER.read_text(encoding="utf-8"), label)


def test_every_ablation_config_and_paper_row_has_a_cell() -> None:
    stems = {p.stem for p in (config_dir() / "ablation").glob("*.yaml")}
    aliases = {"local_64", "lambda_0.5_0.1"}  # model D under another run name
    assert {stem for _, _, stem in ROWS} | aliases == stems
    assert {c.paper for c in ABLATION.cells} == set(PAPER_ABLATION)
    assert {c.paper for c in LC.cells} - {None} == set(LC_PLUS_X)  # LC (matched) + X: not in the paper
    assert len(ABLATION.variants) == 16 and len(ABLATION.cells) == 20 and len(LC.variants) == 12
