"""Typed containers passed between data, models and metrics.

Both are non-frozen dataclasses so that Lightning's ``apply_to_collection`` (device moves) accepts them.
Frames: ``transform_ref_src`` maps source coordinates into the reference frame, ``p_ref = R p_src + t``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import torch

__all__ = ["RegistrationBatch", "RegistrationResult"]


@dataclass
class RegistrationBatch:
    """A batch of registration pairs.

    Attributes:
        points_src: Source clouds ``(B, N, 3)``.
        points_ref: Reference (target) clouds ``(B, M, 3)``.
        transform_ref_src: Ground-truth transforms ``(B, 4, 4)`` or ``None`` when unknown (user data).
            Never used by self-supervised losses.
        normals_src: Unit normals of the source ``(B, N, 3)`` or ``None``.
        normals_ref: Unit normals of the reference ``(B, M, 3)`` or ``None``.
        index: Dataset index of each pair ``(B,)`` (int64).
    """

    points_src: torch.Tensor
    points_ref: torch.Tensor
    transform_ref_src: torch.Tensor | None = None
    normals_src: torch.Tensor | None = None
    normals_ref: torch.Tensor | None = None
    index: torch.Tensor | None = None

    def __len__(self) -> int:
        return int(self.points_src.shape[0])


@dataclass
class RegistrationResult:
    """What every registration method returns.

    Attributes:
        transform_ref_src: Estimated transforms ``(B, 4, 4)`` mapping source into reference.
        converged: Per-item convergence flag ``(B,)`` (bool).
        num_iters: Iterations run per item ``(B,)`` (int64); 1 for one-shot methods.
        residual_history: Optional per-iteration residual norms ``(B, T)``.
        aux: Model-specific extras (features, scores, correspondences).
    """

    transform_ref_src: torch.Tensor
    converged: torch.Tensor
    num_iters: torch.Tensor
    residual_history: torch.Tensor | None = None
    aux: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def fixed_iterations(
        cls, transform_ref_src: torch.Tensor, num_iters: int = 1, aux: dict[str, Any] | None = None
    ) -> RegistrationResult:
        """Result of a method that always runs ``num_iters`` steps (one-shot or fixed loops: nothing to converge).

        Args:
            transform_ref_src: Estimates ``(B, 4, 4)``.
            num_iters: Steps run by every item.
            aux: Model-specific extras.
        """
        batch, device = transform_ref_src.shape[0], transform_ref_src.device
        return cls(
            transform_ref_src=transform_ref_src,
            converged=torch.ones(batch, dtype=torch.bool, device=device),
            num_iters=torch.full((batch,), num_iters, dtype=torch.int64, device=device),
            aux={} if aux is None else aux,
        )

    @property
    def rotation(self) -> torch.Tensor:
        """Estimated rotations ``(B, 3, 3)``."""
        return self.transform_ref_src[:, :3, :3]

    @property
    def translation(self) -> torch.Tensor:
        """Estimated translations ``(B, 3)``."""
        return self.transform_ref_src[:, :3, 3]
