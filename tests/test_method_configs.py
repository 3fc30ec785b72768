"""Configs of the compared methods (issue: every method behind one interface): protocol, CLI runs, refinement."""

from __future__ import annotations

import pytest

from lcreg.cli import build_cli, main

from _cli_runs import CONFIGS, SYNTHETIC, TINY_RUN, fit_then_test_embedded  # type: ignore[import-not-found]
from _cli_runs import load_yaml as _load
from _shared_data import shared_data  # type: ignore[import-not-found]

LEARNED = ["pointnetlk", "pcrnet", "fmr"]
CLASSICAL = ["icp", "icp_plane", "ransac", "fgr"]

pytestmark = pytest.mark.usefixtures("isolated_cli")


@pytest.mark.parametrize("method", LEARNED)
def test_learned_configs_use_the_dvds_comparison_protocol(method: str) -> None:
    config, embedded = _load(CONFIGS / f"{method}.yaml"), _load(CONFIGS / "embedded" / f"{method}.yaml")
    assert config["model"] == embedded["model"]  # the embedded demo trains the same model
    reference = _load(CONFIGS / "dvds_modelnet40.yaml")["data"]
    data = config["data"]
    assert data["class_path"] == reference["class_path"]
    ignore = {"batch_size"}  # each method keeps its original batch size
    assert {k: v for k, v in data["init_args"].items() if k not in ignore} == {
        k: v for k, v in reference["init_args"].items() if k not in ignore
    }
    checkpoints = [c for c in config["trainer"]["callbacks"] if c["class_path"].endswith("ModelCheckpoint")]
    assert [c["init_args"]["monitor"] for c in checkpoints] == ["val/rre_mean_deg"]  # never the test split


@pytest.mark.parametrize("method", LEARNED)
def test_fit_then_test_embedded_config_end_to_end(method: str) -> None:
    fit_then_test_embedded(method)


@pytest.mark.parametrize("method", CLASSICAL)
def test_fit_refuses_classical_methods_with_a_clear_message(method: str) -> None:
    with pytest.raises(RuntimeError, match=r"nothing to train.*lcreg test"):
        main(["fit", "--config", str(CONFIGS / f"{method}.yaml")])


@pytest.mark.data
@pytest.mark.parametrize("method", CLASSICAL)
def test_classical_configs_run_lcreg_test_on_modelnet40(method: str) -> None:
    root = shared_data("modelnet40_mini")
    main(
        [
            "test",
            "--config",
            str(CONFIGS / f"{method}.yaml"),
            f"--data.init_args.root={root}",
            "--data.init_args.batch_size=2",
            "--trainer.limit_test_batches=1",
            "--trainer.enable_progress_bar=false",
        ]
    )


def test_refine_fragment_attaches_icp_to_any_model() -> None:
    from lcreg.baselines.classical import ICP

    fragment = _load(CONFIGS / "refine" / "icp.yaml")
    assert set(fragment) == {"refine"}  # a pure add-on: it changes nothing else
    cli = build_cli(
        ["--config", str(CONFIGS / "embedded" / "pointnetlk.yaml"), "--config", str(CONFIGS / "refine" / "icp.yaml")],
        run=False,
    )
    refiner = cli.model.refiner
    assert isinstance(refiner, ICP)
    for key, value in fragment["refine"]["init_args"].items():
        assert getattr(refiner, key) == value, key
    plain = build_cli(["--config", str(CONFIGS / "embedded" / "pointnetlk.yaml")], run=False)
    assert plain.model.refiner is None


def test_test_with_refinement_end_to_end() -> None:
    config = str(CONFIGS / "embedded" / "pointnetlk.yaml")
    main(["test", "--config", config, "--config", str(CONFIGS / "refine" / "icp.yaml"), *TINY_RUN, *SYNTHETIC])
