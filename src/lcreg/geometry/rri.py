"""Rigorously rotation-invariant (RRI) point features (Chen et al., ClusterNet 2019), as DeepGMR feeds them.

For a cloud centred at its mean, each point ``p`` and each of its ``k`` nearest neighbours ``q`` (the point itself
excluded, ascending distance, the order of DeepGMR's k-d tree query) give four numbers:

* ``r_p = ||p||`` and ``r_q = ||q||``;
* ``theta = angle(p, q)`` in ``[0, pi]``;
* ``phi``: with ``T(q) = q - cos(theta) p`` (DeepGMR's "projection" of ``q`` against ``p``; it is the projection onto
  the plane orthogonal to ``p`` only when ``||q|| = ||p||``, and it is kept as in the original), ``phi`` is the
  smallest angle in ``[0, 2 pi)`` from ``T(q)`` to the ``T(q')`` of another neighbour ``q'``, measured
  counter-clockwise about ``p``: ``psi = atan2((T(q) x T(q')) . p/||p||, T(q) . T(q'))``.

Every quantity is built from norms, dot products and one triple product with ``p``, so the features are exactly
invariant to proper rotations (and, through the centring, to translations) up to floating-point rounding and
neighbour-order ties. Layout: ``(B, N, k, 4)`` flattened to ``(B, N, 4k)``, the four numbers of neighbour 0 first.

Notes on the original (``wentaoyuan/deepgmr``): its CUDA kernel (``rri.cu``, used whenever a GPU is present, i.e. for
the released models) measures ``psi`` from the neighbour's own ``T(q)`` to the others, as above; its CPU fallback
(``data.py``) takes the cross product the other way round, which yields the mirrored angle (``2 pi - psi``, also
rotation invariant). We follow the CUDA kernel / ClusterNet. ``theta`` is computed as ``atan2(||p x q||, p . q)``,
equal to the original ``arccos`` of the clipped cosine but accurate for the small angles between close neighbours.
A point exactly at the centroid (or a neighbour there) has no direction; its unit vector is taken as 0, where the
original produces NaN. The features are meant as fixed network inputs (DeepGMR computes them in the data loader);
they are not differentiated (``atan2`` and the minimum over neighbours are non-smooth).
"""

from __future__ import annotations

import math

import torch

from lcreg.checks import check_points
from lcreg.geometry.neighbors import gather_points, knn_indices, safe_norm
from lcreg.geometry.precision import full_precision

__all__ = ["neighbours_excluding_self", "rri_features"]


def _unit(x: torch.Tensor, norm: torch.Tensor) -> torch.Tensor:
    """``x / norm`` along the last axis, 0 where ``norm == 0`` (``x (..., 3)``, ``norm (...)``)."""
    positive = norm > 0
    return torch.where(positive[..., None], x / torch.where(positive, norm, 1.0)[..., None], 0.0)


@full_precision
def neighbours_excluding_self(points: torch.Tensor, k: int) -> torch.Tensor:
    """Indices ``(B, N, k)`` of the ``k`` nearest other points of every point, ascending distance.

    The point itself is dropped from its ``k + 1`` nearest neighbours; if duplicates push it out of that list, the
    farthest of the ``k + 1`` is dropped instead (the duplicate then stands in for it, with identical features).
    """
    idx = knn_indices(points, points, k + 1)  # (B, N, k + 1)
    own = torch.arange(points.shape[1], device=points.device)[None, :, None]
    is_self = (idx == own).to(torch.int8)
    order = torch.argsort(is_self, dim=-1, stable=True)  # non-self first, in distance order
    return idx.gather(-1, order)[..., :k]


@full_precision
def rri_features(points: torch.Tensor, k: int = 20) -> torch.Tensor:
    """RRI features of every point of batched clouds (module docstring for the definition).

    Args:
        points: Clouds ``(B, N, 3)``, ``N >= k + 1`` (any frame; they are centred at their mean here).
        k: Neighbours per point (DeepGMR: 20).

    Returns:
        ``(B, N, 4k)`` features: for neighbour ``j`` of point ``i``, entries ``4j .. 4j + 3`` are
        ``(||p_i||, ||q_j||, theta_ij, phi_ij)`` (distances in the input's units, angles in radians).

    Raises:
        ValueError: If ``k < 2``.
        TooFewPointsError: If ``N < k + 1``.
        ShapeError, TypeError, NonFiniteError: On invalid clouds.

    Example:
        >>> points = torch.randn(2, 32, 3, dtype=torch.float64)
        >>> rri_features(points, k=4).shape
        torch.Size([2, 32, 16])
    """
    if k < 2:
        raise ValueError(f"`k` must be >= 2 (phi compares a neighbour with the others), got {k}")
    check_points(points, "points", min_points=k + 1)
    centred = points - points.mean(dim=1, keepdim=True)  # (B, N, 3)
    p = centred[:, :, None, :]  # (B, N, 1, 3)
    q = gather_points(centred, neighbours_excluding_self(centred, k))  # (B, N, k, 3)
    r_p, r_q = safe_norm(p), safe_norm(q)  # (B, N, 1), (B, N, k)
    p_hat, q_hat = _unit(p, r_p), _unit(q, r_q)
    cos = (p_hat * q_hat).sum(-1)  # (B, N, k)
    theta = torch.atan2(safe_norm(torch.linalg.cross(p_hat.expand_as(q_hat), q_hat)), cos)
    tangent = q - cos.clamp(-1.0, 1.0)[..., None] * p  # (B, N, k, 3) = T(q)
    # psi[a, c] = atan2((T_a x T_c) . p_hat, T_a . T_c); (T_a x T_c) . p_hat = (p_hat x T_a) . T_c.
    sin_psi = torch.linalg.cross(p_hat.expand_as(tangent), tangent) @ tangent.transpose(-1, -2)  # (B, N, k, k)
    cos_psi = tangent @ tangent.transpose(-1, -2)  # (B, N, k, k)
    psi = torch.remainder(torch.atan2(sin_psi, cos_psi), 2 * math.pi)
    eye = torch.eye(k, dtype=torch.bool, device=points.device)
    phi = psi.masked_fill(eye, math.inf).amin(dim=-1)  # (B, N, k)
    feats = torch.stack([r_p.expand_as(r_q), r_q, theta, phi], dim=-1)  # (B, N, k, 4)
    return feats.flatten(start_dim=2)
