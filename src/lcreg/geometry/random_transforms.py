"""Random rigid transforms drawn from an explicit ``torch.Generator`` (reproducible, CPU-generated)."""

from __future__ import annotations

import math

import torch

from lcreg.geometry.euler import euler_zyx_to_matrix
from lcreg.geometry.se3 import make_transform

__all__ = ["random_euler_transform", "random_rotation"]


def random_euler_transform(
    batch: int,
    max_angle_deg: float = 45.0,
    max_translation: float = 0.5,
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float32,
) -> tuple[torch.Tensor, torch.Tensor]:
    """DCP-protocol transforms: each Euler angle ``U[0, max_angle]``, each translation ``U[-t, t]``.

    Args:
        batch: Number of transforms.
        max_angle_deg: Upper bound of every angle in degrees (the paper uses 45).
        max_translation: Bound of every translation component (the paper uses 0.5).
        generator: CPU generator for reproducibility (``None`` uses the global RNG).
        dtype: Output dtype.

    Returns:
        ``(transforms (batch, 4, 4), angles_zyx (batch, 3) in radians)``.
    """
    if max_angle_deg < 0 or max_translation < 0:
        raise ValueError(f"bounds must be >= 0, got max_angle_deg={max_angle_deg}, max_translation={max_translation}")
    angles = torch.rand(batch, 3, generator=generator, dtype=torch.float64) * math.radians(max_angle_deg)
    trans = (torch.rand(batch, 3, generator=generator, dtype=torch.float64) * 2 - 1) * max_translation
    transform = make_transform(euler_zyx_to_matrix(angles), trans)
    return transform.to(dtype), angles.to(dtype)


def random_rotation(
    batch: int, generator: torch.Generator | None = None, dtype: torch.dtype = torch.float32
) -> torch.Tensor:
    """Uniformly distributed rotations ``(batch, 3, 3)`` (normalised Gaussian quaternions)."""
    q = torch.randn(batch, 4, generator=generator, dtype=torch.float64)
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    # fmt: off
    rot = torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
            2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
            2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(batch, 3, 3)
    # fmt: on
    return rot.to(dtype)
