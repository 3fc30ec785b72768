"""Pose losses of the supervised baselines (shared, never copied per model).

All take transforms ``(B, 4, 4)`` mapping source into reference and return a scalar (PyTorch ``mse_loss``
reduction: mean over every element).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from lcreg.geometry import se3
from lcreg.geometry.precision import full_precision

__all__ = ["cycle_consistency_mse", "lk_pose_loss", "rotation_translation_mse", "transform_mse", "weighted_pose_loss"]


@full_precision
def rotation_translation_mse(transform_pred: torch.Tensor, transform_gt: torch.Tensor) -> torch.Tensor:
    """DCP/PRNet pose loss ``MSE(R_pred^T R_gt, I) + MSE(t_pred, t_gt)``."""
    rot_p, t_p = se3.split(transform_pred)
    rot_g, t_g = se3.split(transform_gt)
    eye = torch.eye(3, dtype=rot_p.dtype, device=rot_p.device).expand_as(rot_p)
    return F.mse_loss(rot_p.transpose(1, 2) @ rot_g, eye) + F.mse_loss(t_p, t_g)


@full_precision
def transform_mse(transform_a: torch.Tensor, transform_b: torch.Tensor) -> torch.Tensor:
    """``MSE(T_a T_b, I_4)`` (DeepGMR's and PointNetLK's pose loss with ``T_b`` the inverse ground truth)."""
    eye = torch.eye(4, dtype=transform_a.dtype, device=transform_a.device).expand_as(transform_a)
    return F.mse_loss(transform_a @ transform_b, eye)


@full_precision
def lk_pose_loss(transform_pred: torch.Tensor, transform_gt: torch.Tensor) -> torch.Tensor:
    """PointNetLK's pose loss ``16 MSE(T_pred T_gt^-1, I_4)``: the squared Frobenius norm, averaged over the batch.

    Args:
        transform_pred: Estimates ``(B, 4, 4)``.
        transform_gt: Ground truths ``(B, 4, 4)`` (both map source into reference).
    """
    return 16.0 * transform_mse(transform_pred, se3.inverse(transform_gt))


@full_precision
def weighted_pose_loss(
    transform_pred: torch.Tensor, transform_gt: torch.Tensor, translation_weight: float = 1.0
) -> torch.Tensor:
    """``||R_e - I||_F^2 + w ||t_e||^2`` of the error ``[R_e t_e] = T_pred T_gt^-1``, averaged over the batch.

    With ``w = 1`` it equals :func:`lk_pose_loss` (the error's last row is exactly ``[0 0 0 1]``). At a rotation
    error of ``theta`` radians the first part is ``4 (1 - cos theta) ~ 2 theta^2``: at the recall thresholds
    (2 deg, 0.01) it is 24 times the second, so ``w`` of about 25 weighs both thresholds alike.

    Args:
        transform_pred: Estimates ``(B, 4, 4)``.
        transform_gt: Ground truths ``(B, 4, 4)`` (both map source into reference).
        translation_weight: ``w >= 0`` (cloud units^-2).
    """
    rot, trans = se3.split(se3.compose(transform_pred, se3.inverse(transform_gt)))
    eye = torch.eye(3, dtype=rot.dtype, device=rot.device)
    return ((rot - eye).pow(2).sum(dim=(1, 2)) + translation_weight * trans.pow(2).sum(dim=-1)).mean()


@full_precision
def cycle_consistency_mse(transform_a: torch.Tensor, transform_b: torch.Tensor) -> torch.Tensor:
    """``MSE(R_a R_b, I) + MSE(R_a t_b + t_a, 0)``: how far ``T_a T_b`` is from the identity.

    Zero exactly when ``T_b = T_a^-1``. DCP and PRNet penalise their forward/reverse estimates with it; their original
    translation terms (``R_ba^T t_ab + t_ba`` in DCP, ``t_ab + t_ba`` in PRNet) are not zero at exact inverses.
    """
    rot, trans = se3.split(se3.compose(transform_a, transform_b))
    eye = torch.eye(3, dtype=rot.dtype, device=rot.device).expand_as(rot)
    return F.mse_loss(rot, eye) + F.mse_loss(trans, torch.zeros_like(trans))
