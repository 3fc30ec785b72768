from __future__ import annotations

import pytest
import torch
from torch import nn

from lcreg.data.synthetic import synthetic_shapes
from lcreg.geometry import se3, so3
from lcreg.metrics.functional import rotation_error_deg, translation_error
from lcreg.nn.lk import InverseCompositionalLK, twist_jacobian
from lcreg.nn.pointnet import PointNetEncoder


def _encoder(seed: int = 0) -> PointNetEncoder:
    torch.manual_seed(seed)
    return PointNetEncoder((32, 64, 128)).double().eval()


def _problem(b: int = 3, n: int = 192) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Smooth asymmetric shapes, reference = T source (same sampling), rotations of 5-10 degrees."""
    points, _, _ = synthetic_shapes(b, n, seed=3)
    src = torch.tensor(points, dtype=torch.float64)
    gen = torch.Generator().manual_seed(0)
    axis = torch.randn(b, 3, generator=gen, dtype=torch.float64)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    angle = torch.deg2rad(torch.linspace(5.0, 10.0, b, dtype=torch.float64))
    trans = (torch.rand(b, 3, generator=gen, dtype=torch.float64) * 2 - 1) * 0.05
    transform = se3.make_transform(so3.exp(axis * angle[:, None]), trans)
    return src, se3.transform_points(transform, src), transform


@pytest.mark.parametrize("jacobian", ["analytic", "autodiff", "finite_difference"])
def test_recovers_a_known_small_transform(jacobian: str) -> None:
    src, ref, gt = _problem(b=2 if jacobian == "autodiff" else 3)
    identity = se3.identity(len(src), dtype=torch.float64)
    initial = rotation_error_deg(identity, gt)
    assert (initial > 4.9).all()
    result = InverseCompositionalLK(max_iterations=10, jacobian=jacobian)(_encoder(), src, ref)  # type: ignore[arg-type]
    assert result.transform_ref_src.shape == (len(src), 4, 4)
    assert result.transform_ref_src.dtype == torch.float64
    err = rotation_error_deg(result.transform_ref_src, gt)
    assert (err < 0.1 * initial).all(), (err, initial)
    assert (translation_error(result.transform_ref_src, gt) < 0.02).all()
    assert result.residual_history is not None and result.residual_history.shape[0] == len(src)
    assert (result.residual_history[:, -1] < 0.1 * result.residual_history[:, 0]).all()
    assert result.aux["feature_ref"].shape == (len(src), 128)


@pytest.mark.parametrize("tolerance", [1e-7, 1e-3])
def test_batched_equals_per_item_loop(tolerance: float) -> None:
    # With tolerance 1e-3 items stop while their updates are still far from zero: updating an item after its
    # convergence would show here.
    src, ref, _ = _problem(b=3)
    ref = torch.cat([ref, src[:1]])  # an identical pair: converges after one (zero) update
    src = torch.cat([src, src[:1]])
    enc = _encoder()
    solver = InverseCompositionalLK(max_iterations=10, tolerance=tolerance)
    batched = solver(enc, src, ref)
    singles = [solver(enc, src[i : i + 1], ref[i : i + 1]) for i in range(len(src))]
    iters = torch.cat([s.num_iters for s in singles])
    assert len(set(iters.tolist())) > 1, iters  # the items stop at different iterations
    assert iters[-1] == 1
    torch.testing.assert_close(batched.num_iters, iters)
    torch.testing.assert_close(batched.converged, torch.cat([s.converged for s in singles]))
    torch.testing.assert_close(
        batched.transform_ref_src, torch.cat([s.transform_ref_src for s in singles]), atol=1e-9, rtol=0
    )
    torch.testing.assert_close(batched.transform_ref_src[-1], torch.eye(4, dtype=torch.float64), atol=1e-12, rtol=0)


def test_convergence_flags_and_iteration_limit() -> None:
    src, ref, _ = _problem(b=2)
    enc = _encoder()
    loose = InverseCompositionalLK(max_iterations=10, tolerance=1e9)(enc, src, ref)
    assert loose.num_iters.tolist() == [1, 1] and loose.converged.all()
    assert loose.num_iters.dtype == torch.int64 and loose.converged.dtype == torch.bool
    capped = InverseCompositionalLK(max_iterations=3, tolerance=0.0)(enc, src, ref)
    assert capped.num_iters.tolist() == [3, 3] and not capped.converged.any()
    assert capped.residual_history is not None and capped.residual_history.shape == (2, 3)


class _Constant(nn.Module):
    """Ignores the points: zero Jacobian."""

    def __init__(self) -> None:
        super().__init__()
        self.value = nn.Parameter(torch.linspace(-1.0, 1.0, 8, dtype=torch.float64))

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        return self.value.expand(points.shape[0], -1) + 0 * points.sum()


@pytest.mark.parametrize("jacobian", ["autodiff", "finite_difference", "analytic"])
def test_zero_jacobian_gives_identity_and_no_nan(jacobian: str) -> None:
    src, ref, _ = _problem(b=2)
    if jacobian == "analytic":  # a PointNet whose last layer is dead outputs a constant too
        encoder: nn.Module = _encoder()
        with torch.no_grad():
            encoder.linears[-1].weight.zero_()
    else:
        encoder = _Constant()
    _, jac = twist_jacobian(encoder, ref, jacobian)  # type: ignore[arg-type]
    assert torch.equal(jac, torch.zeros_like(jac))
    result = InverseCompositionalLK(jacobian=jacobian)(encoder, src, ref)  # type: ignore[arg-type]
    transform = result.transform_ref_src
    assert torch.isfinite(transform).all()
    torch.testing.assert_close(transform[:, :3, :3], torch.eye(3, dtype=torch.float64).expand(2, 3, 3))
    torch.testing.assert_close(transform[:, :3, 3], ref.mean(1) - src.mean(1))  # centring only
    assert result.converged.all() and result.num_iters.tolist() == [1, 1]
    uncentred = InverseCompositionalLK(jacobian=jacobian, center=False)(encoder, src, ref)  # type: ignore[arg-type]
    torch.testing.assert_close(uncentred.transform_ref_src, se3.identity(2, dtype=torch.float64))


def test_differentiable_flag() -> None:
    src, ref, _ = _problem(b=2)
    src.requires_grad_(True)
    enc = _encoder()
    frozen = InverseCompositionalLK(max_iterations=2)(enc, src, ref)
    assert not frozen.transform_ref_src.requires_grad
    assert not frozen.aux["feature_ref"].requires_grad
    live = InverseCompositionalLK(max_iterations=2, differentiable=True)(enc, src, ref)
    assert live.transform_ref_src.requires_grad
    live.transform_ref_src.sum().backward()
    assert src.grad is not None and torch.isfinite(src.grad).all()
    assert enc.linears[0].weight.grad is not None and enc.linears[0].weight.grad.abs().sum() > 0
    with torch.no_grad():  # differentiable=True still respects no_grad
        assert not InverseCompositionalLK(max_iterations=1, differentiable=True)(
            enc, src, ref
        ).transform_ref_src.requires_grad


@pytest.mark.parametrize(
    "kwargs",
    [
        {"max_iterations": 0},
        {"tolerance": -1.0},
        {"damping": -1e-3},
        {"fd_step": 0.0},
        {"jacobian": "numerical"},
    ],
)
def test_invalid_constructor_arguments(kwargs: dict) -> None:
    with pytest.raises(ValueError):
        InverseCompositionalLK(**kwargs)


def test_unknown_jacobian_mode_in_function() -> None:
    with pytest.raises(ValueError, match="mode"):
        twist_jacobian(_encoder(), torch.zeros(1, 4, 3, dtype=torch.float64), "numerical")  # type: ignore[arg-type]


def test_encoder_mode_is_restored_and_running_stats_untouched() -> None:
    src, ref, _ = _problem(b=2)
    enc = _encoder().train()
    stats = [n.running_mean.clone() for n in enc.norms]  # type: ignore[union-attr]
    InverseCompositionalLK(max_iterations=2)(enc, src, ref)
    assert enc.training and all(m.training for m in enc.modules())
    for before, norm in zip(stats, enc.norms):
        assert torch.equal(before, norm.running_mean)  # type: ignore[arg-type]
    enc.eval()
    InverseCompositionalLK(max_iterations=2)(enc, src, ref)
    assert not enc.training


class _MeanPoolMLP(nn.Module):
    """A third-party encoder without `twist_jacobian`: smooth per-point MLP and mean pooling."""

    def __init__(self) -> None:
        super().__init__()
        self.mlp = nn.Sequential(nn.Linear(3, 32), nn.Tanh(), nn.Linear(32, 24)).double()

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        return torch.tanh(self.mlp(points)).mean(dim=1)


def test_autodiff_works_for_any_encoder_and_analytic_refuses() -> None:
    torch.manual_seed(0)
    enc = _MeanPoolMLP()
    src, ref, _ = _problem(b=2, n=128)
    _, jac_ad = twist_jacobian(enc, ref, "autodiff")
    _, jac_fd = twist_jacobian(enc, ref, "finite_difference", fd_step=1e-6)
    torch.testing.assert_close(jac_ad, jac_fd, atol=1e-5, rtol=1e-4)
    result = InverseCompositionalLK(jacobian="autodiff")(enc, src, ref)
    assert torch.isfinite(result.transform_ref_src).all()
    assert result.residual_history is not None
    assert (result.residual_history[:, -1] < result.residual_history[:, 0]).all()
    with pytest.raises(ValueError, match="twist_jacobian"):
        InverseCompositionalLK(jacobian="analytic")(enc, src, ref)


def test_points_are_validated() -> None:
    enc = _encoder()
    good = torch.zeros(2, 16, 3, dtype=torch.float64)
    with pytest.raises(ValueError, match="points_src"):
        InverseCompositionalLK()(enc, good[..., :2], good)
    with pytest.raises(ValueError, match="points_ref"):
        InverseCompositionalLK()(enc, good, good[:1])


def test_jacobian_diagnostics_match_numpy_svd_and_see_a_blind_direction() -> None:
    import numpy as np

    from lcreg.nn.lk import TWIST_NAMES, jacobian_diagnostics

    gen = torch.Generator().manual_seed(0)
    jac = torch.randn(5, 40, 6, generator=gen, dtype=torch.float64)
    feat = torch.randn(5, 40, generator=gen, dtype=torch.float64)
    out = jacobian_diagnostics(jac, feat)
    sv = np.linalg.svd(jac.numpy(), compute_uv=False)  # (5, 6) descending
    norm = np.linalg.norm(feat.numpy(), axis=-1)
    np.testing.assert_allclose(float(out["cond"]), np.median(sv[:, -1] / sv[:, 0]), rtol=1e-10)
    np.testing.assert_allclose(float(out["sensitivity"]), np.median(sv[:, -1] / norm), rtol=1e-10)
    cols = np.linalg.norm(jac.numpy(), axis=1) / norm[:, None]
    for k, name in enumerate(TWIST_NAMES):
        np.testing.assert_allclose(float(out[f"dir_{name}"]), np.median(cols[:, k]), rtol=1e-10)
    blind = jac.clone()
    blind[..., 2] = 0  # the descriptor no longer sees rotations about z
    out_blind = jacobian_diagnostics(blind, feat)
    assert float(out_blind["cond"]) < 1e-12 and float(out_blind["dir_rz"]) == 0.0


def test_solver_returns_its_jacobian_and_a_per_call_differentiable_override() -> None:
    src, ref, _ = _problem(b=2, n=64)
    encoder = _encoder()
    solver = InverseCompositionalLK(max_iterations=3)
    plain = solver(encoder, src, ref)
    _, jac = twist_jacobian(encoder, ref - ref.mean(1, keepdim=True))
    torch.testing.assert_close(plain.aux["jacobian"], jac)
    assert not plain.transform_ref_src.requires_grad
    kept = solver(encoder, src, ref, differentiable=True)
    assert kept.transform_ref_src.requires_grad and not solver.differentiable
    torch.testing.assert_close(kept.transform_ref_src.detach(), plain.transform_ref_src)
    grads = torch.autograd.grad(kept.transform_ref_src.sum(), list(encoder.parameters()), allow_unused=True)
    assert any(g is not None and g.abs().sum() > 0 for g in grads)


def test_float64_clouds_with_a_float32_encoder() -> None:
    from lcreg.nn.pointnet import PointNetEncoder

    torch.manual_seed(0)
    encoder = PointNetEncoder([16, 32]).eval()
    src = torch.rand(2, 64, 3, dtype=torch.float64) - 0.5
    out64 = InverseCompositionalLK(max_iterations=3)(encoder, src, src)  # was "expected scalar type Float"
    out32 = InverseCompositionalLK(max_iterations=3)(encoder, src.float(), src.float())
    assert out64.transform_ref_src.dtype == torch.float64
    torch.testing.assert_close(out64.transform_ref_src.float(), out32.transform_ref_src)


def test_axis_rotation_starts_match_scipy_rotations() -> None:
    from scipy.spatial.transform import Rotation

    from lcreg.nn.lk import axis_rotation_starts

    assert torch.equal(axis_rotation_starts([], dtype=torch.float64), torch.eye(4, dtype=torch.float64)[None])
    starts = axis_rotation_starts([60.0, 30.0], dtype=torch.float64)
    assert starts.shape == (13, 4, 4) and torch.equal(starts[0], torch.eye(4, dtype=torch.float64))
    for i, angle in enumerate((60.0, 30.0)):
        for axis in range(3):
            for k, sign in enumerate((1.0, -1.0)):
                vec = [0.0, 0.0, 0.0]
                vec[axis] = sign * angle
                expected = torch.tensor(Rotation.from_rotvec(vec, degrees=True).as_matrix())
                torch.testing.assert_close(starts[1 + 6 * i + 2 * axis + k, :3, :3], expected)
    assert (starts[:, :3, 3] == 0).all()


def test_one_identity_start_is_the_plain_solve() -> None:
    src, ref, _ = _problem(b=3)
    enc, solver = _encoder(), InverseCompositionalLK(max_iterations=6)
    plain = solver(enc, src, ref)
    started = solver(enc, src, ref, starts=torch.eye(4, dtype=torch.float64)[None])
    torch.testing.assert_close(started.transform_ref_src, plain.transform_ref_src)
    assert torch.equal(started.num_iters, plain.num_iters) and (started.aux["start"] == 0).all()
    torch.testing.assert_close(started.residual_history, plain.residual_history)


def test_several_starts_keep_the_lowest_final_residual_per_item() -> None:
    """Against a per-start, per-item loop of one-start solves: each item gets the start with the lowest final
    residual, its transform, iterations and residual history."""
    from lcreg.nn.lk import axis_rotation_starts

    src, ref, gt = _problem(b=3)
    turn = so3.exp(torch.tensor([[0.0, 0.0, 2.2]], dtype=torch.float64))  # 126 deg about z
    ref = ref @ turn.transpose(1, 2)
    gt = se3.make_transform(turn.expand(3, 3, 3), torch.zeros(3, 3, dtype=torch.float64)) @ gt
    enc, solver = _encoder(), InverseCompositionalLK(max_iterations=8)
    starts = axis_rotation_starts([60.0, 120.0], dtype=torch.float64)
    batched = solver(enc, src, ref, starts=starts)
    for i in range(len(src)):
        singles = [solver(enc, src[i : i + 1], ref[i : i + 1], starts=s[None]) for s in starts]
        finals = torch.cat([s.aux["final_residual"] for s in singles])
        best = int(finals.argmin())
        assert int(batched.aux["start"][i]) == best
        torch.testing.assert_close(batched.aux["final_residual"][i], finals[best])
        torch.testing.assert_close(batched.transform_ref_src[i], singles[best].transform_ref_src[0])
        assert batched.residual_history is not None and singles[best].residual_history is not None
        steps = int(singles[best].num_iters[0])
        assert int(batched.num_iters[i]) == steps  # the history runs on while other items iterate
        torch.testing.assert_close(batched.residual_history[i, :steps], singles[best].residual_history[0, :steps])
    identity_only = solver(enc, src, ref, starts=starts[:1])
    assert (batched.aux["final_residual"] <= identity_only.aux["final_residual"]).all()
    # from the identity IC-LK fails on this turn; the +120 deg start about z (index 11) finds it
    assert (rotation_error_deg(identity_only.transform_ref_src, gt) > 90).all()
    assert (batched.aux["start"] == 11).all() and (rotation_error_deg(batched.transform_ref_src, gt) < 1e-3).all()


def test_select_start_keeps_the_identity_unless_another_start_is_clearly_lower() -> None:
    from lcreg.nn.lk import select_start

    final = torch.tensor(  # (S=3 starts, B=4 items); start 0 is the identity
        [[1.00, 1.00, 1.00, 0.50], [0.95, 0.70, 0.80, 0.60], [0.99, 0.80, 0.74, 0.90]], dtype=torch.float64
    )
    assert select_start(final).tolist() == [1, 1, 2, 0]  # margin 0: the lowest residual
    assert select_start(final, 0.25).tolist() == [0, 1, 2, 0]  # 0.95 and 0.70 / 0.74: only clear wins move
    assert select_start(final, 0.29).tolist() == [0, 1, 0, 0]
    assert select_start(final, 0.99).tolist() == [0, 0, 0, 0]


def test_start_margin_picks_per_item_as_select_start_on_one_start_solves() -> None:
    """Against a per-item loop of one-start solves: with a margin the kept start is ``select_start`` of their final
    residuals. Items 0-1 are turned 126 deg (another start fits far better), item 2 is not (the starts land on the
    identity's pose with almost the same residual): a small margin keeps item 2 on the identity, a large one all."""
    from lcreg.nn.lk import axis_rotation_starts, select_start

    src, ref, _ = _problem(b=3)
    turn = so3.exp(torch.tensor([[0.0, 0.0, 2.2]], dtype=torch.float64))[0]
    noise = 0.02 * torch.randn(ref.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    ref = torch.cat([ref[:2] @ turn.T, ref[2:]]) + noise  # noise: no start fits exactly
    enc, solver = _encoder(), InverseCompositionalLK(max_iterations=8)
    starts = axis_rotation_starts([60.0, 120.0], dtype=torch.float64)
    finals = torch.stack(
        [
            torch.cat(
                [solver(enc, src[i : i + 1], ref[i : i + 1], starts=s[None]).aux["final_residual"] for s in starts]
            )
            for i in range(len(src))
        ],
        dim=1,
    )  # (S, B)
    gain = 1 - finals.min(0).values / finals[0]  # the best start's relative gain over the identity
    assert gain[:2].min() > 0.5 and 0 < gain[2] < 0.1
    identity = solver(enc, src, ref, starts=starts[:1])
    for margin, moved in ((0.0, [1, 1, 1]), (0.1, [1, 1, 0]), (float(gain.max()) + 0.01, [0, 0, 0])):
        batched = solver(enc, src, ref, starts=starts, start_margin=margin)
        assert torch.equal(batched.aux["start"], select_start(finals, margin))
        assert (batched.aux["start"] != 0).long().tolist() == moved
    torch.testing.assert_close(batched.transform_ref_src, identity.transform_ref_src)  # the largest margin
    for bad in (-0.1, 1.0, float("nan")):
        with pytest.raises(ValueError, match="start_margin"):
            solver(enc, src, ref, starts=starts, start_margin=bad)


def test_starts_are_differentiable_and_checked() -> None:
    src, ref, _ = _problem(b=2)
    enc = _encoder()
    from lcreg.nn.lk import axis_rotation_starts

    solver = InverseCompositionalLK(max_iterations=3, differentiable=True)
    result = solver(enc, src, ref, starts=axis_rotation_starts([45.0], dtype=torch.float64))
    result.transform_ref_src.sum().backward()
    grads = [p.grad for p in enc.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads)
    for bad in (torch.eye(4)[None, :3], torch.eye(4), torch.zeros(0, 4, 4)):
        with pytest.raises(ValueError, match="`starts` must have shape"):
            solver(enc, src, ref, starts=bad)


def test_step_from_is_one_update_of_the_solve_zero_at_an_exact_fixed_point() -> None:
    """``step_from``: from the pose that centres both clouds it is the solve's first update (``max_iterations=1``);
    at the true pose of one sampling (``psi(G X0) = psi(Y0)``) it does not move; independent samplings move it;
    the graph reaches the encoder's weights; its mode is restored; bad poses are refused."""
    src, ref, truth = _problem()
    enc, solver = _encoder().train(), InverseCompositionalLK(max_iterations=1, tolerance=0.0)
    centring = se3.make_transform(torch.eye(3, dtype=src.dtype).expand(3, 3, 3), ref.mean(1) - src.mean(1))
    torch.testing.assert_close(solver.step_from(enc, src, ref, centring), solver(enc, src, ref).transform_ref_src)
    assert enc.training
    torch.testing.assert_close(solver.step_from(enc, src, ref, truth), truth, atol=1e-9, rtol=0)
    resampled, _, _ = _problem(n=160)  # other points of the same shapes: the true pose is not a fixed point
    moved = solver.step_from(enc, resampled, ref, truth)
    assert float(translation_error(moved, truth).min()) > 1e-6
    moved.sum().backward()
    grads = [p.grad for p in enc.parameters() if p.grad is not None]
    assert grads and all(bool(torch.isfinite(g).all()) for g in grads) and any(bool(g.abs().sum() > 0) for g in grads)
    with pytest.raises(TypeError):
        solver.step_from(enc, src, ref, truth.float())
    with pytest.raises(ValueError):
        solver.step_from(enc, src, ref, truth[:, :3])


def test_step_from_gradients_match_finite_differences() -> None:
    """gradcheck of ``step_from`` (analytic Jacobian, float64) in the source points and the start pose's twist."""
    src, ref, truth = _problem(b=1, n=24)
    torch.manual_seed(0)
    enc = PointNetEncoder((8, 16)).double().eval()
    solver = InverseCompositionalLK()
    resampled = src + 0.01 * torch.randn_like(src)  # off the fixed point, so the update is not zero
    xi = torch.zeros(1, 6, dtype=torch.float64, requires_grad=True)
    points = resampled.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p: solver.step_from(enc, p, ref, truth), (points,))
    assert torch.autograd.gradcheck(lambda x: solver.step_from(enc, resampled, ref, se3.exp(x) @ truth), (xi,))
