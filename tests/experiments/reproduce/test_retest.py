"""``lcreg reproduce ... --retest PRECISION``: kept weights tested again on the same pairs, nothing trained."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import yaml

from _reproduce_outputs import read_jsonl  # type: ignore[import-not-found]
from lcreg.__main__ import main
from lcreg.data.modelnet40 import load_shape_names
from lcreg.experiments.benchmarking import build_cli_for
from lcreg.experiments.reproduce.budgets import DataChoice, RunBudget
from lcreg.experiments.reproduce.lc import LC
from lcreg.experiments.reproduce.retest import Retest, is_retest_output
from lcreg.experiments.reproduce.sweep import METRICS, Sweep, run_sweep, run_values
from lcreg.weights.export import save

from _shared_data import shared_data  # type: ignore[import-not-found]

pytestmark = pytest.mark.usefixtures("isolated_cli")

SWEEP = ["reproduce", "lc", "--budget", "smoke", "--only", "idam/X"]
BF16 = "--set=trainer.precision=bf16-mixed"


def _sweep(out: Path, *extra: str, seeds: tuple[str, ...] = ("0",)) -> list[dict]:
    main([*SWEEP, "--seeds", *seeds, "--out", str(out), *extra])
    return read_jsonl(out / "lc.jsonl")


def _retest(out: Path, precision: str, *extra: str, seeds: tuple[str, ...] = ("0",), tag: str = "") -> list[dict]:
    main([*SWEEP, "--seeds", *seeds, "--out", str(out), *extra, "--retest", precision])
    return read_jsonl(out / f"lc.{tag or 'retest-' + precision}.jsonl")


def _assert_same_test(row: dict, retested: dict) -> None:
    for key in METRICS:
        assert retested[key] == pytest.approx(row[key], rel=1e-6, abs=1e-9), key


def _per_pair(row: dict, tag: str) -> list[str]:
    """The lines of the per-pair errors a retest tagged ``tag`` wrote for the run of ``row`` (header first)."""
    (per_pair,) = (Path(row["metrics_csv"]).parent.parent / tag).rglob("test_per_pair.csv")
    return per_pair.read_text().splitlines()


def test_a_retest_at_the_runs_own_precision_gives_its_test_again(tmp_path: Path, capsys) -> None:
    """The same weights, pairs and precision: every metric of the row again, from a run rebuilt without training;
    its per-pair errors and the precision it ran in are in the run's ``retest-<precision>/`` folder."""
    rows = _sweep(tmp_path, seeds=("0", "1"))
    capsys.readouterr()
    retested = _retest(tmp_path, "32-true", seeds=("0", "1"))
    assert [(r["variant"], r["seed"], r["precision"], r["trained_precision"]) for r in retested] == [
        ("idam/X", 0, "32-true", "32-true"),
        ("idam/X", 1, "32-true", "32-true"),
    ]
    for row, again in zip(rows, retested, strict=True):
        assert {k: again[k] for k in ("budget", "data")} == {k: row[k] for k in ("budget", "data")}
        _assert_same_test(row, again)
        logs = Path(row["metrics_csv"]).parent.parent / "retest-32-true"
        (per_pair,) = logs.rglob("test_per_pair.csv")
        assert len(per_pair.read_text().splitlines()) == 1 + row["num_test_pairs"]
        (config,) = logs.rglob("config.yaml")
        assert yaml.safe_load(config.read_text())["trainer"]["precision"] == "32-true"
    report = (tmp_path / "lc.retest-32-true.md").read_text()
    assert "| idam/X | 0 | 32-true |" in report and "| idam/X | 2 seeds | 32-true |" in report
    assert (tmp_path / "lc.jsonl").read_text().count("\n") == 2  # the sweep's own rows are untouched
    capsys.readouterr()
    assert _retest(tmp_path, "32-true", seeds=("0", "1")) == retested  # a rerun skips what was retested
    assert capsys.readouterr().out.count("retested before, skipped") == 2


def test_a_bf16_run_is_retested_in_float32_and_in_bf16_again(tmp_path: Path) -> None:
    """A run trained and tested under bf16-mixed: ``--retest bf16-mixed`` gives its own test again (so the rebuilt
    run is the same), ``--retest 32-true`` runs the same weights in float32 and says what the run trained in."""
    (row,) = _sweep(tmp_path, BF16)
    assert row["overrides"] == {"trainer.precision": "bf16-mixed"}
    (again,) = _retest(tmp_path, "bf16-mixed", BF16)
    _assert_same_test(row, again)
    (float32,) = _retest(tmp_path, "32-true", BF16)
    assert (float32["precision"], float32["trained_precision"]) == ("32-true", "bf16-mixed")
    logs = Path(row["metrics_csv"]).parent.parent / "retest-32-true"
    (config,) = logs.rglob("config.yaml")
    assert yaml.safe_load(config.read_text())["trainer"]["precision"] == "32-true"
    assert "| idam/X | 0 | bf16-mixed |" in (tmp_path / "lc.retest-32-true.md").read_text()


def test_a_copy_of_the_output_folder_finds_its_weights_and_missing_weights_are_one_clear_line(
    tmp_path: Path, capsys
) -> None:
    """The training queue commits a copy of ``--out`` elsewhere: the weights are found under it by the recorded path's
    tail. Without them the command ends with exit code 2 and one line naming the file, after the runs it could test."""
    (row,) = _sweep(tmp_path / "trained", seeds=("0",))
    copy = tmp_path / "copy"
    shutil.copytree(tmp_path / "trained", copy)
    shutil.rmtree(tmp_path / "trained")
    (retested,) = _retest(copy, "32-true")
    _assert_same_test(row, retested)
    assert Path(retested["weights"]).is_relative_to(copy)
    main([*SWEEP, "--seeds", "1", "--out", str(copy)])
    seed1 = read_jsonl(copy / "lc.jsonl")[-1]
    kept = Path(seed1["weights"]).read_bytes()  # as the queue keeps it in <job>/best/
    Path(seed1["weights"]).unlink()
    capsys.readouterr()
    with pytest.raises(SystemExit) as stop:
        _retest(copy, "32-true", seeds=("0", "1"))
    assert stop.value.code == 2
    error = capsys.readouterr().err.strip()
    assert error.startswith("lcreg reproduce: error: idam/X seed 1: its kept weights ") and "\n" not in error
    assert seed1["weights"] in error
    assert len(read_jsonl(copy / "lc.retest-32-true.jsonl")) == 1
    place = Path(error.split("; copy them to ")[1].split(" (")[0])  # the place the message names finds them
    place.write_bytes(kept)
    (_, again) = _retest(copy, "32-true", seeds=("0", "1"))
    _assert_same_test(seed1, again)


def test_retest_data_tests_the_same_weights_on_other_pairs(tmp_path: Path) -> None:
    """``--retest-data noise_sigma=<the run's own>`` gives the run's test again; another value other pairs, with its
    own files, folder and config, beside the plain retest's."""
    (row,) = _sweep(tmp_path)
    (config,) = (Path(row["metrics_csv"]).parent).rglob("config.yaml")
    own = yaml.safe_load(config.read_text())["data"]["init_args"]["noise_sigma"]
    (same,) = _retest(tmp_path, "32-true", f"--retest-data=noise_sigma={own}", tag=f"retest-32-true-noise_sigma-{own}")
    _assert_same_test(row, same)
    tag = "retest-32-true-noise_sigma-0.2"
    (noisier,) = _retest(tmp_path, "32-true", "--retest-data", "noise_sigma=0.2", tag=tag)
    assert noisier["test_data"] == {"noise_sigma": 0.2} and noisier["precision"] == "32-true"
    assert noisier["rmse_t"] != pytest.approx(row["rmse_t"], rel=1e-3)  # other pairs, other errors
    (config,) = (Path(row["metrics_csv"]).parent.parent / tag).rglob("config.yaml")
    assert yaml.safe_load(config.read_text())["data"]["init_args"]["noise_sigma"] == 0.2
    assert len(_per_pair(row, tag)) == 1 + row["num_test_pairs"]
    report = (tmp_path / f"lc.{tag}.md").read_text()
    assert "`32-true, noise_sigma=0.2`" in report and "other test pairs" in report
    assert not (tmp_path / "lc.retest-32-true.jsonl").exists()  # a plain retest keeps its own files
    _retest(
        tmp_path,
        "32-true",
        "--retest-data=noise_clip=0.1",
        "--retest-data=noise_sigma=0.2",
        tag=f"{tag}-noise_clip-0.1",
    )


def test_retest_precise_bn_recomputes_the_batchnorm_statistics_before_the_test(tmp_path: Path) -> None:
    """``--retest-precise-bn N``: a test of the same weights with other BatchNorm running statistics, in its own
    files; without it the retest gives the run's own test again (so the difference is the statistics')."""
    (row,) = _sweep(tmp_path)
    tag = "retest-32-true-precise_bn-2"
    (again,) = _retest(tmp_path, "32-true", "--retest-precise-bn", "2", tag=tag)
    assert again["precise_bn_batches"] == 2
    assert any(again[key] != pytest.approx(row[key], rel=1e-6) for key in METRICS)
    assert "running statistics recomputed over 2 training batches" in (tmp_path / f"lc.{tag}.md").read_text()
    assert len(_per_pair(row, tag)) == 1 + row["num_test_pairs"]


def test_a_model_trained_on_labels_0_to_19_is_retested_on_unseen_categories(tmp_path: Path) -> None:
    """On real ModelNet40: the kept weights of an unseen-objects run tested on labels 20-39 (both splits), nothing
    trained; the run's own test pairs were labels 0-19 of the test split."""
    root = shared_data("modelnet40_mini")
    names = load_shape_names(root)
    assert names is not None
    sweep = Sweep(LC.select(["idam/X"]), "cpu", (0,), DataChoice(str(root)), tmp_path)

    def keep_untrained(
        name: str, budget: RunBudget, data: DataChoice, run_dir: Path, seed: int, overrides: dict
    ) -> dict:  # a finished run without training: its weights as the sweep keeps them
        cli = build_cli_for(name, (), run_values(budget, data, run_dir, seed, overrides))
        weights = save(cli.model, run_dir / "selected_weights.pt")
        return {"weights": str(weights), "train_s": 0.0, **dict.fromkeys(METRICS, 1.0)}

    run_sweep(sweep, keep_untrained)
    options = ["--budget", "cpu", "--root", str(root), "--seeds", "0", "--out", str(tmp_path)]
    main(
        [
            "reproduce",
            "lc",
            "--only",
            "idam/X",
            *options,
            "--retest",
            "32-true",
            "--retest-data=protocol=unseen_categories",
        ]
    )
    (row,) = read_jsonl(tmp_path / "lc.retest-32-true-protocol-unseen_categories.jsonl")
    assert row["test_data"] == {"protocol": "unseen_categories"}
    (per_pair,) = (sweep.run_dir(sweep.experiment.variants[0], 0) / "retest-32-true-protocol-unseen_categories").rglob(
        "test_per_pair.csv"
    )
    classes = [line.split(",")[3] for line in per_pair.read_text().splitlines()[1:]]
    assert len(classes) == 80  # labels 20-39 of both splits of modelnet40_mini (its README)
    assert set(classes) <= set(names[20:]) and len(set(classes)) == 20


def test_retest_tags_name_the_changed_data() -> None:
    retest = Retest("32-true", (("protocol", "unseen_categories"), ("noise_sigma", 0)))
    assert retest.tag == "retest-32-true-protocol-unseen_categories-noise_sigma-0"
    assert retest.label == "32-true, protocol=unseen_categories, noise_sigma=0"
    assert Retest("bf16-mixed").tag == "retest-bf16-mixed"
    assert is_retest_output(Path("out/runs/converge/lc/idam_X/seed0") / retest.tag / "run/metrics.csv")


def test_a_retest_that_matches_no_finished_run_is_an_error_not_an_empty_table(tmp_path: Path, capsys) -> None:
    """Options that differ from the training command's find no run: exit code 2 and what to repeat, no report."""
    with pytest.raises(SystemExit) as stop:
        _retest(tmp_path, "32-true")
    assert stop.value.code == 2 and "does not exist" in capsys.readouterr().err
    _sweep(tmp_path)
    with pytest.raises(SystemExit) as stop:
        _retest(tmp_path, "32-true", "--set=model.init_args.optimizer.init_args.lr=0.5")
    error = capsys.readouterr().err
    assert stop.value.code == 2 and "none of the 1 rows" in error and "repeat the training command's options" in error
    assert not list(tmp_path.glob("lc.retest-*"))


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["runtime", "--budget", "smoke", "--retest", "32-true"], "--retest applies to"),
        (["lc", "--budget", "smoke", "--only", "idam/X", "--jobs", "2", "--retest", "32-true"], "leave out --jobs"),
        (["lc", "--budget", "smoke", "--retest-data", "noise_sigma=0"], "give --retest too"),
        (["lc", "--budget", "smoke", "--retest-precise-bn", "5"], "give --retest too"),
        (["lc", "--budget", "smoke", "--retest", "32-true", "--retest-precise-bn", "-1"], "number of batches >= 1"),
        (["lc", "--budget", "smoke", "--retest", "32-true", "--retest-data", "colour=1"], "'colour' is not one of"),
        (["lc", "--budget", "smoke", "--retest", "32-true", "--retest-data", "protocol=all"], "protocol must be one"),
        (["lc", "--budget", "smoke", "--retest", "32-true", "--retest-data", "noise_sigma=-1"], "finite number >= 0"),
        (["lc", "--budget", "smoke", "--retest", "32-true", "--retest-data", "noise_sigma"], "expected KEY=VALUE"),
        (
            ["lc", "--budget", "smoke", "--retest", "32-true", "--retest-data", "protocol=unseen_categories"],
            "embedded synthetic shapes have no ModelNet40 protocol",
        ),
    ],
)
def test_retest_is_refused_where_it_means_nothing(argv: list[str], message: str, tmp_path: Path, capsys) -> None:
    with pytest.raises(SystemExit) as stop:
        main(["reproduce", *argv, "--out", str(tmp_path)])
    assert stop.value.code == 2 and message in capsys.readouterr().err


def test_report_only_writes_the_retest_table_from_its_jsonl(tmp_path: Path) -> None:
    _sweep(tmp_path)
    _retest(tmp_path, "32-true")
    (tmp_path / "lc.retest-32-true.md").unlink()
    main([*SWEEP, "--seeds", "0", "--out", str(tmp_path), "--retest", "32-true", "--report-only"])
    assert "| idam/X | 0 | 32-true |" in (tmp_path / "lc.retest-32-true.md").read_text()


@pytest.mark.parametrize(
    ("path", "retest"),
    [
        ("out/lc.retest-32-true.jsonl", True),
        ("out/lc.retest-bf16-mixed.md", True),
        ("out/runs/converge/lc/idam_X/seed0/retest-32-true/version_0/metrics.csv", True),
        ("out/lc.jsonl", False),
        ("out/runs/converge/lc/idam_X/seed0/run/metrics.csv", False),
        ("out/runs/converge/lc/retest_X/seed0/run/metrics.csv", False),
    ],
)
def test_retest_outputs_are_told_from_a_runs_files(path: str, retest: bool) -> None:
    assert is_retest_output(Path(path)) is retest
