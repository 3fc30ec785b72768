from __future__ import annotations

import contextlib
import time

import numpy as np
import pytest
import torch
from scipy.spatial.distance import cdist

from lcreg.checks import NonFiniteError, ShapeError
from lcreg.geometry import chamfer
from lcreg.geometry.chamfer import chamfer_distance
from lcreg.reference import reference_mode


def brute_force(a: np.ndarray, b: np.ndarray, squared: bool) -> np.ndarray:
    out = []
    for x, y in zip(a, b):
        d = cdist(x, y, "sqeuclidean" if squared else "euclidean")
        out.append(d.min(1).mean() + d.min(0).mean())
    return np.array(out)


@pytest.mark.parametrize("squared", [False, True])
def test_matches_brute_force(dtype: torch.dtype, squared: bool) -> None:
    gen = np.random.default_rng(0)
    a, b = gen.normal(size=(3, 40, 3)), gen.normal(size=(3, 25, 3)) + 0.3
    got = chamfer_distance(torch.tensor(a, dtype=dtype), torch.tensor(b, dtype=dtype), squared=squared)
    assert got.shape == (3,) and got.dtype == dtype
    np.testing.assert_allclose(got.double().numpy(), brute_force(a, b, squared), rtol=1e-5)


@pytest.mark.parametrize("offset", [0.0, 1e3])
def test_float32_matches_a_float64_brute_force_on_the_same_points(offset: float) -> None:
    gen = torch.Generator().manual_seed(5)
    a = torch.randn(4, 300, 3, generator=gen) + offset
    b = torch.randn(4, 200, 3, generator=gen) + offset + 0.1
    expected = brute_force(a.double().numpy(), b.double().numpy(), squared=False)
    np.testing.assert_allclose(chamfer_distance(a, b).double().numpy(), expected, rtol=1e-6)


def test_hand_made_value() -> None:
    a = torch.tensor([[[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]]])
    b = torch.tensor([[[0.0, 1.0, 0.0]]])
    # a -> b: distances 1 and sqrt(5); b -> a: 1.
    torch.testing.assert_close(chamfer_distance(a, b), torch.tensor([(1 + 5**0.5) / 2 + 1]))
    torch.testing.assert_close(chamfer_distance(a, b, squared=True), torch.tensor([(1 + 5) / 2 + 1.0]))


def test_symmetry_permutation_invariance_and_zero(dtype: torch.dtype, rng: torch.Generator) -> None:
    a, b = torch.randn(2, 30, 3, generator=rng, dtype=dtype), torch.randn(2, 20, 3, generator=rng, dtype=dtype)
    torch.testing.assert_close(chamfer_distance(a, b), chamfer_distance(b, a))
    perm = torch.randperm(30, generator=rng)
    torch.testing.assert_close(chamfer_distance(a[:, perm], b), chamfer_distance(a, b))
    assert torch.equal(chamfer_distance(a, a), torch.zeros(2, dtype=dtype))


@pytest.mark.parametrize("squared", [False, True])
def test_finite_gradient_when_clouds_coincide(dtype: torch.dtype, squared: bool) -> None:
    a = torch.randn(2, 16, 3, generator=torch.Generator().manual_seed(1), dtype=dtype)
    b = torch.cat([a[:, :8], a[:, 8:] + 0.5], dim=1).requires_grad_(True)  # half of the points coincide
    a.requires_grad_(True)
    chamfer_distance(a, a.detach().clone().requires_grad_(True), squared).sum().backward()
    assert a.grad is not None and torch.isfinite(a.grad).all() and (a.grad == 0).all()
    a.grad = None
    chamfer_distance(a, b, squared).sum().backward()
    assert torch.isfinite(a.grad).all() and b.grad is not None and torch.isfinite(b.grad).all()


def test_gradcheck() -> None:
    gen = torch.Generator().manual_seed(2)
    a = torch.randn(2, 4, 3, generator=gen, dtype=torch.float64, requires_grad=True)
    b = torch.randn(2, 3, 3, generator=gen, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(chamfer_distance, (a, b))
    assert torch.autograd.gradcheck(lambda x, y: chamfer_distance(x, y, squared=True), (a, b))


def test_chunked_equals_unchunked(monkeypatch: pytest.MonkeyPatch) -> None:
    gen = torch.Generator().manual_seed(3)
    a, b = torch.randn(2, 53, 3, generator=gen), torch.randn(2, 31, 3, generator=gen)
    with reference_mode():  # the distance-matrix search (the k-d trees do not chunk)
        full = chamfer_distance(a, b)
        monkeypatch.setattr(chamfer, "_CHUNK_ELEMENTS", 2 * 31 * 5)  # chunks of 5 points of `a`
        assert torch.equal(chamfer_distance(a, b), full)


@pytest.mark.parametrize("sizes", [(53, 31), (200, 200), (7, 64)])
def test_kdtree_search_finds_the_distance_matrix_neighbours(dtype: torch.dtype, sizes: tuple[int, int]) -> None:
    gen = torch.Generator().manual_seed(5)
    a = torch.randn(3, sizes[0], 3, generator=gen, dtype=dtype)
    b = torch.randn(3, sizes[1], 3, generator=gen, dtype=dtype) * 0.7 + 0.1
    idx_ab, idx_ba = chamfer._nearest_both_ways_kdtree(a, b)
    dense_ab, dense_ba = chamfer._nearest_both_ways_dense(a, b)
    assert idx_ab.dtype == idx_ba.dtype == torch.int64
    assert idx_ab.shape == (3, sizes[0]) and idx_ba.shape == (3, sizes[1])
    assert torch.equal(idx_ab, dense_ab) and torch.equal(idx_ba, dense_ba)


def test_kdtree_path_matches_the_reference_values_and_gradients(dtype: torch.dtype) -> None:
    gen = torch.Generator().manual_seed(6)
    a0, b0 = torch.randn(2, 40, 3, generator=gen, dtype=dtype), torch.randn(2, 25, 3, generator=gen, dtype=dtype)
    results = []
    for reference in (True, False):
        a, b = a0.clone().requires_grad_(True), b0.clone().requires_grad_(True)
        with reference_mode() if reference else contextlib.nullcontext():
            value = chamfer_distance(a, b)
        value.sum().backward()
        results.append((value.detach(), a.grad, b.grad))
    for ref, fast in zip(*results):
        torch.testing.assert_close(fast, ref)


def test_large_batch_forward_and_backward_is_fast() -> None:
    gen = torch.Generator().manual_seed(4)
    a = torch.randn(32, 1024, 3, generator=gen, requires_grad=True)
    b = torch.randn(32, 1024, 3, generator=gen)
    start = time.perf_counter()
    chamfer_distance(a, b).mean().backward()
    assert time.perf_counter() - start < 10.0
    assert a.grad is not None and torch.isfinite(a.grad).all()


def test_errors() -> None:
    a = torch.randn(2, 5, 3)
    with pytest.raises(ShapeError, match="points_b"):
        chamfer_distance(a, torch.randn(3, 5, 3))
    with pytest.raises(ShapeError, match="points_a"):
        chamfer_distance(torch.randn(2, 5, 2), a)
    with pytest.raises(TypeError, match="points_b"):
        chamfer_distance(a, a.double())
    with pytest.raises(NonFiniteError, match="points_a"):
        chamfer_distance(a * float("nan"), a)
