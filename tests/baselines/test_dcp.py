from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from lcreg.baselines.dcp import CYCLE_WEIGHT, DCP
from lcreg.checks import TooFewPointsError
from lcreg.geometry import se3, so3
from lcreg.nn.losses import cycle_consistency_mse
from lcreg.types import RegistrationBatch, RegistrationResult

from _host_contract import (  # type: ignore[import-not-found]
    check_bad_inputs,
    check_forward_backward,
    check_local_consistency_gradient,
    check_rotation_equivariance,
    check_training_lowers_loss,
    lc_terms,
    tiny_batch,
)
from _numpy_refs import kabsch  # type: ignore[import-not-found]

EMB = 32
TINY = {"emb_dims": EMB, "k": 8, "heads": 4, "ff_dims": 64, "edge_channels": (8, 8, 16, 16)}
CONFIGS = Path(__file__).resolve().parents[2] / "configs"


def _model(seed: int = 0, **overrides: object) -> DCP:
    torch.manual_seed(seed)
    return DCP(**{**TINY, **overrides})  # type: ignore[arg-type]


def _eval64(model: DCP) -> DCP:
    """Float64 eval-mode model whose BatchNorm layers carry non-trivial running statistics."""
    model = model.double().train()
    with torch.no_grad():
        for _ in range(2):
            model(torch.randn(3, 48, 3, dtype=torch.float64) * 0.7 + 0.2, torch.randn(3, 48, 3, dtype=torch.float64))
    return model.eval()


@pytest.fixture(scope="module")
def batch() -> RegistrationBatch:
    return tiny_batch(batch_size=3, num_points=64, independent_sampling=False)


def _batch64(batch: RegistrationBatch) -> RegistrationBatch:
    gt = batch.transform_ref_src
    assert gt is not None
    return RegistrationBatch(batch.points_src.double(), batch.points_ref.double(), gt.double())


# --- host contract -----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("pointer", ["transformer", "identity"])
def test_forward_backward(batch: RegistrationBatch, pointer: str) -> None:
    result = check_forward_backward(lambda: _model(pointer=pointer), batch)
    assert result.converged.all() and (result.num_iters == 1).all()
    assert set(result.aux) == {"matched"} and result.aux["matched"].shape == batch.points_src.shape


def test_forward_backward_with_cycle(batch: RegistrationBatch) -> None:
    result = check_forward_backward(lambda: _model(cycle=True), batch)
    assert result.aux["transform_src_ref"].shape == (3, 4, 4)


def test_training_lowers_loss(batch: RegistrationBatch) -> None:
    check_training_lowers_loss(lambda: _model(), batch, steps=12)


def test_without_batch_norm_the_trained_network_is_the_evaluated_one(batch: RegistrationBatch) -> None:
    """With BatchNorm (the original) a training-mode pass normalises the reference batch by its own statistics, which
    carry the batch's mean translation, and differs from the eval pass; ``batch_norm=False`` has no such layer."""
    for batch_norm in (True, False):
        model = _model(batch_norm=batch_norm)
        assert any(isinstance(m, torch.nn.BatchNorm1d) for m in model.modules()) is batch_norm
        with torch.no_grad():
            trained = model.train()(batch.points_src, batch.points_ref).transform_ref_src
            evaluated = model.eval()(batch.points_src, batch.points_ref).transform_ref_src
        gap = float((trained - evaluated).abs().max())
        assert gap > 1e-2 if batch_norm else gap < 1e-4, (batch_norm, gap)  # without: float32 rounding only
    check_training_lowers_loss(lambda: _model(batch_norm=False), batch, steps=12)


def test_local_consistency_reaches_the_dgcnn_encoder(batch: RegistrationBatch) -> None:
    check_local_consistency_gradient(lambda terms: _model(loss_terms=terms), batch)
    model = _model(loss_terms=lc_terms(num_local_points=16, weight=0.5))
    assert model.descriptor_encoder() is model.encoder and model.descriptor_dim == EMB and model.min_points == 16
    losses = model.training_losses(model(batch.points_src, batch.points_ref), batch)
    assert set(losses) == {"pose", "lc", "loss"}
    torch.testing.assert_close(losses["loss"], losses["pose"] + 0.5 * losses["lc"])  # LC added exactly once


def test_bad_inputs() -> None:
    check_bad_inputs(lambda: _model())


def test_bad_arguments_and_minimum_size() -> None:
    with pytest.raises(ValueError, match="pointer"):
        _model(pointer="mlp")
    with pytest.raises(ValueError, match=f"built for {EMB + 1} features, the encoder has {EMB}"):
        _model(loss_terms=lc_terms(num_local_points=16, feature_dim=EMB + 1))
    assert _model().min_points == 8  # the k-NN graph
    model = _model(loss_terms=lc_terms(num_local_points=64))
    assert model.min_points == 64
    with pytest.raises(TooFewPointsError, match="points_ref"):
        model.register(torch.randn(1, 64, 3), torch.randn(1, 40, 3))


def test_loss_needs_a_ground_truth(batch: RegistrationBatch) -> None:
    model = _model()
    result = model(batch.points_src, batch.points_ref)
    with pytest.raises(ValueError, match="ground-truth"):
        model.training_losses(result, RegistrationBatch(batch.points_src, batch.points_ref))


# --- numerics ----------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("pointer", ["transformer", "identity"])
def test_forward_matches_a_manual_pipeline(batch: RegistrationBatch, pointer: str) -> None:
    """Scores from the (pointer-refined) embeddings, row softmax, Kabsch on y_hat = P y (numpy per-pair reference)."""
    model = _eval64(_model(pointer=pointer, return_probabilities=True))
    b = _batch64(batch)
    with torch.no_grad():
        result = model(b.points_src, b.points_ref)
        f_src, f_ref = model.encoder(b.points_src), model.encoder(b.points_ref)
        if pointer == "transformer":
            assert model.pointer is not None
            d_src, d_ref = model.pointer(f_src, f_ref)
            assert not torch.allclose(d_src, f_src)  # the pointer does change the embeddings
            f_src, f_ref = d_src, d_ref
    probs = torch.softmax(torch.einsum("bnc,bmc->bnm", f_src, f_ref) / math.sqrt(EMB), dim=-1)
    torch.testing.assert_close(result.aux["probabilities"], probs)
    matched = probs @ b.points_ref
    torch.testing.assert_close(result.aux["matched"], matched)
    for i in range(len(b)):
        expected = kabsch(b.points_src[i].numpy(), matched[i].numpy())
        np.testing.assert_allclose(result.transform_ref_src[i].numpy(), expected, atol=1e-9)


@pytest.mark.parametrize("pointer", ["transformer", "identity"])
def test_estimate_is_invariant_to_point_order(batch: RegistrationBatch, pointer: str) -> None:
    """Exact for DCP: DGCNN, the transformer (no positional encoding) and the weighted sums ignore the point order."""
    model = _eval64(_model(pointer=pointer))
    b = _batch64(batch)
    gen = torch.Generator().manual_seed(3)
    perm_src, perm_ref = torch.randperm(64, generator=gen), torch.randperm(64, generator=gen)
    with torch.no_grad():
        base = model(b.points_src, b.points_ref)
        moved = model(b.points_src[:, perm_src], b.points_ref[:, perm_ref])
    torch.testing.assert_close(moved.transform_ref_src, base.transform_ref_src, atol=1e-10, rtol=0)
    torch.testing.assert_close(moved.aux["matched"], base.aux["matched"][:, perm_src], atol=1e-10, rtol=0)


def test_svd_head_with_fixed_probabilities_is_rigidly_equivariant(batch: RegistrationBatch) -> None:
    """With the matching held fixed the head is exactly equivariant: T(G x, H y) = H T(x, y) G^-1.

    The full model is not: the DGCNN edge features ``[x_j, x_i]`` are raw coordinates, so the embeddings (and the
    matching) change when a cloud is rotated or translated.
    """
    model = _eval64(_model())
    b = _batch64(batch)
    with torch.no_grad():
        f_src, f_ref = model.embed(b.points_src, b.points_ref)
        probs = torch.softmax(torch.einsum("bnc,bmc->bnm", f_src, f_ref) / math.sqrt(EMB), dim=-1)

    def estimate(src: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
        return model.head(src, ref, probs)[0]

    check_rotation_equivariance(estimate, b.points_src, b.points_ref, atol=1e-10)
    gen = torch.Generator().manual_seed(7)
    h = se3.make_transform(
        so3.exp(torch.randn(3, 3, generator=gen, dtype=torch.float64)), torch.randn(3, 3, dtype=torch.float64)
    )
    moved = estimate(b.points_src, se3.transform_points(h, b.points_ref))
    torch.testing.assert_close(moved, h @ estimate(b.points_src, b.points_ref), atol=1e-10, rtol=0)


def test_head_with_true_correspondences_recovers_the_ground_truth(batch: RegistrationBatch) -> None:
    """One-hot probabilities of the true matches (same points, shuffled) give back ``transform_ref_src``."""
    b = _batch64(batch)
    assert b.transform_ref_src is not None
    moved = se3.transform_points(b.transform_ref_src, b.points_src)
    match = torch.cdist(moved, b.points_ref).argmin(dim=-1)  # (B, N)
    assert torch.cdist(moved, b.points_ref).amin(dim=-1).max() < 1e-5  # exact correspondences exist
    one_hot = torch.nn.functional.one_hot(match, 64).double()
    transform, matched = DCP.head(b.points_src, b.points_ref, one_hot)
    torch.testing.assert_close(matched, moved, atol=1e-5, rtol=0)
    torch.testing.assert_close(transform, b.transform_ref_src, atol=1e-5, rtol=0)


def test_reverse_estimate_equals_the_swapped_forward(batch: RegistrationBatch) -> None:
    """The cycle pass (transposed scores) is what the model estimates with the clouds swapped."""
    model = _eval64(_model(cycle=True))
    b = _batch64(batch)
    with torch.no_grad():
        forward = model(b.points_src, b.points_ref)
        swapped = model(b.points_ref, b.points_src)
    torch.testing.assert_close(forward.aux["transform_src_ref"], swapped.transform_ref_src, atol=1e-10, rtol=0)


# --- losses ------------------------------------------------------------------------------------------------------
def _result(transform: torch.Tensor, reverse: torch.Tensor | None = None) -> RegistrationResult:
    b = transform.shape[0]
    aux = {} if reverse is None else {"transform_src_ref": reverse}
    return RegistrationResult(transform, torch.ones(b, dtype=torch.bool), torch.ones(b, dtype=torch.int64), aux=aux)


def _random_transforms(b: int, seed: int, scale: float = 1.0) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    rot = so3.exp(scale * torch.randn(b, 3, generator=gen, dtype=torch.float64))
    return se3.make_transform(rot, torch.randn(b, 3, generator=gen, dtype=torch.float64))


def test_pose_loss_matches_hand_computation_and_vanishes_at_the_ground_truth(batch: RegistrationBatch) -> None:
    b = _batch64(batch)
    gt = b.transform_ref_src
    assert gt is not None
    model = _model()
    assert float(model.training_losses(_result(gt.clone()), b)["loss"]) == pytest.approx(0.0, abs=1e-12)  # float32 GT
    pred = _random_transforms(3, seed=1)
    losses = model.training_losses(_result(pred), b)
    p, g = pred.numpy(), gt.numpy()
    rot = np.mean([(p[i, :3, :3].T @ g[i, :3, :3] - np.eye(3)) ** 2 for i in range(3)])
    trans = np.mean([(p[i, :3, 3] - g[i, :3, 3]) ** 2 for i in range(3)])
    assert set(losses) == {"pose", "loss"}
    assert float(losses["loss"]) == pytest.approx(rot + trans, rel=1e-12)


def test_cycle_term_uses_the_exact_inverse_identity(batch: RegistrationBatch) -> None:
    """Zero at ``T_ba = T_ab^-1`` (the original's ``R_ba^T t_ab + t_ba`` is not), hand-computed elsewhere."""
    t_ab = _random_transforms(3, seed=2)
    t_ba = se3.inverse(t_ab)
    assert float(cycle_consistency_mse(t_ba, t_ab)) == pytest.approx(0.0, abs=1e-20)
    r_ba, tr_ba = t_ba[:, :3, :3], t_ba[:, :3, 3]
    original = ((r_ba.transpose(1, 2) @ t_ab[:, :3, 3:]).squeeze(-1) + tr_ba).pow(2).mean()
    assert float(original) > 1e-3  # the original's transposed formula penalises the exact inverse

    other = _random_transforms(3, seed=3)
    a, o = t_ab.numpy(), other.numpy()
    rot = np.mean([(o[i, :3, :3] @ a[i, :3, :3] - np.eye(3)) ** 2 for i in range(3)])
    trans = np.mean([(o[i, :3, :3] @ a[i, :3, 3] + o[i, :3, 3]) ** 2 for i in range(3)])
    assert float(cycle_consistency_mse(other, t_ab)) == pytest.approx(rot + trans, rel=1e-12)

    b = _batch64(batch)
    assert b.transform_ref_src is not None
    losses = _model(cycle=True).training_losses(_result(t_ab, other), b)
    assert set(losses) == {"pose", "cycle", "loss"}
    torch.testing.assert_close(losses["loss"], losses["pose"] + CYCLE_WEIGHT * losses["cycle"])
    assert float(losses["cycle"]) == pytest.approx(rot + trans, rel=1e-12)


# --- configs -----------------------------------------------------------------------------------------------------
def test_config_follows_the_original() -> None:
    # Every composition (with/without configs/lc.yaml, each data file) is built in tests/test_method_configs.py.
    plain = yaml.safe_load((CONFIGS / "models" / "dcp.yaml").read_text())
    assert plain["trainer"]["max_epochs"] == 250
    args = plain["model"]["init_args"]
    assert plain["model"]["class_path"] == "lcreg.baselines.dcp.DCP"
    assert (args["emb_dims"], args["k"], args["pointer"], args["heads"], args["ff_dims"]) == (
        512,
        20,
        "transformer",
        4,
        1024,
    )
    assert args["optimizer"]["init_args"] == {"lr": 0.001, "weight_decay": 0.0001}
    assert args["lr_scheduler"]["init_args"] == {"milestones": [75, 150, 200], "gamma": 0.1}
