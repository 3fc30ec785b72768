from __future__ import annotations

import math

import pytest
import torch

from lcreg.geometry.euler import euler_zyx_to_matrix
from lcreg.geometry.random_transforms import random_euler_transform, random_rotation


def assert_rotations(rot: torch.Tensor) -> None:
    eye = torch.eye(3, dtype=rot.dtype).expand_as(rot)
    torch.testing.assert_close(rot.transpose(-1, -2) @ rot, eye, atol=1e-5, rtol=0)
    torch.testing.assert_close(torch.linalg.det(rot), torch.ones(rot.shape[0], dtype=rot.dtype), atol=1e-5, rtol=0)


def test_random_euler_transform_ranges(dtype: torch.dtype, rng: torch.Generator) -> None:
    transform, angles = random_euler_transform(2000, generator=rng, dtype=dtype)
    assert transform.shape == (2000, 4, 4) and angles.shape == (2000, 3)
    assert transform.dtype == dtype and angles.dtype == dtype
    assert angles.min() >= 0 and angles.max() <= math.radians(45)
    assert angles.max() > math.radians(44) and angles.min() < math.radians(1)  # the whole range is used
    trans = transform[:, :3, 3]
    assert trans.min() >= -0.5 and trans.max() <= 0.5
    assert trans.max() > 0.49 and trans.min() < -0.49
    assert_rotations(transform[:, :3, :3])
    torch.testing.assert_close(transform[:, :3, :3], euler_zyx_to_matrix(angles), atol=1e-6, rtol=0)
    assert torch.equal(transform[:, 3], torch.tensor([0, 0, 0, 1], dtype=dtype).expand(2000, 4))


def test_random_euler_transform_bounds() -> None:
    gen = torch.Generator().manual_seed(1)
    transform, angles = random_euler_transform(500, max_angle_deg=10.0, max_translation=0.1, generator=gen)
    assert angles.max() <= math.radians(10) and transform[:, :3, 3].abs().max() <= 0.1
    transform, angles = random_euler_transform(3, max_angle_deg=0.0, max_translation=0.0, generator=gen)
    assert torch.equal(transform, torch.eye(4).expand(3, 4, 4)) and torch.equal(angles, torch.zeros(3, 3))


def test_random_euler_transform_is_reproducible() -> None:
    first = random_euler_transform(8, generator=torch.Generator().manual_seed(7))
    second = random_euler_transform(8, generator=torch.Generator().manual_seed(7))
    other = random_euler_transform(8, generator=torch.Generator().manual_seed(8))
    assert torch.equal(first[0], second[0]) and torch.equal(first[1], second[1])
    assert not torch.equal(first[0], other[0])
    # float32 output is the rounding of the float64 draw: the same pairs whatever the dtype.
    double = random_euler_transform(8, generator=torch.Generator().manual_seed(7), dtype=torch.float64)
    torch.testing.assert_close(double[0].float(), first[0])


def test_random_euler_transform_rejects_negative_bounds() -> None:
    with pytest.raises(ValueError, match="max_angle_deg"):
        random_euler_transform(2, max_angle_deg=-1.0)
    with pytest.raises(ValueError, match="max_translation"):
        random_euler_transform(2, max_translation=-0.1)


def test_random_rotation(dtype: torch.dtype, rng: torch.Generator) -> None:
    rot = random_rotation(20000, generator=rng, dtype=dtype)
    assert rot.shape == (20000, 3, 3) and rot.dtype == dtype
    assert_rotations(rot)
    # Haar-uniform rotations have E[R] = 0 and E[R_ij^2] = 1/3.
    assert rot.mean(0).abs().max() < 0.02
    torch.testing.assert_close(rot.square().mean(0), torch.full((3, 3), 1 / 3, dtype=dtype), atol=0.02, rtol=0)
    again = random_rotation(20000, generator=torch.Generator().manual_seed(0), dtype=dtype)
    assert torch.equal(rot, again)
