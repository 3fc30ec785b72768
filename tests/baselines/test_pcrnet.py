from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from lcreg.baselines.pcrnet import CHAMFER_SCALE, PCRNet
from lcreg.cli import build_cli
from lcreg.geometry import se3
from lcreg.geometry.chamfer import chamfer_distance
from lcreg.types import RegistrationBatch, RegistrationResult

from _host_contract import (  # type: ignore[import-not-found]
    check_bad_inputs,
    check_forward_backward,
    check_local_consistency_gradient,
    check_training_lowers_loss,
    tiny_batch,
)

TINY = {"encoder_channels": (16, 32), "regressor_hidden": (32, 16)}
CONFIGS = Path(__file__).resolve().parents[2] / "configs"


def _model(seed: int = 0, **overrides: object) -> PCRNet:
    torch.manual_seed(seed)
    return PCRNet(**{**TINY, **overrides})


@pytest.fixture(scope="module")
def batch() -> RegistrationBatch:
    return tiny_batch(batch_size=3, num_points=64)


def _batch64(batch: RegistrationBatch) -> RegistrationBatch:
    gt = batch.transform_ref_src
    return RegistrationBatch(batch.points_src.double(), batch.points_ref.double(), None if gt is None else gt.double())


def _numpy_chamfer(a: np.ndarray, b: np.ndarray) -> float:
    """The reference's loss for one pair: average of the two mean nearest-neighbour distances (not squared)."""
    d = np.linalg.norm(a[:, None] - b[None], axis=-1)
    return 0.5 * (d.min(1).mean() + d.min(0).mean())


# --- host contract -----------------------------------------------------------------------------------------------
def test_forward_backward(batch: RegistrationBatch) -> None:
    result = check_forward_backward(lambda: _model(), batch)
    assert result.converged.all() and (result.num_iters == 8).all()
    assert set(result.aux) == {"transformed_src", "feature_ref"}
    assert result.aux["transformed_src"].shape == batch.points_src.shape and result.aux["feature_ref"].shape == (3, 32)
    assert result.residual_history is not None and result.residual_history.shape == (3, 8)


def test_training_lowers_loss(batch: RegistrationBatch) -> None:
    check_training_lowers_loss(lambda: _model(), batch, steps=12)


@pytest.mark.filterwarnings("ignore:You are trying to `self.log\\(\\)`")
def test_trains_without_a_ground_truth(batch: RegistrationBatch) -> None:
    """Unsupervised: the loss never reads ``transform_ref_src``, so a batch without one trains."""
    unlabelled = RegistrationBatch(batch.points_src, batch.points_ref, transform_ref_src=None)
    first, _ = check_training_lowers_loss(lambda: _model(), unlabelled, steps=12)
    model = _model()
    labelled = model.training_losses(model(batch.points_src, batch.points_ref), batch)["loss"]
    assert first == pytest.approx(float(labelled.detach()), rel=1e-6)  # same value with or without the ground truth
    loss = model.training_step(unlabelled, 0)  # the Lightning step (input validation; logging outside a trainer)
    assert torch.isfinite(loss)


def test_injected_local_consistency_reaches_the_pointnet_encoder(batch: RegistrationBatch) -> None:
    check_local_consistency_gradient(lambda terms: _model(loss_terms=terms), batch)


def test_bad_inputs() -> None:
    check_bad_inputs(lambda: _model())


def test_bad_arguments() -> None:
    with pytest.raises(ValueError, match="regressor_hidden"):
        _model(regressor_hidden=())
    with pytest.raises(ValueError, match="dropout"):
        _model(dropout=1.0)
    with pytest.raises(ValueError, match="num_iterations"):
        _model(num_iterations=0)


def test_default_size_is_the_original() -> None:
    model = PCRNet()
    widths = [lin.out_features for lin in model.encoder.linears]
    assert widths == [64, 64, 64, 128, 1024]
    assert all(isinstance(n, torch.nn.Identity) for n in model.encoder.norms)  # no BatchNorm
    regressor = [lin.out_features for lin in model.regressor.linears]
    assert model.regressor.first_linear.in_features == 2048 and regressor == [1024, 1024, 512, 512, 256]
    assert (model.pose.in_features, model.pose.out_features) == (256, 7)
    assert model.num_iterations == 8 and model.dropout.p == 0.0


# --- numerics ----------------------------------------------------------------------------------------------------
def test_batched_matches_per_item(batch: RegistrationBatch) -> None:
    model = _model().double().eval()
    b = _batch64(batch)
    with torch.no_grad():
        full = model(b.points_src, b.points_ref)
        for i in range(len(b)):
            one = model(b.points_src[i : i + 1], b.points_ref[i : i + 1])
            torch.testing.assert_close(one.transform_ref_src[0], full.transform_ref_src[i], atol=1e-12, rtol=0)
            torch.testing.assert_close(one.aux["transformed_src"][0], full.aux["transformed_src"][i])
            assert full.residual_history is not None and one.residual_history is not None
            torch.testing.assert_close(one.residual_history[0], full.residual_history[i])


def test_identity_regressor_gives_the_centroid_translation(batch: RegistrationBatch) -> None:
    """With every delta at the identity, ``T = Trans(mean_ref) I Trans(-mean_src)`` is a pure translation."""
    model = _model(identity_init=True).double().eval()
    b = _batch64(batch)
    with torch.no_grad():
        result = model(b.points_src, b.points_ref)
    src, ref = b.points_src.numpy(), b.points_ref.numpy()
    for i in range(len(b)):
        expected = np.eye(4)
        expected[:3, 3] = ref[i].mean(0) - src[i].mean(0)
        np.testing.assert_allclose(result.transform_ref_src[i].numpy(), expected, atol=1e-12)
        np.testing.assert_allclose(result.aux["transformed_src"][i].numpy(), src[i] + expected[:3, 3], atol=1e-12)
    assert result.residual_history is not None  # nothing moves: the feature residual stays the same
    torch.testing.assert_close(result.residual_history, result.residual_history[:, :1].expand(-1, 8))


def test_default_init_is_the_original_and_identity_init_starts_at_the_identity(batch: RegistrationBatch) -> None:
    b = _batch64(batch)
    feats = [torch.randn(3, 32, dtype=torch.float64) for _ in range(2)]
    with torch.no_grad():
        delta = _model(identity_init=True).double().delta_transform(*feats)
        torch.testing.assert_close(delta, se3.identity(3, dtype=torch.float64).expand(3, 4, 4), atol=0, rtol=0)
        faithful = _model().double()(b.points_src, b.points_ref).transform_ref_src
    angles = torch.rad2deg(torch.acos(((faithful[:, :3, :3].diagonal(dim1=1, dim2=2).sum(-1) - 1) / 2).clamp(-1, 1)))
    assert (angles > 1.0).all()  # default PyTorch init: the normalised output quaternion is far from the identity


def test_transform_composes_the_deltas_and_uncentres(batch: RegistrationBatch) -> None:
    """``T`` equals ``Trans(mean_ref) dT_8 ... dT_1 Trans(-mean_src)`` from a hand-written loop, and maps the source
    onto ``aux["transformed_src"]``."""
    model = _model(num_iterations=3).double().eval()
    b = _batch64(batch)
    with torch.no_grad():
        result = model(b.points_src, b.points_ref)
        mean_src, mean_ref = b.points_src.mean(1), b.points_ref.mean(1)
        feat_ref = model.encoder(b.points_ref - mean_ref[:, None])
        moved = (b.points_src - mean_src[:, None]).numpy()
        g = np.tile(np.eye(4), (3, 1, 1))
        for _ in range(3):
            delta = model.delta_transform(feat_ref, model.encoder(torch.from_numpy(moved))).numpy()
            moved = np.einsum("bij,bnj->bni", delta[:, :3, :3], moved) + delta[:, None, :3, 3]
            g = delta @ g
    for i in range(3):
        to_ref, from_src = np.eye(4), np.eye(4)
        to_ref[:3, 3], from_src[:3, 3] = mean_ref[i].numpy(), -mean_src[i].numpy()
        np.testing.assert_allclose(result.transform_ref_src[i].numpy(), to_ref @ g[i] @ from_src, atol=1e-12)
    moved_by_t = se3.transform_points(result.transform_ref_src, b.points_src)
    torch.testing.assert_close(moved_by_t, result.aux["transformed_src"], atol=1e-12, rtol=0)
    np.testing.assert_allclose(result.aux["transformed_src"].numpy(), moved + mean_ref[:, None].numpy(), atol=1e-12)


def test_gradients_flow_through_every_iteration(batch: RegistrationBatch) -> None:
    """Nothing is detached between iterations: the gradient differs from a loop that stops it at the moved source."""
    model = _model(num_iterations=3).double()
    b = _batch64(batch)
    loss = model.training_losses(model(b.points_src, b.points_ref), b)["loss"]
    full = torch.autograd.grad(loss, list(model.parameters()))

    mean_src, mean_ref = b.points_src.mean(1), b.points_ref.mean(1)
    feat_ref = model.encoder(b.points_ref - mean_ref[:, None])
    moved = b.points_src - mean_src[:, None]
    for _ in range(3):
        moved = se3.transform_points(model.delta_transform(feat_ref, model.encoder(moved.detach())), moved.detach())
    cut = CHAMFER_SCALE * chamfer_distance(moved + mean_ref[:, None], b.points_ref).mean()
    torch.testing.assert_close(cut, loss)  # same value ...
    detached = torch.autograd.grad(cut, list(model.parameters()))
    diff = sum(float((a - d).abs().sum()) for a, d in zip(full, detached))
    assert diff > 1e-6  # ... different gradient: the earlier iterations contribute


# --- loss --------------------------------------------------------------------------------------------------------
def test_loss_is_the_originals_chamfer(batch: RegistrationBatch) -> None:
    model = _model().double()
    b = _batch64(batch)
    result = model(b.points_src, b.points_ref)
    losses = model.training_losses(result, b)
    assert set(losses) == {"chamfer", "loss"}
    moved, ref = result.aux["transformed_src"].detach().numpy(), b.points_ref.numpy()
    expected = np.mean([_numpy_chamfer(moved[i], ref[i]) for i in range(len(b))])
    assert float(losses["loss"]) == pytest.approx(expected, rel=1e-10)
    without_aux = RegistrationResult.fixed_iterations(result.transform_ref_src, 8)  # falls back to T applied to src
    assert float(model.training_losses(without_aux, b)["loss"]) == pytest.approx(expected, rel=1e-10)


def test_loss_gradient_is_finite_at_coinciding_points() -> None:
    """The sqrt-at-zero pitfall: an exact alignment has zero NN distances; the safe norm keeps the gradient finite."""
    half = torch.tensor([[0.5, 0.25, 0.0], [-0.25, 0.5, 0.75], [1.0, -0.5, 0.25], [0.0, 0.0, 1.0]], dtype=torch.float64)
    points = torch.cat([half, -half])[None]  # centroid exactly 0: the identity model moves the source exactly onto ref
    model = _model(identity_init=True).double()
    result = model(points, points[:, torch.randperm(8)])
    assert torch.equal(result.aux["transformed_src"].sort(1).values, points.sort(1).values)
    loss = model.training_losses(result, RegistrationBatch(points, points))["loss"]
    assert float(loss) == 0.0
    loss.backward()
    grads = [p.grad for p in model.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads)

    naive = points.clone().requires_grad_(True)  # the reference's sqrt of squared distances gives NaN here
    sq = (naive[:, :, None] - points[:, None]).pow(2).sum(-1)  # (1, 8, 8) squared distances
    sq.min(-1).values.sqrt().mean().backward()
    assert naive.grad is not None and torch.isnan(naive.grad).any()


# --- configs and CLI ---------------------------------------------------------------------------------------------
def test_model_config_pins_the_originals_hyperparameters() -> None:
    config = yaml.safe_load((CONFIGS / "models" / "pcrnet.yaml").read_text())
    model = config["model"]
    assert model["class_path"] == "lcreg.baselines.pcrnet.PCRNet"
    args = model["init_args"]
    assert args["encoder_channels"] == [64, 64, 64, 128, 1024]
    assert args["regressor_hidden"] == [1024, 1024, 512, 512, 256]
    assert (args["num_iterations"], args["dropout"], args["identity_init"]) == (8, 0.0, False)
    assert args["optimizer"] == {"class_path": "torch.optim.Adam", "init_args": {"lr": 0.001}}
    assert "lr_scheduler" not in args and "loss_terms" not in args
    assert config["trainer"] == {"max_epochs": 200}  # seed, logger, val/rre_mean_deg checkpoints: lcreg.cli defaults
    # The original batch size (20): tests/test_method_configs.py::test_original_batch_sizes.


@pytest.mark.parametrize("data", ["modelnet40", "embedded"])
def test_configs_build(data: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """The YAML instantiates the original-size model and a clean, independently sampled pair protocol."""
    monkeypatch.setattr(sys, "argv", ["lcreg"])
    args = ["--config", str(CONFIGS / "models" / "pcrnet.yaml"), "--config", str(CONFIGS / "data" / f"{data}.yaml")]
    cli = build_cli(args, run=False)
    assert isinstance(cli.model, PCRNet) and cli.model.num_iterations == 8 and len(cli.model.loss_terms) == 0
    assert cli.model.encoder.feature_dim == 1024 and cli.model.pose.in_features == 256
    protocol = cli.datamodule.pair_protocol
    assert (protocol.independent_sampling, protocol.noise_sigma, protocol.partial) == (True, 0.0, "none")
