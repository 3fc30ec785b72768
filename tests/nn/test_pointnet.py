from __future__ import annotations

import contextlib
import math

import pytest
import torch
from torch import nn

from lcreg.checks import NonFiniteError, ShapeError, TooFewPointsError
from lcreg.geometry import se3
from lcreg.nn import pointnet
from lcreg.nn.lk import twist_jacobian
from lcreg.nn.pointnet import PointNetEncoder
from lcreg.reference import reference_mode

CHANNELS = (16, 32, 64)


def _encoder(batch_norm: bool = True, dtype: torch.dtype = torch.float64, seed: int = 0) -> PointNetEncoder:
    """A small encoder in eval mode whose BatchNorm layers have non-trivial running statistics and affine terms."""
    torch.manual_seed(seed)
    enc = PointNetEncoder(CHANNELS, batch_norm=batch_norm).double()
    if batch_norm:
        with torch.no_grad():
            for norm in enc.norms:
                assert isinstance(norm, nn.BatchNorm1d)
                norm.weight.uniform_(0.5, 1.5)
                norm.bias.uniform_(-0.2, 0.2)
        enc.train()
        with torch.no_grad():
            for _ in range(3):
                enc(torch.randn(4, 64, 3, dtype=torch.float64) * 1.5 + 0.3)
        for norm in enc.norms:
            assert isinstance(norm, nn.BatchNorm1d)
            assert not torch.allclose(norm.running_mean, torch.zeros_like(norm.running_mean))
            assert not torch.allclose(norm.running_var, torch.ones_like(norm.running_var))
    return enc.to(dtype).eval()


def _reference(enc: PointNetEncoder, points: torch.Tensor) -> torch.Tensor:
    """Run the Linear / BatchNorm (eval) / ReLU modules one by one, then max-pool over the points."""
    h = points
    for lin, norm in zip(enc.linears, enc.norms):
        z = lin(h)
        b, n, c = z.shape
        h = torch.relu(norm(z.reshape(b * n, c)).reshape(b, n, c))
    return h.max(dim=1).values


def _points(b: int = 2, n: int = 96, dtype: torch.dtype = torch.float64, seed: int = 1) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    return torch.randn(b, n, 3, generator=gen, dtype=torch.float64).to(dtype)


@pytest.mark.parametrize("batch_norm", [True, False])
def test_eval_forward_matches_module_by_module_reference(dtype: torch.dtype, batch_norm: bool) -> None:
    enc = _encoder(batch_norm, dtype)
    points = _points(dtype=dtype)
    with torch.no_grad():
        out = enc(points)
        expected = _reference(enc, points)
    assert out.shape == (2, CHANNELS[-1]) and out.dtype == dtype
    assert enc.feature_dim == CHANNELS[-1]
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    torch.testing.assert_close(out, expected, atol=tol, rtol=tol)


def test_point_features_max_equals_forward_in_eval_and_train() -> None:
    enc = _encoder()
    points = _points()
    with torch.no_grad():
        torch.testing.assert_close(enc.point_features(points).max(1).values, enc(points))
        enc.train()
        torch.testing.assert_close(enc.point_features(points).max(1).values, enc(points))
    assert enc.point_features(points).shape == (2, 96, CHANNELS[-1])


def test_train_mode_uses_batch_statistics() -> None:
    enc = _encoder().train()
    points = _points()
    with torch.no_grad():
        out = enc(points)
        expected = points
        for lin, norm in zip(enc.linears, enc.norms):
            z = lin(expected)
            flat = z.reshape(-1, z.shape[-1])
            flat = (flat - flat.mean(0)) / torch.sqrt(flat.var(0, unbiased=False) + norm.eps) * norm.weight + norm.bias
            expected = torch.relu(flat.reshape(z.shape))
    torch.testing.assert_close(out, expected.max(1).values)


@pytest.mark.parametrize("chunk_size", [1, 7, 96, 1000])
def test_chunk_size_does_not_change_the_result(chunk_size: int) -> None:
    enc = _encoder()
    points = _points()
    with torch.no_grad():
        expected = enc(points)
        enc.chunk_size = chunk_size
        torch.testing.assert_close(enc(points), expected, atol=1e-13, rtol=0)


@pytest.mark.parametrize("batch_norm", [True, False])
def test_analytic_twist_jacobian_equals_autodiff(batch_norm: bool) -> None:
    enc = _encoder(batch_norm)
    points = _points()
    psi, jac = enc.twist_jacobian(points)
    psi_ad, jac_ad = twist_jacobian(enc, points, "autodiff")
    assert psi.shape == (2, CHANNELS[-1]) and jac.shape == (2, CHANNELS[-1], 6)
    torch.testing.assert_close(psi, enc(points), atol=1e-12, rtol=0)
    torch.testing.assert_close(psi, psi_ad, atol=1e-12, rtol=0)
    assert jac.abs().max() > 1e-3  # not trivially zero
    torch.testing.assert_close(jac, jac_ad, atol=1e-10, rtol=1e-10)


def test_analytic_twist_jacobian_float32_close_to_float64() -> None:
    points = _points()
    _, jac64 = _encoder().twist_jacobian(points)
    _, jac32 = _encoder(dtype=torch.float32).twist_jacobian(points.float())
    assert jac32.dtype == torch.float32
    torch.testing.assert_close(jac32.double(), jac64, atol=1e-4, rtol=1e-3)


def test_analytic_twist_jacobian_matches_central_finite_differences() -> None:
    enc = _encoder()
    points = _points()
    _, jac = enc.twist_jacobian(points)
    eps = 1e-6
    cols = []
    with torch.no_grad():
        for k in range(6):
            step = torch.zeros(6, dtype=torch.float64)
            step[k] = eps
            plus = enc(se3.transform_points(se3.exp(step).expand(2, 4, 4), points))
            minus = enc(se3.transform_points(se3.exp(-step).expand(2, 4, 4), points))
            cols.append((plus - minus) / (2 * eps))
    fd = torch.stack(cols, dim=-1)
    err = (fd - jac).abs()
    # Arg-max switches of the max pool make a few finite differences locally wrong; most entries must agree.
    assert err.median() < 1e-7
    assert (err < 1e-5 * (1 + jac.abs())).double().mean() > 0.95


def test_twist_jacobian_columns_are_rotation_then_translation() -> None:
    enc = _encoder()
    points = _points()
    _, jac = enc.twist_jacobian(points)
    eps = 1e-6
    with torch.no_grad():
        for j in range(3):
            shift = torch.zeros(3, dtype=torch.float64)
            shift[j] = eps
            d_t = (enc(points + shift) - enc(points - shift)) / (2 * eps)
            err = (d_t - jac[..., 3 + j]).abs()
            assert err.median() < 1e-7, j
        # Rotation about x by a small angle: y -> y cos - z sin, z -> y sin + z cos.
        c, s = math.cos(eps), math.sin(eps)
        rx = torch.tensor([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]], dtype=torch.float64)
        d_wx = (enc(points @ rx.T) - enc(points @ rx)) / (2 * eps)
    assert (d_wx - jac[..., 0]).abs().median() < 1e-7
    # The translation columns are not the rotation columns.
    assert (jac[..., 3:] - jac[..., :3]).abs().max() > 1e-3


def test_twist_jacobian_does_not_depend_on_the_mode_of_the_module() -> None:
    enc = _encoder()
    points = _points()
    psi_eval, jac_eval = enc.twist_jacobian(points)
    enc.train()
    psi_train, jac_train = enc.twist_jacobian(points)  # running statistics always (IC-LK semantics)
    torch.testing.assert_close(psi_train, psi_eval)
    torch.testing.assert_close(jac_train, jac_eval)


def test_gradients_reach_all_parameters_in_train_mode() -> None:
    enc = _encoder().train()
    enc(_points()).sum().backward()
    for name, param in enc.named_parameters():
        assert param.grad is not None and torch.isfinite(param.grad).all(), name
    assert enc.linears[0].weight.grad is not None and enc.linears[0].weight.grad.abs().sum() > 0


def _mode(reference: bool) -> contextlib.AbstractContextManager[None]:
    return reference_mode() if reference else contextlib.nullcontext()


def _train_outputs(enc: PointNetEncoder, points: torch.Tensor, reference: bool) -> list[torch.Tensor]:
    """Training-mode descriptor and the parameter gradients of a weighted sum of it."""
    enc.zero_grad()
    with _mode(reference):
        out = enc(points)
    weights = torch.linspace(-1, 2, out.shape[-1], dtype=out.dtype)
    (out * weights).sum().backward()
    return [out.detach(), *(p.grad for p in enc.parameters() if p.grad is not None)]


@pytest.mark.parametrize("chunk_size", [1, 7, 96, 1000])
def test_fast_training_forward_matches_the_reference(dtype: torch.dtype, chunk_size: int) -> None:
    """The last layer differentiated at the arg-max points only: same descriptor and gradients as the dense one."""
    enc = _encoder(batch_norm=False, dtype=dtype).train()
    enc.chunk_size = chunk_size
    points = _points(n=160, dtype=dtype)
    assert enc._pools_sparsely(160)
    ref, fast = _train_outputs(enc, points, True), _train_outputs(enc, points, False)
    assert len(fast) == len(ref) == 1 + 2 * len(CHANNELS)
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    for a, b in zip(fast, ref, strict=True):
        torch.testing.assert_close(a, b, atol=tol, rtol=tol)


def test_training_forward_with_batch_norm_matches_the_reference() -> None:
    """A BatchNorm after the last layer needs every point's output (batch statistics): the dense path is used."""
    enc = _encoder(batch_norm=True).train()
    points = _points(n=160)
    assert not enc._pools_sparsely(160)
    for a, b in zip(_train_outputs(enc, points, False), _train_outputs(enc, points, True), strict=True):
        torch.testing.assert_close(a, b, atol=1e-12, rtol=1e-12)


def test_small_clouds_use_the_dense_training_backward() -> None:
    """Below ``_SPARSE_MIN_POINTS`` points per cloud gathering ``K`` rows per cloud costs more than the dense pass."""
    enc = _encoder(batch_norm=False).train()
    assert not enc._pools_sparsely(pointnet._SPARSE_MIN_POINTS - 1)
    assert enc._pools_sparsely(pointnet._SPARSE_MIN_POINTS)


def _eval_outputs(enc: PointNetEncoder, points: torch.Tensor, reference: bool) -> list[torch.Tensor]:
    """Eval-mode descriptor with a graph, and the gradients of a weighted sum of it (points, then parameters)."""
    enc.zero_grad()
    points = points.clone().requires_grad_()
    with _mode(reference):
        out = enc(points)
    weights = torch.linspace(-1, 2, out.shape[-1], dtype=out.dtype)
    (out * weights).sum().backward()
    assert points.grad is not None
    return [out.detach(), points.grad, *(p.grad for p in enc.parameters() if p.grad is not None)]


@pytest.mark.parametrize("batch_norm", [True, False])
@pytest.mark.parametrize("chunk_size", [1, 7, 1000])
def test_eval_forward_with_a_graph_matches_the_chunked_max(batch_norm: bool, chunk_size: int) -> None:
    """Through an eval-mode solve (the self-motion term's): arg-max points only, same values and gradients.

    The reference is the chunked max under autograd (the path without a graph, differentiated densely); the
    gradients reach the points, every linear layer and the BatchNorm affine terms alike.
    """
    enc = _encoder(batch_norm)
    enc.chunk_size = chunk_size
    points = _points(n=pointnet._SPARSE_MIN_POINTS + 32)
    ref, fast = _eval_outputs(enc, points, True), _eval_outputs(enc, points, False)
    assert len(fast) == len(ref) == 2 + (4 if batch_norm else 2) * len(CHANNELS)
    for a, b in zip(fast, ref, strict=True):
        torch.testing.assert_close(a, b, atol=1e-12, rtol=1e-12)
    with torch.no_grad():
        torch.testing.assert_close(enc(points), ref[0], atol=1e-12, rtol=1e-12)


def test_eval_forward_with_a_graph_passes_gradcheck() -> None:
    enc = _encoder(batch_norm=True)
    points = _points(b=1, n=pointnet._SPARSE_MIN_POINTS).requires_grad_()
    assert torch.autograd.gradcheck(enc, (points,), eps=1e-6, atol=1e-6)


@pytest.mark.parametrize("batch_norm", [True, False])
@pytest.mark.parametrize("chunk_size", [1, 7, 1000])
def test_fast_twist_jacobian_matches_the_reference(batch_norm: bool, chunk_size: int) -> None:
    enc = _encoder(batch_norm)
    enc.chunk_size = chunk_size
    points = _points()
    with reference_mode():
        psi_ref, jac_ref = enc.twist_jacobian(points)
    psi, jac = enc.twist_jacobian(points)
    torch.testing.assert_close(psi, psi_ref, atol=1e-12, rtol=1e-12)
    torch.testing.assert_close(jac, jac_ref, atol=1e-12, rtol=1e-12)


def test_fast_twist_jacobian_is_differentiable_like_the_reference() -> None:
    """PointNetLK back-propagates through the Jacobian (differentiable solver): same parameter gradients."""
    enc = _encoder()
    points = _points()
    grads = []
    for reference in (True, False):
        enc.zero_grad()
        with _mode(reference):
            psi, jac = enc.twist_jacobian(points)
        (psi.sum() + jac.square().sum()).backward()
        grads.append([p.grad.clone() for p in enc.parameters() if p.grad is not None])
    assert len(grads[0]) == len(grads[1]) > 0
    for a, b in zip(*grads, strict=True):
        torch.testing.assert_close(a, b, atol=1e-12, rtol=1e-10)


def test_twist_jacobian_of_a_single_layer_encoder() -> None:
    torch.manual_seed(0)
    enc = PointNetEncoder((8,), batch_norm=False).double().eval()
    points = _points()
    psi, jac = enc.twist_jacobian(points)
    psi_ad, jac_ad = twist_jacobian(enc, points, "autodiff")
    torch.testing.assert_close(psi, psi_ad, atol=1e-12, rtol=0)
    torch.testing.assert_close(jac, jac_ad, atol=1e-10, rtol=1e-10)


@pytest.mark.parametrize("chunk_size", [1, 2])
def test_pooled_argmax_ties_go_to_the_first_point(chunk_size: int) -> None:
    enc = PointNetEncoder((4, 6), batch_norm=False)
    enc.chunk_size = chunk_size
    h = torch.tensor([[1.0, 2.0, 0.5, 0.0]]).expand(2, 5, 4)  # five identical points per cloud
    assert torch.equal(enc._pooled_argmax(h, torch.randn(6, 4)), torch.zeros(2, 6, dtype=torch.long))


@pytest.mark.parametrize(
    ("bad", "error"),
    [
        (torch.tensor([[[0.0, float("nan"), 0.0]] * 4]), NonFiniteError),
        (torch.tensor([[[0.0, float("inf"), 0.0]] * 4]), NonFiniteError),
        (torch.zeros(2, 8, 2), ShapeError),
        (torch.zeros(8, 3), ShapeError),
        (torch.zeros(2, 8, 3, dtype=torch.int64), TypeError),
        (torch.zeros(2, 0, 3), TooFewPointsError),
    ],
    ids=["nan", "inf", "two_columns", "unbatched", "int", "empty"],
)
@pytest.mark.parametrize("method", ["forward", "twist_jacobian"])
def test_bad_inputs_raise_typed_errors(bad: torch.Tensor, error: type[Exception], method: str) -> None:
    enc = PointNetEncoder((8, 16)).eval()
    with pytest.raises(error, match="points"):
        getattr(enc, method)(bad)


def test_invalid_channels() -> None:
    with pytest.raises(ValueError, match="channels"):
        PointNetEncoder(())
    with pytest.raises(ValueError, match="channels"):
        PointNetEncoder((16, 0))
