from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from lcreg.baselines.pointnetlk import PointNetLK
from lcreg.types import RegistrationBatch

from _host_contract import (  # type: ignore[import-not-found]
    check_bad_inputs,
    check_forward_backward,
    check_local_consistency_gradient,
    check_training_lowers_loss,
    tiny_batch,
)

TINY = {"encoder_channels": (16, 32)}
CONFIGS = Path(__file__).resolve().parents[2] / "configs"


def _model(seed: int = 0, **overrides: object) -> PointNetLK:
    torch.manual_seed(seed)
    return PointNetLK(**{**TINY, **overrides})  # type: ignore[arg-type]


@pytest.fixture(scope="module")
def batch() -> RegistrationBatch:
    return tiny_batch(batch_size=3, num_points=64, max_angle_deg=20.0, max_translation=0.2)


def test_forward_backward_and_training_lower_the_loss(batch: RegistrationBatch) -> None:
    check_forward_backward(_model, batch)
    check_training_lowers_loss(_model, batch, steps=10)


@pytest.mark.parametrize("jacobian", ["finite_difference", "analytic"])
def test_the_pose_loss_back_propagates_through_the_solve(batch: RegistrationBatch, jacobian: str) -> None:
    model = _model(jacobian=jacobian).train()
    result = model.training_forward(batch)
    assert result.transform_ref_src.requires_grad  # the original differentiates through J and the iterations
    pose = model.training_losses(result, batch)["pose"]
    grads = torch.autograd.grad(pose, list(model.encoder.parameters()), allow_unused=True)
    assert any(g is not None and g.abs().sum() > 0 for g in grads)
    with torch.no_grad():
        assert not model.eval()(batch.points_src, batch.points_ref).transform_ref_src.requires_grad


def test_loss_matches_a_numpy_reference(batch: RegistrationBatch) -> None:
    model = _model(residual_weight=0.5, pose_weight=2.0).train()
    result = model.training_forward(batch)
    losses = model.training_losses(result, batch)
    assert batch.transform_ref_src is not None
    est, gt = result.transform_ref_src.detach().double().numpy(), batch.transform_ref_src.double().numpy()
    pose = np.mean([np.sum((e @ np.linalg.inv(g) - np.eye(4)) ** 2) for e, g in zip(est, gt)])
    residual = np.mean(np.sum(result.aux["residual"].detach().double().numpy() ** 2, axis=1))
    np.testing.assert_allclose(float(losses["pose"]), pose, rtol=1e-4)
    np.testing.assert_allclose(float(losses["residual"]), residual, rtol=1e-4)
    np.testing.assert_allclose(float(losses["loss"]), 0.5 * residual + 2.0 * pose, rtol=1e-4)


def test_ten_iterations_in_training_twenty_at_test(batch: RegistrationBatch) -> None:
    model = _model(tolerance=0.0)
    assert model.train().training_forward(batch).num_iters.tolist() == [10, 10, 10]
    assert model.register(batch.points_src, batch.points_ref).num_iters.tolist() == [20, 20, 20]


def test_training_forward_updates_batch_norm_statistics_then_restores_train_mode(batch: RegistrationBatch) -> None:
    model = _model().train()
    norm = model.encoder.norms[0]
    assert isinstance(norm, torch.nn.BatchNorm1d) and norm.running_mean is not None
    before = norm.running_mean.clone()
    model.training_forward(batch)
    assert not torch.equal(before, norm.running_mean)
    assert model.encoder.training


def test_training_needs_the_ground_truth(batch: RegistrationBatch) -> None:
    model = _model().train()
    no_gt = dataclasses.replace(batch, transform_ref_src=None)
    with pytest.raises(ValueError, match="transform_ref_src"):
        model.training_losses(model.training_forward(no_gt), no_gt)


def test_injected_local_consistency_reaches_the_pointnet_encoder(batch: RegistrationBatch) -> None:
    check_local_consistency_gradient(lambda terms: _model(loss_terms=terms), batch)


def test_bad_inputs_and_arguments() -> None:
    check_bad_inputs(_model)
    with pytest.raises(ValueError, match="loss weights"):
        _model(pose_weight=-1.0)
    with pytest.raises(ValueError, match="eval_iterations"):
        _model(eval_iterations=0)


def test_config_pins_the_original_hyper_parameters() -> None:
    config = yaml.safe_load((CONFIGS / "models" / "pointnetlk.yaml").read_text())
    args = config["model"]["init_args"]
    assert args["encoder_channels"] == [64, 64, 64, 128, 1024] and args["batch_norm"] is True
    assert (args["max_iterations"], args["eval_iterations"], args["tolerance"]) == (10, 20, 1e-7)
    assert (args["jacobian"], args["fd_step"], args["residual_weight"], args["pose_weight"]) == (
        "finite_difference",
        0.01,
        1.0,
        1.0,
    )
    assert args["optimizer"] == {"class_path": "torch.optim.Adam", "init_args": {"lr": 0.001}}
    assert config["model"]["class_path"] == "lcreg.baselines.pointnetlk.PointNetLK"
    assert config["trainer"]["max_epochs"] == 200  # batch 32: tests/test_method_configs.py::test_original_batch_sizes
