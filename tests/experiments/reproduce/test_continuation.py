"""``lcreg reproduce --continue-from``: a run its step cap cut off goes on under a higher cap, as if never stopped."""

from __future__ import annotations

import csv
import json
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from _reproduce_outputs import read_jsonl  # type: ignore[import-not-found]
from lcreg.__main__ import main
from lcreg.experiments.reproduce.ablation import ABLATION
from lcreg.experiments.reproduce.budgets import DataChoice, RunBudget
from lcreg.experiments.reproduce.continuation import ContinuationError, keeps_resume_state
from lcreg.experiments.reproduce.sweep import METRICS, Sweep, continued_runs, run_sweep

pytestmark = pytest.mark.usefixtures("isolated_cli")

# Validated every 2 steps; no early stop within 6 steps (patience 50): every run here ends at its cap.
BUDGET = RunBudget(steps=6, points=64, batch=2, checks=3, patience=50, val_pairs=2)
EXPERIMENT = replace(ABLATION.select(["paper/model_A"]), budgets={"smoke": {"dvds": BUDGET}})


def _sweep(out: Path, cap: int, continues: Path | None = None) -> Sweep:
    settings = (("trainer.max_steps", cap),)
    return Sweep(EXPERIMENT, "smoke", (0,), DataChoice(None), out, settings=settings, continues=continues)


def _run(sweep: Sweep) -> dict:
    run_sweep(sweep)
    (row,) = read_jsonl(sweep.log_path)
    return row


def _validations(row: dict) -> list[tuple[int, str]]:
    """``(step, val/rre_clip5_deg)`` of every validation in the run's metrics files (every segment)."""
    folder = Path(row["metrics_csv"]).parent
    rows = [r for path in sorted(folder.glob("metrics*.csv")) for r in csv.DictReader(path.open())]
    return sorted({(int(r["step"]), r["val/rre_clip5_deg"]) for r in rows if r.get("val/rre_clip5_deg")})


def test_a_capped_run_continued_under_a_higher_cap_ends_as_the_run_trained_to_that_cap(tmp_path: Path) -> None:
    """Before: a raised cap was a new run folder, trained from step 0 (session 55: 2,139 steps, 2 CPU-hours again)."""
    capped = _run(_sweep(tmp_path / "capped", 3))  # a cap mid-epoch, between two validations
    assert capped["steps"] == 3 and capped["stopped_early"] is False and capped["kept_resume_state"] is True
    checkpoints = Path(capped["metrics_csv"]).parent / "checkpoints"
    assert sorted(p.name for p in checkpoints.glob("*.ckpt")) == sorted(["last.ckpt", capped["selected"]])

    continued = _run(_sweep(tmp_path / "continued", 6, continues=tmp_path / "capped"))
    whole = _run(_sweep(tmp_path / "whole", 6))
    assert (continued["continues"], continued["continued_from"]) == (str(Path(capped["weights"]).parent), 3)
    assert "continues" not in whole and continued["steps"] == whole["steps"] == 6
    assert continued["selected"] == whole["selected"]  # chosen over both segments
    assert {k: continued[k] for k in METRICS} == {k: whole[k] for k in METRICS}
    ours, theirs = torch.load(continued["weights"]), torch.load(whole["weights"])
    assert all(torch.equal(ours["state_dict"][k], v) for k, v in theirs["state_dict"].items())
    assert _validations(continued) == _validations(whole) and len(_validations(whole)) == 3
    assert (checkpoints / "last.ckpt").is_file()  # the earlier run is left as it was


def test_a_continued_run_cut_off_resumes_from_its_own_state_not_the_earlier_runs(tmp_path: Path) -> None:
    _run(_sweep(tmp_path / "capped", 2))
    first = _run(_sweep(tmp_path / "to4", 4, continues=tmp_path / "capped"))
    log_dir = Path(first["metrics_csv"]).parent
    (tmp_path / "to4" / "ablation.jsonl").unlink()  # as if cut off after its last checkpoint, before its row
    again = _run(_sweep(tmp_path / "to4", 4, continues=tmp_path / "capped"))
    assert again["steps"] == 4 and again["continued_from"] == 2
    assert sorted(p.name for p in log_dir.glob("metrics*.csv")) == ["metrics.csv", "metrics.segment1.csv"]
    assert not (log_dir / "abandoned").exists()


def _row_edited(out: Path, **fields: object) -> None:
    log = out / "ablation.jsonl"
    (row,) = read_jsonl(log)
    log.write_text(json.dumps({**row, **fields}) + "\n")


@pytest.mark.parametrize(
    ("edit", "cap", "message"),
    [
        (None, 2, r"trained 2 steps; trainer.max_steps 2 is not above"),
        ({"stopped_early": True, "steps": 1}, 4, r"stopped early at step 1 \(its validation stopped improving\)"),
        ({"failed": "10 consecutive steps had a non-finite loss"}, 4, r"failed \(10 consecutive"),
        ({"overrides": {"trainer.max_steps": 2, "model.init_args.lr": 0.1}}, 4, r"has no run of this budget"),
        ("last.ckpt", 4, r"last.ckpt is missing: the run cannot be continued"),
    ],
    ids=["same-cap", "stopped-early", "failed", "other-settings", "state-gone"],
)
def test_what_cannot_be_continued_is_refused_before_anything_trains(
    tmp_path: Path, edit: dict | str | None, cap: int, message: str
) -> None:
    capped = _run(_sweep(tmp_path / "capped", 2))
    if isinstance(edit, dict):
        _row_edited(tmp_path / "capped", **edit)
    elif edit is not None:
        (Path(capped["metrics_csv"]).parent / "checkpoints" / edit).unlink()
    with pytest.raises(ContinuationError, match=message) as err:
        continued_runs(_sweep(tmp_path / "next", cap, continues=tmp_path / "capped"), rerun=False)
    assert "paper/model_A seed 0" in str(err.value)
    assert not (tmp_path / "next").exists()


def test_only_a_converge_run_stopped_by_its_cap_keeps_its_resume_state() -> None:
    assert keeps_resume_state(converge=True, steps=3000, cap=3000)
    assert not keeps_resume_state(converge=True, steps=2750, cap=3000)  # stopped early: done
    assert not keeps_resume_state(converge=False, steps=2, cap=2)  # fixed-step budgets end at their cap by design


def test_continue_from_on_the_command_line_refuses_what_it_cannot_continue(tmp_path: Path, capsys) -> None:
    base = ["reproduce", "lc", "--budget", "smoke", "--seeds", "0", "--only", "idam/X", "--out", str(tmp_path)]
    for extra, message in [
        (["--continue-from", str(tmp_path / "none")], "--continue-from: no folder"),
        (["--continue-from", str(tmp_path)], "idam/X: the smoke budget has no early stop"),
        (["--continue-from", str(tmp_path), "--no-resume"], "not with --no-resume or --retest"),
    ]:
        with pytest.raises(SystemExit) as info:
            main([*base, *extra])
        assert info.value.code == 2 and message in capsys.readouterr().err
    assert not (tmp_path / "lc.jsonl").exists()


def test_the_workers_of_jobs_continue_the_same_runs(tmp_path: Path) -> None:
    from lcreg.experiments.reproduce.command import _worker_options, build_parser

    args = build_parser().parse_args(["lc", "--budget", "converge", "--continue-from", str(tmp_path), "--jobs", "2"])
    worker = build_parser().parse_args(["lc", "--only", "dcp/X", "--seeds", "0", *_worker_options(args, tmp_path)])
    assert worker.continue_from == str(tmp_path) and worker.budget == "converge"
