from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from lcreg.checks import ShapeError
from lcreg.geometry import so3

TOL = {torch.float32: 1e-5, torch.float64: 1e-11}
# Angles that exercise every branch: exact zero, deep and shallow Taylor regions, both sides of the small-angle
# thresholds (1e-4 in float64, 1e-2 in float32) and both sides of the near-pi thresholds.
SPECIAL_ANGLES = [0.0, 1e-8, 1e-4, 5e-3, 2e-2, 1.0, math.pi - 1e-3, math.pi - 1e-6]


def random_rotvecs(num: int, angle: float | None = None, seed: int = 0) -> np.ndarray:
    """Random axes times ``angle`` (or angles uniform in [0, pi))."""
    gen = np.random.default_rng(seed)
    axes = gen.normal(size=(num, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = gen.uniform(0, math.pi, size=(num, 1)) if angle is None else np.full((num, 1), angle)
    return axes * angles


def test_hat_vee() -> None:
    a, b = torch.randn(2, 5, 3, dtype=torch.float64).unbind(0)
    torch.testing.assert_close(so3.hat(a) @ b[..., None], torch.linalg.cross(a, b)[..., None])
    torch.testing.assert_close(so3.vee(so3.hat(a)), a)
    torch.testing.assert_close(so3.hat(a).transpose(-1, -2), -so3.hat(a))


def test_exp_matches_scipy_random(dtype: torch.dtype) -> None:
    rotvecs = random_rotvecs(64)
    rot = so3.exp(torch.tensor(rotvecs, dtype=dtype))
    assert rot.dtype == dtype and rot.shape == (64, 3, 3)
    np.testing.assert_allclose(rot.double().numpy(), Rotation.from_rotvec(rotvecs).as_matrix(), atol=TOL[dtype])


@pytest.mark.parametrize("angle", SPECIAL_ANGLES)
def test_exp_matches_scipy_special_angles(dtype: torch.dtype, angle: float) -> None:
    rotvecs = random_rotvecs(8, angle, seed=1)
    rot = so3.exp(torch.tensor(rotvecs, dtype=dtype))
    np.testing.assert_allclose(rot.double().numpy(), Rotation.from_rotvec(rotvecs).as_matrix(), atol=TOL[dtype])


def test_log_matches_scipy_random(dtype: torch.dtype) -> None:
    rotvecs = random_rotvecs(64)
    rotvecs = rotvecs[np.linalg.norm(rotvecs, axis=1) < math.pi - 0.05]  # float32 sign is ambiguous closer to pi
    mats = Rotation.from_rotvec(rotvecs).as_matrix()
    omega = so3.log(torch.tensor(mats, dtype=dtype))
    np.testing.assert_allclose(omega.double().numpy(), rotvecs, atol=20 * TOL[dtype])


@pytest.mark.parametrize("angle", SPECIAL_ANGLES)
def test_log_matches_scipy_special_angles(dtype: torch.dtype, angle: float) -> None:
    rotvecs = random_rotvecs(8, angle, seed=2)
    mats = Rotation.from_rotvec(rotvecs).as_matrix()
    omega = so3.log(torch.tensor(mats, dtype=dtype)).double().numpy()
    expected = Rotation.from_matrix(mats).as_rotvec()
    tol = 1e-9 if dtype == torch.float64 else 1e-3
    if dtype == torch.float32 and angle > math.pi - 1e-2:
        # In float32 the sign of the axis at pi - 1e-6 is below the rounding of R: both signs are valid logs.
        flip = (omega * expected).sum(1, keepdims=True) < 0
        expected = np.where(flip, -expected, expected)
    np.testing.assert_allclose(omega, expected, atol=tol)
    np.testing.assert_allclose(np.linalg.norm(omega, axis=1), angle, atol=tol)


def test_log_at_exact_pi_about_coordinate_axes(dtype: torch.dtype) -> None:
    mats = torch.diag_embed(torch.tensor([[1.0, -1.0, -1.0], [-1.0, 1.0, -1.0], [-1.0, -1.0, 1.0]], dtype=dtype))
    omega = so3.log(mats)
    torch.testing.assert_close(omega.abs(), math.pi * torch.eye(3, dtype=dtype))
    torch.testing.assert_close(so3.exp(omega), mats, atol=10 * TOL[dtype], rtol=0)


def test_round_trip_log_exp(dtype: torch.dtype) -> None:
    rotvecs = random_rotvecs(200, seed=3)
    rotvecs = rotvecs[np.linalg.norm(rotvecs, axis=1) < math.pi - 0.05]
    omega = torch.tensor(rotvecs, dtype=dtype)
    torch.testing.assert_close(so3.log(so3.exp(omega)), omega, atol=20 * TOL[dtype], rtol=0)
    small = torch.tensor(random_rotvecs(16, 1e-6, seed=4), dtype=dtype)
    torch.testing.assert_close(so3.log(so3.exp(small)), small, atol=1e-12, rtol=1e-6)


def test_round_trip_exp_log_near_pi(dtype: torch.dtype) -> None:
    mats = so3.exp(torch.tensor(random_rotvecs(16, math.pi - 1e-6, seed=5), dtype=dtype))
    torch.testing.assert_close(so3.exp(so3.log(mats)), mats, atol=20 * TOL[dtype], rtol=0)


def test_exp_is_a_rotation(dtype: torch.dtype) -> None:
    omega = torch.tensor(random_rotvecs(100, seed=6) * 3.0, dtype=dtype)  # angles beyond pi too
    rot = so3.exp(omega)
    eye = torch.eye(3, dtype=dtype).expand_as(rot)
    torch.testing.assert_close(rot.transpose(-1, -2) @ rot, eye, atol=10 * TOL[dtype], rtol=0)
    torch.testing.assert_close(torch.linalg.det(rot), torch.ones(100, dtype=dtype), atol=10 * TOL[dtype], rtol=0)


def test_batched_matches_per_item(dtype: torch.dtype) -> None:
    omega = torch.tensor(random_rotvecs(12, seed=7), dtype=dtype).reshape(3, 4, 3)
    rot = so3.exp(omega)
    assert rot.shape == (3, 4, 3, 3)
    for i in range(3):
        for j in range(4):
            torch.testing.assert_close(rot[i, j], so3.exp(omega[i, j]))
            torch.testing.assert_close(so3.log(rot)[i, j], so3.log(rot[i, j]))


def test_gradcheck_exp() -> None:
    omega = torch.tensor(random_rotvecs(4, seed=8), requires_grad=True)
    assert torch.autograd.gradcheck(so3.exp, (omega,))
    tiny = torch.tensor(random_rotvecs(3, 1e-5, seed=9), requires_grad=True)  # Taylor branch
    assert torch.autograd.gradcheck(so3.exp, (tiny,))


def test_gradcheck_log_away_from_pi() -> None:
    rotvecs = random_rotvecs(4, seed=10)
    rotvecs = rotvecs * (2.5 / np.linalg.norm(rotvecs, axis=1, keepdims=True)) * np.linspace(0.2, 1, 4)[:, None]
    mats = torch.tensor(Rotation.from_rotvec(rotvecs).as_matrix(), requires_grad=True)
    assert torch.autograd.gradcheck(so3.log, (mats,))
    small = torch.tensor(Rotation.from_rotvec(random_rotvecs(2, 1e-3, seed=11)).as_matrix(), requires_grad=True)
    assert torch.autograd.gradcheck(so3.log, (small,))


def test_jacobians_at_zero_are_the_generators(dtype: torch.dtype) -> None:
    zero = torch.zeros(3, dtype=dtype)
    jac_exp = torch.autograd.functional.jacobian(so3.exp, zero)  # (3, 3, 3): d R_ij / d omega_k
    generators = so3.hat(torch.eye(3, dtype=dtype))  # (3, 3, 3): hat(e_k)
    torch.testing.assert_close(jac_exp.permute(2, 0, 1), generators)
    jac_round_trip = torch.autograd.functional.jacobian(lambda w: so3.log(so3.exp(w)), zero)
    torch.testing.assert_close(jac_round_trip, torch.eye(3, dtype=dtype))


def test_finite_gradients_at_zero_and_mixed_batch(dtype: torch.dtype) -> None:
    omega = torch.tensor(np.concatenate([np.zeros((1, 3)), random_rotvecs(2, math.pi - 1e-6)]), dtype=dtype)
    omega.requires_grad_(True)
    so3.exp(omega).sum().backward()
    assert omega.grad is not None and torch.isfinite(omega.grad).all()

    mats = so3.exp(omega.detach()).requires_grad_(True)  # identity next to near-pi rotations
    so3.log(mats).square().sum().backward()
    assert mats.grad is not None and torch.isfinite(mats.grad).all()

    eye = torch.eye(3, dtype=dtype, requires_grad=True)
    (grad,) = torch.autograd.grad(so3.log(eye).sum(), eye)
    assert torch.isfinite(grad).all()


def test_errors() -> None:
    with pytest.raises(ShapeError, match="omega"):
        so3.exp(torch.zeros(2, 4))
    with pytest.raises(TypeError, match="omega"):
        so3.exp(torch.zeros(2, 3, dtype=torch.int64))
    with pytest.raises(ShapeError, match="rot"):
        so3.log(torch.zeros(2, 3, 4))
    with pytest.raises(TypeError, match="rot"):
        so3.log(torch.eye(3, dtype=torch.int32))
    with pytest.raises(ShapeError, match="omega"):
        so3.hat(torch.zeros(2))
    with pytest.raises(ShapeError, match="mat"):
        so3.vee(torch.zeros(4, 4))


# --- quaternions -------------------------------------------------------------------------------------------------
def _wxyz(quat_xyzw: np.ndarray) -> np.ndarray:
    """scipy's scalar-last ``(x, y, z, w)`` to our scalar-first ``(w, x, y, z)``."""
    return np.roll(quat_xyzw, 1, axis=-1)


def test_quaternion_to_matrix_matches_scipy(dtype: torch.dtype) -> None:
    rots = Rotation.random(64, random_state=12)
    quat = torch.tensor(_wxyz(rots.as_quat()), dtype=dtype)
    mats = so3.quaternion_to_matrix(quat)
    assert mats.dtype == dtype and mats.shape == (64, 3, 3)
    np.testing.assert_allclose(mats.double().numpy(), rots.as_matrix(), atol=TOL[dtype])
    # One axis by hand: (w, x, y, z) = (cos 30deg, sin 30deg, 0, 0) is 60 degrees about x.
    half = math.radians(30)
    about_x = so3.quaternion_to_matrix(torch.tensor([math.cos(half), math.sin(half), 0.0, 0.0], dtype=dtype))
    np.testing.assert_allclose(
        about_x.double().numpy(), Rotation.from_euler("x", 60, degrees=True).as_matrix(), atol=TOL[dtype]
    )


def test_quaternion_to_matrix_normalises_and_ignores_sign(dtype: torch.dtype) -> None:
    gen = np.random.default_rng(13)
    raw = gen.normal(size=(32, 4)) * gen.uniform(1e-3, 1e3, size=(32, 1))  # arbitrary norms
    expected = Rotation.from_quat(np.roll(raw, -1, axis=-1)).as_matrix()  # scipy normalises too
    quat = torch.tensor(raw, dtype=dtype)
    torch.testing.assert_close(so3.quaternion_to_matrix(quat).double(), torch.tensor(expected), atol=TOL[dtype], rtol=0)
    torch.testing.assert_close(so3.quaternion_to_matrix(-quat), so3.quaternion_to_matrix(quat))
    rot = so3.quaternion_to_matrix(quat)
    eye = torch.eye(3, dtype=dtype).expand_as(rot)
    torch.testing.assert_close(rot.transpose(-1, -2) @ rot, eye, atol=10 * TOL[dtype], rtol=0)
    torch.testing.assert_close(torch.linalg.det(rot), torch.ones(32, dtype=dtype), atol=10 * TOL[dtype], rtol=0)


def test_quaternion_to_matrix_agrees_with_exp(dtype: torch.dtype) -> None:
    """``q = (cos(theta/2), sin(theta/2) axis)`` is the rotation ``exp(theta axis)``."""
    rotvecs = torch.tensor(random_rotvecs(16, seed=14), dtype=dtype)
    half = rotvecs.norm(dim=-1, keepdim=True) / 2
    quat = torch.cat([half.cos(), half.sin() * rotvecs / (2 * half)], dim=-1)
    torch.testing.assert_close(so3.quaternion_to_matrix(quat), so3.exp(rotvecs), atol=10 * TOL[dtype], rtol=0)


def test_quaternion_to_matrix_batched_matches_per_item(dtype: torch.dtype) -> None:
    quat = torch.randn(2, 3, 5, 4, dtype=dtype, generator=torch.Generator().manual_seed(15))
    mats = so3.quaternion_to_matrix(quat)
    assert mats.shape == (2, 3, 5, 3, 3)
    for index in np.ndindex(2, 3, 5):
        torch.testing.assert_close(mats[index], so3.quaternion_to_matrix(quat[index]))


def test_quaternion_to_matrix_zero_norm_is_the_identity_with_finite_gradient(dtype: torch.dtype) -> None:
    quat = torch.tensor([[0.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]], dtype=dtype, requires_grad=True)
    mats = so3.quaternion_to_matrix(quat)
    torch.testing.assert_close(mats[0], torch.eye(3, dtype=dtype))
    torch.testing.assert_close(mats[1], torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=dtype)))
    mats.square().sum().backward()
    assert quat.grad is not None and torch.isfinite(quat.grad).all()
    assert (quat.grad[0] == 0).all()


def test_gradcheck_quaternion_to_matrix() -> None:
    quat = torch.randn(5, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(16)).requires_grad_(True)
    assert torch.autograd.gradcheck(so3.quaternion_to_matrix, (quat,))
    # The gradient is tangent to the scale: d R / d q . q = 0 (R does not depend on |q|).
    (jac,) = torch.autograd.functional.jacobian(so3.quaternion_to_matrix, (quat[0].detach(),))
    torch.testing.assert_close(jac @ quat[0].detach(), torch.zeros(3, 3, dtype=torch.float64), atol=1e-12, rtol=0)


def test_quaternion_to_matrix_errors() -> None:
    with pytest.raises(ShapeError, match="quat"):
        so3.quaternion_to_matrix(torch.zeros(2, 3))
    with pytest.raises(TypeError, match="quat"):
        so3.quaternion_to_matrix(torch.zeros(2, 4, dtype=torch.int64))
