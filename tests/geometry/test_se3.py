from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.linalg
import torch
from scipy.spatial.transform import Rotation

from lcreg.checks import ShapeError
from lcreg.geometry import se3, so3

TOL = {torch.float32: 2e-5, torch.float64: 1e-10}


def random_twists(num: int, angle: float | None = None, seed: int = 0) -> np.ndarray:
    """Twists ``[omega, v]`` with random axes, angles uniform in [0, pi - 0.05) (or ``angle``), ``v ~ N(0, 1)``."""
    gen = np.random.default_rng(seed)
    axes = gen.normal(size=(num, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = gen.uniform(0, math.pi - 0.05, size=(num, 1)) if angle is None else np.full((num, 1), angle)
    return np.concatenate([axes * angles, gen.normal(size=(num, 3))], axis=1)


def twist_matrix(xi: np.ndarray) -> np.ndarray:
    """The 4x4 Lie-algebra matrix ``[[hat(omega), v], [0, 0]]`` of a twist ordered ``[omega, v]``."""
    out = np.zeros((4, 4))
    wx, wy, wz = xi[:3]
    out[:3, :3] = [[0, -wz, wy], [wz, 0, -wx], [-wy, wx, 0]]
    out[:3, 3] = xi[3:]
    return out


def random_transforms(num: int, seed: int = 0) -> np.ndarray:
    gen = np.random.default_rng(seed)
    out = np.tile(np.eye(4), (num, 1, 1))
    out[:, :3, :3] = Rotation.random(num, random_state=seed).as_matrix()
    out[:, :3, 3] = gen.normal(size=(num, 3))
    return out


@pytest.mark.parametrize("angle", [None, 0.0, 1e-8, 1e-4, 5e-3, 2e-2, math.pi - 1e-3, math.pi - 1e-6])
def test_exp_matches_expm_of_twist_matrix(dtype: torch.dtype, angle: float | None) -> None:
    xis = random_twists(16, angle)
    expected = np.stack([scipy.linalg.expm(twist_matrix(x)) for x in xis])
    np.testing.assert_allclose(se3.exp(torch.tensor(xis, dtype=dtype)).double().numpy(), expected, atol=TOL[dtype])


def test_twist_order_is_rotation_first() -> None:
    xi = torch.tensor([0.0, 0.0, 0.0, 1.0, 2.0, 3.0], dtype=torch.float64)  # pure translation
    torch.testing.assert_close(se3.exp(xi)[:3, 3], xi[3:])
    torch.testing.assert_close(se3.exp(xi)[:3, :3], torch.eye(3, dtype=torch.float64))
    xi = torch.tensor([0.0, 0.0, 0.5, 0.0, 0.0, 0.0], dtype=torch.float64)  # pure rotation about z
    torch.testing.assert_close(se3.exp(xi)[:3, :3], so3.exp(xi[:3]))
    torch.testing.assert_close(se3.exp(xi)[:3, 3], torch.zeros(3, dtype=torch.float64))


def test_exp_structure(dtype: torch.dtype) -> None:
    transform = se3.exp(torch.tensor(random_twists(32, seed=1), dtype=dtype))
    rot = transform[:, :3, :3]
    torch.testing.assert_close(rot.transpose(1, 2) @ rot, torch.eye(3, dtype=dtype).expand_as(rot), atol=1e-5, rtol=0)
    torch.testing.assert_close(torch.linalg.det(rot), torch.ones(32, dtype=dtype), atol=1e-5, rtol=0)
    bottom = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=dtype).expand(32, 4)
    assert torch.equal(transform[:, 3, :], bottom)


@pytest.mark.parametrize("angle", [None, 0.0, 1e-8, 1e-4, 2e-2, math.pi - 1e-3])
def test_round_trip_log_exp(dtype: torch.dtype, angle: float | None) -> None:
    xi = torch.tensor(random_twists(32, angle, seed=2), dtype=dtype)
    atol = 1e-9 if dtype == torch.float64 else (2e-3 if angle == math.pi - 1e-3 else 1e-4)
    torch.testing.assert_close(se3.log(se3.exp(xi)), xi, atol=atol, rtol=0)


def test_log_matches_scipy_logm(dtype: torch.dtype) -> None:
    mats = random_transforms(8, seed=3)
    xi = se3.log(torch.tensor(mats, dtype=dtype)).double().numpy()
    for x, mat in zip(xi, mats):
        np.testing.assert_allclose(twist_matrix(x), np.real(scipy.linalg.logm(mat)), atol=200 * TOL[dtype])


def test_round_trip_exp_log(dtype: torch.dtype) -> None:
    mats = torch.tensor(random_transforms(32, seed=4), dtype=dtype)
    torch.testing.assert_close(se3.exp(se3.log(mats)), mats, atol=100 * TOL[dtype], rtol=0)


def test_batched_matches_per_item(dtype: torch.dtype) -> None:
    xi = torch.tensor(random_twists(6, seed=5), dtype=dtype).reshape(2, 3, 6)
    transform = se3.exp(xi)
    assert transform.shape == (2, 3, 4, 4)
    for i in range(2):
        for j in range(3):
            torch.testing.assert_close(transform[i, j], se3.exp(xi[i, j]))
            torch.testing.assert_close(se3.log(transform)[i, j], se3.log(transform[i, j]))


def test_gradcheck_exp_and_log() -> None:
    xi = torch.tensor(random_twists(3, seed=6), requires_grad=True)
    assert torch.autograd.gradcheck(se3.exp, (xi,))
    tiny = torch.tensor(random_twists(2, 1e-5, seed=7), requires_grad=True)
    assert torch.autograd.gradcheck(se3.exp, (tiny,))
    mats = torch.tensor(random_transforms(3, seed=8))
    mats = se3.exp(se3.log(mats) * 0.8).detach().requires_grad_(True)  # angles < 0.8 pi
    assert torch.autograd.gradcheck(se3.log, (mats,))


def test_jacobian_at_zero_pins_the_twist_order(dtype: torch.dtype) -> None:
    jac = torch.autograd.functional.jacobian(se3.exp, torch.zeros(6, dtype=dtype))  # (4, 4, 6)
    for k in range(6):
        expected = torch.tensor(twist_matrix(np.eye(6)[k]), dtype=dtype)
        torch.testing.assert_close(jac[..., k], expected)
    jac_round_trip = torch.autograd.functional.jacobian(lambda x: se3.log(se3.exp(x)), torch.zeros(6, dtype=dtype))
    torch.testing.assert_close(jac_round_trip, torch.eye(6, dtype=dtype))


def test_finite_gradients_at_zero(dtype: torch.dtype) -> None:
    xi = torch.zeros(2, 6, dtype=dtype, requires_grad=True)
    se3.exp(xi).sum().backward()
    assert xi.grad is not None and torch.isfinite(xi.grad).all()
    eye = torch.eye(4, dtype=dtype).expand(2, 4, 4).clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(se3.log(eye).sum(), eye)
    assert torch.isfinite(grad).all()


def test_inverse_compose_transform_points_against_numpy(dtype: torch.dtype) -> None:
    mats_a, mats_b = random_transforms(5, seed=9), random_transforms(5, seed=10)
    a, b = torch.tensor(mats_a, dtype=dtype), torch.tensor(mats_b, dtype=dtype)
    atol = 1e-5 if dtype == torch.float32 else 1e-12
    np.testing.assert_allclose(se3.inverse(a).double().numpy(), np.linalg.inv(mats_a), atol=atol)
    np.testing.assert_allclose(se3.compose(a, b).double().numpy(), mats_a @ mats_b, atol=atol)
    points = np.random.default_rng(11).normal(size=(5, 7, 3))
    expected = np.einsum("bij,bnj->bni", mats_a[:, :3, :3], points) + mats_a[:, None, :3, 3]
    got = se3.transform_points(a, torch.tensor(points, dtype=dtype)).double().numpy()
    np.testing.assert_allclose(got, expected, atol=atol)
    normals = se3.transform_normals(a, torch.tensor(points, dtype=dtype)).double().numpy()
    np.testing.assert_allclose(normals, np.einsum("bij,bnj->bni", mats_a[:, :3, :3], points), atol=atol)


def test_compose_order_and_frames() -> None:
    t_ab, t_bc = (torch.tensor(m) for m in (random_transforms(3, seed=12), random_transforms(3, seed=13)))
    points_c = torch.randn(3, 4, 3, dtype=torch.float64)
    via_b = se3.transform_points(t_ab, se3.transform_points(t_bc, points_c))
    torch.testing.assert_close(se3.transform_points(se3.compose(t_ab, t_bc), points_c), via_b)
    back = se3.transform_points(se3.inverse(t_ab), se3.transform_points(t_ab, points_c))
    torch.testing.assert_close(back, points_c)


def test_make_transform_split_identity(dtype: torch.dtype) -> None:
    rot = so3.exp(torch.randn(4, 3, dtype=dtype))
    trans = torch.randn(4, 3, dtype=dtype)
    transform = se3.make_transform(rot, trans)
    assert transform.shape == (4, 4, 4)
    r, t = se3.split(transform)
    assert torch.equal(r, rot) and torch.equal(t, trans)
    ident = se3.identity(3, dtype=dtype)
    assert ident.dtype == dtype and torch.equal(ident, torch.eye(4, dtype=dtype).expand(3, 4, 4))


def test_errors() -> None:
    with pytest.raises(ShapeError, match="xi"):
        se3.exp(torch.zeros(2, 3))
    with pytest.raises(TypeError, match="xi"):
        se3.exp(torch.zeros(2, 6, dtype=torch.int64))
    with pytest.raises(ShapeError, match="transform"):
        se3.log(torch.zeros(2, 3, 3))
    with pytest.raises(TypeError, match="transform"):
        se3.log(torch.eye(4, dtype=torch.int64))
    with pytest.raises(ShapeError, match="trans"):
        se3.make_transform(torch.zeros(2, 3, 3), torch.zeros(3, 3))
    with pytest.raises(ShapeError, match="rot"):
        se3.make_transform(torch.zeros(2, 4, 3), torch.zeros(2, 3))
    eye = se3.identity(2)
    with pytest.raises(ShapeError, match="points"):
        se3.transform_points(eye, torch.zeros(2, 5, 2))
    with pytest.raises(TypeError, match="points"):
        se3.transform_points(eye, torch.zeros(2, 5, 3, dtype=torch.int64))
    with pytest.raises(TypeError, match="points"):
        se3.transform_points(eye, torch.zeros(2, 5, 3, dtype=torch.float64))
    with pytest.raises(ShapeError, match="transform"):
        se3.transform_points(torch.zeros(2, 3, 4), torch.zeros(2, 5, 3))
    with pytest.raises(ShapeError, match="normals"):
        se3.transform_normals(eye, torch.zeros(2, 5, 4))
    with pytest.raises(ShapeError, match="transform"):
        se3.inverse(torch.zeros(2, 3, 3))
    with pytest.raises(ShapeError, match="transform_b_c"):
        se3.compose(eye, torch.zeros(2, 3, 3))
    with pytest.raises(TypeError, match="transform_a_b"):
        se3.compose(eye.long(), eye)


def test_uncenter_matches_the_translation_sandwich() -> None:
    gen = torch.Generator().manual_seed(3)
    g = se3.exp(torch.randn(4, 6, generator=gen, dtype=torch.float64))
    mean_src, mean_ref = (
        torch.randn(4, 3, generator=gen, dtype=torch.float64),
        torch.randn(4, 3, generator=gen, dtype=torch.float64),
    )
    eye = torch.eye(3, dtype=torch.float64).expand(4, 3, 3)
    expected = se3.make_transform(eye, mean_ref) @ g @ se3.make_transform(eye, -mean_src)
    torch.testing.assert_close(se3.uncenter(g, mean_src, mean_ref), expected)
    points = torch.randn(4, 10, 3, generator=gen, dtype=torch.float64)
    centred = se3.transform_points(g, points - mean_src[:, None]) + mean_ref[:, None]
    torch.testing.assert_close(se3.transform_points(se3.uncenter(g, mean_src, mean_ref), points), centred)
