from __future__ import annotations

import numpy as np
import pytest
import torch

from lcreg.baselines.deepgmr import DeepGMR, DeepGMREncoder, gmm_params, gmm_register
from lcreg.geometry import se3
from lcreg.geometry.random_transforms import random_rotation
from lcreg.models.loss_terms import LossTerm
from lcreg.types import RegistrationBatch

from _host_contract import (
    check_bad_inputs,
    check_forward_backward,
    check_local_consistency_gradient,
    check_rotation_equivariance,
    check_training_lowers_loss,
    lc_terms,
    tiny_batch,
)

TINY = {"d_model": 32, "num_clusters": 4, "k": 8}


def _model(loss_terms: list[LossTerm] | None = None, seed: int = 0, **overrides: object) -> DeepGMR:
    torch.manual_seed(seed)
    return DeepGMR(**{**TINY, **overrides}, loss_terms=loss_terms or [])  # type: ignore[arg-type]


@pytest.fixture(scope="module")
def batch() -> RegistrationBatch:
    # Independent samplings: with the same points in both clouds an RRI model is exact from the start (pose loss
    # ~1e-12, nothing to train), see test_exact_on_the_moved_same_points_untrained.
    return tiny_batch(batch_size=3, num_points=96)


def _random_transform(batch: int, gen: torch.Generator) -> torch.Tensor:
    rot = random_rotation(batch, gen, torch.float64)
    return se3.make_transform(rot, torch.randn(batch, 3, generator=gen, dtype=torch.float64))


# --- host contract ---------------------------------------------------------------------------------------------
def test_forward_backward(batch: RegistrationBatch) -> None:
    result = check_forward_backward(_model, batch)
    for key in ("transform_21", "gamma_src", "pi_ref", "mu_ref", "sigma2_ref"):
        assert key in result.aux
    torch.testing.assert_close(result.aux["gamma_src"].sum(-1), torch.ones(3, 96), atol=1e-5, rtol=0)


def test_training_lowers_loss(batch: RegistrationBatch) -> None:
    check_training_lowers_loss(_model, batch, steps=10)


def test_local_consistency_gradient(batch: RegistrationBatch) -> None:
    check_local_consistency_gradient(_model, batch)


def test_bad_inputs() -> None:
    check_bad_inputs(_model)
    with pytest.raises(ValueError, match="num_clusters"):
        DeepGMR(num_clusters=0)


def test_min_points() -> None:
    assert _model().min_points == 9
    assert _model(use_rri=False).min_points == 3
    assert _model(lc_terms(num_local_points=64)).min_points == 64


def test_loss_matches_the_original_formula(batch: RegistrationBatch) -> None:
    model = _model().eval()
    result = model(batch.points_src, batch.points_ref)
    losses = model.training_losses(result, batch)
    gt = batch.transform_ref_src
    assert gt is not None
    eye = torch.eye(4).expand(3, 4, 4)
    mse_12 = ((result.transform_ref_src @ torch.linalg.inv(gt) - eye) ** 2).mean()
    mse_21 = ((result.aux["transform_21"] @ gt - eye) ** 2).mean()
    torch.testing.assert_close(losses["loss"], mse_12 + mse_21, atol=1e-6, rtol=1e-5)


# --- GMM ---------------------------------------------------------------------------------------------------------
def test_gmm_params_match_an_explicit_loop() -> None:
    gen = torch.Generator().manual_seed(0)
    points = torch.randn(2, 30, 3, generator=gen, dtype=torch.float64)
    gamma = torch.softmax(torch.randn(2, 30, 5, generator=gen, dtype=torch.float64), dim=-1)
    pi, mu, sigma2 = gmm_params(gamma, points)
    for b in range(2):
        for j in range(5):
            g, x = gamma[b, :, j].numpy(), points[b].numpy()
            mass = g.sum()
            mean = (g[:, None] * x).sum(0) / mass
            total_var = sum(g[i] * np.sum((x[i] - mean) ** 2) for i in range(30)) / mass
            assert pi[b, j].item() == pytest.approx(mass / 30, abs=1e-12)
            np.testing.assert_allclose(mu[b, j].numpy(), mean, atol=1e-12)
            assert sigma2[b, j].item() == pytest.approx(total_var / 3, abs=1e-12)  # per-axis variance


def reference_register(pi: np.ndarray, mu_s: np.ndarray, mu_t: np.ndarray, var_t: np.ndarray) -> np.ndarray:
    """DeepGMR's formula with the original's total variances, numpy SVD (one batch item)."""
    c_s, c_t = pi @ mu_s, pi @ mu_t
    m = sum(pi[j] * np.outer(mu_s[j] - c_s, mu_t[j] - c_t) / var_t[j] for j in range(len(pi)))
    u, _, vt = np.linalg.svd(m)
    s = np.diag([1.0, 1.0, np.linalg.det(vt.T @ u.T)])
    rot = vt.T @ s @ u.T
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = rot, c_t - rot @ c_s
    return out


def test_gmm_register_matches_the_original_formula() -> None:
    gen = torch.Generator().manual_seed(1)
    pi = torch.softmax(torch.randn(4, 6, generator=gen, dtype=torch.float64), dim=-1)
    mu_s = torch.randn(4, 6, 3, generator=gen, dtype=torch.float64)
    mu_t = torch.randn(4, 6, 3, generator=gen, dtype=torch.float64)
    sigma2_t = torch.rand(4, 6, generator=gen, dtype=torch.float64) + 0.05  # unequal: the centroid choice matters
    transform = gmm_register(pi, mu_s, mu_t, sigma2_t)
    for b in range(4):
        # the original stores 3 sigma2 (total variance); the estimate must not depend on that factor
        expected = reference_register(pi[b].numpy(), mu_s[b].numpy(), mu_t[b].numpy(), 3 * sigma2_t[b].numpy())
        np.testing.assert_allclose(transform[b].numpy(), expected, atol=1e-10)
    torch.testing.assert_close(gmm_register(pi, mu_s, mu_t, 3 * sigma2_t), transform, atol=1e-12, rtol=0)


def test_gmm_register_recovers_a_moved_mixture() -> None:
    gen = torch.Generator().manual_seed(2)
    pi = torch.softmax(torch.randn(3, 8, generator=gen, dtype=torch.float64), dim=-1)
    mu_s = torch.randn(3, 8, 3, generator=gen, dtype=torch.float64)
    sigma2 = torch.rand(3, 8, generator=gen, dtype=torch.float64) + 0.01
    transform = _random_transform(3, gen)
    estimate = gmm_register(pi, mu_s, se3.transform_points(transform, mu_s), sigma2)
    torch.testing.assert_close(estimate, transform, atol=1e-10, rtol=0)


# --- model invariances ----------------------------------------------------------------------------------------
def test_rotation_equivariant_with_rri(batch: RegistrationBatch) -> None:
    model = _model().double().eval()
    src, ref = batch.points_src.double(), batch.points_ref.double()
    with torch.no_grad():
        # the contract draws its rotation in float32 (orthogonal to ~1e-7 only), hence the tolerance
        check_rotation_equivariance(lambda a, b: model(a, b).transform_ref_src, src, ref, atol=1e-6)
        # exact version: a float64 rigid motion G of the source turns T into T G^-1
        motion = _random_transform(3, torch.Generator().manual_seed(5))
        moved = model(se3.transform_points(motion, src), ref).transform_ref_src
        expected = se3.compose(model(src, ref).transform_ref_src, se3.inverse(motion))
    torch.testing.assert_close(moved, expected, atol=1e-9, rtol=0)


def test_exact_on_the_moved_same_points_untrained(batch: RegistrationBatch) -> None:
    # With RRI, gamma depends only on the shape: a permuted, rigidly moved copy gives the same mixture, moved.
    model = _model().double().eval()
    gen = torch.Generator().manual_seed(3)
    src = batch.points_src.double()
    transform = _random_transform(3, gen)
    ref = se3.transform_points(transform, src)[:, torch.randperm(96, generator=gen)]
    with torch.no_grad():
        result = model(src, ref)
    torch.testing.assert_close(result.transform_ref_src, transform, atol=1e-8, rtol=0)
    torch.testing.assert_close(result.aux["transform_21"], se3.inverse(transform), atol=1e-8, rtol=0)


def test_encoder_features_are_rotation_invariant_on_lc_subsets() -> None:
    encoder = DeepGMREncoder(d_model=32, k=20).double().eval()
    gen = torch.Generator().manual_seed(4)
    points = torch.randn(2, 64, 3, generator=gen, dtype=torch.float64)
    moved = se3.transform_points(_random_transform(2, gen), points)
    with torch.no_grad():
        feats = encoder(points)
        assert feats.shape == (2, 64, 32) and encoder.out_channels == 32
        torch.testing.assert_close(encoder(moved), feats, atol=1e-9, rtol=0)


def test_without_rri_inputs_are_cloud_centred() -> None:
    # Regression for the original's non-RRI input (mean over coordinates, not over points).
    encoder = DeepGMREncoder(d_model=16, use_rri=False).double().eval()
    points = torch.randn(2, 50, 3, dtype=torch.float64)
    shift = torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64)
    torch.testing.assert_close(encoder.input_features(points).mean(dim=1), torch.zeros(2, 3, dtype=torch.float64))
    with torch.no_grad():
        torch.testing.assert_close(encoder(points + shift), encoder(points), atol=1e-10, rtol=0)
