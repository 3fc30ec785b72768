"""Correspondence heads shared by the correspondence-based baselines (DCP, PRNet, IDAM).

:func:`similarity_scores` is the scaled dot product of per-point embeddings; :func:`soft_correspondence_transform`
is DCP's SVD head: each source point is matched to the probability-weighted mean of the reference points, then the
rigid transform comes from (weighted) Procrustes (:func:`lcreg.geometry.procrustes.weighted_kabsch`, reflection
fixed, differentiable through the SVD).
"""

from __future__ import annotations

import math

import torch

from lcreg.geometry.precision import full_precision
from lcreg.geometry.procrustes import weighted_kabsch

__all__ = ["similarity_scores", "soft_correspondence_transform"]


def similarity_scores(feat_src: torch.Tensor, feat_ref: torch.Tensor) -> torch.Tensor:
    """``F_src F_ref^T / sqrt(d)``: ``(B, N, d)``, ``(B, M, d)`` -> ``(B, N, M)``."""
    return feat_src @ feat_ref.transpose(1, 2) / math.sqrt(feat_src.shape[-1])


@full_precision
def soft_correspondence_transform(
    points_src: torch.Tensor,
    points_ref: torch.Tensor,
    probabilities: torch.Tensor,
    weights: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Rigid transform from soft correspondences ``y_hat_i = sum_j p_ij y_j``.

    Args:
        points_src: ``(B, N, 3)``.
        points_ref: ``(B, M, 3)``.
        probabilities: Row-stochastic matching ``(B, N, M)`` (softmax, or a straight-through one-hot).
        weights: Optional per-source-point weights ``(B, N)`` for the Procrustes fit.

    Returns:
        ``(transform_ref_src (B, 4, 4), matched (B, N, 3))``.
    """
    matched = probabilities @ points_ref  # (B, N, 3)
    return weighted_kabsch(points_src, matched, weights), matched
