"""Composable additions to any :class:`~lcreg.models.base.RegistrationModule`."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch

from lcreg.nn.local_consistency import LocalConsistency
from lcreg.types import RegistrationBatch, RegistrationResult

__all__ = ["LocalConsistencyMixin"]


class LocalConsistencyMixin:
    """Adds ``lc_weight * LocalConsistency(encoder, src, ref, estimate)`` to a host's training losses.

    The host only declares its encoder by overriding :meth:`lc_encoder` (default: ``self.encoder``) and, in its
    constructor, either builds the module (:meth:`init_local_consistency`, DVDs' flat arguments) or receives one
    (:meth:`attach_local_consistency`: the baselines take ``local_consistency: LocalConsistency | None`` and
    ``lc_weight``, so a YAML config switches LC on with one block). Place the mixin first:
    ``class X(LocalConsistencyMixin, RegistrationModule)``. The host's ``compute_loss`` never mentions LC: the shared
    step calls :meth:`training_losses`, which this mixin extends with the weighted term (logged as ``{stage}/lc``).
    """

    local_consistency: LocalConsistency | None
    lc_weight: float

    def init_local_consistency(self, feature_dim: int, lc_weight: float = 1.0, **lc_kwargs: Any) -> None:
        """Create the LC module (``None`` when ``lc_weight == 0``).

        Args:
            feature_dim: Descriptor size ``K`` of the host's encoder.
            lc_weight: Weight of the LC term in the loss.
            **lc_kwargs: Forwarded to :class:`~lcreg.nn.local_consistency.LocalConsistency`.
        """
        module = LocalConsistency(feature_dim, **lc_kwargs) if lc_weight > 0 else None
        self.attach_local_consistency(module, lc_weight)

    def attach_local_consistency(
        self, module: LocalConsistency | None, lc_weight: float = 1.0, feature_dim: int | None = None
    ) -> None:
        """Use ``module`` (``None``: LC off) with weight ``lc_weight`` (``0`` also switches it off).

        Args:
            module: The injected LC module.
            lc_weight: Weight of the LC term.
            feature_dim: The host encoder's width ``K``, checked against ``module.feature_dim`` at construction.

        Raises:
            ValueError: If ``lc_weight < 0`` or the module's ``feature_dim`` is not the encoder's width.
            TypeError: If ``module`` is not a :class:`LocalConsistency`.
        """
        if lc_weight < 0:
            raise ValueError(f"`lc_weight` must be >= 0, got {lc_weight}")
        if module is not None and not isinstance(module, LocalConsistency):
            raise TypeError(f"`local_consistency` must be a LocalConsistency module, got {type(module).__name__}")
        if module is not None and feature_dim is not None and module.feature_dim != feature_dim:
            raise ValueError(
                f"`local_consistency.feature_dim` ({module.feature_dim}) must equal the encoder's width ({feature_dim})"
            )
        self.lc_weight = lc_weight
        self.local_consistency = module if lc_weight > 0 else None

    @property
    def lc_min_points(self) -> int:
        """Smallest cloud LC accepts (``N_l``), 0 when LC is off; hosts fold it into ``min_points``."""
        return 0 if self.local_consistency is None else self.local_consistency.num_local_points

    def lc_encoder(self) -> Callable[[torch.Tensor], torch.Tensor]:
        """The host's encoder ``psi``: ``(B, n, 3) -> (B, K)`` or ``(B, n, K)``."""
        return self.encoder  # type: ignore[attr-defined]

    def add_local_consistency(
        self, losses: dict[str, torch.Tensor], result: RegistrationResult, batch: RegistrationBatch
    ) -> dict[str, torch.Tensor]:
        """Add ``losses["lc"]`` and its weighted value to ``losses["loss"]`` (no-op when LC is off)."""
        if self.local_consistency is not None:
            lc = self.local_consistency(self.lc_encoder(), batch.points_src, batch.points_ref, result.transform_ref_src)
            losses["lc"] = lc
            losses["loss"] = losses["loss"] + self.lc_weight * lc
        return losses

    def training_losses(self, result: RegistrationResult, batch: RegistrationBatch) -> dict[str, torch.Tensor]:
        """The host's losses (its ``compute_loss``, untouched) plus the weighted LC term."""
        losses: dict[str, Any] = super().training_losses(result, batch)  # type: ignore[misc]
        return self.add_local_consistency(losses, result, batch)
