"""``lcreg reproduce runtime``: the smoke preset end to end, resume, and the paper's figures against the LaTeX."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

import lcreg.experiments.reproduce.command
import lcreg.experiments.reproduce.runtime
from _reproduce_outputs import count_calls, read_jsonl  # type: ignore[import-not-found]
from lcreg.__main__ import main
from lcreg.experiments.reproduce.paper import RUNTIME_MS, RUNTIME_POINTS
from lcreg.experiments.reproduce.runtime import RUNTIME

pytestmark = pytest.mark.usefixtures("isolated_cli")
pytest.importorskip("matplotlib")

PAPER = Path(__file__).resolve().parents[4] / "shared" / "paper" / "dvds-paper.tex"
LABELS = {"Ours": "dvds", "ICP": "icp", "PointNetLK": "pointnetlk", "DCP": "dcp", "FGR": "fgr", "RANSAC": "ransac"}
LABELS |= {"FMR-Net": "fmr", "PCRNet": "pcrnet"}


@pytest.mark.skipif(not PAPER.is_file(), reason=f"the paper's source is not at {PAPER}")
def test_paper_runtime_figures_are_the_latex_rows_in_order() -> None:
    table = next(t for t in PAPER.read_text(encoding="utf-8").split("\\begin{table") if "\\label{table3}" in t)
    assert "Running time comparisons" in table and "Points & 500 & 1000 & 2000" in table
    rows = re.findall(r"^\s*(?!Points)([\w-]+)\s*&\s*(\d+)\s*&\s*(\d+)\s*&\s*(\d+)\s*\\\\", table, flags=re.M)
    assert [(LABELS[name], tuple(float(v) for v in values)) for name, *values in rows] == list(RUNTIME_MS.items())
    assert RUNTIME_POINTS == (500, 1000, 2000) and set(RUNTIME.methods) == set(RUNTIME_MS)


def test_smoke_preset_writes_rows_report_with_paper_column_and_plot(tmp_path: Path, monkeypatch, capsys) -> None:
    builds = count_calls(monkeypatch, lcreg.experiments.reproduce.runtime, "build")
    out = tmp_path / "out"
    args = ["reproduce", "runtime", "--budget", "smoke", "--seeds", "0", "--out", str(out)]
    main(args)
    rows = read_jsonl(out / "runtime.jsonl")
    assert sorted(r["method"] for r in rows) == sorted(RUNTIME.methods)
    assert all(r["device"] == "cpu" and r["points"] == 500 and r["pairs"] == 1 and r["ms_per_pair"] > 0 for r in rows)
    text = (out / "runtime.md").read_text()
    assert (
        "paper ms/pair" in text and "Titan Xp" in text and "E5-2620" in text and "Measurements finished: 8 of 8" in text
    )
    assert "| DVDs | 500 |" in text and "| 66 |" in text and "| 1.00× | 1.00× |" in text  # DVDs: paper 66 ms
    from matplotlib.image import imread

    image = imread(out / "runtime.png")[..., :3]
    assert image.shape[0] > 300 and image.std() > 0.05
    assert f"wrote {out / 'runtime'}.png" in capsys.readouterr().out
    assert sorted(builds) == sorted(RUNTIME.methods)

    builds.clear()  # resume: every row is there, nothing is built or measured again
    main(args)
    assert builds == [] and len(read_jsonl(out / "runtime.jsonl")) == len(rows)
    main([*args[:-2], "--seeds", "0", "1", "--only", "icp", "--out", str(out)])  # only the missing seed
    assert builds == ["icp"]
    new = read_jsonl(out / "runtime.jsonl")[len(rows) :]
    assert [(r["method"], r["seed"]) for r in new] == [("icp", 1)]
    assert "Measurements finished: 2 of 2" in (out / "runtime.md").read_text()


def test_only_matching_nothing_is_a_usage_error(tmp_path: Path, capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["reproduce", "runtime", "--budget", "smoke", "--only", "nope", "--out", str(tmp_path)])
    assert exc.value.code == 2 and "matches no method of runtime" in capsys.readouterr().err


def test_a_runtime_report_that_fails_exits_3_and_keeps_the_measurements(tmp_path: Path, monkeypatch, capsys) -> None:
    def broken(*args: object, **kwargs: object) -> str:
        raise RuntimeError("no display")

    monkeypatch.setattr(lcreg.experiments.reproduce.command, "render_runtime", broken)
    args = ["reproduce", "runtime", "--budget", "smoke", "--seeds", "0", "--only", "icp", "--out", str(tmp_path)]
    with pytest.raises(SystemExit) as exit_:
        main(args)
    err = capsys.readouterr().err
    assert exit_.value.code == 3 and "report not written (RuntimeError: no display)" in err  # before: a traceback
    assert str(tmp_path / "runtime.jsonl") in err and len(read_jsonl(tmp_path / "runtime.jsonl")) == 1
