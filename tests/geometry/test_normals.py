from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from lcreg.checks import ShapeError, TooFewPointsError
from lcreg.geometry.normals import estimate_normals
from lcreg.geometry.random_transforms import random_rotation


def fibonacci_sphere(num: int) -> np.ndarray:
    i = np.arange(num) + 0.5
    phi = np.arccos(1 - 2 * i / num)
    theta = math.pi * (1 + 5**0.5) * i
    return np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], axis=1)


def random_ellipsoid(num: int, seed: int) -> np.ndarray:
    p = np.random.default_rng(seed).normal(size=(num, 3))
    return p / np.linalg.norm(p, axis=1, keepdims=True) * np.array([1.0, 0.7, 0.4])


def test_sphere_normals_are_radial(dtype: torch.dtype) -> None:
    points = torch.tensor(fibonacci_sphere(600), dtype=dtype)[None]
    normals = estimate_normals(points, k=16)
    assert normals.shape == (1, 600, 3) and normals.dtype == dtype
    torch.testing.assert_close(normals.norm(dim=-1), torch.ones(1, 600, dtype=dtype))
    cos = (normals * points).sum(-1).abs()
    assert cos.min() > 0.99


def test_orient_towards_viewpoint(dtype: torch.dtype) -> None:
    points = torch.tensor(fibonacci_sphere(300), dtype=dtype)[None].repeat(2, 1, 1)
    outward = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]], dtype=dtype)
    normals = estimate_normals(points, k=12, orient_towards=outward)
    assert ((normals * points).sum(-1) < 0).all()  # facing the centre
    far = torch.tensor([[0.0, 0.0, 100.0], [0.0, 0.0, -100.0]], dtype=dtype)
    normals = estimate_normals(points, k=12, orient_towards=far)
    assert ((normals * (far[:, None] - points)).sum(-1) >= 0).all()


def test_plane_normals_are_exact(dtype: torch.dtype, rng: torch.Generator) -> None:
    points = torch.rand(3, 200, 3, generator=rng, dtype=dtype) * 2 - 1
    points[..., 2] = 0
    rot = random_rotation(3, rng, dtype)
    points = points @ rot.transpose(1, 2) + 5.0  # tilted planes away from the origin
    normals = estimate_normals(points, k=10)
    cos = (normals * rot[:, None, :, 2]).sum(-1).abs()
    torch.testing.assert_close(cos, torch.ones_like(cos), atol=1e-4 if dtype == torch.float32 else 1e-10, rtol=0)


def test_matches_open3d() -> None:
    o3d = pytest.importorskip("open3d")
    points = random_ellipsoid(800, seed=0)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(16))
    expected = np.asarray(cloud.normals)
    got = estimate_normals(torch.tensor(points)[None], k=16)[0].numpy()
    cos = np.abs((got * expected).sum(1))
    assert np.mean(cos > 0.99) > 0.98
    assert np.median(cos) > 0.9999


def test_batched_matches_per_item(dtype: torch.dtype) -> None:
    points = torch.stack([torch.tensor(random_ellipsoid(100, seed=s), dtype=dtype) for s in range(3)])
    batched = estimate_normals(points, k=8)
    for b in range(3):
        single = estimate_normals(points[b : b + 1], k=8)[0]
        cos = (batched[b] * single).sum(-1).abs()
        torch.testing.assert_close(cos, torch.ones_like(cos), atol=1e-4, rtol=0)


def test_errors() -> None:
    points = torch.randn(2, 10, 3)
    with pytest.raises(ValueError, match="`k`"):
        estimate_normals(points, k=2)
    with pytest.raises(TooFewPointsError, match="points"):
        estimate_normals(points, k=11)
    with pytest.raises(ShapeError, match="orient_towards"):
        estimate_normals(points, k=4, orient_towards=torch.zeros(3))
    with pytest.raises(TypeError, match="orient_towards"):
        estimate_normals(points, k=4, orient_towards=torch.zeros(2, 3, dtype=torch.float64))
