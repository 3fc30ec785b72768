"""Composable training-loss terms injected into any :class:`~lcreg.models.base.RegistrationModule`.

A model's training objective is its own terms (``_compute_loss``, e.g. DCP's pose MSE, DVDs' global residual) plus
the :class:`LossTerm` s given to its constructor (``loss_terms=[...]``, a YAML list). The base class adds each
term as ``weight * value`` to ``"loss"`` and logs it as ``{stage}/{name}``; the one public way to get the sum is
:meth:`~lcreg.models.base.RegistrationModule.training_losses`, so no caller can leave an injected term out.

Write a term by subclassing :class:`LossTerm` and implementing :meth:`LossTerm.forward`; :meth:`LossTerm.bind` is
called once when the model is built (check widths there, so a mismatch fails at construction, not at a step).

YAML (``configs/lc.yaml`` appends LC to any model's list; ``loss_terms+:`` appends, ``loss_terms:`` replaces)::

    model:
      init_args:
        loss_terms+:
          - class_path: lcreg.models.loss_terms.LocalConsistencyLoss
            init_args: {weight: 1.0, local_consistency: {num_local_points: 64}}
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch
from torch import nn

from lcreg.nn.local_consistency import LocalConsistency
from lcreg.types import RegistrationBatch, RegistrationResult

if TYPE_CHECKING:
    from lcreg.models.base import RegistrationModule

__all__ = ["LocalConsistencyLoss", "LossTerm"]


class LossTerm(nn.Module):
    """One weighted term of a model's training loss.

    Args:
        weight: Factor of the term in ``"loss"`` (``>= 0``; 0 logs the term without optimising it).
        name: Key of the term in the loss dict and in the logs (``{stage}/{name}``).

    Raises:
        ValueError: On a negative or non-finite weight, or an empty name.
    """

    def __init__(self, weight: float = 1.0, name: str = "term") -> None:
        super().__init__()
        if not math.isfinite(weight) or weight < 0:
            raise ValueError(f"`weight` of loss term {name!r} must be finite and >= 0, got {weight}")
        if not name or name == "loss":
            raise ValueError(f"a loss term needs a name other than '' and 'loss', got {name!r}")
        self.weight = weight
        self.name = name

    @property
    def min_points(self) -> int:
        """Smallest cloud this term accepts (folded into the model's ``min_points``)."""
        return 0

    def bind(self, model: RegistrationModule) -> None:
        """Called once by the model's constructor: check (or adapt to) the model; default does nothing."""

    def forward(
        self, model: RegistrationModule, result: RegistrationResult, batch: RegistrationBatch
    ) -> torch.Tensor:  # pragma: no cover - interface
        """The term's unweighted scalar value for ``model``'s ``result`` on ``batch``."""
        raise NotImplementedError


class LocalConsistencyLoss(LossTerm):
    """The DVDs local-consistency term on any host's descriptor encoder.

    Uses ``model.descriptor_encoder()`` (``(B, n, 3) -> (B, K)`` or ``(B, n, K)``) and ``model.descriptor_dim``;
    the clouds of the batch and, for ``pairing="estimate"``, the model's current estimate.

    Args:
        local_consistency: The LC module (default: ``LocalConsistency()``); its ``feature_dim`` may be left
            ``None`` and is then set to the host's ``descriptor_dim`` when bound.
        weight: Factor of the term (paper: 1).
        name: Log key (``{stage}/lc``).
    """

    def __init__(
        self, local_consistency: LocalConsistency | None = None, weight: float = 1.0, name: str = "lc"
    ) -> None:
        super().__init__(weight, name)
        if local_consistency is not None and not isinstance(local_consistency, LocalConsistency):
            raise TypeError(
                f"`local_consistency` must be a LocalConsistency module, got {type(local_consistency).__name__}"
            )
        self.local_consistency = local_consistency if local_consistency is not None else LocalConsistency()

    @property
    def min_points(self) -> int:
        """``N_l``: LC needs clouds of at least ``num_local_points``."""
        return self.local_consistency.num_local_points

    def bind(self, model: RegistrationModule) -> None:
        """Set (or check) the LC width against the host's descriptor width.

        Raises:
            ValueError: If the LC module was built for another width.
        """
        self.local_consistency.bind(model.descriptor_dim)

    def forward(self, model: RegistrationModule, result: RegistrationResult, batch: RegistrationBatch) -> torch.Tensor:
        """``LocalConsistency(psi, X, Y, estimate)`` (scalar, nats)."""
        return self.local_consistency(
            model.descriptor_encoder(), batch.points_src, batch.points_ref, result.transform_ref_src
        )
