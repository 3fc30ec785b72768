"""The baselines' configs: X and LC + X differ by the LC block only, and `lcreg fit` runs them end to end."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from lcreg.cli import build_cli, main

from _cli_runs import CONFIGS, TINY_RUN, fit_then_test_embedded  # type: ignore[import-not-found]
from _cli_runs import load_yaml as _load
from _shared_data import shared_data

HOSTS = ["dcp", "prnet", "idam", "deepgmr"]
LC_KEYS = {"local_consistency", "lc_weight"}


pytestmark = pytest.mark.usefixtures("isolated_cli")


@pytest.mark.parametrize("folder", ["", "embedded"])
@pytest.mark.parametrize("host", HOSTS)
def test_lc_variant_differs_by_the_lc_block_only(host: str, folder: str) -> None:
    base, lc = _load(CONFIGS / folder / f"{host}.yaml"), _load(CONFIGS / folder / f"{host}_lc.yaml")
    base_args, lc_args = base["model"]["init_args"], lc["model"]["init_args"]
    assert LC_KEYS.isdisjoint(base_args)
    assert {k: v for k, v in lc_args.items() if k not in LC_KEYS} == base_args
    assert lc_args["lc_weight"] > 0
    assert lc_args["local_consistency"]["class_path"] == "lcreg.nn.local_consistency.LocalConsistency"
    assert lc_args["local_consistency"]["init_args"]["num_local_points"] == 64
    for key in ("data", "seed_everything"):
        assert base[key] == lc[key]
    base["trainer"].pop("logger"), lc["trainer"].pop("logger")
    assert base["trainer"] == lc["trainer"]


@pytest.mark.parametrize("host", HOSTS)
def test_modelnet_configs_follow_the_table_protocol(host: str) -> None:
    config = _load(CONFIGS / f"{host}.yaml")
    embedded = _load(CONFIGS / "embedded" / f"{host}.yaml")
    assert config["model"] == embedded["model"]  # the embedded demo trains the same model
    data = config["data"]
    assert data["class_path"] == "lcreg.data.datamodule.ModelNet40DataModule"
    assert data["init_args"]["protocol"] == "unseen_objects"
    assert data["init_args"]["root"] == "../shared/data/modelnet40_mini"
    protocol = {k: data["init_args"][k] for k in ("independent_sampling", "noise_sigma", "noise_clip")}
    assert protocol == {"independent_sampling": False, "noise_sigma": 0.01, "noise_clip": 0.05}
    checkpoints = [c for c in config["trainer"]["callbacks"] if c["class_path"].endswith("ModelCheckpoint")]
    assert [c["init_args"]["monitor"] for c in checkpoints] == ["val/rre_mean_deg"]  # never the test split


@pytest.mark.parametrize("host", HOSTS)
def test_lc_feature_dim_matches_the_host_encoder(host: str) -> None:
    cli = build_cli(["--config", str(CONFIGS / f"{host}_lc.yaml")], run=False)
    model = cli.model.eval()
    with torch.no_grad():
        features = model.lc_encoder()(torch.randn(2, 64, 3))  # type: ignore[operator]
    lc = model.local_consistency  # type: ignore[attr-defined]
    assert lc is not None and features.shape[-1] == lc.feature_dim


@pytest.mark.parametrize("host", HOSTS)
def test_fit_embedded_lc_config_end_to_end(host: str) -> None:
    fit_then_test_embedded(f"{host}_lc")


@pytest.mark.data
def test_fit_dcp_lc_on_modelnet40(tmp_path: Path) -> None:
    root = shared_data("modelnet40_mini")
    main(["fit", "--config", str(CONFIGS / "dcp_lc.yaml"), *TINY_RUN, f"--data.init_args.root={root}"])


@pytest.mark.parametrize("host", HOSTS)
def test_every_host_rejects_an_lc_module_of_the_wrong_width(host: str) -> None:
    from importlib import import_module

    from lcreg.nn.local_consistency import LocalConsistency

    cls = {"dcp": "DCP", "prnet": "PRNet", "idam": "IDAM", "deepgmr": "DeepGMR"}[host]
    model_cls = getattr(import_module(f"lcreg.baselines.{host}"), cls)
    with pytest.raises(ValueError, match=r"`local_consistency.feature_dim` \(7\) must equal the encoder's width"):
        model_cls(local_consistency=LocalConsistency(feature_dim=7, num_local_points=64))
