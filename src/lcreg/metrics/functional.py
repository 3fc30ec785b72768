"""Per-pair registration errors as pure torch functions (the core of :mod:`lcreg.metrics.registration`).

Every function takes estimated and ground-truth ``transform_ref_src`` batches ``(B, 4, 4)`` and returns one error per
pair. Inputs are validated for dtype and shape but **not** for finiteness: a NaN/Inf estimate (a diverged solver)
yields NaN for all errors of that pair, which are never dropped; :func:`registration_recall` counts them as failures.

* :func:`rotation_error_deg`: isotropic (geodesic) angle of ``R_pred^T R_gt`` in degrees, ``[0, 180]``.
* :func:`translation_error`: ``||t_pred - t_gt||`` in the units of the points.
* :func:`euler_errors_deg` and :func:`translation_errors`: signed per-component differences, for the DCP-style
  RMSE/MAE tables (Euler angles in the DCP ``'zyx'`` convention of :mod:`lcreg.geometry.euler`, not wrapped,
  as DCP computes them).
"""

from __future__ import annotations

import math

import torch

from lcreg.checks import check_float, check_same_batch, check_shape
from lcreg.geometry.euler import matrix_to_euler_zyx

__all__ = [
    "euler_errors_deg",
    "registration_recall",
    "rotation_error_deg",
    "translation_error",
    "translation_errors",
]


def _check_pair(transform_pred: torch.Tensor, transform_gt: torch.Tensor) -> None:
    """Check dtype and ``(B, 4, 4)`` shapes of both transforms (finiteness deliberately not checked)."""
    check_float(transform_pred, "transform_pred")
    check_float(transform_gt, "transform_gt")
    dims = check_shape(transform_pred, ("B", 4, 4), "transform_pred")
    check_shape(transform_gt, (dims["B"], 4, 4), "transform_gt")
    check_same_batch(transform_pred=transform_pred, transform_gt=transform_gt)


def _nan_if_nonfinite(err: torch.Tensor, transform_pred: torch.Tensor, transform_gt: torch.Tensor) -> torch.Tensor:
    """Set ``err (B, ...)`` to NaN for every pair whose transforms hold a NaN/Inf (an Inf could give finite atan2)."""
    finite = torch.isfinite(transform_pred).all(-1).all(-1) & torch.isfinite(transform_gt).all(-1).all(-1)  # (B,)
    finite = finite.reshape(-1, *([1] * (err.ndim - 1)))
    return torch.where(finite, err, torch.full_like(err, float("nan")))


def rotation_error_deg(transform_pred: torch.Tensor, transform_gt: torch.Tensor) -> torch.Tensor:
    """Isotropic rotation error ``arccos((tr(R_pred^T R_gt) - 1) / 2)`` in degrees.

    Evaluated as ``atan2(sin, cos)`` with ``sin = ||vee(skew(R_pred^T R_gt))||`` and the clamped
    ``cos = (tr - 1) / 2``: equal to the clamped ``arccos`` for rotation matrices, but accurate near 0 and 180
    degrees, where ``arccos`` loses half of the digits (about 0.02 degrees in float32).

    Args:
        transform_pred: Estimated transforms ``(B, 4, 4)``.
        transform_gt: Ground-truth transforms ``(B, 4, 4)``.

    Returns:
        ``(B,)`` errors in degrees, in ``[0, 180]``; NaN where an input is not finite.

    Example:
        >>> gt = torch.eye(4).expand(1, 4, 4)
        >>> pred = gt.clone()
        >>> pred[0, :2, :2] = torch.tensor([[0.0, -1.0], [1.0, 0.0]])
        >>> rotation_error_deg(pred, gt)
        tensor([90.])
    """
    _check_pair(transform_pred, transform_gt)
    rel = transform_pred[:, :3, :3].transpose(1, 2) @ transform_gt[:, :3, :3]  # (B, 3, 3)
    cos = (0.5 * (rel.diagonal(dim1=1, dim2=2).sum(-1) - 1)).clamp(-1.0, 1.0)  # (B,)
    skew = torch.stack([rel[:, 2, 1] - rel[:, 1, 2], rel[:, 0, 2] - rel[:, 2, 0], rel[:, 1, 0] - rel[:, 0, 1]], -1)
    sin = 0.5 * skew.norm(dim=-1)  # (B,)
    return _nan_if_nonfinite(torch.rad2deg(torch.atan2(sin, cos)), transform_pred, transform_gt)


def translation_error(transform_pred: torch.Tensor, transform_gt: torch.Tensor) -> torch.Tensor:
    """Translation error ``||t_pred - t_gt||`` ``(B,)`` in the units of the points (NaN for non-finite input)."""
    return translation_errors(transform_pred, transform_gt).norm(dim=-1)


def translation_errors(transform_pred: torch.Tensor, transform_gt: torch.Tensor) -> torch.Tensor:
    """Signed per-component translation differences ``t_pred - t_gt`` ``(B, 3)`` (DCP's RMSE/MAE(t) input)."""
    _check_pair(transform_pred, transform_gt)
    return _nan_if_nonfinite(transform_pred[:, :3, 3] - transform_gt[:, :3, 3], transform_pred, transform_gt)


def euler_errors_deg(transform_pred: torch.Tensor, transform_gt: torch.Tensor) -> torch.Tensor:
    """Signed Euler-angle differences in degrees, DCP style.

    Args:
        transform_pred: Estimated transforms ``(B, 4, 4)``.
        transform_gt: Ground-truth transforms ``(B, 4, 4)``.

    Returns:
        ``(B, 3)`` differences ``euler_pred - euler_gt`` of the ``[z, y, x]`` angles
        (:func:`lcreg.geometry.euler.matrix_to_euler_zyx`) in degrees. Not wrapped to ``[-180, 180)``, exactly as
        DCP computes its RMSE/MAE(R); meaningful for the ``[0, 45]`` degree protocol, far from gimbal lock.
    """
    _check_pair(transform_pred, transform_gt)
    diff = matrix_to_euler_zyx(transform_pred[:, :3, :3]) - matrix_to_euler_zyx(transform_gt[:, :3, :3])
    return _nan_if_nonfinite(torch.rad2deg(diff), transform_pred, transform_gt)


def registration_recall(
    rot_err: torch.Tensor, trans_err: torch.Tensor, rot_thr_deg: float, trans_thr: float
) -> torch.Tensor:
    """Fraction of pairs with ``rot_err < rot_thr_deg`` and ``trans_err < trans_thr``.

    Args:
        rot_err: Rotation errors ``(B,)`` in degrees (e.g. :func:`rotation_error_deg`).
        trans_err: Translation errors ``(B,)`` (e.g. :func:`translation_error`).
        rot_thr_deg: Rotation threshold in degrees (strict).
        trans_thr: Translation threshold in point units (strict).

    Returns:
        Scalar float tensor in ``[0, 1]`` (NaN for ``B = 0``); NaN errors count as failures.

    Raises:
        ShapeError: If the errors are not 1-D of one length.

    Example:
        >>> registration_recall(torch.tensor([1.0, 1.0, float("nan")]), torch.tensor([0.0, 1.0, 0.0]), 2.0, 0.5)
        tensor(0.3333)
    """
    dims = check_shape(rot_err, ("B",), "rot_err")
    check_shape(trans_err, (dims["B"],), "trans_err")
    if math.isnan(rot_thr_deg) or math.isnan(trans_thr):
        raise ValueError("thresholds must not be NaN")
    success = (rot_err < rot_thr_deg) & (trans_err < trans_thr)  # NaN compares False
    return success.to(rot_err.dtype if rot_err.dtype.is_floating_point else torch.float32).mean()
