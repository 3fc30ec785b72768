from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist

from lcreg.checks import ShapeError, TooFewPointsError
from lcreg.geometry import neighbors
from lcreg.geometry.neighbors import (
    EXACT_MAX_DIM,
    gather_points,
    knn,
    knn_indices,
    neighbour_max,
    pairwise_sq_distances,
    safe_norm,
)

TOL = {torch.float32: 1e-5, torch.float64: 1e-12}


def test_pairwise_sq_distances_matches_scipy(dtype: torch.dtype) -> None:
    gen = np.random.default_rng(0)
    a, b = gen.normal(size=(3, 20, 5)), gen.normal(size=(3, 30, 5))
    got = pairwise_sq_distances(torch.tensor(a, dtype=dtype), torch.tensor(b, dtype=dtype))
    assert got.shape == (3, 20, 30) and got.dtype == dtype
    expected = np.stack([cdist(a[i], b[i], "sqeuclidean") for i in range(3)])
    np.testing.assert_allclose(got.double().numpy(), expected, atol=10 * TOL[dtype], rtol=TOL[dtype])


def test_pairwise_sq_distances_far_from_origin_and_nonnegative() -> None:
    gen = np.random.default_rng(1)
    # A small cloud far away: the raw |a|^2 - 2ab + |b|^2 expansion would lose every digit in float32.
    a = torch.tensor(gen.normal(size=(1, 50, 3)) * 1e-2 + 1e3, dtype=torch.float32)
    got = pairwise_sq_distances(a, a)
    assert (got >= 0).all()
    expected = cdist(a[0].double().numpy(), a[0].double().numpy(), "sqeuclidean")
    np.testing.assert_allclose(got[0].double().numpy(), expected, atol=1e-9, rtol=1e-4)


def _brute_force(query: torch.Tensor, points: torch.Tensor) -> np.ndarray:
    """float64 distances ``(B, Q, N)`` of the (float32) points, by explicit differences."""
    q, p = query.double().numpy(), points.double().numpy()
    return np.sqrt(((q[:, :, None, :] - p[:, None, :, :]) ** 2).sum(-1))


@pytest.mark.parametrize("dim", [3, 5, 64])
def test_cdist_matches_brute_force_far_from_the_origin(dim: int) -> None:
    """Both modes stay accurate 1 km from the origin (exact sums for D <= 3, centroid-shifted product above)."""
    gen = torch.Generator().manual_seed(7)
    a = torch.randn(2, 70, dim, generator=gen) + 1e3
    b = torch.randn(2, 90, dim, generator=gen) + 1e3
    expected = _brute_force(a, b)
    got = neighbors.cdist(a, b)
    assert got.shape == (2, 70, 90) and got.dtype == torch.float32
    rtol = 1e-6 if dim <= EXACT_MAX_DIM else 1e-4
    np.testing.assert_allclose(got.double().numpy(), expected, rtol=rtol)


def test_cdist_plain_matrix_product_would_fail_far_away() -> None:
    """Why the exact mode: torch.cdist's unshifted matrix product loses the neighbours of float32 points at 1 km."""
    gen = torch.Generator().manual_seed(8)
    a, b = torch.randn(1, 200, 3, generator=gen) + 1e3, torch.randn(1, 300, 3, generator=gen) + 1e3
    truth = _brute_force(a, b).argmin(-1)
    assert (neighbors.cdist(a, b).argmin(-1).numpy() == truth).all()
    plain = torch.cdist(a, b, compute_mode="use_mm_for_euclid_dist").argmin(-1).numpy()
    assert (plain != truth).mean() > 0.5


@pytest.mark.parametrize("dim", [3, 5])
def test_pairwise_sq_distances_gradcheck(dim: int) -> None:
    gen = torch.Generator().manual_seed(9)
    a = torch.randn(2, 5, dim, generator=gen, dtype=torch.float64, requires_grad=True)
    b = torch.randn(2, 4, dim, generator=gen, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(pairwise_sq_distances, (a, b))


@pytest.mark.parametrize("offset", [0.0, 1e3])
def test_knn_equals_a_brute_force_reference(offset: float) -> None:
    """float32 kNN = float64 brute force on the same points: indices (no ties here), distances to 1e-6 relative."""
    gen = torch.Generator().manual_seed(10)
    query = torch.randn(3, 64, 3, generator=gen) + offset
    points = torch.randn(3, 500, 3, generator=gen) + offset
    dists, idx = knn(query, points, 8)
    reference = _brute_force(query, points)
    ref_idx = np.argsort(reference, axis=-1, kind="stable")[..., :8]
    np.testing.assert_array_equal(idx.numpy(), ref_idx)
    np.testing.assert_allclose(dists.double().numpy(), np.take_along_axis(reference, ref_idx, -1), rtol=1e-6)


def test_knn_indices_in_feature_space_match_brute_force() -> None:
    """Wide features (matrix-product mode, as DGCNN's dynamic graph uses it)."""
    gen = torch.Generator().manual_seed(11)
    features = torch.randn(2, 128, 64, generator=gen, dtype=torch.float64)
    idx = knn_indices(features, features, 10)
    ref_idx = np.argsort(_brute_force(features, features), axis=-1, kind="stable")[..., :10]
    np.testing.assert_array_equal(idx.numpy(), ref_idx)


@pytest.mark.parametrize("k", [1, 4, 16])
def test_knn_matches_ckdtree(dtype: torch.dtype, k: int) -> None:
    gen = np.random.default_rng(2)
    query, points = gen.normal(size=(2, 40, 3)), gen.normal(size=(2, 100, 3))
    dists, idx = knn(torch.tensor(query, dtype=dtype), torch.tensor(points, dtype=dtype), k)
    assert dists.shape == idx.shape == (2, 40, k) and idx.dtype == torch.int64 and dists.dtype == dtype
    for b in range(2):
        ref_d, ref_i = cKDTree(points[b]).query(query[b], k=k)
        np.testing.assert_allclose(dists[b].double().numpy(), ref_d.reshape(40, k), atol=TOL[dtype])
        np.testing.assert_array_equal(idx[b].numpy(), ref_i.reshape(40, k))
    assert (dists[..., 1:] >= dists[..., :-1]).all()


def test_knn_chunked_equals_unchunked(monkeypatch: pytest.MonkeyPatch) -> None:
    gen = torch.Generator().manual_seed(3)
    query, points = torch.randn(2, 37, 3, generator=gen), torch.randn(2, 50, 3, generator=gen)
    full = knn(query, points, 5)
    monkeypatch.setattr(neighbors, "_CHUNK_ELEMENTS", 2 * 50 * 4)  # chunks of 4 queries, the last one shorter
    chunked = knn(query, points, 5)
    assert torch.equal(full[1], chunked[1]) and torch.equal(full[0], chunked[0])


def test_knn_self_query_and_gradients(dtype: torch.dtype) -> None:
    points = torch.randn(2, 30, 3, generator=torch.Generator().manual_seed(4), dtype=dtype).requires_grad_(True)
    dists, idx = knn(points, points, 3)
    assert torch.equal(idx[..., 0], torch.arange(30).expand(2, 30))
    assert (dists[..., 0] == 0).all()
    dists.sum().backward()
    assert points.grad is not None and torch.isfinite(points.grad).all()


def test_knn_gradcheck() -> None:
    gen = torch.Generator().manual_seed(5)
    query = torch.randn(1, 4, 3, generator=gen, dtype=torch.float64, requires_grad=True)
    points = torch.randn(1, 9, 3, generator=gen, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda q, p: knn(q, p, 3)[0], (query, points))


def test_knn_errors() -> None:
    points = torch.randn(2, 5, 3)
    with pytest.raises(TooFewPointsError, match="k=6"):
        knn(points, points, 6)
    with pytest.raises(ValueError, match="`k`"):
        knn(points, points, 0)
    with pytest.raises(ShapeError, match="points"):
        knn(points, torch.randn(3, 5, 3), 2)
    with pytest.raises(ShapeError, match="query"):
        knn(torch.randn(2, 5, 2), points, 2)
    with pytest.raises(TypeError, match="points"):
        knn(points, points.double(), 2)


def test_gather_points_matches_numpy_indexing() -> None:
    gen = torch.Generator().manual_seed(6)
    points = torch.randn(3, 10, 4, generator=gen)
    idx = torch.randint(0, 10, (3, 5, 2), generator=gen)
    got = gather_points(points, idx)
    assert got.shape == (3, 5, 2, 4)
    expected = np.stack([points[b].numpy()[idx[b].numpy()] for b in range(3)])
    np.testing.assert_array_equal(got.numpy(), expected)
    assert gather_points(points, idx[:, 0, 0]).shape == (3, 4)  # idx (B,) -> (B, C)


def test_gather_points_errors() -> None:
    points = torch.randn(2, 10, 3)
    with pytest.raises(TypeError, match="idx"):
        gather_points(points, torch.zeros(2, 4))
    with pytest.raises(ShapeError, match="idx"):
        gather_points(points, torch.zeros(3, 4, dtype=torch.long))
    with pytest.raises(ShapeError, match="points"):
        gather_points(torch.randn(10, 3), torch.zeros(10, 4, dtype=torch.long))


def test_safe_norm_value_and_gradient_at_zero(dtype: torch.dtype) -> None:
    x = torch.tensor([[0.0, 0.0, 0.0], [3.0, 4.0, 0.0]], dtype=dtype, requires_grad=True)
    norm = safe_norm(x)
    torch.testing.assert_close(norm, torch.tensor([0.0, 5.0], dtype=dtype))
    norm.sum().backward()
    assert x.grad is not None
    torch.testing.assert_close(x.grad, torch.tensor([[0.0, 0.0, 0.0], [0.6, 0.8, 0.0]], dtype=dtype))


def test_gather_points_from_an_empty_cloud_is_a_typed_error() -> None:
    from lcreg.checks import TooFewPointsError

    with pytest.raises(TooFewPointsError, match="`points` has no rows"):  # was an index-out-of-bounds RuntimeError
        gather_points(torch.zeros(2, 0, 3), torch.zeros(2, 5, dtype=torch.long))
    assert gather_points(torch.zeros(2, 0, 3), torch.zeros(2, 0, dtype=torch.long)).shape == (2, 0, 3)


def test_neighbour_max_equals_amax_and_its_gradient_without_ties() -> None:
    gen = torch.Generator().manual_seed(0)
    values = torch.randn(2, 5, 6, 3, generator=gen, dtype=torch.float64, requires_grad=True)
    grad = torch.randn(2, 5, 3, generator=gen, dtype=torch.float64)
    out = neighbour_max(values)
    assert out.shape == (2, 5, 3) and torch.equal(out, values.detach().amax(dim=2))
    (ours,) = torch.autograd.grad(out, values, grad)
    (reference,) = torch.autograd.grad(values.amax(dim=2), values, grad)
    assert torch.equal(ours, reference)
    assert torch.autograd.gradcheck(neighbour_max, (values,))


def test_neighbour_max_at_a_tie_keeps_the_neighbour_sum_of_the_gradient() -> None:
    values = torch.tensor([[[[1.0], [3.0], [3.0], [2.0]]]], requires_grad=True)  # (1, 1, 4, 1): neighbours 1, 2 tie
    (grad,) = torch.autograd.grad(neighbour_max(values), values, torch.tensor([[[2.0]]]))
    assert grad[0, 0, [0, 3], 0].tolist() == [0.0, 0.0]  # only tied neighbours receive it
    assert sorted(grad[0, 0, [1, 2], 0].tolist()) == [0.0, 2.0]  # one of them, whole (amax: 1.0 each)
    assert float(grad.sum()) == 2.0


def test_neighbour_max_rejects_other_shapes() -> None:
    with pytest.raises(ShapeError, match="values"):
        neighbour_max(torch.zeros(2, 5, 3))
    with pytest.raises(ShapeError, match="values"):
        neighbour_max(torch.zeros(2, 5, 0, 3))
