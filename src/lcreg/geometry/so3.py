"""SO(3): hat/vee, exponential and logarithm maps, batched over leading dimensions.

Rotation vectors ``omega`` have shape ``(..., 3)`` (axis times angle, radians); rotation matrices ``(..., 3, 3)``.
Small angles use Taylor series behind a "safe where" (the unselected branch never sees a division by ~0), so
values and gradients stay finite at ``theta = 0``; the log map has a dedicated branch near ``theta = pi``.
Quaternions (:func:`quaternion_to_matrix`) are ``(..., 4)`` in scalar-first ``(w, x, y, z)`` order.
"""

from __future__ import annotations

import torch

from lcreg.checks import ShapeError, check_float
from lcreg.geometry._eps import nan_where_non_finite, near_pi, small_angle
from lcreg.geometry.precision import full_precision

__all__ = ["exp", "hat", "log", "quaternion_to_matrix", "vee"]


@full_precision
def hat(omega: torch.Tensor) -> torch.Tensor:
    """Skew-symmetric matrix ``[omega]_x`` of ``(..., 3)`` vectors, shape ``(..., 3, 3)``."""
    if omega.shape[-1:] != (3,):
        raise ShapeError("omega", ("...", 3), omega.shape)
    x, y, z = omega.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], dim=-1).reshape(*omega.shape[:-1], 3, 3)


@full_precision
def vee(mat: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`hat` applied to the skew part of ``(..., 3, 3)`` matrices, shape ``(..., 3)``."""
    if mat.shape[-2:] != (3, 3):
        raise ShapeError("mat", ("...", 3, 3), mat.shape)
    return 0.5 * torch.stack(
        [mat[..., 2, 1] - mat[..., 1, 2], mat[..., 0, 2] - mat[..., 2, 0], mat[..., 1, 0] - mat[..., 0, 1]], dim=-1
    )


def _exp_coefficients(theta2: torch.Tensor, small: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Return ``A = sin(t)/t`` and ``B = (1 - cos t)/t^2`` with series for small ``t``."""
    theta_nz = torch.where(small, torch.ones_like(theta2), theta2).sqrt()
    a = torch.where(small, 1 - theta2 / 6 + theta2**2 / 120, torch.sin(theta_nz) / theta_nz)
    # 1 - cos t = 2 sin^2(t/2) avoids the cancellation that costs (1 - cos t) half of its digits for small t.
    b = torch.where(small, 0.5 - theta2 / 24 + theta2**2 / 720, 2 * (torch.sin(0.5 * theta_nz) / theta_nz) ** 2)
    return a, b


@full_precision
def exp(omega: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula ``R = I + A K + B K^2`` with ``K = [omega]_x``.

    Args:
        omega: Rotation vectors ``(..., 3)`` in radians.

    Returns:
        Rotation matrices ``(..., 3, 3)``.
    """
    check_float(omega, "omega")
    theta2 = (omega * omega).sum(-1)  # (...)
    small = theta2 < small_angle(omega.dtype) ** 2
    a, b = _exp_coefficients(theta2, small)
    k = hat(omega)
    eye = torch.eye(3, dtype=omega.dtype, device=omega.device).expand_as(k)
    return eye + a[..., None, None] * k + b[..., None, None] * (k @ k)


def _log_near_pi(rot: torch.Tensor, theta: torch.Tensor, skew: torch.Tensor) -> torch.Tensor:
    """Axis from the symmetric part ``(R + R^T)/2 = cos(t) I + (1 - cos t) a a^T``; sign from the skew part."""
    sym = 0.5 * (rot + rot.transpose(-1, -2))
    cos = torch.cos(theta)[..., None, None]
    eye = torch.eye(3, dtype=rot.dtype, device=rot.device)
    aat = (sym - cos * eye) / (1 - cos).clamp_min(1e-12)  # (..., 3, 3) ~ a a^T
    col = aat.diagonal(dim1=-2, dim2=-1).argmax(-1)  # column with the largest |a_i|
    axis = torch.take_along_dim(aat, col[..., None, None].expand(*col.shape, 3, 1), dim=-1).squeeze(-1)
    axis = axis / axis.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    sign = torch.where((axis * skew).sum(-1, keepdim=True) < 0, -1.0, 1.0).to(rot.dtype)
    return sign * axis * theta[..., None]


@full_precision
def log(rot: torch.Tensor) -> torch.Tensor:
    """Logarithm map: rotation vector of each rotation matrix, angle in ``[0, pi]``.

    Args:
        rot: Rotation matrices ``(..., 3, 3)``.

    Returns:
        Rotation vectors ``(..., 3)`` in radians.
    """
    check_float(rot, "rot")
    if rot.shape[-2:] != (3, 3):
        raise ShapeError("rot", ("...", 3, 3), rot.shape)
    skew = vee(rot)  # sin(theta) * axis
    sin2 = (skew * skew).sum(-1)
    cos = 0.5 * (rot.diagonal(dim1=-2, dim2=-1).sum(-1) - 1)
    # clamp_min keeps sqrt's gradient finite at sin = 0 (the clamped entries take another branch anyway).
    theta = torch.atan2(sin2.clamp_min(torch.finfo(rot.dtype).tiny).sqrt(), cos)
    small = (sin2 < small_angle(rot.dtype) ** 2) & (cos > 0)
    near = theta > torch.pi - near_pi(rot.dtype)
    sin_nz = torch.where(small | near, torch.ones_like(sin2), sin2).sqrt()
    factor = torch.where(small, 1 + sin2 / 6 + 3 * sin2**2 / 40, theta / sin_nz)
    omega = factor[..., None] * skew
    if bool(near.any()):
        omega = torch.where(near[..., None], _log_near_pi(rot, theta, skew), omega)
    return nan_where_non_finite(omega, rot, 2)


@full_precision
def quaternion_to_matrix(quat: torch.Tensor) -> torch.Tensor:
    """Rotation matrices of quaternions in **scalar-first** ``(w, x, y, z)`` order (scipy uses ``(x, y, z, w)``).

    The input need not be unit: it is normalised inside, so ``q`` and ``c q`` (any ``c != 0``, ``-q`` included)
    give the same rotation. A quaternion whose squared norm is below ``torch.finfo(dtype).tiny`` (zero, or
    underflowing) maps to the identity with a zero gradient instead of raising: the function runs inside networks
    (PCRNet's pose head), where a data-dependent check would force a device synchronisation and a division by
    the norm would give NaN. Callers that need to reject such inputs must check the norm themselves.

    Args:
        quat: Quaternions ``(..., 4)`` as ``(w, x, y, z)``.

    Returns:
        Rotation matrices ``(..., 3, 3)`` (column-vector convention, ``p' = R p``).

    Raises:
        ShapeError: If the last dimension is not 4.
        TypeError: If ``quat`` is not a float32/float64 tensor.

    Example:
        >>> quaternion_to_matrix(torch.tensor([0.0, 0.0, 0.0, 2.0]))  # 180 degrees about z, not unit
        tensor([[-1.,  0.,  0.],
                [ 0., -1.,  0.],
                [ 0.,  0.,  1.]])
    """
    check_float(quat, "quat")
    if quat.shape[-1:] != (4,):
        raise ShapeError("quat", ("...", 4), quat.shape)
    sq = (quat * quat).sum(-1, keepdim=True)  # (..., 1)
    degenerate = sq < torch.finfo(quat.dtype).tiny
    # Safe where: the degenerate rows divide by 1 (finite gradient) and are then replaced by the identity.
    unit = quat / torch.where(degenerate, torch.ones_like(sq), sq).sqrt()
    identity = torch.zeros_like(quat)
    identity[..., 0] = 1
    w, x, y, z = torch.where(degenerate, identity, unit).unbind(-1)
    xx, yy, zz, xy, xz, yz, wx, wy, wz = x * x, y * y, z * z, x * y, x * z, y * z, w * x, w * y, w * z
    rows = [
        1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy),
        2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx),
        2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy),
    ]  # fmt: skip
    return torch.stack(rows, dim=-1).reshape(*quat.shape[:-1], 3, 3)
