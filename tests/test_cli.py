from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from lcreg.cli import ConfigFileError, ConfigValueError, build_cli, expand_configs, instantiate, main
from lcreg.data.synthetic import PRIMITIVES
from lcreg.experiments.reproduce.budgets import PRESETS
from lcreg.models.evaluation import COMPONENT_COLUMNS

from _cli_runs import TINY_DVDS  # type: ignore[import-not-found]

REPO_ROOT = Path(__file__).resolve().parents[1]
CONFIGS = REPO_ROOT / "configs"
DVDS = CONFIGS / "dvds.yaml"
ALL_CONFIGS = sorted(CONFIGS.rglob("*.yaml"))

TINY = TINY_DVDS


pytestmark = pytest.mark.usefixtures("isolated_cli")


def _outputs(tmp_path: Path) -> list[str]:
    return [
        f"--trainer.default_root_dir={tmp_path / 'root'}",
        f"--trainer.logger.init_args.save_dir={tmp_path / 'runs'}",
    ]


def test_fit_then_test_from_the_saved_config(tmp_path: Path) -> None:
    main(["fit", "--config", str(DVDS), *TINY, *_outputs(tmp_path)])
    run_dir = tmp_path / "runs" / "lcreg" / "version_0"
    last = run_dir / "checkpoints" / "last.ckpt"
    saved = run_dir / "config.yaml"
    assert last.is_file() and saved.is_file()
    assert len(list((run_dir / "checkpoints").glob("epoch000-rre*.ckpt"))) == 1
    checkpoint = torch.load(last, map_location="cpu", weights_only=False)
    # selected on the validation registration error (configs/dvds.yaml), a single checkpoint callback
    assert [k for k in checkpoint["callbacks"] if "ModelCheckpoint" in k] == [
        k for k in checkpoint["callbacks"] if "'monitor': 'val/rre_mean_deg'" in k
    ]
    assert checkpoint["hyper_parameters"]["encoder_channels"] == [16, 32]
    config = yaml.safe_load(saved.read_text())
    assert config["model"]["class_path"] == "lcreg.models.dvds.DVDs"
    assert config["model"]["init_args"]["encoder_channels"] == [16, 32]
    terms = [t["class_path"] for t in config["model"]["init_args"]["loss_terms"]]  # the main job: the recipe
    assert terms == ["lcreg.models.loss_terms.LocalConsistencyLoss", "lcreg.models.loss_terms.SelfMotionLoss"]
    assert config["compose"] is None  # already expanded: the saved config is complete
    metrics = list(csv.DictReader((run_dir / "metrics.csv").open()))
    assert any(row.get("val/loss") for row in metrics)
    assert any(row.get("train/lc_epoch") for row in metrics) and any(row.get("val/lc") for row in metrics)

    main(["test", "--config", str(saved), "--ckpt_path", str(last)])
    per_pair = list(csv.reader((tmp_path / "runs" / "lcreg" / "version_1" / "test_per_pair.csv").open()))
    assert per_pair[0] == ["index", "rotation_error_deg", "translation_error", "class", *COMPONENT_COLUMNS]
    assert [int(row[0]) for row in per_pair[1:]] == [0, 1]
    assert {row[3] for row in per_pair[1:]} <= set(PRIMITIVES)  # the synthetic shapes' kinds

    main(["predict", "--config", str(saved), "--ckpt_path", str(last)])
    predictions = np.load(tmp_path / "runs" / "lcreg" / "version_2" / "predictions.npz")
    assert predictions["transform_ref_src"].shape == (2, 4, 4) and predictions["transform_gt"].shape == (2, 4, 4)
    assert predictions["index"].tolist() == [0, 1] and predictions["converged"].dtype == bool
    assert np.isfinite(predictions["transform_ref_src"]).all()


def test_fit_with_the_wandb_logging_fragment(tmp_path: Path) -> None:
    wandb_config = CONFIGS / "logging" / "wandb.yaml"
    main(["fit", "--config", str(DVDS), "--config", str(wandb_config), *TINY, *_outputs(tmp_path)])
    assert list((tmp_path / "runs").rglob("last.ckpt"))
    assert not (tmp_path / "runs" / "lcreg" / "version_0").exists()  # not the CSV logger


def _logged_test_metrics(run_dir: Path) -> dict[str, float]:
    rows = list(csv.DictReader((run_dir / "metrics.csv").open()))
    return {k: float(v) for row in rows for k, v in row.items() if k.startswith("test/") and v}


def test_lcreg_test_logs_the_recalls_asked_for_on_the_command_line_or_in_yaml(tmp_path: Path) -> None:
    """Before: `lcreg test` logged only recall_r2_t0p01 and recall_r5_t0p05 (object units); no other recall could be
    asked for (`recall_thresholds` was an unknown key)."""
    from lcreg.metrics.functional import registration_recall

    recall_yaml = _write(tmp_path / "recall.yaml", "model:\n  init_args:\n    recall_thresholds: [[5, 2]]\n")
    runs = {
        "version_0": ["--model.init_args.recall_thresholds", "[[15, 0.3], [90, 1.5]]"],
        "version_1": ["--config", str(recall_yaml)],
    }
    expected = {"version_0": {(15.0, 0.3), (90.0, 1.5)}, "version_1": {(5.0, 2.0)}}
    for version, extra in runs.items():
        main(["test", "--config", str(DVDS), *TINY, *_outputs(tmp_path), *extra])
        run_dir = tmp_path / "runs" / "lcreg" / version
        metrics = _logged_test_metrics(run_dir)
        names = {f"test/recall_r{r:g}_t{t:g}".replace(".", "p"): (r, t) for r, t in expected[version]}
        assert {k for k in metrics if k.startswith("test/recall")} == {
            "test/recall_r2_t0p01",
            "test/recall_r5_t0p05",
            *names,
        }
        pairs = list(csv.DictReader((run_dir / "test_per_pair.csv").open()))
        rot = torch.tensor([float(p["rotation_error_deg"]) for p in pairs])
        trans = torch.tensor([float(p["translation_error"]) for p in pairs])
        for name, (r, t) in names.items():
            assert metrics[name] == pytest.approx(float(registration_recall(rot, trans, r, t)), abs=1e-6), name


def test_wandb_fragment_sets_only_the_logger() -> None:
    fragment = yaml.safe_load((CONFIGS / "logging" / "wandb.yaml").read_text())
    assert list(fragment) == ["trainer"] and list(fragment["trainer"]) == ["logger"]
    logger = fragment["trainer"]["logger"]
    assert logger["class_path"] == "lightning.pytorch.loggers.WandbLogger"
    assert logger["init_args"] == {"project": "lcreg", "save_dir": "runs"}


def test_print_config_exits_zero(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["fit", "--config", str(DVDS), "--print_config"])
    assert exc.value.code in (0, None)
    printed = yaml.safe_load(capsys.readouterr().out)
    assert printed["model"]["class_path"] == "lcreg.models.dvds.DVDs"
    assert printed["data"]["class_path"] == "lcreg.data.datamodule.SyntheticDataModule"


def test_the_top_level_help_names_every_reproduce_budget(capsys: pytest.CaptureFixture[str]) -> None:
    """Session 62: it named smoke|cpu|paper, without the converge budget ``lcreg reproduce`` takes."""
    with pytest.raises(SystemExit):
        main(["--help"])
    assert f"--budget {'|'.join(PRESETS)}" in " ".join(capsys.readouterr().out.split())


@pytest.mark.parametrize(
    "bad", ["--model.init_args.not_a_key=1", "--trainer.not_a_key=1", "--data.init_args.num_points=many"]
)
def test_unknown_key_or_bad_value_exits_non_zero(bad: str) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["fit", "--config", str(DVDS), bad])
    assert exc.value.code not in (0, None)


@pytest.mark.parametrize("config", ALL_CONFIGS, ids=[str(p.relative_to(CONFIGS)) for p in ALL_CONFIGS])
def test_every_config_parses(config: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Each file parses on top of a complete base (DVDs on the embedded data): fragments as the add-ons they are,
    model, data and recipe files replacing the base's blocks. The compositions themselves are built with their
    expected classes and loss terms in tests/test_method_configs.py."""
    base = ["--config", str(CONFIGS / "models" / "dvds.yaml"), "--config", str(CONFIGS / "data" / "embedded.yaml")]
    with pytest.raises(SystemExit) as exc:
        main(["fit", *base, "--config", str(config), "--print_config"])
    assert exc.value.code in (0, None)
    assert yaml.safe_load(capsys.readouterr().out)["trainer"] is not None


def test_modelnet40_config_parses_without_data(capsys: pytest.CaptureFixture[str]) -> None:
    missing = "/nonexistent/modelnet40_ply_hdf5_2048"
    with pytest.raises(SystemExit) as exc:
        main(
            [
                "fit",
                "--config",
                str(CONFIGS / "dvds_modelnet40.yaml"),
                f"--data.init_args.root={missing}",
                "--print_config",
            ]
        )
    assert exc.value.code in (0, None)
    printed = yaml.safe_load(capsys.readouterr().out)
    assert printed["data"]["class_path"] == "lcreg.data.datamodule.ModelNet40DataModule"
    assert printed["data"]["init_args"]["root"] == missing


def test_a_listed_checkpoint_replaces_the_default(tmp_path: Path) -> None:
    listed = (
        "--trainer.callbacks=[{class_path: lightning.pytorch.callbacks.ModelCheckpoint, "
        "init_args: {monitor: val/loss, save_last: true, filename: 'epoch{epoch:03d}-val_loss{val/loss:.4f}', "
        "auto_insert_metric_name: false}}]"
    )
    main(["fit", "--config", str(DVDS), listed, *TINY, *_outputs(tmp_path)])
    checkpoints = tmp_path / "runs" / "lcreg" / "version_0" / "checkpoints"
    assert len(list(checkpoints.glob("epoch000-val_loss*.ckpt"))) == 1 and (checkpoints / "last.ckpt").is_file()
    assert not list(checkpoints.glob("*rre*.ckpt"))  # the default val/rre_mean_deg checkpoint was not added
    checkpoint = torch.load(checkpoints / "last.ckpt", map_location="cpu", weights_only=False)
    monitors = [key for key in checkpoint["callbacks"] if "ModelCheckpoint" in key]
    assert len(monitors) == 1 and "'monitor': 'val/loss'" in monitors[0]


def test_trainer_defaults_live_in_the_cli(tmp_path: Path) -> None:
    """Seed, CSV logger under runs/, log interval, val/rre_mean_deg + latest last.ckpt, RNG states, progress bar."""
    from lightning.pytorch.callbacks import ModelCheckpoint, TQDMProgressBar
    from lightning.pytorch.loggers import CSVLogger

    from lcreg.callbacks import LatestCheckpoint, RngState, TimedProgressBar, TrainingClock

    model_only = CONFIGS / "models" / "pcrnet.yaml"
    cli = build_cli(["--config", str(model_only), "--config", str(CONFIGS / "data" / "embedded.yaml")], run=False)
    assert cli.config["seed_everything"] == 1234
    assert isinstance(cli.trainer.logger, CSVLogger) and Path(cli.trainer.logger.save_dir).name == "runs"
    assert cli.trainer.log_every_n_steps == 10
    (checkpoint,) = [c for c in cli.trainer.callbacks if isinstance(c, ModelCheckpoint)]
    assert (checkpoint.monitor, checkpoint.mode, checkpoint.save_last) == ("val/rre_mean_deg", "min", None)
    (latest,) = [c for c in cli.trainer.callbacks if isinstance(c, LatestCheckpoint)]
    assert latest.every_n_train_steps == 50 and any(isinstance(c, RngState) for c in cli.trainer.callbacks)
    assert sum(isinstance(c, TrainingClock) for c in cli.trainer.callbacks) == 1
    (bar,) = [c for c in cli.trainer.callbacks if isinstance(c, TQDMProgressBar)]
    assert isinstance(bar, TimedProgressBar) and (bar.refresh_rate, bar.min_interval_s) == (1, 0.5)
    raw = yaml.safe_load(model_only.read_text())
    assert "seed_everything" not in raw and set(raw["trainer"]) == {"max_epochs"}  # no file repeats the defaults


def test_default_root_dir_moves_the_default_logger_and_resume_finds_the_run(tmp_path: Path) -> None:
    """``--trainer.default_root_dir D`` logs under D/lcreg/version_k (not ./runs); an explicit save_dir stays."""
    root = tmp_path / "root"
    main(["fit", "--config", str(DVDS), *TINY, f"--trainer.default_root_dir={root}"])
    assert (root / "lcreg" / "version_0" / "checkpoints" / "last.ckpt").is_file()
    main(["fit", "--config", str(DVDS), *TINY, f"--trainer.default_root_dir={root}", "--ckpt_path=last"])
    assert not (root / "lcreg" / "version_1").exists() and not Path("runs", "lcreg").exists()
    explicit = [f"--trainer.default_root_dir={root}", f"--trainer.logger.init_args.save_dir={tmp_path / 'logs'}"]
    cli = build_cli(["--config", str(DVDS), *explicit], run=False)
    assert Path(cli.trainer.logger.save_dir) == tmp_path / "logs"


# --- compose -----------------------------------------------------------------------------------------------------
def _write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def test_expand_configs_reads_composed_files_first_recursively_relative_to_the_composing_file(
    tmp_path: Path,
) -> None:
    leaf = _write(tmp_path / "leaf.yaml", "trainer: {max_epochs: 1}\n")
    inner = _write(tmp_path / "sub" / "inner.yaml", "compose: [../leaf.yaml]\ntrainer: {max_epochs: 2}\n")
    sibling = _write(tmp_path / "sibling.yaml", "trainer: {max_epochs: 3}\n")
    top = _write(tmp_path / "top.yaml", "compose: [sub/inner.yaml, sibling.yaml]\ntrainer: {max_epochs: 4}\n")
    plain = _write(tmp_path / "plain.yaml", "trainer: {max_epochs: 5}\n")
    args = ["fit", "--config", str(top), "--trainer.max_epochs=9", f"--config={plain}"]
    expected = [str(p.resolve()) for p in (leaf, inner, sibling, top)]
    assert expand_configs(args) == [
        "fit",
        *[arg for path in expected for arg in ("--config", path)],
        "--trainer.max_epochs=9",
        "--config",
        str(plain.resolve()),
        "--compose=null",  # the saved config.yaml is complete: it must not compose again
    ]


def test_expand_configs_leaves_arguments_alone_when_nothing_composes(tmp_path: Path) -> None:
    plain = _write(tmp_path / "plain.yaml", "trainer: {max_epochs: 5}\n")
    empty = _write(tmp_path / "empty.yaml", "compose: []\n")
    missing = str(tmp_path / "missing.yaml")  # left for the parser to report
    args = ["fit", "--config", str(plain), "--config", missing, "--model.init_args.k=3"]
    out = expand_configs(args)
    assert out == ["fit", "--config", str(plain.resolve()), "--config", missing, "--model.init_args.k=3"]
    assert "--compose=null" not in expand_configs(["--config", str(empty)])


def test_expand_configs_refuses_cycles_and_names_the_file_of_a_missing_part(tmp_path: Path) -> None:
    _write(tmp_path / "a.yaml", "compose: [b.yaml]\n")
    _write(tmp_path / "b.yaml", "compose: [c.yaml]\n")
    _write(tmp_path / "c.yaml", "compose: [a.yaml]\n")
    with pytest.raises(ValueError, match="cycle"):
        expand_configs(["--config", str(tmp_path / "a.yaml")])
    broken = _write(tmp_path / "broken.yaml", "compose: [absent.yaml]\n")
    with pytest.raises(FileNotFoundError, match=r"'absent\.yaml' not found") as exc:
        expand_configs(["--config", str(broken)])
    assert str(broken.resolve()) in str(exc.value)
    bad = _write(tmp_path / "bad.yaml", "compose: leaf.yaml\n")
    with pytest.raises(ValueError, match="list of config paths"):
        expand_configs(["--config", str(bad)])


def test_shipped_recipes_expand_in_the_documented_order() -> None:
    expanded = expand_configs(["--config", str(CONFIGS / "ablation" / "model_A.yaml")])
    names = [Path(a).relative_to(CONFIGS).as_posix() for a in expanded if a.endswith(".yaml")]
    assert names == [
        "models/dvds.yaml",
        "lc.yaml",
        "data/modelnet40.yaml",
        "dvds_modelnet40.yaml",
        "ablation/model_A.yaml",
    ]
    assert expanded[-1] == "--compose=null"
    expanded = expand_configs(["--config", str(CONFIGS / "dcp_lc.yaml")])
    names = [Path(a).relative_to(CONFIGS).as_posix() for a in expanded if a.endswith(".yaml")]
    assert names == ["models/dcp.yaml", "lc.yaml", "data/modelnet40.yaml", "data/dcp_protocol.yaml", "dcp_lc.yaml"]


# --- instantiate: config files plus typed values (what the experiments build with) -------------------------------
def test_instantiate_applies_typed_values_after_the_files_and_a_list_replaces_the_configs() -> None:
    """A list value replaces the config's list, as ``--key=[...]`` does: before, jsonargparse merged it item by item,
    and a SelfMotionLoss put over the recipe's LocalConsistencyLoss kept its name ``lc``."""
    from lcreg.cli import instantiate
    from lcreg.models.loss_terms import SelfMotionLoss

    values = {
        "data": {"class_path": "lcreg.data.datamodule.SyntheticDataModule", "init_args": {"num_points": 96}},
        "model.init_args.encoder_channels": [16, 32],
        "model.init_args.loss_terms": [{"class_path": "lcreg.models.loss_terms.SelfMotionLoss"}],
        "trainer.max_steps": 7,
        "seed_everything": 5,
    }
    cli = instantiate(["configs/dvds_modelnet40.yaml"], values)
    (term,) = cli.model.loss_terms
    assert isinstance(term, SelfMotionLoss) and term.name == "self_motion"
    assert (
        cli.datamodule.pair_protocol.num_points == 96
        and cli.trainer.max_steps == 7
        and cli.config["seed_everything"] == 5
    )
    assert cli.model.encoder.linears[-1].out_features == 32


@pytest.mark.parametrize("given", ["3", 3, 3.0])
def test_a_train_objects_count_stays_a_count_through_the_cli(given: object) -> None:
    """Session 62: jsonargparse parses an ``int | float | None`` argument (default None) float first under
    LightningCLI, so ``--data.init_args.train_objects 286`` reached the DataModule as 286.0 and was refused as a
    fraction above 1 (the queue's ``--train-objects 286`` job failed so); a count of 1 became 1.0, all the objects."""
    if isinstance(given, str):
        cli = build_cli(["--config", str(DVDS), "--data.init_args.train_objects", given], run=False)
    else:
        cli = instantiate([str(DVDS)], {"data.init_args.train_objects": given})
    assert cli.datamodule.train_objects == 3 and isinstance(cli.datamodule.train_objects, int)


def test_train_objects_one_from_a_config_is_refused_as_ambiguous() -> None:
    with pytest.raises(ConfigValueError, match=r"train_objects.*ambiguous"):
        build_cli(["--config", str(DVDS), "--data.init_args.train_objects", "1"], run=False)
    assert instantiate([str(DVDS)], {"data.init_args.train_objects": 0.5}).datamodule.train_objects == 0.5


def test_instantiate_refuses_a_malformed_key_or_a_missing_file() -> None:
    from lcreg.cli import instantiate

    with pytest.raises(ConfigValueError, match=r"data\.\.x"):
        instantiate(["configs/dvds.yaml"], {"data..x": 1})
    with pytest.raises(ConfigValueError, match="batch_size") as wrong_type:  # before: SystemExit(2)
        instantiate(["configs/dvds.yaml"], {"data.init_args.batch_size": "abc"})
    assert "\n" not in str(wrong_type.value)
    with pytest.raises(ConfigValueError, match="nonsense"):
        instantiate(["configs/dvds.yaml"], {"model.init_args.nonsense": 1})
    with pytest.raises(ConfigFileError, match=r"nowhere\.yaml"):
        instantiate(["configs/nowhere.yaml"])


def test_an_integer_batch_limit_counts_batches_and_a_float_is_a_fraction(tmp_path: Path) -> None:
    """``--trainer.limit_val_batches 1`` validates on one batch. It used to parse as 1.0 (every batch): ``typing``
    handed the Trainer's ``Optional[Union[int, float]]`` back as ``Union[float, int, None]``."""
    limits = ["--trainer.limit_val_batches=1", "--trainer.limit_train_batches=1.0", "--trainer.limit_test_batches=0.5"]
    cli = build_cli(
        ["--config", str(DVDS), *TINY, "--data.init_args.num_val=4", *limits, *_outputs(tmp_path)], run=False
    )
    assert type(cli.trainer.limit_val_batches) is int and cli.trainer.limit_val_batches == 1
    assert type(cli.trainer.limit_train_batches) is float and cli.trainer.limit_test_batches == 0.5
    cli.trainer.fit(cli.model, cli.datamodule)
    assert cli.trainer.num_val_batches == [1] and cli.trainer.num_training_batches == 2  # of 2 val and 2 train batches
    from lcreg.cli import instantiate

    typed = instantiate([str(DVDS)], {"trainer.limit_predict_batches": 1, "trainer.logger": False})
    assert type(typed.trainer.limit_predict_batches) is int
