"""Report and plots of hand-made rows: paper columns and ratios, header facts, claims, PNGs that are not blank."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from lcreg.experiments.reproduce.ablation import ABLATION
from lcreg.experiments.reproduce.budgets import DataChoice, RunBudget
from lcreg.experiments.reproduce.lc import HOSTS, LC
from lcreg.experiments.reproduce.plots import bar_positions, plot_sweep
from lcreg.experiments.reproduce.report import metric_table, render
from lcreg.experiments.reproduce.spec import Cell, Experiment, Variant
from lcreg.experiments.reproduce.sweep import METRICS, Sweep

pytest.importorskip("matplotlib")


def row(value: float, **extra: Any) -> dict[str, Any]:
    """A finished run whose every metric is ``value`` (recalls 0.5)."""
    metrics = {key: 0.5 if key.startswith("recall") else value for key in METRICS}
    return {**metrics, "train_s": 10.0, "test_s": 1.0, "steps": 68, "num_test_pairs": 164, "num_val_pairs": 78, **extra}


def lc_rows() -> dict[str, list[dict[str, Any]]]:
    """X and LC + X both at twice the paper's RMSE(R) of X, ± 0.1 over three seeds."""
    return {
        v.key: [row(2 * LC.paper[HOSTS[v.budget_group]]["rmse_r_deg"] + d) for d in (-0.1, 0, 0.1)] for v in LC.variants
    }


def sweep(experiment: Experiment, tmp_path: Path, preset: str = "cpu") -> Sweep:
    return Sweep(experiment, preset, (0, 1, 2), DataChoice("/data/modelnet40_mini"), tmp_path)  # type: ignore[arg-type]


def test_lc_table_has_paper_ours_and_ratio_per_series(tmp_path: Path) -> None:
    table = metric_table(LC, lc_rows(), "rmse_r_deg").splitlines()
    assert table[0] == (
        "|  | row | paper: X | ours: X | ours / paper | paper: LC + X | ours: LC + X | ours / paper "
        "| ours: LC (matched) + X |"  # not in the paper: no paper column, no ratio
    )
    dcp = table[2].split(" | ")
    assert dcp[1:] == ["DCP-v2", "4.834", "9.67 ± 0.10", "2.00×", "3.950", "9.67 ± 0.10", "2.45×", "9.67 ± 0.10 |"]


def test_zero_paper_values_have_no_ratio_and_pipes_are_escaped() -> None:
    rows = {v.key: [row(0.01)] for v in ABLATION.variants}
    table = metric_table(ABLATION, rows, "mae_t")
    assert "| models | A | 0.002 | 0.0100 ± 0 | 5.00× |" in table
    assert "| D | 0.000 | 0.0100 ± 0 | – |" in table  # the paper prints 0.000
    assert "\\|X1\\| = 96" in table and table.count("ours / paper") == 2  # two objectives, one paper column


def test_report_states_budget_data_pairs_seeds_and_claims(tmp_path: Path) -> None:
    text = render(sweep(LC, tmp_path), lc_rows(), "lcreg reproduce lc --budget cpu")
    assert (
        "Budget `cpu` per run:" in text and "- dcp: 72 steps × 8 pairs × 256 points, validated every 24 steps." in text
    )
    assert "ModelNet40 /data/modelnet40_mini, unseen objects: **164 test pairs**, 78 validation pairs" in text
    assert "Seeds: 0, 1, 2" in text and "Runs finished: 36 of 36" in text
    claims = [line for line in text.splitlines() if line.startswith("| LC ")]
    assert len(claims) == 16 and all("within spread" in line for line in claims)  # LC - X = 0 ± 0.1
    assert "## Differences from the paper" in text and "`cpu`" in text
    assert "- Checkpoint chosen on `val/rre_mean_deg` (validation pairs" in text


def test_a_converge_report_names_the_metric_its_checkpoints_were_chosen_on(tmp_path: Path) -> None:
    rows = {v.key: [row(1.0)] for v in ABLATION.variants}
    text = render(sweep(ABLATION, tmp_path, "converge"), rows, "lcreg reproduce ablation --budget converge")
    assert "- Checkpoint chosen on `val/rre_clip5_deg` (validation pairs" in text and "`val/rre_mean_deg`" not in text


def test_the_header_names_the_machines_that_trained_the_rows_not_the_one_writing_it(tmp_path: Path) -> None:
    rows = lc_rows()
    rows["dcp/X"] = [{**r, "machine": "NVIDIA H100 80GB HBM3 (cuda), torch 2.11.0, 1 threads"} for r in rows["dcp/X"]]
    rows["dcp/LC"][0]["machine"] = "x86_64 (cpu), torch 2.13.0+cpu, 1 threads"
    text = render(sweep(LC, tmp_path, "converge"), rows, "lcreg reproduce lc --budget converge")
    machine = next(line for line in text.splitlines() if line.startswith("- Machine: "))
    assert machine == (
        "- Machine: NVIDIA H100 80GB HBM3 (cuda), torch 2.11.0, 1 threads: 3 runs; "
        "x86_64 (cpu), torch 2.13.0+cpu, 1 threads: 1 runs; not recorded (rows written before lcreg recorded it): "
        "32 runs."
    )


def test_claims_in_the_report_hold_or_fail_beyond_the_spread(tmp_path: Path) -> None:
    rows = lc_rows()
    rows["dcp/LC"] = [row(v) for v in (3.0, 3.1, 3.2)]  # far below X (9.67)
    rows["prnet/LC"] = [row(v) for v in (9.0, 9.1, 9.2)]  # far above X (3.01)
    text = render(sweep(LC, tmp_path), rows, "cmd")
    # the paper's gain at our level: (3.950 / 4.834 - 1) x 9.668 = -1.77, our -6.57 is larger beyond the spread
    dcp = "LC + X − X = -6.57 (spread 0.1): holds, the paper's -1.77: larger than the paper's"
    assert f"| LC + DCP-v2 beats DCP-v2 | RMSE(R) (°) | **holds** | as the paper's or larger | {dcp} |" in text
    assert "| LC + PRNet beats PRNet | MAE(R) (°) | **does not hold** | **smaller than the paper's** |" in text
    assert "| LC + IDAM beats IDAM | RMSE(R) (°) | within spread | **smaller than the paper's** |" in text  # no gain
    assert "(not a claim of the paper) | RMSE(R) (°) | within spread | no paper value |" in text  # LC-matched
    del rows["dcp/LC"]
    assert "| LC + DCP-v2 beats DCP-v2 | RMSE(R) (°) | not run | – | – |" in render(sweep(LC, tmp_path), rows, "cmd")


def test_budgets_validate_and_describe_themselves(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="exactly one of steps and epochs"):
        RunBudget(steps=2, epochs=3)
    with pytest.raises(ValueError, match="positive"):
        RunBudget(steps=0)
    epochs = RunBudget(epochs=200, points=1024)
    assert epochs.describe() == "200 epochs × the config's batch × 1024 points, validated after every epoch"
    values = epochs.fit_overrides(tmp_path, seed=3)
    assert values["trainer.max_epochs"] == 200 and values["trainer.check_val_every_n_epoch"] == 1
    assert values["seed_everything"] == 3 and values["trainer.max_steps"] == -1
    assert RunBudget(steps=68, checks=4).val_every == 17
    data = DataChoice("/m").overrides(RunBudget(steps=1, points=512))
    assert data["data.init_args.seed"] == 1234 and data["data.init_args.num_points"] == 512
    assert "data.init_args.batch_size" not in data  # None: the config's (the original method's) batch


def test_an_experiment_refuses_cells_of_unknown_variants_and_missing_budgets() -> None:
    variant = Variant("x", "dcp", "g")
    good = {"budgets": {"cpu": {"g": RunBudget(steps=1)}}, "series": {}, "claims": (), "paper": {"P": {}}}
    with pytest.raises(ValueError, match="unknown variants"):
        Experiment("e", "t", "p", variants=(variant,), cells=(Cell("b", "r", "s", "y", None),), **good)
    with pytest.raises(ValueError, match="no budget"):
        Experiment("e", "t", "p", variants=(Variant("x", "dcp", "h"),), cells=(), **good)
    with pytest.raises(ValueError, match="--only 'nope' matches no variant of lc"):
        LC.select(["nope"])
    assert [v.key for v in LC.select(["idam/*"]).variants] == ["idam/X", "idam/LC", "idam/LC-matched"] and len(
        LC.select(["idam/*"]).claims
    ) == 2
    assert [v.key for v in LC.select(["idam/X", "idam/LC"]).variants] == ["idam/X", "idam/LC"]
    # --only sets the run order: the paper's claims (X, LC) of both hosts before the matched variants
    order = LC.select(["idam/X", "idam/LC", "deepgmr/X", "deepgmr/LC", "*/LC-matched"]).variants
    assert [v.key for v in order] == [
        "idam/X",
        "idam/LC",
        "deepgmr/X",
        "deepgmr/LC",
        "dcp/LC-matched",
        "prnet/LC-matched",
        "idam/LC-matched",
        "deepgmr/LC-matched",
    ]


def _not_blank(path: Path) -> np.ndarray:
    from matplotlib.image import imread

    image = imread(path)[..., :3]
    assert image.shape[0] > 300 and image.shape[1] > 500 and image.std() > 0.05
    return image


def test_plots_draw_bars_in_series_colours_and_paper_lines(tmp_path: Path) -> None:
    paths = plot_sweep(sweep(LC, tmp_path), lc_rows())
    assert [p.name for p in paths] == ["lc_rotation.png", "lc_translation.png"]
    image = _not_blank(paths[0])
    for colour in ((31, 119, 180), (255, 127, 14)):  # C0 (X) and C1 (LC + X) bars
        assert (np.abs(image * 255 - colour).sum(axis=-1) < 60).sum() > 500
    assert (image.sum(axis=-1) < 0.1).sum() > 200  # black paper lines and text
    rows = {v.key: [row(2.0 + i / 10, num_test_pairs=2)] for i, v in enumerate(ABLATION.variants)}
    assert all(_not_blank(p) is not None for p in plot_sweep(sweep(ABLATION, tmp_path, "smoke"), rows))
    assert plot_sweep(sweep(LC, tmp_path), {v.key: [] for v in LC.variants}) == []  # nothing finished: no figure


def test_bar_positions_leave_a_gap_between_blocks() -> None:
    x = bar_positions(ABLATION)
    assert x[("models", "D")] == 3.0 and x[("local size |X1|", "|X1| = 32")] == pytest.approx(4.6)


def test_converge_budgets_stop_early_select_on_the_clipped_error_and_draw_more_validation_pairs(
    tmp_path: Path,
) -> None:
    from lcreg.experiments.benchmarking import CONVERGE_METRIC, SELECTION_METRIC

    with pytest.raises(ValueError, match="step cap"):
        RunBudget(epochs=3, patience=2)
    with pytest.raises(ValueError, match="positive"):
        RunBudget(steps=10, patience=0)
    budget = RunBudget(steps=3000, points=512, batch=16, checks=60, patience=6, val_pairs=4)
    assert budget.converge and budget.monitor == CONVERGE_METRIC and budget.val_every == 50
    assert budget.describe().endswith("until 6 validations bring no gain (4 pairs per validation object)")
    values = budget.fit_overrides(tmp_path, seed=1)
    stop = [c for c in values["trainer.callbacks"] if c["class_path"].endswith("EarlyStopping")]
    assert values["trainer.max_steps"] == 3000 and [c["init_args"]["patience"] for c in stop] == [6]
    assert [c["class_path"] for c in stop] == ["lcreg.callbacks.MinimumEarlyStopping"]  # counts across min_steps
    assert DataChoice("/m").overrides(budget)["data.init_args.val_pairs_per_object"] == 4
    plain = RunBudget(steps=68)
    assert not plain.converge and plain.monitor == SELECTION_METRIC
    assert "data.init_args.val_pairs_per_object" not in DataChoice("/m").overrides(plain)
    smoke = DataChoice(None).overrides(budget)
    assert (
        smoke["data"]["class_path"].endswith("SyntheticDataModule") and smoke["data"]["init_args"]["batch_size"] == 16
    )


def test_a_converge_budget_may_stop_and_select_on_another_validation_metric(tmp_path: Path) -> None:
    from lcreg.experiments.reproduce.budgets import CONVERGE_SMALL_BATCH

    with pytest.raises(ValueError, match="validation metric"):
        RunBudget(steps=10, metric="val/rre_median_deg")  # not a converge budget
    with pytest.raises(ValueError, match="validation metric"):
        RunBudget(steps=10, patience=2, metric="train/loss")
    budget = RunBudget(steps=3000, checks=60, patience=12, metric="val/rre_median_deg")
    assert budget.monitor == "val/rre_median_deg"
    assert budget.describe().endswith(
        "until 12 validations bring no gain in `val/rre_median_deg` (1 pairs per validation object)"
    )
    callbacks = budget.fit_overrides(tmp_path, seed=0)["trainer.callbacks"]
    assert {c["init_args"]["monitor"] for c in callbacks if "monitor" in c["init_args"]} == {"val/rre_median_deg"}
    assert CONVERGE_SMALL_BATCH.monitor == "val/rre_median_deg"  # DCP-v2 and PRNet: errors near 5°
    text = render(sweep(LC, tmp_path, "converge"), lc_rows(), "lcreg reproduce lc --budget converge")
    assert "- Checkpoint chosen on `val/rre_median_deg` / `val/rre_clip5_deg` (validation pairs" in text


def test_every_experiment_has_a_converge_budget() -> None:
    from lcreg.experiments.reproduce import EXPERIMENTS

    for name, experiment in EXPERIMENTS.items():
        assert "converge" in experiment.budgets, name
    assert {b.patience for b in LC.budgets["converge"].values()} == {12, 8}


def test_the_other_table_gives_the_mean_rte_over_the_rows_that_recorded_it(tmp_path: Path) -> None:
    """Rows written before the mean RTE was kept lack it: the cell says over how many runs its mean is."""
    rows = lc_rows()
    rows["dcp/X"][0] = {k: v for k, v in rows["dcp/X"][0].items() if k != "rte_mean"}
    for run, rte in zip(rows["dcp/LC"], (0.001, 0.002, 0.003), strict=True):
        run["rte_mean"] = rte
    rows["idam/X"] = [{k: v for k, v in r.items() if k != "rte_mean"} for r in rows["idam/X"]]
    text = render(sweep(LC, tmp_path, "converge"), rows, "lcreg reproduce lc --budget converge")
    header = next(line for line in text.splitlines() if line.startswith("|  | row | series |"))
    column = header.split(" | ").index("mean RTE")
    cells = {
        tuple(cells[1:3]): cells[column]
        for line in text.splitlines()
        if line.startswith("| hosts |") and len(cells := line.split(" | ")) > column
    }
    assert cells[("DCP-v2", "LC + X")] == "0.00200 ± 0.0010"
    assert cells[("DCP-v2", "X")].endswith(" (2 of 3)") and cells[("IDAM", "X")] == "–"
