"""Surface normals of batched clouds by local PCA (the Open3D ``estimate_normals`` recipe, batched in torch).

For each point, the covariance of its ``k`` nearest neighbours (the point itself included) is diagonalised; the
normal is the eigenvector of the smallest eigenvalue. The sign of a PCA normal is arbitrary: without
``orient_towards`` the normals are **unoriented** (compare them with ``|cos|``); with a viewpoint they are flipped to
face it.
"""

from __future__ import annotations

import torch

from lcreg.checks import check_finite, check_float, check_points, check_same_batch, check_shape
from lcreg.geometry.neighbors import gather_points, knn
from lcreg.geometry.precision import full_precision

__all__ = ["estimate_normals"]


def _orient(normals: torch.Tensor, points: torch.Tensor, viewpoint: torch.Tensor) -> torch.Tensor:
    """Flip ``normals (B, N, 3)`` so that ``n . (viewpoint - p) >= 0`` for ``viewpoint (B, 3)``."""
    to_view = viewpoint[:, None, :] - points  # (B, N, 3)
    flip = (normals * to_view).sum(-1, keepdim=True) < 0  # (B, N, 1)
    return torch.where(flip, -normals, normals)


@full_precision
def estimate_normals(points: torch.Tensor, k: int = 16, orient_towards: torch.Tensor | None = None) -> torch.Tensor:
    """Unit normals by PCA of the ``k`` nearest neighbours.

    Differentiable through ``torch.linalg.eigh``; its gradient is ill-conditioned where the two smallest
    eigenvalues coincide (isotropic neighbourhoods, lines), so treat the output as data rather than a loss input.

    Args:
        points: Clouds ``(B, N, 3)``.
        k: Neighbourhood size including the point itself, ``3 <= k <= N``.
        orient_towards: Optional viewpoint ``(B, 3)`` in the frame of ``points``; normals are flipped to face it.

    Returns:
        Unit normals ``(B, N, 3)``, sign arbitrary unless ``orient_towards`` is given.

    Raises:
        ValueError: If ``k < 3``.
        TooFewPointsError: If ``N < k``.
        ShapeError, TypeError, NonFiniteError: On an invalid cloud or viewpoint.

    Example:
        >>> xy = torch.stack(torch.meshgrid(torch.arange(4.0), torch.arange(4.0), indexing="ij"), -1).reshape(1, 16, 2)
        >>> plane = torch.cat([xy, torch.zeros(1, 16, 1)], dim=-1)
        >>> normals = estimate_normals(plane, k=5, orient_towards=torch.tensor([[0.0, 0.0, 1.0]]))
        >>> torch.allclose(normals, torch.tensor([0.0, 0.0, 1.0]).expand(1, 16, 3))
        True
    """
    if k < 3:
        raise ValueError(f"`k` must be >= 3 to define a plane, got {k}")
    check_points(points, "points", min_points=k)
    if orient_towards is not None:
        check_float(orient_towards, "orient_towards")
        check_shape(orient_towards, (points.shape[0], 3), "orient_towards")
        check_finite(orient_towards, "orient_towards")
        check_same_batch(points=points, orient_towards=orient_towards)
    _, idx = knn(points, points, k)  # (B, N, k)
    neighbors = gather_points(points, idx)  # (B, N, k, 3)
    centered = neighbors - neighbors.mean(dim=2, keepdim=True)  # (B, N, k, 3)
    cov = centered.transpose(-1, -2) @ centered / k  # (B, N, 3, 3)
    _, eigvecs = torch.linalg.eigh(cov)  # eigenvalues ascending
    normals = eigvecs[..., 0]  # (B, N, 3)
    normals = normals / normals.norm(dim=-1, keepdim=True)
    if orient_towards is not None:
        normals = _orient(normals, points, orient_towards)
    return normals
