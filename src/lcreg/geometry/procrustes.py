"""Weighted orthogonal Procrustes (Kabsch) in closed form, batched and differentiable.

Given corresponding points ``src_i <-> ref_i`` and weights ``w_i >= 0``, :func:`weighted_kabsch` returns the rigid
``transform_ref_src`` ``[R t; 0 1]`` minimising ``sum_i w_i ||R src_i + t - ref_i||^2`` over proper rotations
(``det R = +1``). The rotation comes from the SVD of the weighted cross-covariance with the reflection fix
``R = V diag(1, 1, sign det(V U^T)) U^T``; the translation maps the weighted source centroid onto the reference one.
"""

from __future__ import annotations

import torch

from lcreg.checks import check_finite, check_float, check_points, check_same_batch, check_shape
from lcreg.geometry.precision import full_precision
from lcreg.geometry.se3 import make_transform

__all__ = ["weighted_kabsch"]


def _normalized_weights(weights: torch.Tensor | None, points: torch.Tensor, eps: float) -> torch.Tensor:
    """Validate ``weights (B, N)`` (or build uniform ones) and return them summing to one, shape ``(B, N, 1)``."""
    batch, num = points.shape[:2]
    if weights is None:
        return points.new_full((batch, num, 1), 1.0 / num)
    check_float(weights, "weights")
    check_shape(weights, (batch, num), "weights")
    check_finite(weights, "weights")
    if weights.dtype != points.dtype:
        raise TypeError(f"`weights` has dtype {weights.dtype} but `points_src` has {points.dtype}")
    if bool((weights < 0).any()):
        raise ValueError("`weights` must be non-negative")
    total = weights.sum(dim=1, keepdim=True)  # (B, 1)
    if bool((total <= 0).any()):
        raise ValueError("`weights` must have a positive sum for every batch item")
    return (weights / total.clamp_min(eps))[..., None]


@full_precision
def weighted_kabsch(
    points_src: torch.Tensor,
    points_ref: torch.Tensor,
    weights: torch.Tensor | None = None,
    eps: float = 1e-8,
) -> torch.Tensor:
    """Least-squares rigid transform aligning ``points_src`` onto ``points_ref``.

    Differentiable through ``torch.linalg.svd``. Its gradient is ill-conditioned when the weighted cross-covariance
    has repeated singular values (for example fewer than three non-collinear points, or symmetric clouds); the
    value is still a valid rotation there, but not unique.

    Args:
        points_src: Source points ``(B, N, 3)`` in the source frame.
        points_ref: Corresponding reference points ``(B, N, 3)`` in the reference frame.
        weights: Non-negative correspondence weights ``(B, N)``, each row with a positive sum; ``None`` for uniform.
        eps: Lower bound of the weight sum used for normalising (guards the division; exact for sums >= eps).

    Returns:
        ``transform_ref_src`` ``(B, 4, 4)`` with ``p_ref ~ R p_src + t``.

    Raises:
        ShapeError: If the shapes are not ``(B, N, 3)``/``(B, N)`` with one ``B`` and one ``N``.
        TypeError: On a non-float dtype or mixed dtypes.
        NonFiniteError: On NaN/Inf points or weights.
        ValueError: On negative weights or a batch item whose weights sum to zero.

    Example:
        >>> src = torch.randn(2, 10, 3, dtype=torch.float64)
        >>> transform = weighted_kabsch(src, src + torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64))
        >>> torch.allclose(transform[:, :3, 3], torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64))
        True
    """
    check_points(points_src, "points_src")
    check_points(points_ref, "points_ref")
    check_same_batch(points_src=points_src, points_ref=points_ref)
    check_shape(points_ref, points_src.shape, "points_ref")
    w = _normalized_weights(weights, points_src, eps)  # (B, N, 1)

    centroid_src = (w * points_src).sum(dim=1)  # (B, 3)
    centroid_ref = (w * points_ref).sum(dim=1)  # (B, 3)
    src_c = points_src - centroid_src[:, None, :]  # (B, N, 3)
    ref_c = points_ref - centroid_ref[:, None, :]  # (B, N, 3)
    cov = src_c.transpose(1, 2) @ (w * ref_c)  # (B, 3, 3) = sum_i w_i src_i ref_i^T

    u, _, vh = torch.linalg.svd(cov)  # cov = U S V^T
    v = vh.transpose(1, 2)
    with torch.no_grad():
        reflection = torch.linalg.det(v @ u.transpose(1, 2)) < 0  # (B,)
    diag = torch.ones_like(centroid_src)  # (B, 3)
    diag[:, 2] = torch.where(reflection, -1.0, 1.0).to(diag.dtype)
    rot = (v * diag[:, None, :]) @ u.transpose(1, 2)  # (B, 3, 3) = V D U^T
    trans = centroid_ref - (rot @ centroid_src[..., None]).squeeze(-1)  # (B, 3)
    return make_transform(rot, trans)
