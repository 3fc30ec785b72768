from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from lcreg.geometry import se3, so3
from lcreg.nn.correspondence import similarity_scores, soft_correspondence_transform


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _transform(b: int, seed: int) -> torch.Tensor:
    gen = _gen(seed)
    rot = so3.exp(torch.randn(b, 3, generator=gen, dtype=torch.float64))
    return se3.make_transform(rot, torch.randn(b, 3, generator=gen, dtype=torch.float64))


def _numpy_kabsch(src: np.ndarray, ref: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Weighted Kabsch for one pair, written with NumPy."""
    w = w / w.sum()
    mu_s, mu_r = w @ src, w @ ref
    u, _, vt = np.linalg.svd((src - mu_s).T @ ((ref - mu_r) * w[:, None]))
    rot = vt.T @ np.diag([1.0, 1.0, np.sign(np.linalg.det(vt.T @ u.T))]) @ u.T
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = rot, mu_r - rot @ mu_s
    return out


def test_similarity_scores_are_scaled_dot_products() -> None:
    a = torch.randn(2, 4, 6, generator=_gen(0), dtype=torch.float64)
    b = torch.randn(2, 5, 6, generator=_gen(1), dtype=torch.float64)
    scores = similarity_scores(a, b)
    assert scores.shape == (2, 4, 5)
    for i in range(2):
        for n in range(4):
            for m in range(5):
                assert float(scores[i, n, m]) == pytest.approx(float((a[i, n] * b[i, m]).sum()) / math.sqrt(6))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_one_hot_probabilities_recover_a_known_transform(dtype: torch.dtype) -> None:
    """Reference = shuffled, moved source; the one-hot matching of the true pairs gives back the transform."""
    b, n = 3, 40
    src = torch.randn(b, n, 3, generator=_gen(2), dtype=torch.float64)
    transform = _transform(b, seed=3)
    perm = torch.stack([torch.randperm(n, generator=_gen(10 + i)) for i in range(b)])  # ref[j] = T src[perm[j]]
    ref = torch.gather(se3.transform_points(transform, src), 1, perm[..., None].expand(-1, -1, 3))
    inverse = perm.argsort(dim=1)  # src i sits at ref position inverse[i]
    probs = torch.nn.functional.one_hot(inverse, n).to(dtype)
    estimate, matched = soft_correspondence_transform(src.to(dtype), ref.to(dtype), probs)
    tol = 1e-10 if dtype == torch.float64 else 1e-4
    torch.testing.assert_close(matched, se3.transform_points(transform, src).to(dtype), atol=tol, rtol=0)
    torch.testing.assert_close(estimate, transform.to(dtype), atol=tol, rtol=0)


def test_soft_probabilities_match_a_numpy_weighted_kabsch() -> None:
    b, n, m = 2, 12, 9
    src = torch.randn(b, n, 3, generator=_gen(4), dtype=torch.float64)
    ref = torch.randn(b, m, 3, generator=_gen(5), dtype=torch.float64)
    probs = torch.softmax(3 * torch.randn(b, n, m, generator=_gen(6), dtype=torch.float64), dim=-1)
    weights = torch.rand(b, n, generator=_gen(7), dtype=torch.float64) + 0.1
    for w in (None, weights):
        estimate, matched = soft_correspondence_transform(src, ref, probs, w)
        for i in range(b):
            y_hat = probs[i].numpy() @ ref[i].numpy()
            np.testing.assert_allclose(matched[i].numpy(), y_hat, atol=1e-12)
            w_i = np.ones(n) if w is None else w[i].numpy()
            np.testing.assert_allclose(estimate[i].numpy(), _numpy_kabsch(src[i].numpy(), y_hat, w_i), atol=1e-10)


def test_weights_ignore_corrupted_matches() -> None:
    b, n = 2, 30
    src = torch.randn(b, n, 3, generator=_gen(8), dtype=torch.float64)
    transform = _transform(b, seed=9)
    ref = se3.transform_points(transform, src)
    probs = torch.eye(n, dtype=torch.float64).expand(b, n, n).clone()
    probs[:, :5] = torch.roll(probs[:, :5], shifts=7, dims=-1)  # five wrong matches
    weights = torch.ones(b, n, dtype=torch.float64)
    weights[:, :5] = 0
    estimate, _ = soft_correspondence_transform(src, ref, probs, weights)
    torch.testing.assert_close(estimate, transform, atol=1e-10, rtol=0)
    unweighted, _ = soft_correspondence_transform(src, ref, probs)
    assert not torch.allclose(unweighted, transform, atol=1e-3)


def test_rigid_equivariance_with_fixed_probabilities() -> None:
    """T(G x, H y) = H T(x, y) G^-1 exactly: the soft matches move with the reference and rows sum to one."""
    b, n, m = 2, 15, 11
    src = torch.randn(b, n, 3, generator=_gen(11), dtype=torch.float64)
    ref = torch.randn(b, m, 3, generator=_gen(12), dtype=torch.float64)
    probs = torch.softmax(2 * torch.randn(b, n, m, generator=_gen(13), dtype=torch.float64), dim=-1)
    g, h = _transform(b, seed=14), _transform(b, seed=15)
    base, _ = soft_correspondence_transform(src, ref, probs)
    moved, _ = soft_correspondence_transform(se3.transform_points(g, src), se3.transform_points(h, ref), probs)
    torch.testing.assert_close(moved, h @ base @ se3.inverse(g), atol=1e-10, rtol=0)


def test_gradcheck_through_the_probabilities() -> None:
    src = torch.randn(1, 6, 3, generator=_gen(16), dtype=torch.float64)
    ref = torch.randn(1, 5, 3, generator=_gen(17), dtype=torch.float64)
    logits = torch.randn(1, 6, 5, generator=_gen(18), dtype=torch.float64, requires_grad=True)

    def fn(lg: torch.Tensor) -> torch.Tensor:
        return soft_correspondence_transform(src, ref, torch.softmax(lg, dim=-1))[0]

    assert torch.autograd.gradcheck(fn, (logits,))
