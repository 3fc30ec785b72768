"""Learning curves (lcreg.experiments.benchmarking.curves): sparse metrics.csv parsing, seed aggregation, summary,
PNGs."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from lcreg.experiments.benchmarking import format_mean_std
from lcreg.experiments.benchmarking.curves import (
    DPI,
    PANEL_SIZE,
    SUMMARY_HEADER,
    Panel,
    Series,
    _band,
    _layout,
    aggregate,
    canonical_key,
    curve_figures,
    ema,
    figure_pixels,
    load_runs,
    lr_changes,
    plot_curves,
    read_metrics,
    run_batch_size,
    run_files,
    summary_rows,
    summary_table,
    write_synthetic_metrics,
)

# Lightning's layout: train rows (step-level keys), a validation row at the same step as a train row, an epoch-end
# row with the _epoch means, empty cells for keys a row did not log, a repeated train step, a NaN.
SPARSE_CSV = """\
epoch,step,train/loss_step,train/loss_epoch,train/lc,train/recon_epoch,train/j_cond,val/rre_mean_deg,val/loss
0,0,1.0,,0.5,,0.01,,
0,1,0.8,,0.4,,,,
0,1,,,,,,12.0,0.9
0,2,0.7,,nan,,0.02,,
0,2,,0.9,,1.5,,,
1,3,0.6,,0.3,,0.03,,
1,3,0.5,,,,,,
1,3,,,,,,8.0,0.7
1,3,,0.55,,1.2,,,
"""


def write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def series(steps: list[int], values: list[float]) -> Series:
    return Series(np.array(steps, dtype=np.int64), np.array(values, dtype=np.float64))


def assert_series(s: Series, steps: list[int], values: list[float]) -> None:
    assert s.steps.dtype == np.int64 and s.steps.tolist() == steps
    np.testing.assert_allclose(s.values, values)


# ------------------------------------------------------------------------------------------------ parsing


@pytest.mark.parametrize(
    ("column", "expected"),
    [
        ("train/loss_step", ("train/loss", 0)),
        ("train/global_step", ("train/global", 0)),
        ("train/loss_epoch", ("train/loss", 2)),
        ("train/j_cond", ("train/j_cond", 1)),
        ("val/rre_mean_deg", ("val/rre_mean_deg", 1)),
        ("_step", ("_step", 1)),
    ],
)
def test_canonical_key_strips_lightnings_suffixes(column: str, expected: tuple[str, int]) -> None:
    assert canonical_key(column) == expected


def test_read_metrics_parses_interleaved_sparse_rows(tmp_path: Path) -> None:
    metrics = read_metrics(write(tmp_path / "metrics.csv", SPARSE_CSV))
    assert sorted(metrics) == ["train/j_cond", "train/lc", "train/loss", "train/recon", "val/loss", "val/rre_mean_deg"]
    assert_series(metrics["train/loss"], [0, 1, 2, 3], [1.0, 0.8, 0.7, 0.5])  # _step wins; repeated step: last
    assert_series(metrics["train/lc"], [0, 1, 3], [0.5, 0.4, 0.3])  # NaN skipped
    assert_series(metrics["train/recon"], [2, 3], [1.5, 1.2])  # only the _epoch variant was logged
    assert_series(metrics["train/j_cond"], [0, 2, 3], [0.01, 0.02, 0.03])
    assert_series(metrics["val/rre_mean_deg"], [1, 3], [12.0, 8.0])
    assert_series(metrics["val/loss"], [1, 3], [0.9, 0.7])


def test_read_metrics_prefers_a_plain_key_over_the_epoch_variant(tmp_path: Path) -> None:
    path = write(tmp_path / "metrics.csv", "epoch,step,train/x_epoch,train/x\n0,0,,2.0\n0,0,9.0,\n0,1,,3.0\n")
    assert_series(read_metrics(path)["train/x"], [0, 1], [2.0, 3.0])


def test_read_metrics_needs_a_step_column(tmp_path: Path) -> None:
    with pytest.raises(KeyError):
        read_metrics(write(tmp_path / "metrics.csv", "epoch,loss\n0,1.0\n"))


def test_run_files_takes_a_file_a_folder_or_a_glob(tmp_path: Path) -> None:
    a = write(tmp_path / "runs" / "x" / "version_0" / "metrics.csv", SPARSE_CSV)
    b = write(tmp_path / "runs" / "x" / "version_1" / "metrics.csv", SPARSE_CSV)
    assert run_files(a) == [a]
    assert run_files(tmp_path / "runs") == [a, b]
    assert run_files(str(tmp_path / "runs" / "x" / "version_*" / "metrics.csv")) == [a, b]
    assert run_files(str(tmp_path / "runs" / "x" / "version_*")) == [a, b]
    write(tmp_path / "runs" / "x" / "version_1" / "retest-32-true" / "metrics.csv", SPARSE_CSV)  # a test, not a seed
    assert run_files(tmp_path / "runs") == [a, b] and run_files(str(tmp_path / "runs" / "x" / "version_*")) == [a, b]
    with pytest.raises(FileNotFoundError, match=r"no metrics\.csv"):
        run_files(tmp_path / "nothing*")


def test_load_runs_reads_each_labels_files_as_its_seeds(tmp_path: Path) -> None:
    a = write_synthetic_metrics(tmp_path / "a.csv", seed=0)
    b = write_synthetic_metrics(tmp_path / "b.csv", seed=1)
    runs = load_runs({"D": [a, b], "recipe": [a]})
    assert [len(seeds) for seeds in runs.values()] == [2, 1]
    assert_series(
        runs["recipe"][0]["val/loss"], runs["D"][0]["val/loss"].steps.tolist(), runs["D"][0]["val/loss"].values
    )


def test_load_runs_on_training_pairs_scales_each_run_by_its_batch_size(tmp_path: Path) -> None:
    b8 = write_synthetic_metrics(tmp_path / "b8" / "metrics.csv", batch_size=8)
    b16 = write_synthetic_metrics(tmp_path / "b16" / "metrics.csv", batch_size=16)
    by_step = load_runs({"8": [b8], "16": [b16]})
    by_pairs = load_runs({"8": [b8], "16": [b16]}, x="pairs")
    for label, batch in (("8", 8), ("16", 16)):
        for key, s in by_step[label][0].items():
            assert_series(by_pairs[label][0][key], (s.steps * batch).tolist(), s.values)
    assert by_pairs["16"][0]["val/loss"].steps.tolist() == [19 * 16, 39 * 16, 59 * 16]


def test_load_runs_on_training_pairs_needs_each_runs_batch_size(tmp_path: Path) -> None:
    lone = write(tmp_path / "lone" / "metrics.csv", SPARSE_CSV)
    with pytest.raises(FileNotFoundError, match=r"no hparams\.yaml beside .*lone"):
        load_runs({"D": [lone]}, x="pairs")
    assert load_runs({"D": [lone]})["D"][0]["val/loss"].steps.tolist() == [1, 3]  # steps need no hparams
    hparams = lone.parent / "hparams.yaml"
    for text in ("lr: 0.001\n", "batch_size: 0\n", "batch_size: eight\n", "batch_size: true\n", "- 8\n"):
        hparams.write_text(text)
        with pytest.raises(ValueError, match="no positive integer batch_size"):
            run_batch_size(lone)
    hparams.write_text("batch_size: 4\nencoder: !!python/object:torch.nn.Linear {}\n")  # a logged object
    assert run_batch_size(lone) == 4
    with pytest.raises(ValueError, match=r"x must be one of \['pairs', 'step'\]"):
        load_runs({"D": [lone]}, x="epoch")


def test_synthetic_metrics_look_like_lightnings(tmp_path: Path) -> None:
    header = write_synthetic_metrics(tmp_path / "m.csv", steps=64).read_text().splitlines()[0].split(",")
    assert header[:2] == ["epoch", "step"] and "train/loss_step" in header and "train/loss_epoch" in header
    metrics = read_metrics(tmp_path / "m.csv")
    assert metrics["val/rre_mean_deg"].steps.tolist() == [19, 39, 59]
    assert metrics["train/loss"].steps.tolist() == list(range(1, 64, 2))  # the _step values, not the epoch means
    assert {f"train/j_dir_{d}" for d in ("rx", "ry", "rz", "tx", "ty", "tz")} <= set(metrics)


# ------------------------------------------------------------------------------------------------ seeds


def test_aggregate_aligns_seeds_on_step() -> None:
    band = aggregate([series([0, 2, 4], [1.0, 2.0, 3.0]), series([0, 2], [3.0, 6.0]), series([2, 6], [4.0, 9.0])])
    assert band.steps.tolist() == [0, 2, 4, 6]
    assert band.count.tolist() == [2, 3, 1, 1]
    np.testing.assert_allclose(band.mean, [2.0, 4.0, 3.0, 9.0])
    np.testing.assert_allclose(band.low, [1.0, 2.0, 3.0, 9.0])
    np.testing.assert_allclose(band.high, [3.0, 6.0, 3.0, 9.0])
    np.testing.assert_allclose(band.std, [np.sqrt(2.0), 2.0, 0.0, 0.0])  # sample std; one seed: 0


def test_aggregate_of_one_series_is_that_series() -> None:
    band = aggregate([series([1, 3], [0.5, 0.25])])
    np.testing.assert_array_equal(band.mean, [0.5, 0.25])
    np.testing.assert_array_equal(band.low, band.high)
    with pytest.raises(ValueError, match="at least one"):
        aggregate([])


def test_ema_is_bias_corrected() -> None:
    s = series([0, 1, 2], [1.0, 3.0, 3.0])
    assert ema(s, 0.0) is s
    np.testing.assert_allclose(ema(s, 0.5).values, [1.0, 1.75 / 0.75, 2.375 / 0.875])


def test_lr_changes_are_the_first_logged_steps_at_each_new_rate() -> None:
    metrics = {"train/lr": series([0, 10, 20, 30, 40, 50], [1e-3, 1e-3, 1e-4, 1e-4, 1e-4, 5e-5])}
    changes = lr_changes(metrics)
    assert [s for s, _ in changes] == [20, 50]
    np.testing.assert_allclose([f for _, f in changes], [0.1, 0.5])
    assert lr_changes({"train/lr": series([0, 10], [1e-3, 1e-3])}) == []
    assert lr_changes({"train/loss": series([0, 10], [1.0, 0.5])}) == []  # no rate logged


def test_the_learning_rate_is_the_last_training_panel_not_a_loss(tmp_path: Path) -> None:
    metrics = read_metrics(write_synthetic_metrics(tmp_path / "m.csv"))
    assert [s for s, _ in lr_changes(metrics)] == [41]  # the first logged step after the synthetic drop at 40
    (fig, training), *_ = [(fig, panels) for fig, panels in _layout(sorted(metrics)) if fig.name == "training"]
    assert [p.title for p, _ in training][-1] == "learning rate" and "lr loss" not in [p.title for p, _ in training]
    assert fig.title == "training losses and learning rate"
    (fig, training), *_ = [(f, panels) for f, panels in _layout(["train/loss", "val/loss"]) if f.name == "training"]
    assert [p.title for p, _ in training] == ["total loss"] and fig.title == "training losses"  # no rate: no panel


def test_smoothing_leaves_the_learning_rate_and_validation_values_as_logged(tmp_path: Path) -> None:
    metrics = read_metrics(write_synthetic_metrics(tmp_path / "m.csv"))
    for key in ("train/lr", "val/rre_mean_deg"):
        band = _band([metrics], key, smooth=0.9)
        assert band is not None
        np.testing.assert_array_equal(band.mean, metrics[key].values)
    band = _band([metrics], "train/loss", smooth=0.9)
    assert band is not None and not np.allclose(band.mean, metrics["train/loss"].values)


def test_panels_match_patterns_in_order_and_name_keys() -> None:
    panel = Panel("norms", ("train/*_grad_norm", "train/x"))
    present = ["train/x", "train/lc_grad_norm", "train/global_grad_norm", "val/x"]
    assert panel.matches(present) == ["train/global_grad_norm", "train/lc_grad_norm", "train/x"]
    assert [panel.name(k) for k in panel.matches(present)] == ["global", "lc", "x"]
    assert Panel("rre", ("val/a", "val/b"), names=("mean", "median")).name("val/b") == "median"


# ------------------------------------------------------------------------------------------------ summary


def test_summary_rows_first_last_best_over_seeds() -> None:
    runs = {
        "D": [
            {
                "val/rre_mean_deg": series([19, 39, 59], [10.0, 4.0, 6.0]),
                "val/recall_r5_t0p05": series([19, 39], [0.2, 0.6]),
            },
            {
                "val/rre_mean_deg": series([19, 39, 59], [12.0, 8.0, 5.0]),
                "val/recall_r5_t0p05": series([19, 39], [0.4, 0.3]),
            },
        ],
        "recipe": [{"val/rre_mean_deg": series([19, 39], [9.0, 3.0])}],
    }
    rows = summary_rows(runs, ["val/rre_mean_deg", "val/recall_r5_t0p05", "val/rte_mean"])
    assert rows == [
        [
            "val/rre_mean_deg",
            "D",
            "2",
            f"{format_mean_std([10.0, 12.0], digits=4)} @ 19",
            f"{format_mean_std([6.0, 5.0], digits=4)} @ 59",
            format_mean_std([4.0, 5.0], digits=4),  # seed 0 at step 39, seed 1 at step 59
            "39/59",
        ],
        ["val/rre_mean_deg", "recipe", "1", "9 @ 19", "3 @ 39", "3", "39"],  # one seed: no ± 0
        [
            "val/recall_r5_t0p05",
            "D",
            "2",
            f"{format_mean_std([0.2, 0.4], '.1f', '.1f', scale=100.0)} % @ 19",
            f"{format_mean_std([0.6, 0.3], '.1f', '.1f', scale=100.0)} % @ 39",
            f"{format_mean_std([0.6, 0.4], '.1f', '.1f', scale=100.0)} %",  # recall: the highest is best
            "19/39",
        ],
    ]
    assert rows[0][3] == "11.00 ± 1.4 @ 19" and rows[2][5] == "50.0 ± 14.1 %"


def test_summary_table_is_markdown(tmp_path: Path) -> None:
    runs = load_runs({"D": [write_synthetic_metrics(tmp_path / "a.csv")]})
    lines = summary_table(runs).splitlines()
    assert lines[0] == "| " + " | ".join(SUMMARY_HEADER) + " |" and lines[1].startswith("|---")
    assert [line.split(" | ")[0] for line in lines[2:]] == [
        "| val/rre_mean_deg",
        "| val/rre_median_deg",
        "| val/rte_mean",
        "| val/recall_r5_t0p05",
        "| val/recall_r2_t0p01",
        "| val/loss",
        "| train/loss",
        "| train/j_sensitivity",
        "| train/j_cond",
    ]


# ------------------------------------------------------------------------------------------------ figures

needs_matplotlib = pytest.mark.skipif(
    importlib.util.find_spec("matplotlib") is None, reason="matplotlib is not installed (pip install -e '.[dev]')"
)


def read_png(path: Path) -> np.ndarray:
    from matplotlib.image import imread

    assert path.is_file() and path.stat().st_size > 0
    return imread(path)


def assert_drawn(image: np.ndarray, axes: int) -> None:
    """A PNG of ``axes`` panels: the size of figure_pixels, not blank."""
    width, height = figure_pixels(axes)
    assert image.shape == (height, width, 4)
    assert image[..., :3].std() > 0.05 and (image[..., :3] < 0.5).mean() > 0.005  # lines and text, not blank


def test_figure_pixels() -> None:
    assert (DPI, PANEL_SIZE) == (100, (4.0, 3.0))
    assert figure_pixels(1) == (400, 345)
    assert figure_pixels(3) == (1200, 345)
    assert figure_pixels(5) == (1200, 645)


@needs_matplotlib
def test_plot_curves_writes_one_png_per_figure_of_the_expected_size(tmp_path: Path) -> None:
    runs = {
        "model D": [read_metrics(write_synthetic_metrics(tmp_path / f"d{s}.csv", seed=s)) for s in range(3)],
        "recipe": [read_metrics(write_synthetic_metrics(tmp_path / f"r{s}.csv", seed=10 + s)) for s in range(2)],
    }
    written = plot_curves(runs, tmp_path / "out", smooth=0.5)
    assert [p.name for p in written] == ["validation.png", "jacobian.png", "training.png"]
    assert_drawn(read_png(written[0]), 3)  # RRE, RTE, recall (no RMSE/MAE logged)
    assert_drawn(read_png(written[1]), 5)  # J cond, J sensitivity, gradient norms, per direction for each label
    assert_drawn(read_png(written[2]), 6)  # loss, global, lc, recon, normal, learning rate


@needs_matplotlib
def test_absent_keys_leave_their_panels_and_figures_out(tmp_path: Path) -> None:
    runs = {"D": [{"val/rre_median_deg": series([0, 5], [3.0, 2.0]), "lr": series([0, 5], [1e-3, 1e-4])}]}
    written = plot_curves(runs, tmp_path, prefix="x_")
    assert [p.name for p in written] == ["x_validation.png", "x_other.png"]
    assert_drawn(read_png(written[0]), 1)
    assert_drawn(read_png(written[1]), 1)
    assert plot_curves({"D": [{}]}, tmp_path / "empty") == [] and not (tmp_path / "empty").exists()


@needs_matplotlib
def test_the_title_of_a_one_panel_figure_fits_its_width(tmp_path: Path) -> None:
    """Before: "Other logged values (line: mean over seeds, shade: min–max)" ran past both edges of a 4-inch PNG."""
    seeds = [{"lr": series([0, 5], [1e-3, 1e-4 * (1 + s)])} for s in range(2)]
    (path,) = plot_curves({"a run with a long label": seeds}, tmp_path)
    image = read_png(path)
    assert_drawn(image, 1)
    top = image[: image.shape[0] // 5, :, :3]  # title and legend rows
    assert (top[:, :3] > 0.9).all() and (top[:, -3:] > 0.9).all()  # no text cut at the left or right edge


LONG_LABELS = [f"DVDs recipe tw100 + BatchNorm + variant {i}, seed 0" for i in range(5)]


@needs_matplotlib
def test_the_run_legend_fits_a_narrow_figure(tmp_path: Path) -> None:
    """Before (session 24's ``other.png``): five long labels in four columns ran past both edges of a 2-panel PNG."""
    runs = {label: [{"lr": series([0, 5], [1e-3, 1e-4]), "val/x": series([0, 5], [1.0, 2.0])}] for label in LONG_LABELS}
    fig = next(f for n, f in curve_figures(runs) if n == "other")
    fig.canvas.draw()
    (legend,) = fig.legends
    box = legend.get_window_extent()
    assert 0 <= box.x0 and box.x1 <= fig.bbox.width
    assert 1 < legend._ncols < 4  # as many columns as fit, not one per row


@needs_matplotlib
def test_long_panel_titles_wrap_instead_of_overlapping(tmp_path: Path) -> None:
    """Before: per-direction panel titles ("… ‖J col‖/‖φ‖: <label>") of neighbouring panels overwrote each other."""
    runs = {
        label: [read_metrics(write_synthetic_metrics(tmp_path / f"{i}.csv", seed=i))]
        for i, label in enumerate(LONG_LABELS[:3])
    }
    fig = next(f for n, f in curve_figures(runs) if n == "jacobian")
    fig.canvas.draw()
    boxes = [ax.title.get_window_extent() for ax in fig.axes if ax.get_visible()]
    assert all(0 <= b.x0 and b.x1 <= fig.bbox.width for b in boxes)
    assert not any(a.overlaps(b) for i, a in enumerate(boxes) for b in boxes[i + 1 :])
    assert any("\n" in ax.get_title() for ax in fig.axes)


@needs_matplotlib
def test_negative_values_keep_a_linear_axis(tmp_path: Path) -> None:
    runs = {"D": [{"train/loss": series([0, 1, 2], [0.5, -0.2, -0.4])}]}
    (path,) = plot_curves(runs, tmp_path)
    assert_drawn(read_png(path), 1)


# ------------------------------------------------------------------------------------------------ end to end


@needs_matplotlib
@pytest.mark.usefixtures("isolated_cli")
def test_a_real_fit_run_is_plotted(tmp_path: Path) -> None:
    from lcreg.cli import main

    dvds = Path(__file__).resolve().parents[3] / "configs" / "dvds.yaml"
    main(
        [
            "fit",
            "--config",
            str(dvds),
            "--model.init_args.encoder_channels=[16,32]",
            "--model.init_args.decoder_grid_size=8",
            "--model.init_args.decoder_hidden=[32]",
            "--model.init_args.normal_hidden=[16]",
            "--model.init_args.diagnostics_every_n_steps=1",
            "--data.init_args.num_points=64",
            "--data.init_args.points_per_shape=128",
            "--data.init_args.num_train=4",
            "--data.init_args.num_val=2",
            "--data.init_args.batch_size=2",
            "--trainer.max_steps=4",
            "--trainer.max_epochs=-1",
            "--trainer.val_check_interval=2",
            "--trainer.check_val_every_n_epoch=null",
            "--trainer.log_every_n_steps=1",
            "--trainer.enable_progress_bar=false",
            "--trainer.enable_model_summary=false",
            "--model.init_args.lr_scheduler=torch.optim.lr_scheduler.StepLR",  # stepped per epoch of 2 steps
            "--model.init_args.lr_scheduler.init_args.step_size=1",
            "--model.init_args.lr_scheduler.init_args.gamma=0.5",
        ]
    )
    (csv,) = run_files(tmp_path / "runs")
    runs = load_runs({"model D": [csv]})
    metrics = runs["model D"][0]
    assert metrics["val/rre_mean_deg"].steps.tolist() == [0, 1, 3]  # configs/dvds.yaml validates its start first
    assert metrics["train/loss"].steps.tolist() == [0, 1, 2, 3]  # the _step values, not the epoch means
    assert {"train/lc", "train/recon", "train/normal", "train/global_grad_norm"} <= set(metrics)
    assert_series(metrics["train/lr"], [0, 1, 2, 3], [3e-5, 3e-5, 1.5e-5, 1.5e-5])  # the rate each step used
    assert [(s, round(f, 6)) for s, f in lr_changes(metrics)] == [(2, 0.5)]
    written = plot_curves(runs, tmp_path / "curves")
    assert {p.name for p in written} >= {"validation.png", "jacobian.png", "training.png"}
    for path in written:
        read_png(path)
    assert "| val/rre_mean_deg | model D | 1 |" in summary_table(runs)
    pairs = load_runs({"model D": [csv]}, x="pairs")["model D"][0]  # the hparams.yaml lcreg fit writes
    assert pairs["val/rre_mean_deg"].steps.tolist() == [0, 2, 6]  # batch_size 2
    assert "first @ pairs" in summary_table({"model D": [pairs]}, x="pairs").splitlines()[0]


@needs_matplotlib
def test_curves_on_training_pairs_say_so_on_their_x_axes(tmp_path: Path) -> None:
    runs = load_runs({"D": [write_synthetic_metrics(tmp_path / "d" / "metrics.csv")]}, x="pairs")
    for x, label in (("step", "step"), ("pairs", "training pairs")):
        for _, fig in curve_figures(runs, x=x):
            assert {ax.get_xlabel() for ax in fig.axes if ax.get_visible()} == {label}
    with pytest.raises(ValueError, match="x must be one of"):
        curve_figures(runs, x="epochs")


def test_summary_lists_the_jacobian_diagnostics_best_when_highest(tmp_path: Path) -> None:
    from lcreg.experiments.benchmarking.curves import summary_rows

    path = tmp_path / "metrics.csv"
    path.write_text("epoch,step,train/j_sensitivity,train/j_cond\n0,9,0.05,0.3\n0,19,0.01,0.1\n0,29,0.02,0.2\n")
    rows = {row[0]: row for row in summary_rows(load_runs({"collapse": [path]}))}
    assert rows["train/j_sensitivity"][3:6] == ["0.05 @ 9", "0.02 @ 29", "0.05"]
    assert rows["train/j_cond"][5:] == ["0.3", "9"]
