"""Euler angles in the DCP convention (owned here, pinned by ``tests/geometry/test_euler.py``).

Angles are stored in ``'zyx'`` order ``[z, y, x]`` (radians) and ``R = Rx(x) Ry(y) Rz(z)``, which equals
``scipy.spatial.transform.Rotation.from_euler('zyx', [z, y, x])`` (lower-case: extrinsic axes).
This is the convention of DCP / PRNet / IDAM data generators and of their RMSE/MAE(R) metrics.
"""

from __future__ import annotations

import torch

from lcreg.checks import ShapeError, check_float
from lcreg.geometry._eps import nan_where_non_finite
from lcreg.geometry.precision import full_precision

__all__ = ["euler_zyx_to_matrix", "matrix_to_euler_zyx"]


def _axis_rotation(angle: torch.Tensor, axis: int) -> torch.Tensor:
    """Rotation ``(..., 3, 3)`` by ``angle (...)`` about a coordinate axis (0=x, 1=y, 2=z)."""
    c, s = torch.cos(angle), torch.sin(angle)
    one, zero = torch.ones_like(angle), torch.zeros_like(angle)
    if axis == 0:
        rows = [one, zero, zero, zero, c, -s, zero, s, c]
    elif axis == 1:
        rows = [c, zero, s, zero, one, zero, -s, zero, c]
    else:
        rows = [c, -s, zero, s, c, zero, zero, zero, one]
    return torch.stack(rows, dim=-1).reshape(*angle.shape, 3, 3)


@full_precision
def euler_zyx_to_matrix(angles_zyx: torch.Tensor) -> torch.Tensor:
    """Rotation matrices from ``[z, y, x]`` angles.

    Args:
        angles_zyx: ``(..., 3)`` angles in radians, ordered ``[z, y, x]``.

    Returns:
        ``R = Rx(x) @ Ry(y) @ Rz(z)``, shape ``(..., 3, 3)``.
    """
    check_float(angles_zyx, "angles_zyx")
    if angles_zyx.shape[-1:] != (3,):
        raise ShapeError("angles_zyx", ("...", 3), angles_zyx.shape)
    z, y, x = angles_zyx.unbind(-1)
    return _axis_rotation(x, 0) @ _axis_rotation(y, 1) @ _axis_rotation(z, 2)


@full_precision
def matrix_to_euler_zyx(rot: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`euler_zyx_to_matrix`, matching scipy's ``as_euler('zyx')``.

    With ``R = Rx(x) Ry(y) Rz(z)``: ``y = atan2(R[0, 2], hypot(R[0, 0], R[0, 1]))``, ``x = atan2(-R[1, 2], R[2, 2])``,
    ``z = atan2(-R[0, 1], R[0, 0])``. At gimbal lock (``|cos y| ~ 0``) only ``z + x`` (``y = pi/2``) or
    ``z - x`` (``y = -pi/2``) is defined; as scipy does, the third angle ``x`` is set to 0 and
    ``z = atan2(R[1, 0], R[1, 1])``.

    Args:
        rot: ``(..., 3, 3)`` rotation matrices.

    Returns:
        ``(..., 3)`` angles ``[z, y, x]`` in radians, ``y`` in ``[-pi/2, pi/2]``.
    """
    check_float(rot, "rot")
    if rot.shape[-2:] != (3, 3):
        raise ShapeError("rot", ("...", 3, 3), rot.shape)
    cos_y2 = rot[..., 0, 0] ** 2 + rot[..., 0, 1] ** 2
    # clamp_min keeps sqrt's gradient finite at gimbal lock; atan2 is accurate near y = +-pi/2 where asin is not.
    cos_y = cos_y2.clamp_min(torch.finfo(rot.dtype).tiny).sqrt()
    y = torch.atan2(rot[..., 0, 2], cos_y)
    locked = cos_y < 1e-6
    x = torch.where(locked, torch.zeros_like(y), torch.atan2(-rot[..., 1, 2], rot[..., 2, 2]))
    z = torch.where(locked, torch.atan2(rot[..., 1, 0], rot[..., 1, 1]), torch.atan2(-rot[..., 0, 1], rot[..., 0, 0]))
    return nan_where_non_finite(torch.stack([z, y, x], dim=-1), rot, 2)
