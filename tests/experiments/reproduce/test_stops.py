"""Where each run of a sweep stopped and its learning curves, also from a copy of the output folder made elsewhere."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from _reproduce_outputs import assert_png_drawn, read_jsonl  # type: ignore[import-not-found]
from lcreg.__main__ import main
from lcreg.experiments.reproduce import stops
from lcreg.experiments.reproduce.lc import LC
from lcreg.experiments.reproduce.stops import metrics_file, stops_table, with_metrics_files

pytestmark = pytest.mark.usefixtures("isolated_cli")


def test_metrics_file_is_the_recorded_path_or_its_longest_tail_under_the_output_folder(tmp_path: Path) -> None:
    recorded = tmp_path / "machine_a" / "out" / "runs" / "lc" / "dcp_X" / "seed0" / "metrics.csv"
    recorded.parent.mkdir(parents=True)
    recorded.write_text("step\n")
    assert metrics_file({"metrics_csv": str(recorded)}) == recorded
    copy = tmp_path / "docs" / "results" / "job" / "runs"
    (copy / "runs" / "lc" / "dcp_X" / "seed0").mkdir(parents=True)
    (copy / "runs" / "lc" / "dcp_X" / "seed0" / "metrics.csv").write_text("step\n")
    (copy / "seed0").mkdir()
    (copy / "seed0" / "metrics.csv").write_text("step\n")  # a shorter tail: not the run's file
    shutil.rmtree(tmp_path / "machine_a")
    row = {"metrics_csv": str(recorded)}
    assert metrics_file(row) is None
    assert metrics_file(row, copy) == copy / "runs" / "lc" / "dcp_X" / "seed0" / "metrics.csv"
    assert metrics_file(row, tmp_path / "elsewhere") is None and metrics_file({}, copy) is None
    rows = with_metrics_files({"dcp/X": [row, {"metrics_csv": None}]}, copy)
    assert rows["dcp/X"][0]["metrics_csv"] == str(copy / "runs" / "lc" / "dcp_X" / "seed0" / "metrics.csv")
    assert rows["dcp/X"][1] == {"metrics_csv": None} and row["metrics_csv"] == str(recorded)  # not modified


@pytest.mark.parametrize("field", ["metrics_csv", "weights"])
def test_a_tail_shorter_than_the_runs_own_folders_is_not_taken_for_its_file(tmp_path: Path, field: str) -> None:
    name = "metrics.csv" if field == "metrics_csv" else "selected_weights.pt"
    recorded = Path("/machine_a/out/runs/converge/lc/dcp_X/seed1/run/lcreg/version_0", name)
    copy = tmp_path / "copy"
    others = [copy / "lcreg" / "version_0" / name, copy / "seed1" / "run" / "lcreg" / "version_0" / name]
    for other in others:  # another run's file (a fit logged into the folder; a run of another variant's layout)
        other.parent.mkdir(parents=True)
        other.write_text("step\n")
    row = {field: str(recorded)}
    assert stops.recorded_file(row, field, copy) is None
    own = copy / "dcp_X" / "seed1" / "run" / "lcreg" / "version_0" / name  # the shortest tail that is the run's
    own.parent.mkdir(parents=True)
    own.write_text("step\n")
    assert stops.recorded_file(row, field, copy) == own
    assert stops.recorded_file({field: "/machine_a/out/lcreg/version_0/" + name}, field, copy) is None  # no seed


def test_stops_table_says_where_and_why_each_run_stopped_in_variant_and_seed_order() -> None:
    base = {"selected_on": "val/rre_clip5_deg", "train_s": 12.4}
    rows = {
        "idam/LC": [
            {
                **base,
                "seed": 0,
                "steps": 5016,
                "stopped_early": False,
                "selected": "s.ckpt",
                "best_val": 1.3,
                "peak_mib": 812.46,
            }
        ],
        "idam/X": [
            {**base, "seed": 2, "steps": 4664, "stopped_early": True, "selected": "b.ckpt", "best_val": 1.50341},
            {"seed": 1, "steps": 68, "train_s": 3.0},  # a row without selection fields
        ],
    }
    lines = stops_table(LC, rows, "converge").splitlines()[2:]
    assert lines == [
        "| idam/X | 1 | 68 | step cap | – | – | – | 3 | – |",
        "| idam/X | 2 | 4664 | early stop (no gain) | `b.ckpt` | 1.503 (`val/rre_clip5_deg`) | – | 12 | – |",
        "| idam/LC | 0 | 5016 | step cap | `s.ckpt` | 1.3 (`val/rre_clip5_deg`) | – | 12 | 812 |",
    ]
    assert "| idam/LC | 0 | 5016 | end of the budget |" in stops_table(LC, rows, "cpu")


def test_a_run_stopped_below_its_raised_step_cap_is_an_early_stop_also_in_rows_written_before_the_fix() -> None:
    """Rows before session 44 compared the steps with the budget's cap (5,016), not ``--set trainer.max_steps``."""
    raised = {"overrides": {"trainer.min_steps": 5984, "trainer.max_steps": 7040}, "stopped_early": False}
    assert stops.stopped_early({**raised, "steps": 6776}) is True  # idam_partial_drop5280_seeds_512, seed 1
    assert stops.stopped_early({**raised, "steps": 7040}) is False
    assert stops.stopped_early({"steps": 4664, "stopped_early": True}) is True  # no override: the row's own
    assert stops.stopped_early({"steps": 5016, "stopped_early": False}) is False
    assert stops.stopped_early({"steps": 68}) is None and stops.stopped_early({**raised, "steps": None}) is False
    rows = {"idam/X": [{**raised, "seed": 1, "steps": 6776}, {**raised, "seed": 0, "steps": 7040}]}
    lines = stops_table(LC, rows, "converge").splitlines()[2:]
    assert [line.split(" | ")[2:4] for line in lines] == [["7040", "step cap"], ["6776", "early stop (no gain)"]]


def test_stops_table_says_when_each_runs_learning_rate_changed(tmp_path: Path) -> None:
    """An epoch-stepped schedule drops at a step set by the training set's size: the table shows the step."""
    dropped, constant, older = (tmp_path / name / "metrics.csv" for name in ("dropped", "constant", "older"))
    for path, text in (
        (dropped, "epoch,step,train/lr\n0,9,1e-4\n1,19,1e-4\n2,29,1e-5\n3,39,1e-5\n4,49,2e-6\n"),
        (constant, "epoch,step,train/lr\n0,9,1e-4\n1,19,1e-4\n"),
        (older, "epoch,step,train/loss_step\n0,9,1.0\n"),  # written before the rate was logged
    ):
        path.parent.mkdir()
        path.write_text(text)
    rows = {
        "idam/X": [{"seed": s, "steps": 50, "metrics_csv": str(p)} for s, p in enumerate((dropped, constant, older))]
        + [{"seed": 3, "steps": 50, "metrics_csv": str(tmp_path / "gone" / "metrics.csv")}]
    }
    cells = [line.split(" | ")[6] for line in stops_table(LC, rows, "converge").splitlines()[2:]]
    assert cells == ["29: ×0.1, 49: ×0.2", "none", "–", "–"]


def test_a_report_of_a_copied_output_folder_has_the_stops_and_learning_curves(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Trained in one folder, reported from a copy after the original is gone (as the queue commits results)."""
    trained = tmp_path / "machine_a"
    args = ["reproduce", "lc", "--budget", "smoke", "--seeds", "0", "--only", "dcp/*"]
    main([*args, "--out", str(trained)])
    assert all(Path(r["metrics_csv"]).is_file() for r in read_jsonl(trained / "lc.jsonl"))
    copy = tmp_path / "docs" / "job" / "runs"
    shutil.copytree(trained, copy)
    shutil.rmtree(trained)
    for png in copy.glob("*.png"):
        png.unlink()
    drawn: list[set[str]] = []
    real = stops.plot_curves

    def spy(runs: dict[str, list[dict[str, object]]], *a: object, **k: object) -> list[Path]:
        drawn.append({key for seeds in runs.values() for metrics in seeds for key in metrics})
        return real(runs, *a, **k)  # type: ignore[arg-type]

    monkeypatch.setattr(stops, "plot_curves", spy)
    main([*args, "--out", str(copy), "--report-only"])
    assert drawn and "val/rre_mean_deg" in drawn[0] and not any(k.startswith("test/") for k in drawn[0])
    text = (copy / "lc.md").read_text()
    assert "## Where each run stopped" in text and "| dcp/LC | 0 | 2 | end of the budget |" in text
    assert "`lc_curves_dcp_validation.png`" in text
    assert_png_drawn(copy / "lc_curves_dcp_validation.png")
    assert (copy / "lc_curves_dcp_training.png").is_file()
