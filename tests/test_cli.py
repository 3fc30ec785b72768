from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from lcreg.cli import main

REPO_ROOT = Path(__file__).resolve().parents[1]
CONFIGS = REPO_ROOT / "configs"
DVDS = CONFIGS / "dvds.yaml"
ALL_CONFIGS = sorted(CONFIGS.rglob("*.yaml"))

TINY = [
    "--model.init_args.encoder_channels=[16,32]",
    "--model.init_args.num_local_points=16",
    "--model.init_args.decoder_grid_size=8",
    "--model.init_args.decoder_hidden=[32]",
    "--model.init_args.normal_hidden=[16]",
    "--data.init_args.num_points=128",
    "--data.init_args.points_per_shape=256",
    "--data.init_args.num_train=4",
    "--data.init_args.num_val=2",
    "--data.init_args.num_test=2",
    "--data.init_args.batch_size=2",
    "--trainer.max_epochs=1",
    "--trainer.limit_train_batches=2",
    "--trainer.enable_progress_bar=false",
    "--trainer.enable_model_summary=false",
]


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
    metrics = list(csv.DictReader((run_dir / "metrics.csv").open()))
    assert any(row.get("val/loss") for row in metrics)

    main(["test", "--config", str(saved), "--ckpt_path", str(last)])
    per_pair = list(csv.reader((tmp_path / "runs" / "lcreg" / "version_1" / "test_per_pair.csv").open()))
    assert per_pair[0] == ["index", "rotation_error_deg", "translation_error"]
    assert [int(row[0]) for row in per_pair[1:]] == [0, 1]

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


@pytest.mark.parametrize(
    "bad", ["--model.init_args.not_a_key=1", "--trainer.not_a_key=1", "--data.init_args.num_points=many"]
)
def test_unknown_key_or_bad_value_exits_non_zero(bad: str) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["fit", "--config", str(DVDS), bad])
    assert exc.value.code not in (0, None)


@pytest.mark.parametrize("config", ALL_CONFIGS, ids=[str(p.relative_to(CONFIGS)) for p in ALL_CONFIGS])
def test_every_config_parses(config: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["fit", "--config", str(config), "--print_config"])
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


# (lc_weight, lambda_recon, lambda_normal, num_local_points) of the paper's ablation rows.
ABLATION = {
    "model_A": (0.0, 0.0, 0.0, 64),
    "model_B": (1.0, 0.0, 0.0, 64),
    "model_C": (1.0, 0.5, 0.0, 64),
    "model_D": (1.0, 0.5, 0.1, 64),
    "local_32": (1.0, 0.5, 0.1, 32),
    "local_64": (1.0, 0.5, 0.1, 64),
    "local_96": (1.0, 0.5, 0.1, 96),
    "lambda_0.5_0.5": (1.0, 0.5, 0.5, 64),
    "lambda_1_0.1": (1.0, 1.0, 0.1, 64),
    "lambda_0.5_0.1": (1.0, 0.5, 0.1, 64),
}


def test_ablation_configs_match_the_paper_rows() -> None:
    assert {p.stem for p in (CONFIGS / "ablation").glob("*.yaml")} == set(ABLATION)
    reference = yaml.safe_load((CONFIGS / "dvds_modelnet40.yaml").read_text())
    names = set()
    for stem, (lc, recon, normal, local) in ABLATION.items():
        config = yaml.safe_load((CONFIGS / "ablation" / f"{stem}.yaml").read_text())
        args = config["model"]["init_args"]
        assert (args["lc_weight"], args["lambda_recon"], args["lambda_normal"], args["num_local_points"]) == (
            lc,
            recon,
            normal,
            local,
        ), stem
        names.add(config["trainer"]["logger"]["init_args"]["name"])
        # Everything else is the ModelNet40 reference config.
        for key in ("lc_weight", "lambda_recon", "lambda_normal", "num_local_points"):
            args.pop(key)
        expected = yaml.safe_load(yaml.safe_dump(reference))
        for key in ("lc_weight", "lambda_recon", "lambda_normal", "num_local_points"):
            expected["model"]["init_args"].pop(key)
        expected["trainer"]["logger"]["init_args"].pop("name")
        config["trainer"]["logger"]["init_args"].pop("name")
        assert config == expected, stem
    assert len(names) == len(ABLATION)  # every run logs under its own name
    readme = (CONFIGS / "ablation" / "README.md").read_text()
    assert all(f"`{stem}.yaml`" in readme for stem in ABLATION)


def test_default_checkpoint_is_label_free_when_the_config_lists_none(tmp_path: Path) -> None:
    main(["fit", "--config", str(DVDS), "--trainer.callbacks=[]", *TINY, *_outputs(tmp_path)])
    checkpoints = tmp_path / "runs" / "lcreg" / "version_0" / "checkpoints"
    assert len(list(checkpoints.glob("epoch000-val_loss*.ckpt"))) == 1 and (checkpoints / "last.ckpt").is_file()
    checkpoint = torch.load(checkpoints / "last.ckpt", map_location="cpu", weights_only=False)
    assert any("'monitor': 'val/loss'" in key for key in checkpoint["callbacks"])
