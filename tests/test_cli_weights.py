"""`lcreg <subcommand> --weights NAME_OR_PATH`: pretrained weights loaded into the configured model.

The weights come from a tiny real `lcreg fit` on the embedded shapes, exported by the test itself.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import pytest
import torch
import yaml

import lcreg
from lcreg.cli import ConfigLayers, build_cli, explicit_model_args, main
from lcreg.metrics.functional import rotation_error_deg
from lcreg.weights import (
    PretrainedBuildError,
    PretrainedClassError,
    PretrainedMismatchError,
    PretrainedNotFoundError,
    UnknownPretrainedError,
    read_weights,
)
from lcreg.weights.export import export_weights

from _cli_runs import TINY_DVDS, cli_isolation, config_args  # type: ignore[import-not-found]
from _weights_files import exported, rewrite, tiny_model  # type: ignore[import-not-found]

DVDS = config_args("models/dvds.yaml", "data/embedded.yaml")
TINY = [*TINY_DVDS, "--data.init_args.num_test=4"]  # later arguments win
LK = config_args("models/pointnetlk.yaml", "data/embedded.yaml")  # batch_norm true, jacobian finite_difference
TINY_DATA = [arg for arg in TINY if not arg.startswith("--model.")]

pytestmark = pytest.mark.usefixtures("isolated_cli")


@dataclass(frozen=True)
class Trained:
    checkpoint: Path
    weights: Path


def _outputs(root: Path) -> list[str]:
    return [f"--trainer.default_root_dir={root / 'root'}", f"--trainer.logger.init_args.save_dir={root / 'runs'}"]


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> Trained:
    """A tiny real `lcreg fit` of DVDs on the embedded shapes, exported as a weights file."""
    root = tmp_path_factory.mktemp("fit")
    with cli_isolation(root):
        main(["fit", *DVDS, *TINY, *_outputs(root)])
    checkpoint = root / "runs" / "lcreg" / "version_0" / "checkpoints" / "last.ckpt"
    return Trained(checkpoint, export_weights(checkpoint, "tiny-dvds", root / "weights"))


def _per_pair_rotation_errors(run: Path) -> torch.Tensor:
    rows = list(csv.DictReader((run / "test_per_pair.csv").open()))
    return torch.tensor([float(row["rotation_error_deg"]) for row in rows])


def test_test_with_weights_end_to_end(trained: Trained, tmp_path: Path) -> None:
    """The logged per-pair errors are those of ``lcreg.pretrained(file)`` on the same pairs (the first of two
    batches)."""
    main(
        [
            "test",
            *DVDS,
            *TINY,
            "--weights",
            str(trained.weights),
            "--trainer.limit_test_batches=0.5",
            *_outputs(tmp_path),
        ]
    )
    logged = _per_pair_rotation_errors(tmp_path / "runs" / "lcreg" / "version_0")
    datamodule = build_cli([*DVDS, *TINY], run=False).datamodule
    datamodule.setup("test")
    batch = next(iter(datamodule.test_dataloader()))
    model = lcreg.pretrained(trained.weights)
    expected = rotation_error_deg(
        model.register(batch.points_src, batch.points_ref).transform_ref_src, batch.transform_ref_src
    )
    assert logged.shape == (2,)
    torch.testing.assert_close(logged, expected, atol=1e-4, rtol=0)


def test_weights_load_strictly_into_the_inference_modules_of_the_configured_model(trained: Trained) -> None:
    plain = build_cli([*DVDS, *TINY], run=False).model
    loaded = build_cli([*DVDS, *TINY, "--weights", str(trained.weights)], run=False).model
    stored = read_weights(trained.weights).state_dict
    assert all(torch.equal(v, stored[f"encoder.{k}"]) for k, v in loaded.encoder.state_dict().items())
    assert any(not torch.equal(v, stored[f"encoder.{k}"]) for k, v in plain.encoder.state_dict().items())
    # the configured decoder and normal head are built (lambda_recon 0.5) and keep their seeded initialisation
    for name in ("decoder", "normal_head"):
        own, initial = getattr(loaded, name).state_dict(), getattr(plain, name).state_dict()
        assert all(torch.equal(v, initial[k]) for k, v in own.items()), name


def test_fit_starts_from_the_weights(trained: Trained, tmp_path: Path) -> None:
    """Fine-tuning with lr 0: the checkpoint's encoder is exactly the file's (the run started from it)."""
    frozen = "--model.init_args.optimizer.init_args.lr=0"
    main(["fit", *DVDS, *TINY, "--weights", str(trained.weights), frozen, *_outputs(tmp_path)])
    run = tmp_path / "runs" / "lcreg" / "version_0"
    state = torch.load(run / "checkpoints" / "last.ckpt", weights_only=True)["state_dict"]
    stored = read_weights(trained.weights).state_dict
    assert all(torch.equal(state[k], v) for k, v in stored.items())
    assert yaml.safe_load((run / "config.yaml").read_text())["weights"] == str(trained.weights)


def test_a_model_of_another_class_is_refused_in_one_line(trained: Trained) -> None:
    with pytest.raises(PretrainedClassError) as info:
        build_cli(
            [*config_args("models/pointnetlk.yaml", "data/embedded.yaml"), "--weights", str(trained.weights)], run=False
        )
    message = str(info.value)
    assert (
        "holds lcreg.models.dvds.DVDs weights, the configured model is lcreg.baselines.pointnetlk.PointNetLK" in message
    )
    assert "\n" not in message and str(trained.weights) in message


def test_another_architecture_is_refused_in_one_line(trained: Trained) -> None:
    with pytest.raises(PretrainedMismatchError, match=r"shapes \(file vs model\)") as info:
        main(["test", *DVDS, *TINY, "--model.init_args.encoder_channels=[16,48]", "--weights", str(trained.weights)])
    assert "\n" not in str(info.value)


def test_unknown_names_and_missing_files_are_refused() -> None:
    with pytest.raises(UnknownPretrainedError, match="known: dvds-modelnet40"):
        main(["test", *DVDS, *TINY, "--weights", "dvds-imagenet"])
    with pytest.raises(PretrainedNotFoundError, match="no such file"):
        main(["validate", *DVDS, *TINY, "--weights", "absent/weights.pt"])


def test_a_checkpoint_path_replaces_the_weights(trained: Trained, tmp_path: Path) -> None:
    """A saved config of a fine-tuning run names its --weights; testing a checkpoint of it does not read them."""
    args = ["--weights", str(tmp_path / "gone.pt"), "--ckpt_path", str(trained.checkpoint)]
    main(["test", *DVDS, *TINY, *args, "--trainer.limit_test_batches=0.5", *_outputs(tmp_path)])
    assert (tmp_path / "runs" / "lcreg" / "version_0" / "test_per_pair.csv").is_file()


def test_weights_is_an_argument_of_every_subcommand(capsys: pytest.CaptureFixture[str]) -> None:
    for subcommand in ("fit", "validate", "test", "predict"):
        with pytest.raises(SystemExit) as info:
            main([subcommand, *DVDS, "--weights", "dvds-modelnet40", "--print_config"])
        assert info.value.code in (0, None)
        assert yaml.safe_load(capsys.readouterr().out)["weights"] == "dvds-modelnet40"


@pytest.fixture(scope="module")
def lk_weights(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny PointNetLK exported without BatchNorm, analytic Jacobian and 4 IC-LK iterations at test."""
    model = tiny_model("pointnetlk", lc=False, batch_norm=False, jacobian="analytic")
    return exported(model, tmp_path_factory.mktemp("lk"))


def _first_batch_errors(model: torch.nn.Module) -> torch.Tensor:
    datamodule = build_cli([*LK, *TINY_DATA], run=False).datamodule
    datamodule.setup("test")
    batch = next(iter(datamodule.test_dataloader()))
    estimate = model.register(batch.points_src, batch.points_ref).transform_ref_src
    return rotation_error_deg(estimate, batch.transform_ref_src)


def test_test_takes_the_model_arguments_from_the_weights(lk_weights: Path, tmp_path: Path) -> None:
    """The config's PointNetLK has BatchNorm and finite differences, the file none and analytic: `lcreg test` evaluates
    the file's model (the errors of ``lcreg.pretrained(file)``), not a refusal or another Jacobian."""
    args = ["--weights", str(lk_weights), "--trainer.limit_test_batches=0.5"]
    main(["test", *LK, *TINY_DATA, *args, *_outputs(tmp_path)])
    run = tmp_path / "runs" / "lcreg" / "version_0"
    expected = _first_batch_errors(lcreg.pretrained(lk_weights))
    torch.testing.assert_close(_per_pair_rotation_errors(run), expected, atol=1e-4, rtol=0)
    saved = yaml.safe_load((run / "config.yaml").read_text())["model"]["init_args"]
    assert (saved["batch_norm"], saved["jacobian"], saved["eval_iterations"]) == (False, "analytic", 4)
    assert saved["encoder_channels"] == [16, 32]


def test_the_command_line_wins_over_the_weights(lk_weights: Path, tmp_path: Path) -> None:
    args = ["--weights", str(lk_weights), "--model.init_args.eval_iterations=1", "--trainer.limit_test_batches=0.5"]
    main(["test", *LK, *TINY_DATA, *args, *_outputs(tmp_path)])
    run = tmp_path / "runs" / "lcreg" / "version_0"
    assert yaml.safe_load((run / "config.yaml").read_text())["model"]["init_args"]["eval_iterations"] == 1
    expected = _first_batch_errors(lcreg.pretrained(lk_weights, eval_iterations=1))
    torch.testing.assert_close(_per_pair_rotation_errors(run), expected, atol=1e-4, rtol=0)
    assert not torch.allclose(expected, _first_batch_errors(lcreg.pretrained(lk_weights)), atol=1e-3)


def test_fit_keeps_the_config_arguments_and_names_the_differing_ones(lk_weights: Path, tmp_path: Path) -> None:
    """Fine-tuning trains the configured model: a file of another architecture is refused, naming what differs."""
    with pytest.raises(PretrainedMismatchError, match=r"batch_norm=False \(model: True\)") as info:
        main(["fit", *LK, *TINY_DATA, "--weights", str(lk_weights), *_outputs(tmp_path)])
    assert "jacobian='analytic' (model: 'finite_difference')" in str(info.value)


def test_validate_with_a_checkpoint_as_weights_logs_what_the_ckpt_path_does(trained: Trained, tmp_path: Path) -> None:
    """``--weights run.ckpt`` loads all the checkpoint's tensors, the decoder and normal head of the reconstruction
    and normal terms included: every logged validation metric equals ``--ckpt_path run.ckpt``'s."""
    logged = {}
    for name, args in (("weights", ["--weights"]), ("ckpt", ["--ckpt_path"])):
        main(["validate", *DVDS, *TINY, *args, str(trained.checkpoint), *_outputs(tmp_path / name)])
        rows = list(csv.DictReader((tmp_path / name / "runs" / "lcreg" / "version_0" / "metrics.csv").open()))
        logged[name] = {k: float(v) for row in rows for k, v in row.items() if k.startswith("val/") and v}
    assert {"val/recon", "val/normal", "val/rre_mean_deg"} <= set(logged["ckpt"])
    assert logged["weights"] == pytest.approx(logged["ckpt"], rel=1e-6)


def test_a_file_whose_arguments_the_class_refuses_is_named_in_one_line(lk_weights: Path, tmp_path: Path) -> None:
    """A file exported by another lcreg version, with a constructor argument this class no longer has."""
    content = read_weights(lk_weights)
    lying = rewrite(lk_weights, tmp_path / "old.pt", init_args={**content.init_args, "warp_factor": 9})
    refused = r"refuses the file's init_args .*Option 'warp_factor' is not"
    with pytest.raises(PretrainedBuildError, match=refused) as info:
        main(["test", *LK, *TINY_DATA, "--weights", str(lying), *_outputs(tmp_path)])
    assert "\n" not in str(info.value) and str(lying) in str(info.value)


@pytest.mark.parametrize(
    ("args", "names"),
    [
        (["test", "--model.init_args.batch_norm=false", "--model.jacobian", "analytic"], {"batch_norm", "jacobian"}),
        (["--model.init_args.optimizer.init_args.lr=0.1", "--model=x.yaml", "--data.init_args.root=r"], {"optimizer"}),
        (["--model.class_path", "X", "--model.init_args", "{}", "--config", "model.yaml"], set()),
        (ConfigLayers(("a.yaml",), {"model.init_args.eval_iterations": 3, "data.x": 1}), {"eval_iterations"}),
        ({"model": {"init_args": {"batch_norm": False}}}, set()),  # a whole config: no command line
    ],
)
def test_explicit_model_args(args: object, names: set[str]) -> None:
    assert explicit_model_args(args) == names  # type: ignore[arg-type]
