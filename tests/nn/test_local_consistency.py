from __future__ import annotations

import io

import numpy as np
import pytest
import torch
from torch import nn
from torch.distributions import Categorical, kl_divergence

from lcreg.checks import TooFewPointsError
from lcreg.data.synthetic import synthetic_shapes
from lcreg.geometry import se3, so3
from lcreg.nn.local_consistency import LocalConsistency, barycenter_subsets
from lcreg.nn.pointnet import PointNetEncoder

K = 32


def _encoder(seed: int = 0) -> PointNetEncoder:
    torch.manual_seed(seed)
    return PointNetEncoder((16, K)).double().eval()


def _clouds(b: int = 2, n: int = 128, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Source shapes, a random rigid motion and the moved (same-sampling) reference."""
    points, _, _ = synthetic_shapes(b, n, seed=seed)
    src = torch.tensor(points, dtype=torch.float64)
    gen = torch.Generator().manual_seed(seed)
    transform = se3.make_transform(
        so3.exp(torch.randn(b, 3, generator=gen, dtype=torch.float64)),
        torch.randn(b, 3, generator=gen, dtype=torch.float64),
    )
    return src, se3.transform_points(transform, src), transform


def _brute_force(points: np.ndarray, k: int, cap: np.ndarray | None = None) -> tuple[list[set], list[set]]:
    """Farthest (among distances <= cap) and closest point to the barycenter, and their k nearest neighbours."""
    far_sets, close_sets = [], []
    for i, cloud in enumerate(points):
        dist = np.linalg.norm(cloud - cloud.mean(0), axis=1)
        eligible = np.flatnonzero(dist <= (np.inf if cap is None else cap[i]))
        far = eligible[np.argmax(dist[eligible])]
        close = int(np.argmin(dist))
        for anchor, out in ((far, far_sets), (close, close_sets)):
            d = np.linalg.norm(cloud - cloud[anchor], axis=1)
            out.append(set(np.argsort(d, kind="stable")[:k].tolist()))
    return far_sets, close_sets


def _as_sets(idx: torch.Tensor) -> list[set]:
    return [set(row.tolist()) for row in idx]


def test_barycenter_subsets_match_brute_force() -> None:
    gen = torch.Generator().manual_seed(0)
    points = torch.randn(3, 100, 3, generator=gen, dtype=torch.float64) * torch.tensor([1.0, 0.5, 0.2])
    idx_far, idx_close = barycenter_subsets(points, 10)
    assert idx_far.shape == (3, 10) and idx_far.dtype == torch.int64
    far, close = _brute_force(points.numpy(), 10)
    assert _as_sets(idx_far) == far
    assert _as_sets(idx_close) == close
    # The anchors themselves are in their subsets, and the two subsets are disjoint for this anisotropic cloud.
    dist = (points - points.mean(1, keepdim=True)).norm(dim=-1)
    for b in range(3):
        assert int(dist[b].argmax()) in far[b] and int(dist[b].argmin()) in close[b]
        assert not far[b] & close[b]


def test_subsets_invariant_to_rigid_motion_and_permutation() -> None:
    src, ref, _ = _clouds()
    far_src, close_src = barycenter_subsets(src, 16)
    far_ref, close_ref = barycenter_subsets(ref, 16)
    assert _as_sets(far_src) == _as_sets(far_ref)
    assert _as_sets(close_src) == _as_sets(close_ref)
    perm = torch.randperm(src.shape[1], generator=torch.Generator().manual_seed(1))
    far_p, close_p = barycenter_subsets(src[:, perm], 16)
    assert _as_sets(perm[far_p]) == _as_sets(far_src)  # the same points, whatever their order
    assert _as_sets(perm[close_p]) == _as_sets(close_src)
    lc = LocalConsistency(feature_dim=K, num_local_points=16)
    x1, x2 = lc.subsets(src)
    assert x1.shape == x2.shape == (2, 16, 3)
    torch.testing.assert_close(x1, src[torch.arange(2)[:, None], far_src])


def test_outlier_threshold_and_quantile_exclude_far_points() -> None:
    gen = torch.Generator().manual_seed(2)
    points = torch.randn(2, 200, 3, generator=gen, dtype=torch.float64) * 0.3
    points[:, 7] = torch.tensor([8.0, 0.0, 0.0], dtype=torch.float64)  # an isolated outlier
    far, _ = barycenter_subsets(points, 8)
    assert (far == 7).any(dim=1).all()  # without rejection the outlier is x_f
    for kwargs in ({"outlier_threshold": 2.0}, {"outlier_quantile": 0.98}):
        far_robust, _ = barycenter_subsets(points, 8, **kwargs)
        assert not (far_robust == 7).any(), kwargs
        dist = (points - points.mean(1, keepdim=True)).norm(dim=-1).numpy()
        cap = np.full(2, 2.0) if "outlier_threshold" in kwargs else np.quantile(dist, 0.98, axis=1)
        expected, _ = _brute_force(points.numpy(), 8, cap)
        assert _as_sets(far_robust) == expected
    # A threshold below every distance falls back to a valid anchor instead of failing.
    far_all_rejected, _ = barycenter_subsets(points, 8, outlier_threshold=1e-9)
    assert far_all_rejected.shape == (2, 8)


def _manual_sym_kl(
    lc: LocalConsistency, enc: nn.Module, src: torch.Tensor, w1: torch.Tensor, w2: torch.Tensor
) -> torch.Tensor:
    x1, x2 = lc.subsets(src)

    def feat(points: torch.Tensor) -> torch.Tensor:
        f = enc(points)
        if not lc.standardize:
            return f
        centred = f - f.mean(-1, keepdim=True)
        return centred / (centred.pow(2).sum(-1, keepdim=True) / (f.shape[-1] - 1)).sqrt()

    with torch.no_grad():
        tau1 = lc.metric(torch.cat([feat(x1), feat(w1)], -1)) / lc.temperature
        tau2 = lc.metric(torch.cat([feat(x2), feat(w2)], -1)) / lc.temperature
    p, q = Categorical(logits=tau1), Categorical(logits=tau2)
    return (0.5 * (kl_divergence(p, q) + kl_divergence(q, p))).mean()


@pytest.mark.parametrize("standardize", [True, False])
@pytest.mark.parametrize("temperature", [1.0, 0.1])
def test_symmetric_kl_matches_manual_computation(temperature: float, standardize: bool) -> None:
    src, ref, _ = _clouds()
    enc = _encoder()
    torch.manual_seed(1)
    lc = LocalConsistency(feature_dim=K, num_local_points=16, temperature=temperature, standardize=standardize)
    lc = lc.double()
    with torch.no_grad():
        loss = lc(enc, src, ref)
    w1, w2 = lc.subsets(ref)
    expected = _manual_sym_kl(lc, enc, src, w1, w2)
    assert loss.ndim == 0 and loss >= 0
    assert expected > 1e-6  # a non-trivial value
    torch.testing.assert_close(loss, expected, atol=1e-12, rtol=1e-10)


def test_standardized_loss_ignores_the_encoder_output_scale() -> None:
    src, ref, _ = _clouds()
    enc = _encoder()
    torch.manual_seed(1)
    lc = LocalConsistency(feature_dim=K, num_local_points=16).double()
    raw = LocalConsistency(feature_dim=K, num_local_points=16, standardize=False).double()
    raw.load_state_dict(lc.state_dict())

    def scaled(points: torch.Tensor) -> torch.Tensor:
        return 100.0 * enc(points)

    with torch.no_grad():
        torch.testing.assert_close(lc(scaled, src, ref), lc(enc, src, ref), atol=1e-10, rtol=1e-8)
        assert abs(float(raw(scaled, src, ref)) - float(raw(enc, src, ref))) > 1e-3  # the raw loss does depend on it


def test_loss_is_zero_when_both_subsets_coincide() -> None:
    torch.manual_seed(0)
    lc = LocalConsistency(feature_dim=K, num_local_points=8).double()
    degenerate = torch.ones(2, 20, 3, dtype=torch.float64) * 0.3  # every point at the barycenter: X1 = X2
    assert lc(_encoder(), degenerate, degenerate).item() == pytest.approx(0.0, abs=1e-15)

    class Constant(nn.Module):
        def forward(self, points: torch.Tensor) -> torch.Tensor:
            return torch.ones(points.shape[0], K, dtype=points.dtype) + 0 * points.sum()

    src, ref, _ = _clouds()
    assert lc(Constant(), src, ref).item() == pytest.approx(0.0, abs=1e-15)


def test_gradients_reach_the_encoder_and_not_the_frozen_metric() -> None:
    src, ref, _ = _clouds()
    enc = _encoder().train()
    torch.manual_seed(1)
    lc = LocalConsistency(feature_dim=K, num_local_points=16).double()
    assert not any(p.requires_grad for p in lc.parameters())
    loss = lc(enc, src, ref)
    assert loss.requires_grad and loss > 0
    loss.backward()
    grads = [p.grad for p in enc.parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)
    assert sum(float(g.abs().sum()) for g in grads if g is not None) > 0
    assert lc.metric.weight.grad is None and lc.metric.bias.grad is None

    trainable = LocalConsistency(feature_dim=K, num_local_points=16, trainable_metric=True).double()
    assert all(p.requires_grad for p in trainable.parameters())
    trainable(enc, src, ref).backward()
    assert trainable.metric.weight.grad is not None and trainable.metric.weight.grad.abs().sum() > 0


def test_estimate_pairing() -> None:
    src, ref, transform = _clouds()
    enc = _encoder()
    torch.manual_seed(1)
    target = LocalConsistency(feature_dim=K, num_local_points=16).double()
    torch.manual_seed(1)
    estimate = LocalConsistency(feature_dim=K, num_local_points=16, pairing="estimate").double()
    with pytest.raises(ValueError, match="transform_ref_src"):
        estimate(enc, src, ref)
    # With the exact motion and the same sampling, W(X_k) = T X_k is exactly the target's subset of Y.
    live = transform.clone().requires_grad_(True)
    loss = estimate(enc, src, None, live)
    torch.testing.assert_close(loss, target(enc, src, ref), atol=1e-10, rtol=1e-10)
    w1, w2 = (se3.transform_points(transform, x) for x in estimate.subsets(src))
    torch.testing.assert_close(loss.detach(), _manual_sym_kl(estimate, enc, src, w1, w2), atol=1e-10, rtol=1e-10)
    enc.train()
    estimate(enc, src, None, live).backward()
    assert live.grad is None  # the estimate is held fixed
    with pytest.raises(ValueError, match="points_ref"):
        target(enc, src)


def test_per_point_encoder_output_is_max_pooled() -> None:
    src, ref, _ = _clouds()
    enc = _encoder()
    torch.manual_seed(1)
    lc = LocalConsistency(feature_dim=K, num_local_points=16).double()
    with torch.no_grad():
        pooled = lc(enc, src, ref)
        per_point = lc(enc.point_features, src, ref)
    torch.testing.assert_close(per_point, pooled, atol=1e-12, rtol=1e-10)

    def bad(points: torch.Tensor) -> torch.Tensor:
        return torch.zeros(points.shape[0], dtype=points.dtype)

    with pytest.raises(ValueError, match="encoder must return"):
        lc(bad, src, ref)


def test_too_few_points_and_wrong_feature_dim() -> None:
    src, ref, _ = _clouds(n=32)
    lc = LocalConsistency(feature_dim=K, num_local_points=40)
    with pytest.raises(TooFewPointsError, match="points_src"):
        lc(_encoder(), src, ref)
    lc = LocalConsistency(feature_dim=K, num_local_points=20)
    with pytest.raises(TooFewPointsError, match="points_ref"):
        lc(_encoder(), src, ref[:, :10])
    with pytest.raises(ValueError, match="expects 64"):
        LocalConsistency(feature_dim=64, num_local_points=8).double()(_encoder(), src, ref)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"feature_dim": 0},
        {"num_local_points": 0},
        {"pairing": "nearest"},
        {"outlier_quantile": 0.0},
        {"outlier_quantile": 1.5},
        {"temperature": 0.0},
    ],
)
def test_invalid_constructor_arguments(kwargs: dict) -> None:
    with pytest.raises(ValueError):
        LocalConsistency(**kwargs)


def test_third_party_usage_with_a_plain_torch_encoder() -> None:
    from lcreg import LocalConsistency as Exported

    assert Exported is LocalConsistency
    torch.manual_seed(0)
    encoder = nn.Sequential(nn.Linear(3, 32), nn.ReLU(), nn.Linear(32, 24))  # per-point (B, n, 24)
    lc = Exported(feature_dim=24, num_local_points=16)
    src, ref, _ = _clouds()
    loss = lc(encoder, src.float(), ref.float())
    assert loss.dtype == torch.float32 and torch.isfinite(loss) and loss > 0
    loss.backward()
    assert encoder[0].weight.grad is not None and encoder[0].weight.grad.abs().sum() > 0


def test_metric_initialisation_is_seeded_and_leaves_the_global_rng_alone() -> None:
    torch.manual_seed(123)
    expected_next = torch.rand(3)
    torch.manual_seed(123)
    a = LocalConsistency(feature_dim=8, num_local_points=4, metric_seed=7)
    torch.testing.assert_close(torch.rand(3), expected_next)  # building LC consumed no global randomness
    b = LocalConsistency(feature_dim=8, num_local_points=4, metric_seed=7)
    c = LocalConsistency(feature_dim=8, num_local_points=4, metric_seed=8)
    torch.testing.assert_close(a.metric.weight, b.metric.weight)
    assert not torch.allclose(a.metric.weight, c.metric.weight)
    bound = 1 / 16**0.5
    assert a.metric.weight.abs().max() <= bound and a.metric.bias.abs().max() <= bound
    assert a.metric.weight.std() > 0.5 * bound / 3**0.5  # uniform(-b, b) has std b/sqrt(3)


def test_a_frozen_metric_is_left_out_of_the_state_dict_and_rebuilt_from_its_seed() -> None:
    """A frozen metric is a function of the seed and width: checkpoints do not store it (8.4 MB for DVDs' 1024
    channels), a state dict without it loads strictly and gives the same loss; a trainable metric is stored."""
    encoder = PointNetEncoder([16, 24], batch_norm=False)
    src, ref, _ = _clouds()
    src, ref = src.float(), ref.float()
    saved = LocalConsistency(feature_dim=24, num_local_points=16, metric_seed=3)
    state = saved.state_dict()
    assert not any(key.startswith("metric.") for key in state)
    torch.save(state, buffer := io.BytesIO())
    assert buffer.tell() < 2_000  # no 48 x 24 matrix in it
    loaded = LocalConsistency(feature_dim=24, num_local_points=16, metric_seed=3)
    loaded.load_state_dict(torch.load(io.BytesIO(buffer.getvalue())), strict=True)
    torch.testing.assert_close(loaded(encoder, src, ref), saved(encoder, src, ref), rtol=0, atol=0)
    trainable = LocalConsistency(feature_dim=24, num_local_points=16, trainable_metric=True)
    assert {"metric.weight", "metric.bias"} <= set(trainable.state_dict())


def test_a_state_dict_that_holds_the_metric_still_loads_it() -> None:
    """Checkpoints written before the frozen metric was left out hold it; their values are loaded as before."""
    older = {"metric.weight": torch.full((24, 48), 0.5), "metric.bias": torch.zeros(24)}
    lc = LocalConsistency(feature_dim=24, num_local_points=16)
    lc.load_state_dict(older, strict=True)
    torch.testing.assert_close(lc.metric.weight, older["metric.weight"])


def test_estimate_pairing_refuses_a_transform_that_is_not_rigid() -> None:
    from lcreg.nn.pointnet import PointNetEncoder

    bad = torch.eye(4)[None].clone()
    bad[0, :3, :3] *= 3.0
    with pytest.raises(ValueError, match="`transform_ref_src` must hold rigid motions"):
        LocalConsistency(pairing="estimate")(PointNetEncoder(), torch.rand(1, 256, 3), transform_ref_src=bad)
