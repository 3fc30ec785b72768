"""Checks every learned registration host must pass; model test files call them with their own tiny model.

Each function asserts real behaviour (no shape-only checks) and is parametrised by a factory so the caller decides the
model's size. Batches are small synthetic pairs with a ground truth (``tiny_batch``).
"""

from __future__ import annotations

from collections.abc import Callable

import pytest
import torch

from lcreg.checks import NonFiniteError, ShapeError, TooFewPointsError
from lcreg.data.collate import collate_pairs
from lcreg.data.datamodule import PairDataset
from lcreg.data.pairs import PairProtocol
from lcreg.data.synthetic import synthetic_shapes
from lcreg.geometry import se3
from lcreg.models.base import RegistrationModule
from lcreg.models.loss_terms import LocalConsistencyLoss, LossTerm
from lcreg.nn.local_consistency import LocalConsistency
from lcreg.types import RegistrationBatch, RegistrationResult

ModelFactory = Callable[[], RegistrationModule]


def tiny_batch(batch_size: int = 4, num_points: int = 96, seed: int = 0, **protocol: object) -> RegistrationBatch:
    """Deterministic synthetic pairs (the package's pair protocol) with ground truth and normals."""
    points, normals, _ = synthetic_shapes(batch_size, max(256, 2 * num_points), seed=seed)
    dataset = PairDataset(
        points, normals, PairProtocol(num_points=num_points, **protocol), deterministic=True, seed=seed
    )
    return collate_pairs([dataset[i] for i in range(batch_size)])


def check_forward_backward(factory: ModelFactory, batch: RegistrationBatch) -> RegistrationResult:
    """Forward returns a valid ``RegistrationResult``; the training loss back-propagates finite gradients."""
    model = factory().train()
    result = model.training_forward(batch)
    b = len(batch)
    assert isinstance(result, RegistrationResult)
    assert result.transform_ref_src.shape == (b, 4, 4)
    assert torch.isfinite(result.transform_ref_src).all()
    assert result.converged.shape == (b,) and result.converged.dtype == torch.bool
    assert result.num_iters.shape == (b,) and result.num_iters.dtype == torch.int64
    rot = result.rotation
    eye = torch.eye(3, dtype=rot.dtype).expand_as(rot)
    torch.testing.assert_close(rot @ rot.transpose(1, 2), eye, atol=1e-4, rtol=0)
    assert torch.allclose(torch.linalg.det(rot), torch.ones(b, dtype=rot.dtype), atol=1e-4)
    losses = model.training_losses(result, batch)
    assert "loss" in losses
    for name, value in losses.items():
        assert value.ndim == 0 and torch.isfinite(value), name
    losses["loss"].backward()
    grads = [p.grad for p in model.parameters() if p.requires_grad and p.grad is not None]
    assert grads, "no parameter received a gradient"
    assert all(torch.isfinite(g).all() for g in grads)
    assert any(g.abs().sum() > 0 for g in grads)
    return result


def check_training_lowers_loss(
    factory: ModelFactory, batch: RegistrationBatch, steps: int = 15, lr: float = 1e-3, seed: int = 0
) -> tuple[float, float]:
    """``steps`` Adam steps on one fixed batch lower the training loss (returns first and last loss)."""
    torch.manual_seed(seed)
    model = factory().train()
    opt = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=lr)
    history = []
    for _ in range(steps):
        torch.manual_seed(seed)  # identical stochastic choices (sampling, Gumbel noise) every step
        opt.zero_grad()
        loss = model.training_losses(model.training_forward(batch), batch)["loss"]
        loss.backward()
        opt.step()
        history.append(float(loss.detach()))
    assert history[-1] < history[0], f"loss did not decrease: {history}"
    return history[0], history[-1]


def lc_terms(num_local_points: int = 16, weight: float = 1.0, feature_dim: int | None = None) -> list[LossTerm]:
    """The injected LC term as ``configs/lc.yaml`` gives it (width bound to the host's encoder unless given)."""
    return [LocalConsistencyLoss(LocalConsistency(feature_dim, num_local_points=num_local_points), weight=weight)]


def check_local_consistency_gradient(
    factory: Callable[[list[LossTerm]], RegistrationModule],
    batch: RegistrationBatch,
    num_local_points: int = 16,
    weight: float = 0.5,
    seed: int = 0,
) -> None:
    """Injected LC: bound to the host's width, added exactly once, with a finite non-zero encoder gradient.

    ``factory(loss_terms)`` builds the host with those injected loss terms (``[]``: none). Checks that

    * the host without terms has no ``lc`` entry, and LC does not change the host's initial weights;
    * the LC width is bound to ``descriptor_dim`` at construction (a wrong explicit width raises ``ValueError``),
      and ``min_points`` covers ``num_local_points``;
    * ``loss = own loss + weight * lc`` (own loss from the LC-free host on the same estimate), ``lc`` finite > 0;
    * ``lc`` back-propagates a finite, non-zero gradient into ``descriptor_encoder()``.
    """
    torch.manual_seed(seed)
    host = factory([]).train()
    torch.manual_seed(seed)
    model = factory(lc_terms(num_local_points, weight)).train()
    assert len(host.loss_terms) == 0
    (term,) = model.loss_terms
    assert isinstance(term, LocalConsistencyLoss) and term.weight == weight
    assert term.local_consistency.feature_dim == model.descriptor_dim  # bound at construction
    assert not hasattr(model, "local_consistency") and not hasattr(model, "lc_encoder")  # one way in: loss_terms
    assert model.min_points >= num_local_points and model.min_points == max(host.min_points, num_local_points)
    plain_state = host.state_dict()
    for key, value in model.state_dict().items():
        if not key.startswith("loss_terms."):
            torch.testing.assert_close(value, plain_state[key], rtol=0, atol=0, msg=key)  # same host weights

    torch.manual_seed(seed)
    result = model.training_forward(batch)
    torch.manual_seed(seed)
    losses = model.training_losses(result, batch)
    assert "lc" in losses and losses["lc"].ndim == 0 and torch.isfinite(losses["lc"]) and losses["lc"] > 0
    torch.manual_seed(seed)
    own = host.training_losses(result, batch)  # the same estimate, the host's own terms only
    assert set(losses) == {*own, "lc"}
    for name in own:
        if name != "loss":
            torch.testing.assert_close(losses[name], own[name], msg=name)
    torch.testing.assert_close(losses["loss"], own["loss"] + weight * losses["lc"])  # LC added exactly once

    encoder = model.descriptor_encoder()
    assert isinstance(encoder, torch.nn.Module)
    params = [p for p in encoder.parameters() if p.requires_grad]
    grads = torch.autograd.grad(losses["lc"], params, allow_unused=True)
    norms = [g.norm() for g in grads if g is not None]
    assert norms and all(torch.isfinite(n) for n in norms)
    assert sum(norms) > 0, "LC adds no gradient to the encoder"

    with pytest.raises(ValueError, match=f"built for {model.descriptor_dim + 1} features"):
        factory(lc_terms(num_local_points, weight, feature_dim=model.descriptor_dim + 1))


def check_bad_inputs(factory: ModelFactory, num_points: int = 64) -> None:
    """Bad clouds raise typed errors naming the argument (through the validated ``register`` entry point)."""
    model = factory()
    good = torch.randn(2, num_points, 3)
    nan = good.clone()
    nan[0, 0, 0] = float("nan")
    with pytest.raises(NonFiniteError, match="points_src"):
        model.register(nan, good)
    with pytest.raises(ShapeError, match="points_ref"):
        model.register(good, good[..., :2])
    with pytest.raises(TypeError, match="points_src"):
        model.register(good.long(), good)
    with pytest.raises(TooFewPointsError, match="points_src"):
        model.register(good[:, :1], good)
    with pytest.raises(ShapeError):
        model.register(good, good[:1])


def check_rotation_equivariance(
    estimate: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    points_src: torch.Tensor,
    points_ref: torch.Tensor,
    atol: float = 1e-4,
    seed: int = 0,
) -> None:
    """Rotating the source by ``G`` turns the estimate ``T`` into ``T G^-1`` (``estimate`` returns ``(B, 4, 4)``)."""
    from lcreg.geometry.random_transforms import random_rotation

    gen = torch.Generator().manual_seed(seed)
    rot = random_rotation(points_src.shape[0], generator=gen, dtype=points_src.dtype)
    g = se3.make_transform(rot, torch.zeros(points_src.shape[0], 3, dtype=points_src.dtype))
    base = estimate(points_src, points_ref)
    moved = estimate(se3.transform_points(g, points_src), points_ref)
    torch.testing.assert_close(moved, se3.compose(base, se3.inverse(g)), atol=atol, rtol=0)
