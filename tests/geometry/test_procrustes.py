from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from lcreg.checks import NonFiniteError, ShapeError
from lcreg.geometry.procrustes import weighted_kabsch
from lcreg.geometry.random_transforms import random_rotation
from lcreg.geometry.se3 import make_transform, transform_points

TOL = {torch.float32: 1e-4, torch.float64: 1e-10}


def reference_kabsch(src: np.ndarray, ref: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Independent reference: scipy's weighted ``align_vectors`` on centred points, then the translation."""
    w = weights / weights.sum()
    c_src, c_ref = w @ src, w @ ref
    rot, _ = Rotation.align_vectors(ref - c_ref, src - c_src, weights=weights)
    out = np.eye(4)
    out[:3, :3] = rot.as_matrix()
    out[:3, 3] = c_ref - out[:3, :3] @ c_src
    return out


def random_problem(batch: int, num: int, dtype: torch.dtype, seed: int = 0) -> tuple[torch.Tensor, ...]:
    gen = torch.Generator().manual_seed(seed)
    src = torch.randn(batch, num, 3, generator=gen, dtype=dtype)
    transform = make_transform(random_rotation(batch, gen, dtype), torch.randn(batch, 3, generator=gen, dtype=dtype))
    return src, transform, transform_points(transform, src)


def test_recovers_known_transform(dtype: torch.dtype) -> None:
    src, transform, ref = random_problem(8, 50, dtype)
    torch.testing.assert_close(weighted_kabsch(src, ref), transform, atol=TOL[dtype], rtol=0)
    weights = torch.rand(8, 50, generator=torch.Generator().manual_seed(1), dtype=dtype)
    torch.testing.assert_close(weighted_kabsch(src, ref, weights), transform, atol=TOL[dtype], rtol=0)


def test_zero_weights_ignore_outliers(dtype: torch.dtype) -> None:
    src, transform, ref = random_problem(4, 40, dtype, seed=2)
    ref = ref.clone()
    ref[:, :10] += 5 * torch.randn(4, 10, 3, generator=torch.Generator().manual_seed(3), dtype=dtype)
    weights = torch.ones(4, 40, dtype=dtype)
    weights[:, :10] = 0
    torch.testing.assert_close(weighted_kabsch(src, ref, weights), transform, atol=TOL[dtype], rtol=0)


def test_matches_scipy_reference_with_noise_and_weights() -> None:
    gen = np.random.default_rng(4)
    src = gen.normal(size=(5, 30, 3))
    weights = gen.uniform(0.1, 2.0, size=(5, 30))
    ref = src @ Rotation.random(5, random_state=5).as_matrix().transpose(0, 2, 1) + gen.normal(size=(5, 1, 3))
    ref += 0.05 * gen.normal(size=ref.shape)
    got = weighted_kabsch(torch.tensor(src), torch.tensor(ref), torch.tensor(weights)).numpy()
    for b in range(5):
        np.testing.assert_allclose(got[b], reference_kabsch(src[b], ref[b], weights[b]), atol=1e-10)


def test_mirrored_data_gives_a_proper_rotation(dtype: torch.dtype) -> None:
    # The best orthogonal map onto a mirrored cloud is the reflection itself (det -1): naive SVD returns it.
    gen = np.random.default_rng(6)
    src = gen.normal(size=(1, 30, 3)) * np.array([3.0, 2.0, 1.0])
    ref = src * np.array([1.0, 1.0, -1.0])
    got = weighted_kabsch(torch.tensor(src, dtype=dtype), torch.tensor(ref, dtype=dtype)).double().numpy()[0]
    assert np.linalg.det(got[:3, :3]) == pytest.approx(1.0, abs=1e-5)
    np.testing.assert_allclose(got[:3, :3].T @ got[:3, :3], np.eye(3), atol=1e-5)
    np.testing.assert_allclose(got, reference_kabsch(src[0], ref[0], np.ones(30)), atol=1e-4)


def test_planar_data_is_recovered_with_det_plus_one(dtype: torch.dtype) -> None:
    gen = torch.Generator().manual_seed(7)
    src = torch.randn(16, 20, 3, generator=gen, dtype=dtype)
    src[..., 2] = 0  # rank-2 cross-covariance: the third singular vector's sign is arbitrary
    transform = make_transform(random_rotation(16, gen, dtype), torch.randn(16, 3, generator=gen, dtype=dtype))
    got = weighted_kabsch(src, transform_points(transform, src))
    torch.testing.assert_close(torch.linalg.det(got[:, :3, :3]), torch.ones(16, dtype=dtype), atol=1e-5, rtol=0)
    torch.testing.assert_close(got, transform, atol=10 * TOL[dtype], rtol=0)


def test_batched_matches_per_item(dtype: torch.dtype) -> None:
    src, _, ref = random_problem(4, 12, dtype, seed=8)
    ref = ref + 0.1 * torch.randn(ref.shape, generator=torch.Generator().manual_seed(9), dtype=dtype)
    weights = torch.rand(4, 12, generator=torch.Generator().manual_seed(10), dtype=dtype)
    batched = weighted_kabsch(src, ref, weights)
    for b in range(4):
        single = weighted_kabsch(src[b : b + 1], ref[b : b + 1], weights[b : b + 1])
        torch.testing.assert_close(batched[b : b + 1], single, atol=TOL[dtype], rtol=0)


def test_gradcheck() -> None:
    src, _, ref = random_problem(2, 6, torch.float64, seed=11)
    ref = ref + 0.1 * torch.randn(ref.shape, generator=torch.Generator().manual_seed(12), dtype=torch.float64)
    weights = torch.rand(2, 6, generator=torch.Generator().manual_seed(13), dtype=torch.float64) + 0.5
    inputs = (src.requires_grad_(True), ref.requires_grad_(True), weights.requires_grad_(True))
    assert torch.autograd.gradcheck(weighted_kabsch, inputs)


def test_bad_inputs() -> None:
    src, _, ref = random_problem(2, 5, torch.float32)
    with pytest.raises(ValueError, match="non-negative"):
        weighted_kabsch(src, ref, torch.tensor([[1.0, -1.0, 1.0, 1.0, 1.0], [1.0] * 5]))
    with pytest.raises(ValueError, match="positive sum"):
        weighted_kabsch(src, ref, torch.tensor([[0.0] * 5, [1.0] * 5]))
    with pytest.raises(ShapeError, match="weights"):
        weighted_kabsch(src, ref, torch.ones(2, 4))
    with pytest.raises(NonFiniteError, match="weights"):
        weighted_kabsch(src, ref, torch.tensor([[float("nan")] + [1.0] * 4, [1.0] * 5]))
    with pytest.raises(TypeError, match="weights"):
        weighted_kabsch(src, ref, torch.ones(2, 5, dtype=torch.int64))
    with pytest.raises(TypeError, match="weights"):
        weighted_kabsch(src, ref, torch.ones(2, 5, dtype=torch.float64))
    with pytest.raises(ShapeError, match="points_ref"):
        weighted_kabsch(src, ref[:, :4])
    with pytest.raises(ShapeError, match="points_ref"):
        weighted_kabsch(src, ref[:1])
    with pytest.raises(TypeError, match="points_ref"):
        weighted_kabsch(src, ref.double())
    with pytest.raises(NonFiniteError, match="points_src"):
        weighted_kabsch(src * float("inf"), ref)
