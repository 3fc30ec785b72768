from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from lcreg.checks import NonFiniteError, ShapeError, TooFewPointsError
from lcreg.geometry.random_transforms import random_rotation
from lcreg.geometry.rri import neighbours_excluding_self, rri_features


def reference_rri(points: np.ndarray, k: int) -> np.ndarray:
    """Explicit per-point, per-neighbour loop of the definition (arccos angle, brute-force neighbours)."""
    x = points - points.mean(axis=0)
    out = np.zeros((len(x), k, 4))
    for i, p in enumerate(x):
        dist = np.linalg.norm(x - p, axis=1)
        dist[i] = np.inf
        nbrs = np.argsort(dist, kind="stable")[:k]
        rp = np.linalg.norm(p)
        tangents = []
        for q in x[nbrs]:
            cos = np.clip(p @ q / (rp * np.linalg.norm(q)), -1.0, 1.0)
            tangents.append(q - cos * p)
        for j, q in enumerate(x[nbrs]):
            cos = np.clip(p @ q / (rp * np.linalg.norm(q)), -1.0, 1.0)
            psis = []
            for c in range(k):
                if c == j:
                    continue
                sin_psi = np.cross(tangents[j], tangents[c]) @ (p / rp)
                psis.append(math.atan2(sin_psi, tangents[j] @ tangents[c]) % (2 * math.pi))
            out[i, j] = (rp, np.linalg.norm(q), math.acos(cos), min(psis))
    return out.reshape(len(x), 4 * k)


def random_cloud(batch: int, num: int, seed: int = 0, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    return torch.randn(batch, num, 3, generator=gen, dtype=dtype) * 0.5 + 2.0


def test_matches_explicit_loop() -> None:
    points = random_cloud(2, 40)
    feats = rri_features(points, k=6)
    assert feats.shape == (2, 40, 24)
    for b in range(2):
        expected = torch.from_numpy(reference_rri(points[b].numpy(), 6))
        torch.testing.assert_close(feats[b], expected, atol=1e-9, rtol=0)


def test_float32_agrees_with_float64() -> None:
    points = random_cloud(2, 64)
    torch.testing.assert_close(rri_features(points.float(), 8).double(), rri_features(points, 8), atol=1e-4, rtol=0)


def test_exactly_invariant_to_rigid_motion() -> None:
    points = random_cloud(3, 96, seed=1)
    gen = torch.Generator().manual_seed(2)
    rot = random_rotation(3, gen, torch.float64)
    moved = points @ rot.transpose(1, 2) + torch.randn(3, 1, 3, generator=gen, dtype=torch.float64)
    torch.testing.assert_close(rri_features(moved, 8), rri_features(points, 8), atol=1e-10, rtol=0)


def test_phi_changes_under_a_reflection() -> None:
    # A triple product with p: a mirror image (det -1) is not an allowed motion, phi must see it.
    points = random_cloud(1, 64, seed=3)
    feats = rri_features(points, 8).reshape(1, 64, 8, 4)
    mirrored = rri_features(points * torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64), 8).reshape(1, 64, 8, 4)
    torch.testing.assert_close(mirrored[..., :3], feats[..., :3], atol=1e-10, rtol=0)
    assert (mirrored[..., 3] - feats[..., 3]).abs().max() > 0.1


def test_permutation_equivariant() -> None:
    points = random_cloud(1, 50, seed=4)
    perm = torch.randperm(50, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(rri_features(points[:, perm], 5), rri_features(points, 5)[:, perm], atol=1e-12, rtol=0)


def test_neighbours_exclude_self_even_with_duplicates() -> None:
    points = random_cloud(1, 30, seed=5)
    idx = neighbours_excluding_self(points, 4)
    assert not (idx == torch.arange(30)[None, :, None]).any()
    dup = torch.cat([points, points[:, :1]], dim=1)  # point 30 duplicates point 0
    idx = neighbours_excluding_self(dup, 4)
    assert idx[0, 0, 0] == 30 and idx[0, 30, 0] == 0
    assert not (idx == torch.arange(31)[None, :, None]).any()


def test_point_at_the_centroid_gives_finite_features() -> None:
    points = random_cloud(1, 20, seed=6)
    points = torch.cat([points, points.mean(dim=1, keepdim=True)], dim=1)  # point 20 = the centroid of all 21
    feats = rri_features(points, 4)
    assert torch.isfinite(feats).all()
    assert feats[0, 20, 0] < 1e-12


def test_bad_inputs() -> None:
    points = random_cloud(1, 10)
    with pytest.raises(ValueError, match="`k`"):
        rri_features(points, k=1)
    with pytest.raises(TooFewPointsError, match="points"):
        rri_features(points, k=10)
    with pytest.raises(ShapeError, match="points"):
        rri_features(points[..., :2], k=3)
    bad = points.clone()
    bad[0, 0, 0] = float("inf")
    with pytest.raises(NonFiniteError, match="points"):
        rri_features(bad, k=3)
