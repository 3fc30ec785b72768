"""``lcreg reproduce`` end to end: the smoke preset of every experiment, resume, and clear errors for bad arguments."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path
from typing import Any

import pytest
import yaml

import lcreg.experiments.reproduce.command
import lcreg.experiments.reproduce.sweep
from _reproduce_outputs import assert_png_drawn, count_calls, read_jsonl  # type: ignore[import-not-found]
from lcreg.__main__ import main
from lcreg.experiments.reproduce import EXPERIMENTS, PLANNED
from lcreg.experiments.reproduce.budgets import DataChoice, RunBudget
from lcreg.experiments.reproduce.lc import LC
from lcreg.experiments.reproduce.report import render
from lcreg.experiments.reproduce.sweep import METRICS, Sweep, failed_runs, finished_rows, run_sweep
from lcreg.models.base import NonFiniteTrainingError

pytestmark = pytest.mark.usefixtures("isolated_cli")
pytest.importorskip("matplotlib")


@pytest.mark.parametrize("name", list(EXPERIMENTS))
def test_smoke_preset_writes_jsonl_markdown_with_paper_columns_and_plots(name: str, tmp_path: Path, capsys) -> None:
    out = tmp_path / "out"
    main(["reproduce", name, "--budget", "smoke", "--seeds", "0", "--out", str(out)])
    experiment = EXPERIMENTS[name]
    rows = read_jsonl(out / f"{name}.jsonl")
    assert sorted(r["variant"] for r in rows) == sorted(v.key for v in experiment.variants)
    assert all(r["preset"] == "smoke" and r["steps"] == 2 and r["num_test_pairs"] == 2 for r in rows)
    assert all(Path(r["weights"]).is_file() and not list(Path(r["weights"]).parent.rglob("*.ckpt")) for r in rows)
    text = (out / f"{name}.md").read_text()
    assert "ours / paper" in text and "Budget `smoke` per run: 2 steps × 2 pairs × 128 points" in text
    assert "**2 test pairs**" in text and f"Runs finished: {len(rows)} of {len(rows)}" in text
    assert text.count("| one seed |") == 2 * len(experiment.claims)  # RMSE(R) and MAE(R) per claim
    paper_value = f"{experiment.paper[experiment.cells[0].paper or ''].get('rmse_r_deg'):.3f}"
    assert paper_value in text.split("## MAE(R)")[0]
    for suffix in ("rotation", "translation"):
        assert_png_drawn(out / f"{name}_{suffix}.png")
    assert text.count("| end of the budget |") == len(rows)  # one line per run in "Where each run stopped"
    for group in {v.key.split("/")[0] for v in experiment.variants}:
        assert_png_drawn(out / f"{name}_curves_{group}_validation.png")
    assert f"wrote {out / name}.md" in capsys.readouterr().out


def test_an_interrupted_sweep_resumes_without_redoing_finished_runs(tmp_path: Path, monkeypatch) -> None:
    fits = count_calls(monkeypatch, lcreg.experiments.reproduce.sweep, "fit")
    args = [
        "reproduce",
        "lc",
        "--budget",
        "smoke",
        "--seeds",
        "0",
        "--only",
        "idam/*",
        "deepgmr/X",
        "--out",
        str(tmp_path),
    ]
    main(args)
    assert fits == ["idam", "idam_lc", "idam_lc", "deepgmr"]  # X, LC + X, LC (matched) + X
    main(args)  # everything finished: nothing trains, the report is written again
    assert len(fits) == 4 and (tmp_path / "lc.md").is_file()
    log = tmp_path / "lc.jsonl"
    lines = log.read_text().splitlines()
    log.write_text("\n".join(lines[:1]) + "\n")  # interrupted after the first run
    main(args)
    assert fits[4:] == ["idam_lc", "idam_lc", "deepgmr"] and len(read_jsonl(log)) == 4
    matched = next(r for r in read_jsonl(log) if r["variant"] == "idam/LC-matched")
    assert matched["overrides"]["model.init_args.loss_terms"][0]["init_args"]["weight"] == 51.6


def test_a_sweep_cut_off_after_a_run_keeps_the_report_of_that_run(tmp_path: Path, monkeypatch) -> None:
    real = lcreg.experiments.reproduce.sweep.fit
    fits: list[str] = []

    def fit_then_cut_off(*args: Any, **kwargs: Any) -> Any:  # the session ends during the second run
        fits.append("fit")
        if len(fits) == 2:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(lcreg.experiments.reproduce.sweep, "fit", fit_then_cut_off)
    with pytest.raises(KeyboardInterrupt):
        main(["reproduce", "lc", "--budget", "smoke", "--seeds", "0", "1", "--only", "idam/X", "--out", str(tmp_path)])
    text = (tmp_path / "lc.md").read_text()  # session 51: a report written only at a sweep's end was 10 sessions stale
    assert "Runs finished: 1 of 2" in text and len(read_jsonl(tmp_path / "lc.jsonl")) == 1


@pytest.mark.parametrize(("every_s", "reports"), [(1e9, 1), (0.0, 3)])
def test_reports_while_a_sweep_trains_are_at_least_report_every_s_apart(
    every_s: float, reports: int, tmp_path: Path, monkeypatch, capsys
) -> None:
    monkeypatch.setattr(lcreg.experiments.reproduce.command, "REPORT_EVERY_S", every_s)
    main(["reproduce", "lc", "--budget", "smoke", "--seeds", "0", "1", "2", "--only", "idam/X", "--out", str(tmp_path)])
    assert capsys.readouterr().out.count("report of the runs finished so far") == reports  # the first run writes one
    assert "Runs finished: 3 of 3" in (tmp_path / "lc.md").read_text()


def test_a_report_that_fails_while_a_sweep_trains_does_not_stop_the_sweep(tmp_path: Path, monkeypatch, capsys) -> None:
    real = lcreg.experiments.reproduce.command._report
    reports: list[str] = []

    def broken_then_real(*args: Any, **kwargs: Any) -> Any:  # e.g. matplotlib failing on the first mid-sweep report
        reports.append("report")
        if len(reports) == 1:
            raise RuntimeError("no display")
        return real(*args, **kwargs)

    monkeypatch.setattr(lcreg.experiments.reproduce.command, "REPORT_EVERY_S", 0.0)
    monkeypatch.setattr(lcreg.experiments.reproduce.command, "_report", broken_then_real)
    main(["reproduce", "lc", "--budget", "smoke", "--seeds", "0", "1", "--only", "idam/X", "--out", str(tmp_path)])
    assert "report not written (RuntimeError: no display); training goes on" in capsys.readouterr().out
    assert len(read_jsonl(tmp_path / "lc.jsonl")) == 2 and "Runs finished: 2 of 2" in (tmp_path / "lc.md").read_text()


def test_a_report_that_fails_at_a_sweeps_end_exits_3_naming_the_kept_rows(tmp_path: Path, monkeypatch, capsys) -> None:
    real = lcreg.experiments.reproduce.command._report
    # before session 54: a traceback, exit 1, the queue stalled on it
    monkeypatch.setattr(lcreg.experiments.reproduce.command, "_report", _broken_report)
    args = ["reproduce", "lc", "--budget", "smoke", "--seeds", "0", "--only", "idam/X", "--out", str(tmp_path)]
    with pytest.raises(SystemExit) as exit_:
        main(args)
    assert exit_.value.code == lcreg.experiments.reproduce.command.REPORT_NOT_WRITTEN_EXIT_CODE == 3
    err = capsys.readouterr().err
    assert "report not written (RuntimeError: no display)" in err and str(tmp_path / "lc.jsonl") in err
    assert "--report-only" in err and len(read_jsonl(tmp_path / "lc.jsonl")) == 1 and not (tmp_path / "lc.md").exists()
    monkeypatch.setattr(lcreg.experiments.reproduce.command, "_report", real)
    main([*args, "--report-only"])  # what the message says: the kept row is reported, nothing trains again
    assert "Runs finished: 1 of 1" in (tmp_path / "lc.md").read_text()


def test_a_report_only_that_fails_names_its_cause_not_report_only_again(tmp_path: Path, monkeypatch, capsys) -> None:
    args = ["reproduce", "lc", "--budget", "smoke", "--seeds", "0", "--only", "idam/X", "--out", str(tmp_path)]
    main(args)
    monkeypatch.setattr(lcreg.experiments.reproduce.command, "_report", _broken_report)
    with pytest.raises(SystemExit) as exit_:
        main([*args, "--report-only"])  # before session 55 its hint was this very command
    err = capsys.readouterr().err
    assert exit_.value.code == 3 and "report not written (RuntimeError: no display)" in err
    assert "fix its cause and rerun this command to write it" in err and "with --report-only" not in err


def _broken_report(*args: Any, **kwargs: Any) -> Any:
    raise RuntimeError("no display")


def test_a_workers_failure_keeps_its_exit_code_when_the_report_fails_too(tmp_path: Path, monkeypatch, capsys) -> None:
    from lcreg.experiments.reproduce.parallel import WorkersFailedError

    def stopped(*args: Any, **kwargs: Any) -> None:  # a worker stopped by SIGTERM: its run resumes (exit 143)
        raise WorkersFailedError([("idam/X seed 1", 143)])

    monkeypatch.setattr(lcreg.experiments.reproduce.command, "run_workers", stopped)
    monkeypatch.setattr(lcreg.experiments.reproduce.command, "_report", _broken_report)
    args = ["reproduce", "lc", "--budget", "smoke", "--seeds", "0", "1", "--only", "idam/X", "--out", str(tmp_path)]
    with pytest.raises(SystemExit) as exit_:
        main([*args, "--jobs", "2"])
    captured = capsys.readouterr()
    assert exit_.value.code == 143 and "1 run(s) did not finish: idam/X seed 1 (exit 143)" in captured.err
    assert "report not written (RuntimeError: no display)" in captured.out


def test_workers_call_on_finish_after_each_run_that_finished(tmp_path: Path) -> None:
    from lcreg.experiments.reproduce.parallel import WorkerRun, WorkersFailedError, run_workers

    ok = [WorkerRun(f"a seed {k}", (sys.executable, "-c", "pass"), tmp_path / f"{k}.log") for k in range(2)]
    bad = WorkerRun("b seed 0", (sys.executable, "-c", "import sys; sys.exit(3)"), tmp_path / "b.log")
    finished: list[int] = []
    with pytest.raises(WorkersFailedError):
        run_workers([ok[0], bad, ok[1]], jobs=2, progress=lambda _: None, on_finish=lambda: finished.append(1))
    assert finished == [1, 1]


def _fake_train(calls: list[tuple[str, int]]) -> Any:
    def train(
        name: str, budget: RunBudget, data: DataChoice, run_dir: Path, seed: int, overrides: Any
    ) -> dict[str, Any]:
        calls.append((name, seed))
        return {"rmse_r_deg": 1.0, "train_s": 0.0}

    return train


def test_resume_keys_on_budget_and_data_and_no_resume_reruns(tmp_path: Path) -> None:
    calls: list[tuple[str, int]] = []
    idam = LC.select(["idam/X"])
    sweep = Sweep(idam, "smoke", (0, 1), DataChoice(None), tmp_path)
    run_sweep(sweep, _fake_train(calls))
    run_sweep(sweep, _fake_train(calls))
    assert calls == [("idam", 0), ("idam", 1)]
    run_sweep(Sweep(idam, "smoke", (0, 1, 2), DataChoice(None), tmp_path), _fake_train(calls))  # a new seed only
    assert calls[2:] == [("idam", 2)]
    run_sweep(Sweep(idam, "cpu", (0,), DataChoice("/m"), tmp_path), _fake_train(calls))  # another budget and data
    assert calls[3:] == [("idam", 0)]
    run_sweep(sweep, _fake_train(calls), rerun=True)
    assert calls[4:] == [("idam", 0), ("idam", 1)] and len(read_jsonl(sweep.log_path)) == 6
    ordered = Sweep(LC.select(["deepgmr/X", "idam/*"]), "smoke", (0,), DataChoice(None), tmp_path / "order")
    run_sweep(ordered, _fake_train(calls))  # in the order of --only
    assert [method for method, _ in calls[6:]] == ["deepgmr", "idam", "idam_lc", "idam_lc"]


def _error(args: list[str], capsys) -> str:
    with pytest.raises(SystemExit) as info:
        main(["reproduce", *args])
    assert info.value.code == 2
    return capsys.readouterr().err


def test_bad_arguments_give_one_clear_line(tmp_path: Path, capsys) -> None:
    out = ["--out", str(tmp_path)]
    assert "unknown experiment 'tables'; available: ablation, lc" in _error(
        ["tables", "--budget", "smoke", *out], capsys
    )
    for planned in PLANNED:
        assert f"experiment {planned!r} is not available yet" in _error([planned, "--budget", "smoke", *out], capsys)
    assert "the following arguments are required: --budget" in _error(["lc", *out], capsys)
    assert "invalid choice: 'gpu'" in _error(["lc", "--budget", "gpu", *out], capsys)
    assert "--seeds must be distinct non-negative" in _error(
        ["lc", "--budget", "smoke", "--seeds", "1", "1", *out], capsys
    )
    assert "--only 'dvds/*' matches no variant of lc" in _error(
        ["lc", "--budget", "smoke", "--only", "dvds/*", *out], capsys
    )
    assert "--jobs must be >= 1 (above 1 only for ablation, lc), got 0" in _error(
        ["lc", "--budget", "smoke", "--jobs", "0", *out], capsys
    )
    assert ", got 2" in _error(["runtime", "--budget", "smoke", "--jobs", "2", *out], capsys)
    assert "--partial applies to ablation, lc (training sweeps); robustness sets its own data" in _error(
        ["robustness", "--budget", "smoke", "--partial", "prnet", *out], capsys
    )
    assert "invalid _count_or_fraction value: 'most'" in _error(
        ["lc", "--budget", "smoke", "--partial", "prnet", "--partial-keep", "most", *out], capsys
    )
    message = _error(["lc", "--budget", "smoke", "--only", "idam/X", "--set", "trainer.max_steps=1", *out], capsys)
    assert "--set trainer.max_steps=1: idam/X's runs would end before their first validation, at step 2" in message
    missing = tmp_path / "nowhere"
    message = _error(["ablation", "--budget", "cpu", "--root", str(missing), *out], capsys)
    assert message.startswith("lcreg reproduce: error: ModelNet40 not found at") and "pass --root DIR" in message
    assert not list(tmp_path.iterdir())  # nothing written, nothing trained


def test_report_only_writes_the_table_of_what_is_finished(tmp_path: Path, capsys) -> None:
    main(["reproduce", "ablation", "--budget", "smoke", "--report-only", "--out", str(tmp_path)])
    text = (tmp_path / "ablation.md").read_text()
    assert "Runs finished: 0 of 48" in text and "not run" in text
    assert not (tmp_path / "ablation.jsonl").exists() and not list(tmp_path.glob("*.png"))


def test_a_diverged_run_is_recorded_as_failed_not_retried_and_left_out_of_the_means(tmp_path: Path) -> None:
    calls: list[tuple[str, int]] = []
    ok = _fake_train(calls)

    def train(
        name: str, budget: RunBudget, data: DataChoice, run_dir: Path, seed: int, overrides: Any
    ) -> dict[str, Any]:
        if seed == 1:
            calls.append((name, seed))
            raise NonFiniteTrainingError("10 consecutive steps had a non-finite loss")
        return ok(name, budget, data, run_dir, seed, overrides)

    sweep = Sweep(LC.select(["idam/X"]), "smoke", (0, 1), DataChoice(None), tmp_path)
    run_sweep(sweep, train)
    run_sweep(sweep, train)
    assert calls == [("idam", 0), ("idam", 1)]
    log = sweep.open_log()
    assert finished_rows(sweep, log) == {"idam/X": [log.rows[0]]}
    failed = failed_runs(sweep, log)
    assert failed == ["idam/X seed 1: 10 consecutive steps had a non-finite loss"]
    metrics = dict.fromkeys(METRICS, 1.0)
    rows = {"idam/X": [{**log.rows[0], **metrics, "test_s": 0.0, "steps": 2, "num_test_pairs": 2, "num_val_pairs": 2}]}
    assert f"- Failed (non-finite training loss, left out of the means): {failed[0]}" in render(
        sweep, rows, "c", failed
    )


def test_a_converge_run_selects_on_the_clipped_error_and_records_where_it_stopped(tmp_path: Path) -> None:
    from dataclasses import replace

    from lcreg.experiments.benchmarking import CONVERGE_METRIC, machine_line
    from lcreg.experiments.reproduce.ablation import ABLATION

    # min_delta is 0: on 2 synthetic validation pairs the run may stop early or reach the cap; both are recorded.
    budget = RunBudget(steps=4, points=64, batch=2, checks=4, patience=1, val_pairs=2)
    experiment = replace(ABLATION.select(["paper/model_A"]), budgets={"smoke": {"dvds": budget}})
    sweep = Sweep(experiment, "smoke", (0,), DataChoice(None), tmp_path)
    run_sweep(sweep)
    (row,) = read_jsonl(sweep.log_path)
    assert row["selected_on"] == CONVERGE_METRIC and "val_rre_clip5_deg" in row["selected"]
    assert row["num_val_pairs"] == 2 * 2 and row["steps"] <= 4
    assert row["stopped_early"] == (row["steps"] < 4) and row["best_val_rre_mean_deg"] is None
    assert row["machine"] == machine_line("cpu")  # the machine that trained the run, for the report's header
    assert row["peak_mib"] is None or row["peak_mib"] > 0  # None only where Linux's resettable peak is missing


def test_a_converge_run_that_reaches_a_raised_step_cap_is_not_recorded_as_stopped_early(tmp_path: Path) -> None:
    """``--set trainer.max_steps`` is the run's cap: session 44's rows compared the steps with the budget's own."""
    from dataclasses import replace

    from lcreg.experiments.reproduce.ablation import ABLATION

    budget = RunBudget(steps=6, points=64, batch=2, checks=2, patience=50, val_pairs=2)  # no early stop possible
    experiment = replace(ABLATION.select(["paper/model_A"]), budgets={"smoke": {"dvds": budget}})
    settings = (("trainer.max_steps", 3),)
    sweep = Sweep(experiment, "smoke", (0,), DataChoice(None), tmp_path, settings=settings)
    run_sweep(sweep)
    (row,) = read_jsonl(sweep.log_path)
    assert row["steps"] == 3 and row["overrides"] == {"trainer.max_steps": 3}
    assert row["stopped_early"] is False


def test_partial_crops_every_cloud_of_a_sweep_and_keys_its_runs_apart_from_full_clouds(tmp_path: Path) -> None:
    """``--partial prnet --partial-keep 0.5``: the workers of ``--jobs`` get the crop too; full-cloud keys unchanged."""
    args = ["reproduce", "lc", "--budget", "smoke", "--seeds", "0", "--only", "idam/X", "--out", str(tmp_path)]
    main([*args, "--partial", "prnet", "--partial-keep", "0.5", "--jobs", "2"])
    (row,) = read_jsonl(tmp_path / "lc.jsonl")
    assert row["data"].endswith(", partial: prnet crop keeping 0.5")
    assert (row["num_points"], row["points_per_cloud"]) == (128, 64)
    config = (Path(row["metrics_csv"]).parent / "config.yaml").read_text()
    assert "partial: prnet" in config and "partial_keep: 0.5" in config
    # Rows of full clouds keep the key they had before crops existed (the queue's finished runs stay finished).
    synthetic = "embedded synthetic shapes (2 validation and test pairs; smoke: numbers mean nothing)"
    assert (DataChoice(None).describe(), DataChoice("/m").describe()) == (synthetic, "ModelNet40 /m, unseen objects")
    assert "partial" not in str(DataChoice("/m").overrides(RunBudget(steps=2, points=128, batch=2)))
    calls: list[tuple[str, int]] = []
    run_sweep(Sweep(LC.select(["idam/X"]), "smoke", (0,), DataChoice(None), tmp_path), _fake_train(calls))
    assert calls == [("idam", 0)]  # the full-cloud run is another run


def test_train_objects_trains_every_run_of_a_sweep_on_the_subset_and_keys_its_runs_apart(tmp_path: Path) -> None:
    """``--train-objects 0.5``: the workers of ``--jobs`` get it too; the key names it, full data keeps its key."""
    args = ["reproduce", "lc", "--budget", "smoke", "--seeds", "0", "--only", "idam/X", "--out", str(tmp_path)]
    main([*args, "--train-objects", "0.5", "--jobs", "2"])
    (row,) = read_jsonl(tmp_path / "lc.jsonl")
    assert row["data"].endswith(", training objects: 0.5")
    config = (Path(row["metrics_csv"]).parent / "config.yaml").read_text()
    assert "train_objects: 0.5" in config
    # Its own folder: it never resumes from an unfinished run of all the objects (as --points, `<variant>_<N>pts`).
    assert Path(row["metrics_csv"]).parent.parent.parent.name == "idam_X_train0.5"
    assert "train_objects" not in str(DataChoice("/m").overrides(RunBudget(steps=2, points=128, batch=2)))
    assert DataChoice("/m", train_objects=100).describe() == "ModelNet40 /m, unseen objects, training objects: 100"
    calls: list[tuple[str, int]] = []
    run_sweep(Sweep(LC.select(["idam/X"]), "smoke", (0,), DataChoice(None), tmp_path), _fake_train(calls))
    assert calls == [("idam", 0)]  # the run on all the training objects is another run


def test_set_gives_every_run_of_a_sweep_a_config_value_and_keys_its_runs_apart(tmp_path: Path) -> None:
    """``--set KEY=VALUE``: the workers of ``--jobs`` get it too; the row's budget key, folder and report name it."""
    milestones = "model.init_args.lr_scheduler.init_args.milestones"
    args = ["reproduce", "lc", "--budget", "smoke", "--seeds", "0", "--only", "idam/X", "--out", str(tmp_path)]
    main([*args, "--set", f"{milestones}=[60]", "--jobs", "2"])
    (row,) = read_jsonl(tmp_path / "lc.jsonl")
    assert row["budget"].endswith(f"; set {milestones}=[60]") and row["overrides"] == {milestones: [60]}
    config = yaml.safe_load((Path(row["metrics_csv"]).parent / "config.yaml").read_text())
    assert config["model"]["init_args"]["lr_scheduler"]["init_args"]["milestones"] == [60]
    assert Path(row["metrics_csv"]).parent.parent.parent.name.startswith("idam_X_set")
    report = (tmp_path / "lc.md").read_text()  # the budget's own line, then the set values on theirs
    assert "- Budget `smoke` per run: 2 steps × 2 pairs × 128 points, validated every 2 steps.\n" in report
    set_line = "- Set on every run (`--set`; each replaces the budget's value of its key, if it has one): "
    assert f"{set_line}`{milestones}=[60]`.\n" in report
    calls: list[tuple[str, int]] = []
    run_sweep(Sweep(LC.select(["idam/X"]), "smoke", (0,), DataChoice(None), tmp_path), _fake_train(calls))
    assert calls == [("idam", 0)]  # without the setting: another run


def test_a_run_never_trains_in_the_folder_of_another_keys_run(tmp_path: Path) -> None:
    """Session 53: a budget whose lr changed trained in the old runs' folders, so the old rows pointed at new files.

    PRNet's first ``converge`` rows (no lr) in ``lc_dcp_prnet_converge/lc.jsonl`` record the ``selected_weights.pt``
    and ``metrics.csv`` of the lr-2.2e-4 runs that later trained in the same ``prnet_X/seed<k>`` folders.
    """
    from dataclasses import replace

    plain = RunBudget(steps=1, points=64, batch=2, checks=1)
    first, changed = (
        replace(LC.select(["idam/X"]), budgets={"smoke": {"idam": b}}) for b in (plain, replace(plain, lr=3e-4))
    )
    folders: list[Path] = []

    def train(name: str, budget: RunBudget, data: DataChoice, run_dir: Path, seed: int, overrides: Any) -> Any:
        folders.append(run_dir)
        run_dir.mkdir(parents=True, exist_ok=True)
        (run_dir / "selected_weights.pt").write_text(budget.describe())
        return {"rmse_r_deg": 1.0, "train_s": 0.0, "weights": str(run_dir / "selected_weights.pt")}

    sweeps = [Sweep(e, "smoke", (0,), DataChoice(None), tmp_path) for e in (first, changed)]
    for sweep in sweeps:
        run_sweep(sweep, train)
    assert folders[0].parent.name == "idam_X" and folders[1].parent.name.startswith("idam_X_key")
    rows = read_jsonl(tmp_path / "lc.jsonl")
    assert [Path(r["weights"]).read_text() for r in rows] == [plain.describe(), plain.describe() + ", lr 0.0003"]
    run_sweep(sweeps[1], train, rerun=True)  # the same key: its own folder again
    assert folders[2] == folders[1]
    from lcreg.experiments.reproduce.sweep import RUN_KEY_FILE  # after the checks that fail without it

    variant = LC.variant("idam/X")
    for folder in folders[:2]:  # folders of runs from before the key file: the newest row recorded there owns one
        (folder / RUN_KEY_FILE).unlink()
    assert [s.run_dir(variant, 0) for s in sweeps] == folders[:2]
    elsewhere = tmp_path / "other"  # a row written on another machine: its path differs but for the run folder
    elsewhere_row = {**rows[0], "weights": "/gpu/box/runs/smoke/lc/idam_X/seed0/selected_weights.pt"}
    (elsewhere / "lc.jsonl").parent.mkdir()
    (elsewhere / "lc.jsonl").write_text(json.dumps(elsewhere_row) + "\n")
    moved = replace(sweeps[1], out=elsewhere)
    assert moved.run_dir(variant, 0).parent.name == folders[1].parent.name
    assert replace(sweeps[0], out=elsewhere).run_dir(variant, 0) == elsewhere / "runs/smoke/lc/idam_X/seed0"
    (folders[0] / RUN_KEY_FILE).write_text("{")
    with pytest.raises(ValueError, match=f"{RUN_KEY_FILE}: not a run key"):
        sweeps[1].run_dir(variant, 0)


@pytest.mark.parametrize("bad", ["milestones=[60]", "model.init_args.x", "model.init_args.x=[1", ".a.b=1"])
def test_a_malformed_set_is_a_usage_error_naming_the_option(bad: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as stop:
        main(["reproduce", "lc", "--budget", "smoke", "--set", bad])
    assert stop.value.code == 2 and "--set" in capsys.readouterr().err


def test_points_resizes_every_run_and_keeps_its_runs_and_folders_apart(tmp_path: Path) -> None:
    """``--points 96 --partial prnet``: the workers of ``--jobs`` train at 96 points, cropped to 72 (0.75 of 96)."""
    args = ["reproduce", "lc", "--budget", "smoke", "--seeds", "0", "--only", "idam/X", "--out", str(tmp_path)]
    main([*args, "--points", "96", "--partial", "prnet", "--jobs", "2"])
    (row,) = read_jsonl(tmp_path / "lc.jsonl")
    assert (row["num_points"], row["points_per_cloud"]) == (96, 72)
    assert "2 steps × 2 pairs × 96 points" in row["budget"]
    run_dir = Path(row["metrics_csv"]).parent
    while run_dir.name != "seed0":
        run_dir = run_dir.parent
    assert run_dir.parent.name == "idam_X_96pts"
    assert "num_points: 96" in (Path(row["metrics_csv"]).parent / "config.yaml").read_text()
    assert "× 96 points" in (tmp_path / "lc.md").read_text()  # the report's budget line names the size
    # The budget's own size is another run, in another folder; a rerun at 96 points skips its finished run.
    calls: list[tuple[str, int]] = []
    crop = DataChoice(None, partial="prnet")
    run_sweep(Sweep(LC.select(["idam/X"]), "smoke", (0,), crop, tmp_path), _fake_train(calls))
    run_sweep(Sweep(LC.select(["idam/X"]), "smoke", (0,), crop, tmp_path, points=96), _fake_train(calls))
    assert calls == [("idam", 0)]
    own = Sweep(LC.select(["idam/X"]), "smoke", (0,), crop, tmp_path)
    assert own.run_dir(LC.variant("idam/X"), 0).parent.name == "idam_X"
    for bad in (0, 2):
        with pytest.raises(ValueError, match=f"integer of at least 3, got {bad}"):
            LC.with_points(bad)


def test_points_is_refused_where_it_means_nothing(tmp_path: Path, capsys) -> None:
    out = ["--out", str(tmp_path / "out")]
    assert "--points applies to ablation, lc (training sweeps); runtime sets its own data" in _error(
        ["runtime", "--budget", "smoke", "--points", "64", *out], capsys
    )
    assert "--points: points per cloud must be an integer of at least 3, got 2" in _error(
        ["lc", "--budget", "smoke", "--points", "2", *out], capsys
    )
    assert not list(tmp_path.iterdir())


def test_a_budget_lr_trains_at_that_lr_and_keys_its_runs_apart(tmp_path: Path) -> None:
    """``RunBudget.lr`` (PRNet's ``converge``: upstream's lr scaled to batch 8); budgets without it keep their keys."""
    from dataclasses import replace

    from lcreg.experiments.reproduce.budgets import LR_KEY

    with pytest.raises(ValueError, match="lr"):
        RunBudget(steps=2, lr=0.0)
    with pytest.raises(ValueError, match="lr"):
        RunBudget(steps=2, lr=float("nan"))
    budget = RunBudget(steps=1, points=64, batch=2, checks=1, lr=3e-4)
    assert budget.fit_overrides(tmp_path, seed=0)[LR_KEY] == 3e-4
    assert LR_KEY not in RunBudget(steps=1).fit_overrides(tmp_path, seed=0)
    experiment = replace(LC.select(["idam/X"]), budgets={"smoke": {"idam": budget}})
    run_sweep(Sweep(experiment, "smoke", (0,), DataChoice(None), tmp_path))
    (row,) = read_jsonl(tmp_path / "lc.jsonl")
    assert row["budget"].endswith(", lr 0.0003")
    config = yaml.safe_load((Path(row["metrics_csv"]).parent / "config.yaml").read_text())
    assert config["model"]["init_args"]["optimizer"]["init_args"]["lr"] == 3e-4  # idam.yaml says 1e-4
    # Session 52: DCP-v2's converge runs moved to lr 2.5e-4 by dcp_bf16_lr_256's rule (the rows at 1e-3 keep their
    # key, which has no lr); PRNet's at 2.2e-4 since session 17.
    converge = LC.budgets["converge"]
    small_batch = (
        "3000 steps × 8 pairs × 256 points, validated every 50 steps, until 12 validations bring no gain in "
        "`val/rre_median_deg` (4 pairs per validation object)"
    )
    assert converge["dcp"].describe() == small_batch + ", lr 0.00025"
    assert converge["prnet"].describe() == small_batch + ", lr 0.00022"


def test_a_set_lr_replaces_the_budget_lr_in_the_key_so_runs_keep_their_key_when_the_budget_adopts_it(
    tmp_path: Path,
) -> None:
    """Session 52: runs trained at a ``--set`` lr stay finished when the budget later trains at that lr by default."""
    from dataclasses import replace

    from lcreg.experiments.reproduce.budgets import LR_KEY

    plain = RunBudget(steps=1, points=64, batch=2, checks=1)
    settings = ((LR_KEY, 3e-4), ("trainer.precision", "bf16-mixed"))
    variant = LC.variant("idam/X")
    own, adopted = (
        replace(LC.select(["idam/X"]), budgets={"smoke": {"idam": b}}) for b in (plain, replace(plain, lr=3e-4))
    )
    before = Sweep(own, "smoke", (0,), DataChoice(None), tmp_path, settings=settings)
    after = Sweep(adopted, "smoke", (0,), DataChoice(None), tmp_path, settings=settings)
    assert after.key(variant, 0) == before.key(variant, 0) and after.run_dir(variant, 0) == before.run_dir(variant, 0)
    assert "lr 0.0003" not in after.key(variant, 0)["budget"].partition(";")[0]  # named once, in the settings
    without_set = Sweep(adopted, "smoke", (0,), DataChoice(None), tmp_path, settings=settings[1:])
    assert without_set.key(variant, 0)["budget"].startswith(plain.describe() + ", lr 0.0003; set")
    calls: list[tuple[str, int]] = []
    run_sweep(before, _fake_train(calls))
    run_sweep(after, _fake_train(calls))
    assert calls == [("idam", 0)]  # the adopted budget found the run finished


def test_jobs_trains_runs_in_worker_processes_with_the_rows_of_a_serial_sweep(tmp_path: Path) -> None:
    import subprocess

    args = ["reproduce", "lc", "--budget", "smoke", "--seeds", "0", "1", "--only", "idam/X"]
    # the serial sweep in a fresh process too: this test process runs torch on 1 thread, which changes the numbers
    subprocess.run([sys.executable, "-m", "lcreg", *args, "--out", str(tmp_path / "serial")], check=True)
    main([*args, "--out", str(tmp_path / "jobs"), "--jobs", "2"])
    serial, jobs = (read_jsonl(tmp_path / name / "lc.jsonl") for name in ("serial", "jobs"))
    assert sorted(r["seed"] for r in jobs) == [0, 1]
    for row in jobs:  # each run in its own process, the same numbers as in one process
        twin = next(r for r in serial if r["seed"] == row["seed"])
        assert {k: row[k] for k in METRICS} == pytest.approx({k: twin[k] for k in METRICS}, rel=1e-5, abs=1e-6)
        assert (Path(row["metrics_csv"]).parents[1] / "worker.log").is_file()
    assert "Runs finished: 2 of 2" in (tmp_path / "jobs" / "lc.md").read_text()
    main([*args, "--out", str(tmp_path / "jobs"), "--jobs", "2"])  # nothing left to run: no new rows
    assert len(read_jsonl(tmp_path / "jobs" / "lc.jsonl")) == 2


def test_a_failed_worker_ends_the_command_with_an_error_after_the_report(tmp_path: Path, capsys) -> None:
    from lcreg.experiments.reproduce.parallel import WorkerRun, WorkersFailedError, run_workers

    ok = WorkerRun("a seed 0", (sys.executable, "-c", "pass"), tmp_path / "a" / "worker.log")
    bad = WorkerRun("b seed 0", (sys.executable, "-c", "import sys; print('boom'); sys.exit(3)"), tmp_path / "b.log")
    with pytest.raises(WorkersFailedError, match=r"1 run\(s\) did not finish: b seed 0 \(exit 3\)") as err:
        run_workers([ok, bad], jobs=2, progress=print)
    assert err.value.exit_code == 1 and (tmp_path / "b.log").read_text().strip() == "boom"
    assert "a seed 0: finished" in capsys.readouterr().out
    with pytest.raises(ValueError, match="--jobs"):
        run_workers([ok], jobs=0)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_workers_end_when_the_command_that_started_them_is_killed(tmp_path: Path) -> None:
    import signal
    import subprocess
    import time

    pids = tmp_path / "pids"
    worker = f"import os, time; open({str(pids)!r}, 'a').write(f'{{os.getpid()}}\\n'); time.sleep(120)"
    parent = (
        "from pathlib import Path; import sys\n"
        "from lcreg.experiments.reproduce.parallel import WorkerRun, run_workers\n"
        f"runs = [WorkerRun(str(i), (sys.executable, '-c', {worker!r}), Path({str(tmp_path)!r}) / f'{{i}}.log')"
        " for i in range(2)]\n"
        "run_workers(runs, jobs=2)\n"
    )
    process = subprocess.Popen([sys.executable, "-c", parent])
    deadline = time.monotonic() + 60
    while (not pids.is_file() or len(pids.read_text().split()) < 2) and time.monotonic() < deadline:
        time.sleep(0.1)
    children = [int(p) for p in pids.read_text().split()]
    process.send_signal(signal.SIGKILL)  # as the training queue's --max-minutes ends a chunk
    process.wait()
    deadline = time.monotonic() + 10
    while any(_alive(pid) for pid in children) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(_alive(pid) for pid in children)


def _alive(pid: int) -> bool:
    import os

    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0] != "Z"  # a zombie has ended


@pytest.mark.gpu
@pytest.mark.skipif(not __import__("torch").cuda.is_available(), reason="needs a CUDA device")
def test_a_gpu_row_names_the_gpu_and_its_peak_memory(tmp_path: Path) -> None:
    """Lightning moves the model back to the CPU after ``fit``: the row must name the device that trained it."""
    main(["reproduce", "lc", "--budget", "smoke", "--seeds", "0", "--only", "idam/X", "--out", str(tmp_path)])
    (row,) = read_jsonl(tmp_path / "lc.jsonl")
    assert "(cuda)" in row["machine"] and row["peak_mib"] > 0


def test_the_gpu_queue_sweeps_run_where_open3d_and_wandb_are_missing(tmp_path: Path) -> None:
    """The lent GPU machine's image has neither open3d nor wandb (docs/reproducing.md): the DVDs sweep its chunks run
    (``ablation``) trains and reports there, ``--jobs`` workers included (``lc``'s DCP-v2 and PRNet runs have trained
    on that image since session 9)."""
    import subprocess

    missing = tmp_path / "missing"
    for name in ("open3d", "wandb"):  # found first on the path, as if not installed: any import raises
        (missing / name).mkdir(parents=True)
        (missing / name / "__init__.py").write_text(f"raise ImportError('no {name} on the device image')\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(missing), os.environ.get("PYTHONPATH", "")])}
    probe = subprocess.run([sys.executable, "-c", "import open3d"], env=env, capture_output=True, text=True)
    assert "no open3d on the device image" in probe.stderr  # the block holds in a fresh interpreter
    only, out = ["paper/model_A", "recipe/model_D"], tmp_path / "ablation"
    args = ["reproduce", "ablation", "--budget", "smoke", "--seeds", "0", "--only", *only, "--jobs", "2"]
    done = subprocess.run(
        [sys.executable, "-m", "lcreg", *args, "--out", str(out)], env=env, capture_output=True, text=True
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert sorted(r["variant"] for r in read_jsonl(out / "ablation.jsonl")) == sorted(only)
