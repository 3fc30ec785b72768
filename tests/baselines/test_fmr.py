from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from scipy.spatial import cKDTree

from lcreg.baselines.fmr import FMRNet
from lcreg.types import RegistrationBatch

from _host_contract import (  # type: ignore[import-not-found]
    check_bad_inputs,
    check_forward_backward,
    check_local_consistency_gradient,
    check_training_lowers_loss,
    tiny_batch,
)

TINY = {"encoder_channels": (16, 32), "decoder_hidden": (32, 16), "decoder_points": 48}
CONFIGS = Path(__file__).resolve().parents[2] / "configs"


def _model(seed: int = 0, **overrides: object) -> FMRNet:
    torch.manual_seed(seed)
    return FMRNet(**{**TINY, **overrides})  # type: ignore[arg-type]


@pytest.fixture(scope="module")
def batch() -> RegistrationBatch:
    return tiny_batch(batch_size=3, num_points=64)


def test_forward_backward_and_training_lower_the_loss(batch: RegistrationBatch) -> None:
    check_forward_backward(_model, batch)
    check_training_lowers_loss(_model, batch, steps=10)
    check_forward_backward(lambda: _model(pose_weight=1.0), batch)


def _squared_chamfer(a: np.ndarray, b: np.ndarray) -> float:
    return float((cKDTree(b).query(a)[0] ** 2).mean() + (cKDTree(a).query(b)[0] ** 2).mean())


def test_reconstruction_loss_matches_a_scipy_reference(batch: RegistrationBatch) -> None:
    model = _model().train()
    losses = model.training_losses(model.training_forward(batch), batch)
    with torch.no_grad():  # train-mode BatchNorm (batch statistics), as in the loss
        expected = 0.0
        for clouds in (batch.points_src, batch.points_ref):
            decoded = model.decoder(model.encoder(clouds)).double().numpy()
            expected += np.mean([_squared_chamfer(d, c) for d, c in zip(decoded, clouds.double().numpy())])
    np.testing.assert_allclose(float(losses["recon"]), expected, rtol=1e-4)
    assert set(losses) == {"recon", "loss"}


def test_unsupervised_training_never_reads_the_pose_nor_solves(batch: RegistrationBatch) -> None:
    model = _model().train()
    no_gt = dataclasses.replace(batch, transform_ref_src=None)
    result = model.training_forward(no_gt)
    assert result.num_iters.tolist() == [0, 0, 0]  # the Chamfer loss does not use the estimate
    torch.manual_seed(0)
    a = model.training_losses(result, no_gt)["loss"]
    torch.manual_seed(0)
    b = model.training_losses(model.training_forward(batch), batch)["loss"]
    torch.testing.assert_close(a, b)


def test_semi_supervised_variant_adds_the_pose_term_through_the_solve(batch: RegistrationBatch) -> None:
    model = _model(pose_weight=2.0).train()
    result = model.training_forward(batch)
    assert result.transform_ref_src.requires_grad and (result.num_iters > 0).all()
    losses = model.training_losses(result, batch)
    torch.testing.assert_close(losses["loss"], losses["recon"] + 2.0 * losses["pose"])


def test_test_time_registration_uses_ten_iterations(batch: RegistrationBatch) -> None:
    model = _model(tolerance=0.0)
    assert model.register(batch.points_src, batch.points_ref).num_iters.tolist() == [10, 10, 10]


def test_eval_iterations_sets_the_test_time_solve_and_leaves_training_alone(batch: RegistrationBatch) -> None:
    model = _model(tolerance=0.0, eval_iterations=3, pose_weight=1.0)
    assert model.register(batch.points_src, batch.points_ref).num_iters.tolist() == [3, 3, 3]
    assert model.train()(batch.points_src, batch.points_ref).num_iters.tolist() == [10, 10, 10]
    with pytest.raises(ValueError, match="eval_iterations"):
        _model(eval_iterations=0)


def test_injected_local_consistency_reaches_the_pointnet_encoder(batch: RegistrationBatch) -> None:
    check_local_consistency_gradient(lambda terms: _model(loss_terms=terms), batch)


def test_bad_inputs_and_arguments() -> None:
    check_bad_inputs(_model)
    with pytest.raises(ValueError, match="pose_weight"):
        _model(pose_weight=-0.1)


def test_config_pins_the_original_hyper_parameters() -> None:
    config = yaml.safe_load((CONFIGS / "models" / "fmr.yaml").read_text())
    args = config["model"]["init_args"]
    assert args["encoder_channels"] == [64, 64, 64, 128, 1024] and args["batch_norm"] is True
    assert (args["max_iterations"], args["tolerance"], args["jacobian"], args["fd_step"]) == (
        10,
        1e-7,
        "finite_difference",
        0.01,
    )
    assert args["decoder_hidden"] == [1024, 512, 256] and args["pose_weight"] == 0.0
    assert args["optimizer"] == {"class_path": "torch.optim.Adam", "init_args": {"lr": 0.001}}
    assert config["model"]["class_path"] == "lcreg.baselines.fmr.FMRNet"
    assert config["trainer"]["max_epochs"] == 200  # batch 8: tests/test_method_configs.py::test_original_batch_sizes
