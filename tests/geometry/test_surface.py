"""``lcreg.geometry.surface``: point-to-plane residuals of rigid motions, and random motions of a given size."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from lcreg.checks import NonFiniteError, ShapeError
from lcreg.geometry import se3, so3
from lcreg.geometry.normals import estimate_normals
from lcreg.geometry.surface import random_motions_like, surface_residual


def _sphere(n: int, seed: int = 0) -> torch.Tensor:
    points = torch.randn(1, n, 3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    return points / points.norm(dim=-1, keepdim=True)


def _plane(side: int = 40) -> tuple[torch.Tensor, torch.Tensor]:
    grid = torch.linspace(-1, 1, side, dtype=torch.float64)
    xy = torch.stack(torch.meshgrid(grid, grid, indexing="ij"), -1).reshape(1, -1, 2)
    points = torch.cat([xy, torch.zeros(1, side * side, 1, dtype=torch.float64)], dim=-1)
    return points, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand_as(points).clone()


def _motion(rotvec: list[float], trans: list[float]) -> torch.Tensor:
    rot = so3.exp(torch.tensor([rotvec], dtype=torch.float64))
    return se3.make_transform(rot, torch.tensor([trans], dtype=torch.float64))


def _reference(points: np.ndarray, motion: np.ndarray, surface: np.ndarray, normals: np.ndarray) -> float:
    """One item by a plain loop: nearest surface point of each moved point, then |n . offset|."""
    moved = points @ motion[:3, :3].T + motion[:3, 3]
    total = 0.0
    for x in moved:
        k = int(np.argmin(((surface - x) ** 2).sum(-1)))
        total += abs(float(normals[k] @ (x - surface[k])))
    return total / len(moved)


def test_identity_leaves_surface_points_on_the_surface() -> None:
    sphere = _sphere(500)
    normals = estimate_normals(sphere, k=12)
    assert surface_residual(sphere[:, :100], se3.identity(1, dtype=torch.float64), sphere, normals).item() == 0.0


def test_a_sphere_turned_about_its_centre_hides_the_turn_but_not_a_shift() -> None:
    sphere = _sphere(4000)
    normals = estimate_normals(sphere, k=16)
    turned = surface_residual(sphere[:, :300], _motion([0.0, 0.3, 0.4], [0, 0, 0]), sphere, normals).item()
    shifted = surface_residual(sphere[:, :300], _motion([0, 0, 0], [0.1, 0, 0]), sphere, normals).item()
    assert turned < 0.003  # the 0.5 rad turn moves each point by up to 0.5; the sphere shows almost none of it
    assert shifted == pytest.approx(0.05, abs=0.006)  # a shift d shows as d |cos| on a sphere: mean d / 2


def test_a_plane_shows_only_the_normal_part_of_a_motion() -> None:
    plane, normals = _plane()
    inner = plane[:, (plane[0, :, :2].abs() < 0.5).all(-1)]  # away from the edges, so slides stay on the plane
    slide = surface_residual(inner, _motion([0, 0, 0.2], [0.1, -0.05, 0.0]), plane, normals).item()
    lift = surface_residual(inner, _motion([0, 0, 0], [0.02, 0.0, 0.03]), plane, normals).item()
    assert slide < 1e-12
    assert lift == pytest.approx(0.03, abs=1e-12)


def test_batched_equals_a_loop_and_the_normals_sign_does_not_matter() -> None:
    gen = torch.Generator().manual_seed(3)
    surface = torch.rand(3, 200, 3, generator=gen, dtype=torch.float64)
    normals = estimate_normals(surface, k=10)
    points = surface[:, :50] + 0.01 * torch.randn(3, 50, 3, generator=gen, dtype=torch.float64)
    motion = se3.make_transform(
        so3.exp(0.2 * torch.randn(3, 3, generator=gen, dtype=torch.float64)),
        0.05 * torch.randn(3, 3, generator=gen, dtype=torch.float64),
    )
    batched = surface_residual(points, motion, surface, normals)
    signs = torch.where(torch.rand(3, 200, 1, generator=gen) < 0.5, -1.0, 1.0).to(torch.float64)
    assert torch.allclose(surface_residual(points, motion, surface, normals * signs), batched, rtol=0, atol=1e-12)
    for b in range(3):
        expected = _reference(*(t[b].numpy() for t in (points, motion, surface, normals)))
        assert batched[b].item() == pytest.approx(expected, rel=1e-9)


def test_bad_input_is_named() -> None:
    sphere = _sphere(50)
    normals = estimate_normals(sphere, k=8)
    motion = se3.identity(1, dtype=torch.float64)
    with pytest.raises(NonFiniteError, match="motion"):
        surface_residual(sphere, torch.full_like(motion, float("nan")), sphere, normals)
    with pytest.raises(ShapeError, match="normals"):
        surface_residual(sphere, motion, sphere, normals[:, :20])
    with pytest.raises(ShapeError, match="motion"):
        surface_residual(sphere, se3.identity(2, dtype=torch.float64), sphere, normals)


def test_random_motions_keep_each_item_s_angle_and_length_and_vary_the_directions() -> None:
    motion = torch.cat([_motion([0.0, 0.0, 0.25], [0.1, 0.2, 0.0]), _motion([0.6, 0.0, 0.0], [0.0, 0.0, 0.0])])
    draws = random_motions_like(motion, 50, torch.Generator().manual_seed(0))
    assert draws.shape == (2, 50, 4, 4)
    rot, trans = se3.split(draws)
    angles = so3.log(rot).norm(dim=-1)
    assert torch.allclose(angles[0], torch.full((50,), 0.25, dtype=torch.float64), atol=1e-9)
    assert torch.allclose(angles[1], torch.full((50,), 0.6, dtype=torch.float64), atol=1e-9)
    assert torch.allclose(trans[0].norm(dim=-1), torch.full((50,), math.sqrt(0.05), dtype=torch.float64), atol=1e-12)
    assert torch.equal(trans[1], torch.zeros_like(trans[1]))
    axes = so3.log(rot[0]) / 0.25
    assert axes.mean(0).norm() < 0.35  # spread over the sphere, not one axis
    again = random_motions_like(motion, 50, torch.Generator().manual_seed(0))
    assert torch.equal(draws, again)
    with pytest.raises(ValueError, match="draws"):
        random_motions_like(motion, 0)


def test_random_motions_refuse_a_non_finite_motion() -> None:
    with pytest.raises(NonFiniteError, match="motion"):
        random_motions_like(torch.full((1, 4, 4), float("nan")), 4)
