from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from lcreg.checks import ShapeError
from lcreg.geometry.euler import euler_zyx_to_matrix, matrix_to_euler_zyx

TOL = {torch.float32: 1e-5, torch.float64: 1e-12}


def random_angles_zyx(num: int, seed: int = 0) -> np.ndarray:
    gen = np.random.default_rng(seed)
    z = gen.uniform(-math.pi, math.pi, num)
    y = gen.uniform(-math.pi / 2 + 1e-3, math.pi / 2 - 1e-3, num)
    x = gen.uniform(-math.pi, math.pi, num)
    return np.stack([z, y, x], axis=1)


def test_matrix_matches_scipy_from_euler(dtype: torch.dtype) -> None:
    angles = random_angles_zyx(100)
    rot = euler_zyx_to_matrix(torch.tensor(angles, dtype=dtype))
    assert rot.shape == (100, 3, 3) and rot.dtype == dtype
    np.testing.assert_allclose(rot.double().numpy(), Rotation.from_euler("zyx", angles).as_matrix(), atol=TOL[dtype])


def test_convention_is_rx_ry_rz() -> None:
    z, y, x = 0.3, -0.7, 1.1

    def rx(a: float) -> np.ndarray:
        return np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])

    def ry(a: float) -> np.ndarray:
        return np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])

    def rz(a: float) -> np.ndarray:
        return np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])

    rot = euler_zyx_to_matrix(torch.tensor([z, y, x], dtype=torch.float64)).numpy()
    np.testing.assert_allclose(rot, rx(x) @ ry(y) @ rz(z), atol=1e-15)
    # A pure z angle is a right-handed rotation about +z, stored first.
    pure_z = euler_zyx_to_matrix(torch.tensor([0.5, 0.0, 0.0], dtype=torch.float64)).numpy()
    np.testing.assert_allclose(pure_z, rz(0.5), atol=1e-15)


def test_angles_match_scipy_as_euler(dtype: torch.dtype) -> None:
    mats = Rotation.random(200, random_state=1).as_matrix()
    angles = matrix_to_euler_zyx(torch.tensor(mats, dtype=dtype)).double().numpy()
    np.testing.assert_allclose(angles, Rotation.from_matrix(mats).as_euler("zyx"), atol=100 * TOL[dtype])


@pytest.mark.parametrize("pitch", [math.pi / 2, -math.pi / 2])
def test_gimbal_lock_matches_scipy(dtype: torch.dtype, pitch: float) -> None:
    mats = Rotation.from_euler("zyx", [[0.3, pitch, 0.2], [-1.0, pitch, 0.4]]).as_matrix()
    angles = matrix_to_euler_zyx(torch.tensor(mats, dtype=dtype))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # scipy's "Gimbal lock detected"
        expected = Rotation.from_matrix(mats).as_euler("zyx")
    np.testing.assert_allclose(angles.double().numpy(), expected, atol=1e-6 if dtype == torch.float64 else 1e-3)
    torch.testing.assert_close(euler_zyx_to_matrix(angles).double(), torch.tensor(mats), atol=1e-5, rtol=0)


def test_round_trip(dtype: torch.dtype) -> None:
    angles = torch.tensor(random_angles_zyx(100, seed=2), dtype=dtype)
    torch.testing.assert_close(matrix_to_euler_zyx(euler_zyx_to_matrix(angles)), angles, atol=100 * TOL[dtype], rtol=0)


def test_dcp_range_round_trip_and_batching(dtype: torch.dtype) -> None:
    angles = torch.rand(2, 5, 3, generator=torch.Generator().manual_seed(0), dtype=dtype) * math.radians(45)
    rot = euler_zyx_to_matrix(angles)
    assert rot.shape == (2, 5, 3, 3)
    torch.testing.assert_close(rot[1, 3], euler_zyx_to_matrix(angles[1, 3]))
    torch.testing.assert_close(matrix_to_euler_zyx(rot), angles, atol=10 * TOL[dtype], rtol=0)


def test_gradients_are_finite_at_gimbal_lock() -> None:
    angles = torch.tensor([[0.3, math.pi / 2, 0.0], [0.1, 0.2, 0.3]], dtype=torch.float64, requires_grad=True)
    matrix_to_euler_zyx(euler_zyx_to_matrix(angles)).sum().backward()
    assert angles.grad is not None and torch.isfinite(angles.grad).all()


def test_errors() -> None:
    with pytest.raises(ShapeError, match="angles_zyx"):
        euler_zyx_to_matrix(torch.zeros(2, 4))
    with pytest.raises(TypeError, match="angles_zyx"):
        euler_zyx_to_matrix(torch.zeros(2, 3, dtype=torch.int64))
    with pytest.raises(ShapeError, match="rot"):
        matrix_to_euler_zyx(torch.zeros(2, 4, 4))
    with pytest.raises(TypeError, match="rot"):
        matrix_to_euler_zyx(torch.eye(3, dtype=torch.int64))
