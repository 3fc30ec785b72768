"""SE(3): homogeneous transforms, twists, exp/log, composition and point application.

Conventions (pinned by ``tests/geometry/test_se3.py``):

* A transform is a ``(B, 4, 4)`` column-vector matrix ``[R t; 0 1]``; ``transform_ref_src`` maps source
  coordinates into the reference frame: ``p_ref = R p_src + t``.
* A twist is ordered **rotation first**, ``xi = [omega, v]`` ``(..., 6)`` (the PointNetLK / IC-LK lineage), and
  ``exp(xi) = [exp_so3(omega), V(omega) v; 0 1]`` with ``V = I + B K + C K^2``.
* Points are row vectors in ``(B, N, 3)`` tensors.
"""

from __future__ import annotations

import torch

from lcreg.checks import ShapeError, check_float
from lcreg.geometry import so3
from lcreg.geometry._eps import small_angle
from lcreg.geometry.precision import full_precision

__all__ = [
    "compose",
    "exp",
    "identity",
    "inverse",
    "log",
    "make_transform",
    "split",
    "transform_normals",
    "transform_points",
    "uncenter",
]


def _check_transform_like(transform: torch.Tensor, name: str) -> None:
    """Raise ``TypeError``/:class:`ShapeError` unless ``transform`` is a float ``(..., 4, 4)`` tensor."""
    check_float(transform, name)
    if transform.ndim < 2 or transform.shape[-2:] != (4, 4):
        raise ShapeError(name, ("...", 4, 4), transform.shape)


def _check_points_like(points: torch.Tensor, transform: torch.Tensor, name: str) -> None:
    """Raise unless ``points`` is a ``(..., N, 3)`` tensor with the dtype of ``transform`` (leading dims broadcast)."""
    check_float(points, name)
    if points.ndim < 2 or points.shape[-1] != 3:
        raise ShapeError(name, ("...", "N", 3), points.shape)
    if points.dtype != transform.dtype:
        raise TypeError(f"`{name}` has dtype {points.dtype} but `transform` has {transform.dtype}")


def identity(batch: int, device: torch.device | None = None, dtype: torch.dtype | None = None) -> torch.Tensor:
    """Identity transforms ``(batch, 4, 4)``."""
    return torch.eye(4, device=device, dtype=dtype).expand(batch, 4, 4).clone()


@full_precision
def make_transform(rot: torch.Tensor, trans: torch.Tensor) -> torch.Tensor:
    """Assemble ``[R t; 0 1]`` from rotations ``(..., 3, 3)`` and translations ``(..., 3)``."""
    if rot.shape[-2:] != (3, 3):
        raise ShapeError("rot", ("...", 3, 3), rot.shape)
    if trans.shape[-1:] != (3,) or trans.shape[:-1] != rot.shape[:-2]:
        raise ShapeError("trans", (*rot.shape[:-2], 3), trans.shape)
    top = torch.cat([rot, trans[..., None]], dim=-1)  # (..., 3, 4)
    bottom = torch.zeros_like(top[..., :1, :])
    bottom[..., 0, 3] = 1
    return torch.cat([top, bottom], dim=-2)


def split(transform: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Return ``(R (..., 3, 3), t (..., 3))`` of transforms ``(..., 4, 4)``."""
    return transform[..., :3, :3], transform[..., :3, 3]


@full_precision
def compose(transform_a_b: torch.Tensor, transform_b_c: torch.Tensor) -> torch.Tensor:
    """Compose ``T_ac = T_ab T_bc`` (apply ``T_bc`` first); both ``(..., 4, 4)``, broadcast over leading dims."""
    _check_transform_like(transform_a_b, "transform_a_b")
    _check_transform_like(transform_b_c, "transform_b_c")
    return transform_a_b @ transform_b_c


@full_precision
def inverse(transform: torch.Tensor) -> torch.Tensor:
    """Closed-form inverse ``[R^T, -R^T t; 0 1]`` of rigid transforms ``(..., 4, 4)``."""
    _check_transform_like(transform, "transform")
    rot, trans = split(transform)
    rot_t = rot.transpose(-1, -2)
    return make_transform(rot_t, -(rot_t @ trans[..., None]).squeeze(-1))


@full_precision
def uncenter(transform: torch.Tensor, mean_src: torch.Tensor, mean_ref: torch.Tensor) -> torch.Tensor:
    """Undo a centring: ``Trans(mean_ref) G Trans(-mean_src)`` for ``G (B, 4, 4)`` estimated on centred clouds.

    Args:
        transform: ``G (B, 4, 4)`` mapping the centred source onto the centred reference.
        mean_src: Source centroids ``(B, 3)``.
        mean_ref: Reference centroids ``(B, 3)``.

    Returns:
        ``(B, 4, 4)`` transforms ``[R, t + mean_ref - R mean_src; 0 1]`` on the original clouds.
    """
    _check_transform_like(transform, "transform")
    rot, trans = split(transform)
    return make_transform(rot, trans + mean_ref - (rot @ mean_src[..., None]).squeeze(-1))


@full_precision
def transform_points(transform: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Apply transforms ``(B, 4, 4)`` to points ``(B, N, 3)``: ``R p + t``, returns ``(B, N, 3)``."""
    _check_transform_like(transform, "transform")
    _check_points_like(points, transform, "points")
    rot, trans = split(transform)
    return points @ rot.transpose(-1, -2) + trans[..., None, :]


@full_precision
def transform_normals(transform: torch.Tensor, normals: torch.Tensor) -> torch.Tensor:
    """Rotate normals ``(B, N, 3)`` by the rotation part of ``(B, 4, 4)`` transforms."""
    _check_transform_like(transform, "transform")
    _check_points_like(normals, transform, "normals")
    return normals @ transform[..., :3, :3].transpose(-1, -2)


def _v_coefficients(theta2: torch.Tensor, small: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``A = sin t / t``, ``B = (1 - cos t)/t^2``, ``C = (t - sin t)/t^3`` with Taylor series for small ``t``."""
    theta_nz = torch.where(small, torch.ones_like(theta2), theta2).sqrt()
    a = torch.where(small, 1 - theta2 / 6 + theta2**2 / 120, torch.sin(theta_nz) / theta_nz)
    # 1 - cos t = 2 sin^2(t/2) avoids the cancellation that costs (1 - cos t) half of its digits for small t.
    b = torch.where(small, 0.5 - theta2 / 24 + theta2**2 / 720, 2 * (torch.sin(0.5 * theta_nz) / theta_nz) ** 2)
    c = torch.where(small, 1 / 6 - theta2 / 120 + theta2**2 / 5040, (theta_nz - torch.sin(theta_nz)) / theta_nz**3)
    return a, b, c


@full_precision
def exp(xi: torch.Tensor) -> torch.Tensor:
    """Exponential map of twists ``xi = [omega, v]`` ``(..., 6)`` to transforms ``(..., 4, 4)``."""
    check_float(xi, "xi")
    if xi.shape[-1:] != (6,):
        raise ShapeError("xi", ("...", 6), xi.shape)
    omega, v = xi[..., :3], xi[..., 3:]
    theta2 = (omega * omega).sum(-1)
    small = theta2 < small_angle(xi.dtype) ** 2
    a, b, c = _v_coefficients(theta2, small)
    k = so3.hat(omega)
    k2 = k @ k
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device).expand_as(k)
    rot = eye + a[..., None, None] * k + b[..., None, None] * k2
    v_mat = eye + b[..., None, None] * k + c[..., None, None] * k2
    return make_transform(rot, (v_mat @ v[..., None]).squeeze(-1))


@full_precision
def log(transform: torch.Tensor) -> torch.Tensor:
    """Logarithm map of transforms ``(..., 4, 4)`` to twists ``[omega, v]`` ``(..., 6)``.

    Uses ``V^{-1} = I - K/2 + D K^2`` with ``D = (1 - A / (2 B)) / t^2`` (series ``1/12 + t^2/720 + t^4/30240``).
    """
    check_float(transform, "transform")
    if transform.shape[-2:] != (4, 4):
        raise ShapeError("transform", ("...", 4, 4), transform.shape)
    rot, trans = split(transform)
    omega = so3.log(rot)
    theta2 = (omega * omega).sum(-1)
    small = theta2 < small_angle(transform.dtype) ** 2
    a, b, _ = _v_coefficients(theta2, small)
    theta2_nz = torch.where(small, torch.ones_like(theta2), theta2)
    d = torch.where(small, 1 / 12 + theta2 / 720 + theta2**2 / 30240, (1 - a / (2 * b)) / theta2_nz)
    k = so3.hat(omega)
    eye = torch.eye(3, dtype=transform.dtype, device=transform.device).expand_as(k)
    v_inv = eye - 0.5 * k + d[..., None, None] * (k @ k)
    return torch.cat([omega, (v_inv @ trans[..., None]).squeeze(-1)], dim=-1)
