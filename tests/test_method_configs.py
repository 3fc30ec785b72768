"""The composed configs of every method: each documented composition and recipe builds the expected model, loss
terms, data and trainer; the classical methods refuse `lcreg fit`; refinement and learned baselines run end to end.

Composition rules themselves (``compose:`` expansion, order, cycles) are tested in tests/test_cli.py.
"""

from __future__ import annotations

import csv
from pathlib import Path

import pytest
import torch

from lcreg.baselines.classical import FGR, ICP, RANSAC
from lcreg.baselines.dcp import DCP
from lcreg.baselines.deepgmr import DeepGMR
from lcreg.baselines.fmr import FMRNet
from lcreg.baselines.idam import IDAM
from lcreg.baselines.pcrnet import PCRNet
from lcreg.baselines.pointnetlk import PointNetLK
from lcreg.baselines.prnet import PRNet
from lcreg.cli import build_cli, main
from lcreg.data.datamodule import ModelNet40DataModule, SyntheticDataModule
from lcreg.models.dvds import DVDs
from lcreg.models.loss_terms import LocalConsistencyLoss

from _cli_runs import (  # type: ignore[import-not-found]
    CONFIGS,
    DCP_FAMILY,
    SYNTHETIC,
    config_args,
    fit_then_test_embedded,
    host_composition,
    load_yaml,
)
from _shared_data import shared_data  # type: ignore[import-not-found]

LEARNED_HOSTS = {
    "dvds": DVDs,
    "dcp": DCP,
    "prnet": PRNet,
    "idam": IDAM,
    "deepgmr": DeepGMR,
    "pointnetlk": PointNetLK,
    "fmr": FMRNet,
    "pcrnet": PCRNet,
}
CLASSICAL = {"icp": ICP, "icp_plane": ICP, "ransac": RANSAC, "fgr": FGR}
# max_epochs of each model's original schedule (a model-specific trainer key of configs/models/<host>.yaml).
MAX_EPOCHS = {
    "dvds": 200,
    "dcp": 250,
    "prnet": 100,
    "idam": 40,
    "deepgmr": 100,
    "pointnetlk": 200,
    "fmr": 200,
    "pcrnet": 200,
}

pytestmark = pytest.mark.usefixtures("isolated_cli")


def _lc_points(model: torch.nn.Module) -> list[int]:
    """``num_local_points`` of each injected LC term (``[]``: no LC); other terms are only self-motion terms."""
    from lcreg.models.loss_terms import SelfMotionLoss

    terms = list(model.loss_terms)  # type: ignore[arg-type]
    assert all(isinstance(t, LocalConsistencyLoss | SelfMotionLoss) for t in terms), terms
    return [t.local_consistency.num_local_points for t in terms if isinstance(t, LocalConsistencyLoss)]


# --- every documented composition --------------------------------------------------------------------------------
@pytest.mark.parametrize("lc", [False, True], ids=["plain", "lc"])
@pytest.mark.parametrize("host", list(LEARNED_HOSTS))
def test_every_learned_host_composes_with_and_without_lc(host: str, lc: bool) -> None:
    """``models/<host>.yaml`` [+ ``lc.yaml``] + ``data/embedded.yaml``: class, LC term bound to the encoder, data."""
    cli = build_cli(host_composition(host, lc=lc, data="embedded"), run=False)
    model = cli.model
    assert type(model) is LEARNED_HOSTS[host]
    assert _lc_points(model) == ([64] if lc else [])
    if lc:
        (term,) = model.loss_terms
        assert term.weight == 1.0 and term.local_consistency.pairing == "target"
        assert term.local_consistency.feature_dim == model.descriptor_dim  # bound to the host's encoder
        assert model.min_points >= 64
        with torch.no_grad():
            features = model.eval().descriptor_encoder()(torch.randn(2, 64, 3))
        assert features.shape[-1] == model.descriptor_dim
    assert not {"loss_terms", "refiner", "optimizer", "lr_scheduler", "voxel_grid"} & set(model.hparams)
    assert model.refiner is None
    data = cli.datamodule
    assert isinstance(data, SyntheticDataModule) and data.batch_size == 16
    same_points = host in DCP_FAMILY  # data/dcp_protocol.yaml composed after the data file
    assert (data.pair_protocol.independent_sampling, data.pair_protocol.noise_sigma) == (
        (False, 0.01) if same_points else (True, 0.0)
    )
    assert cli.trainer.max_epochs == MAX_EPOCHS[host]
    monitors = [getattr(c, "monitor", "(last.ckpt)") for c in cli.trainer.checkpoint_callbacks]
    assert monitors == ["val/rre_mean_deg", "(last.ckpt)"]  # the best, then LatestCheckpoint


@pytest.mark.parametrize("method", list(CLASSICAL))
def test_classical_methods_compose_with_the_data_files(method: str) -> None:
    cli = build_cli(config_args(f"models/{method}.yaml", "data/embedded.yaml"), run=False)
    assert type(cli.model) is CLASSICAL[method] and not cli.model.has_loss and len(cli.model.loss_terms) == 0
    assert cli.trainer.checkpoint_callbacks == []  # enable_checkpointing: false, nothing to select


# Ablation rows: (LC num_local_points, lambda_recon, lambda_normal); recipes: (class, LC sizes, data module).
DVDS_ROWS = {
    "ablation/model_A.yaml": ([], 0.0, 0.0),
    "ablation/model_B.yaml": ([64], 0.0, 0.0),
    "ablation/model_C.yaml": ([64], 0.5, 0.0),
    "ablation/model_D.yaml": ([64], 0.5, 0.1),
    "ablation/local_32.yaml": ([32], 0.5, 0.1),
    "ablation/local_64.yaml": ([64], 0.5, 0.1),
    "ablation/local_96.yaml": ([96], 0.5, 0.1),
    "ablation/lambda_0.5_0.5.yaml": ([64], 0.5, 0.5),
    "ablation/lambda_1_0.1.yaml": ([64], 1.0, 0.1),
    "ablation/lambda_0.5_0.1.yaml": ([64], 0.5, 0.1),
}
RECIPES = {
    "dvds.yaml": (DVDs, [64], SyntheticDataModule),
    "dvds_paper_objective.yaml": (DVDs, [64], SyntheticDataModule),
    "dvds_modelnet40.yaml": (DVDs, [64], ModelNet40DataModule),
    "dcp_lc.yaml": (DCP, [64], ModelNet40DataModule),
    "dvds_selfsup_modelnet40.yaml": (DVDs, [64], ModelNet40DataModule),
    **{name: (DVDs, lc, ModelNet40DataModule) for name, (lc, _, _) in DVDS_ROWS.items()},
}


@pytest.mark.parametrize("host", ["dvds", "pointnetlk", "dcp"])
def test_self_motion_yaml_appends_the_label_free_term_to_any_host(host: str) -> None:
    from lcreg.models.loss_terms import SelfMotionLoss

    cli = build_cli(config_args(f"models/{host}.yaml", "self_motion.yaml", "data/embedded.yaml"), run=False)
    assert [type(t) for t in cli.model.injected_terms][-1] is SelfMotionLoss
    recipe = build_cli(config_args("dvds_selfsup_modelnet40.yaml"), run=False).model
    assert [t.name for t in recipe.injected_terms] == ["lc", "self_motion"]  # composed once, not twice


def test_every_recipe_and_ablation_file_is_listed() -> None:
    recipes = {p.name for p in CONFIGS.glob("*.yaml") if "compose" in load_yaml(p)}
    ablations = {f"ablation/{p.name}" for p in (CONFIGS / "ablation").glob("*.yaml")}
    assert recipes | ablations == set(RECIPES)
    readme = (CONFIGS / "ablation" / "README.md").read_text()
    assert all(f"`{Path(name).name}`" in readme for name in DVDS_ROWS)


@pytest.mark.parametrize("recipe", list(RECIPES))
def test_recipes_build_with_their_loss_terms(recipe: str) -> None:
    cls, lc_points, data_cls = RECIPES[recipe]
    cli = build_cli(config_args(recipe), run=False)  # ModelNet40's root is only read at setup
    assert type(cli.model) is cls and _lc_points(cli.model) == lc_points
    assert type(cli.datamodule) is data_cls
    if recipe in DVDS_ROWS:
        _, recon, normal = DVDS_ROWS[recipe]
        assert (cli.model.hparams["lambda_recon"], cli.model.hparams["lambda_normal"]) == (recon, normal)


def test_ablations_change_only_the_loss_settings_and_the_run_name() -> None:
    """Each ablation row is dvds_modelnet40.yaml with other loss weights / LC size, logged under its own name."""
    reference = build_cli(config_args("dvds_modelnet40.yaml"), run=False)
    loss_keys = {"lambda_recon", "lambda_normal"}
    expected = {k: v for k, v in reference.model.hparams.items() if k not in loss_keys}
    names = set()
    for recipe in DVDS_ROWS:
        cli = build_cli(config_args(recipe), run=False)
        assert {k: v for k, v in cli.model.hparams.items() if k not in loss_keys} == expected, recipe
        assert dict(cli.datamodule.hparams) == dict(reference.datamodule.hparams), recipe
        assert cli.trainer.max_epochs == reference.trainer.max_epochs == 200
        names.add(cli.trainer.logger.name)  # type: ignore[union-attr]
    assert len(names) == len(DVDS_ROWS) and reference.trainer.logger.name not in names  # type: ignore[union-attr]


def test_recipes_override_what_they_compose() -> None:
    from lcreg.models.loss_terms import LocalConsistencyLoss, SelfMotionLoss

    main_job = build_cli(config_args("dvds.yaml"), run=False)
    assert main_job.trainer.max_epochs == 5  # dvds.yaml over models/dvds.yaml's 200
    # Issue 23: the main job is the self-motion recipe at lr 3e-5 (it learns); the paper objective stays a config.
    terms = [type(t) for t in main_job.model.loss_terms]
    assert terms == [LocalConsistencyLoss, SelfMotionLoss]
    assert main_job.model.configure_optimizers().param_groups[0]["lr"] == 3e-5
    paper = build_cli(config_args("dvds_paper_objective.yaml"), run=False)
    assert [type(t) for t in paper.model.loss_terms] == [LocalConsistencyLoss] and paper.trainer.max_epochs == 5
    dcp_lc = build_cli(config_args("dcp_lc.yaml"), run=False)
    assert dcp_lc.datamodule.batch_size == 32 and dcp_lc.trainer.logger.name == "dcp_lc"  # type: ignore[union-attr]
    protocol = dcp_lc.datamodule.pair_protocol
    assert (protocol.independent_sampling, protocol.noise_sigma, protocol.noise_clip) == (False, 0.01, 0.05)


# The originals' batch sizes are data settings: compositions use the data file's (16); the benchmark registry (the
# runs that reproduce the papers' tables) and the dcp_lc.yaml recipe set each host's original batch.
ORIGINAL_BATCH = {"dcp": 32, "prnet": 36, "idam": 16, "deepgmr": 32, "pointnetlk": 32, "pcrnet": 20, "fmr": 8}


@pytest.mark.parametrize("host", list(ORIGINAL_BATCH))
def test_benchmark_registry_trains_with_the_original_batch_size(host: str) -> None:
    from lcreg.experiments.benchmarking import build

    _, dm = build(host, with_data=True)
    assert dm.batch_size == ORIGINAL_BATCH[host]
    assert build_cli(config_args("dcp_lc.yaml"), run=False).datamodule.batch_size == 32


# --- runs --------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("host", ["pointnetlk", "pcrnet", "fmr"])
def test_fit_then_test_embedded_composition_end_to_end(host: str) -> None:
    fit_then_test_embedded(host)


@pytest.mark.parametrize("method", list(CLASSICAL))
def test_fit_refuses_classical_methods_with_a_clear_message(method: str) -> None:
    with pytest.raises(RuntimeError, match=r"nothing to train.*lcreg test"):
        main(["fit", *config_args(f"models/{method}.yaml", "data/modelnet40.yaml")])


@pytest.mark.data
@pytest.mark.parametrize("method", list(CLASSICAL))
def test_classical_configs_run_lcreg_test_on_modelnet40(method: str) -> None:
    root = shared_data("modelnet40_mini")
    main(
        [
            "test",
            *config_args(f"models/{method}.yaml", "data/modelnet40.yaml"),
            f"--data.init_args.root={root}",
            "--data.init_args.batch_size=2",
            "--trainer.limit_test_batches=1",
            "--trainer.enable_progress_bar=false",
        ]
    )


def test_refine_fragment_attaches_icp_to_any_model() -> None:
    fragment = load_yaml(CONFIGS / "refine" / "icp.yaml")
    assert list(fragment) == ["model"] and list(fragment["model"]) == ["init_args"]  # a pure add-on
    assert list(fragment["model"]["init_args"]) == ["refiner"]
    cli = build_cli([*host_composition("pointnetlk"), *config_args("refine/icp.yaml")], run=False)
    refiner = cli.model.refiner
    assert isinstance(refiner, ICP) and "refiner" not in cli.model.hparams
    for key, value in fragment["model"]["init_args"]["refiner"]["init_args"].items():
        assert getattr(refiner, key) == value, key
    assert build_cli(host_composition("pointnetlk"), run=False).model.refiner is None
    ransac = build_cli([*config_args("models/ransac.yaml", "data/embedded.yaml", "refine/icp.yaml")], run=False)
    assert isinstance(ransac.model, RANSAC) and isinstance(ransac.model.refiner, ICP)


def _iterations_and_errors(run: Path) -> tuple[float, list[str]]:
    """Mean ``test/iterations`` and per-pair rotation errors of a finished ``lcreg test`` run."""
    (metrics,) = [row for row in csv.DictReader((run / "metrics.csv").open()) if row.get("test/iterations")]
    pairs = list(csv.DictReader((run / "test_per_pair.csv").open()))
    return float(metrics["test/iterations"]), [row["rotation_error_deg"] for row in pairs]


def test_test_with_refinement_end_to_end(tmp_path: Path) -> None:
    """``lcreg test ... --config configs/refine/icp.yaml`` runs ICP after a tiny PointNetLK's estimate."""
    tiny = [
        "--model.init_args.encoder_channels=[16,32]",
        "--data.init_args.num_points=96",
        "--data.init_args.batch_size=2",
        "--trainer.limit_test_batches=1",
        "--trainer.enable_progress_bar=false",
        "--trainer.enable_model_summary=false",
        f"--trainer.logger.init_args.save_dir={tmp_path}",
        *SYNTHETIC,
    ]
    main(["test", *host_composition("pointnetlk"), *tiny, "--trainer.logger.init_args.name=plain"])
    main(["test", *host_composition("pointnetlk"), *config_args("refine/icp.yaml"), *tiny])
    plain_iters, plain_errors = _iterations_and_errors(tmp_path / "plain" / "version_0")
    refined_iters, refined_errors = _iterations_and_errors(tmp_path / "lcreg" / "version_0")
    assert len(refined_errors) == len(plain_errors) == 2
    assert refined_iters > plain_iters  # the ICP iterations are added to the model's
    assert refined_errors != plain_errors  # ICP moved the estimate
