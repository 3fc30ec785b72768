"""The real-data add-on configs (configs/real/*.yaml, configs/voxelize/lk27.yaml) built and run through the CLI."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest

from lcreg.cli import build_cli, main
from lcreg.data.kitti import KITTIOdometryDataModule
from lcreg.data.scanobjectnn import ScanObjectNNDataModule
from lcreg.data.threedmatch import SevenScenesDataModule
from lcreg.nn.voxel_lk import VoxelGrid

from _cli_runs import CONFIGS, load_yaml
from _shared_data import shared_data

pytestmark = pytest.mark.usefixtures("isolated_cli")

DVDS = str(CONFIGS / "dvds_modelnet40.yaml")
REAL = CONFIGS / "real"
QUIET = ["--trainer.enable_progress_bar=false", "--trainer.enable_model_summary=false"]


def _test_rows() -> list[dict[str, str]]:
    (table,) = Path("runs").rglob("test_per_pair.csv")
    with table.open() as fh:
        return list(csv.DictReader(fh))


@pytest.mark.parametrize(
    ("name", "cls"),
    [
        ("sevenscenes", SevenScenesDataModule),
        ("kitti", KITTIOdometryDataModule),
        ("scanobjectnn", ScanObjectNNDataModule),
    ],
)
def test_data_add_on_replaces_the_modelnet40_block(name: str, cls: type) -> None:
    cli = build_cli(["--config", DVDS, "--config", str(REAL / f"{name}.yaml")], run=False)
    assert type(cli.datamodule) is cls


def test_scene_configs_pin_the_paper_protocols() -> None:
    seven = load_yaml(REAL / "sevenscenes.yaml")["data"]["init_args"]
    assert seven["test_scenes"] == ["7-scenes-redkitchen"] and seven["min_overlap"] == 0.7
    assert (seven["num_points"], seven["max_angle_deg"], seven["max_translation"]) == (2048, 45.0, 0.5)
    kitti = load_yaml(REAL / "kitti.yaml")["data"]["init_args"]
    assert (kitti["test_split"], kitti["min_distance"], kitti["refine"]) == ("test", 10.0, True)
    assert (kitti["max_angle_deg"], kitti["max_translation"], kitti["align"]) == (0.0, 0.0, False)
    grid = load_yaml(CONFIGS / "voxelize" / "lk27.yaml")["voxelize"]["init_args"]
    assert grid["grid"] ** 3 == 27


def test_voxelize_block_reaches_the_model_and_is_refused_by_other_models() -> None:
    cli = build_cli(["--config", DVDS, "--config", str(CONFIGS / "voxelize" / "lk27.yaml")], run=False)
    assert isinstance(cli.model.voxel_grid, VoxelGrid) and cli.model.voxel_grid.grid == 3
    ransac = str(CONFIGS / "ransac.yaml")
    with pytest.raises(ValueError, match="voxelize"):
        build_cli(["--config", ransac, "--config", str(CONFIGS / "voxelize" / "lk27.yaml")], run=False)


@pytest.mark.data
def test_ransac_icp_on_seven_scenes_through_lcreg_test() -> None:
    root = shared_data("3dmatch")
    config = ["--config", str(REAL / "ransac_icp_sevenscenes.yaml"), "--config", str(REAL / "sevenscenes.yaml")]
    main(["test", *config, *QUIET, f"--data.init_args.root={root}", "--trainer.limit_test_batches=2"])
    rows = _test_rows()
    assert len(rows) == 2
    assert all(float(r["rotation_error_deg"]) < 5.0 for r in rows)  # measured 0.2-0.7 deg on these pairs


@pytest.mark.data
def test_dvds_voxelised_on_seven_scenes_through_lcreg_test() -> None:
    root = shared_data("3dmatch")
    config = ["--config", DVDS, "--config", str(REAL / "sevenscenes.yaml")]
    config += ["--config", str(CONFIGS / "voxelize" / "lk27.yaml")]
    small = ["--model.init_args.encoder_channels=[16, 32]", "--voxelize.init_args.points_per_voxel=64"]
    # limit_test_batches=1 would parse as the fraction 1.0 (every batch): ask for 2 batches
    main(["test", *config, *QUIET, *small, f"--data.init_args.root={root}", "--trainer.limit_test_batches=2"])
    assert len(_test_rows()) == 2


@pytest.mark.data
def test_ransac_icp_on_the_kitti_pair_through_lcreg_test() -> None:
    root = shared_data("kitti")
    config = ["--config", str(REAL / "ransac_icp_kitti.yaml"), "--config", str(REAL / "kitti.yaml")]
    main(["test", *config, *QUIET, f"--data.init_args.root={root}", "--data.init_args.test_split=train"])
    (row,) = _test_rows()
    assert float(row["rotation_error_deg"]) < 2.0 and float(row["translation_error"]) < 1.0
