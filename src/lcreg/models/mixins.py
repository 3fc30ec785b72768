"""Local consistency for a user's own LightningModule (lcreg models take it as an injected loss term instead).

:class:`~lcreg.models.base.RegistrationModule` subclasses get LC through their constructor
(``loss_terms=[LocalConsistencyLoss(...)]``, ``configs/lc.yaml``). A LightningModule written outside lcreg gets it
from :class:`LocalConsistencyMixin`: the mixin wraps the class's ``training_step`` when the class is created, so the
term is added whatever the order of the base classes and whatever the user's ``training_step`` is called.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import torch

from lcreg.nn.local_consistency import LocalConsistency

__all__ = ["LocalConsistencyMixin"]

_WRAPPED = "_adds_local_consistency"


class LocalConsistencyMixin:
    """Adds ``lc_weight * LocalConsistency(encoder, src, ref)`` to the loss a LightningModule's training step returns.

    Any base-class order works (``class Net(LocalConsistencyMixin, LightningModule)`` or the reverse): at class
    creation the mixin wraps the class's ``training_step`` (its own or inherited), which must return the loss tensor
    or a dict with ``"loss"``. The wrapped step adds the weighted term, logs ``train/lc`` and adds it once even when a
    subclass's step calls ``super().training_step``. The class provides, in ``__init__``,
    ``self.attach_local_consistency(LocalConsistency(...), lc_weight)``, and may override :meth:`lc_encoder`
    (default ``self.encoder``), :meth:`lc_clouds` (default ``batch.points_src``/``points_ref``, a dict's
    ``"points_src"``/``"points_ref"`` or a sequence's first two items) and :meth:`lc_estimate` (for
    ``pairing="estimate"``). ``examples/third_party_lightning_lc.py`` is a complete example.

    Raises:
        TypeError: At class creation, for a :class:`~lcreg.models.base.RegistrationModule` (use
            ``loss_terms=[LocalConsistencyLoss(...)]``) or a class without a ``training_step``.
    """

    # No class-level defaults: nn.Module keeps submodules in _modules, and a class attribute would shadow them.
    local_consistency: LocalConsistency | None
    lc_weight: float

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        from lcreg.models.base import RegistrationModule  # models.base imports nothing from here

        if issubclass(cls, RegistrationModule):
            raise TypeError(
                f"{cls.__name__}: lcreg models take local consistency as an injected loss term "
                "(loss_terms=[lcreg.models.loss_terms.LocalConsistencyLoss(...)], configs/lc.yaml), not through "
                "LocalConsistencyMixin, which is for LightningModules written outside lcreg"
            )
        step = getattr(cls, "training_step", None)
        if step is None:
            raise TypeError(f"{cls.__name__} uses LocalConsistencyMixin but has no training_step")
        if not getattr(step, _WRAPPED, False):
            cls.training_step = _adding_local_consistency(step)  # type: ignore[attr-defined]

    def attach_local_consistency(self, module: LocalConsistency | None, lc_weight: float = 1.0) -> None:
        """Use ``module`` (``None``: LC off) with weight ``lc_weight`` (``0`` also switches it off).

        Raises:
            ValueError: If ``lc_weight < 0``.
            TypeError: If ``module`` is not a :class:`LocalConsistency`.
        """
        if lc_weight < 0:
            raise ValueError(f"`lc_weight` must be >= 0, got {lc_weight}")
        if module is not None and not isinstance(module, LocalConsistency):
            raise TypeError(f"`local_consistency` must be a LocalConsistency module, got {type(module).__name__}")
        self.lc_weight = lc_weight
        self.local_consistency = module if lc_weight > 0 else None

    def lc_encoder(self) -> Callable[[torch.Tensor], torch.Tensor]:
        """The encoder ``psi``: ``(B, n, 3) -> (B, K)`` or ``(B, n, K)`` (default ``self.encoder``)."""
        encoder = getattr(self, "encoder", None)
        if not callable(encoder):
            raise TypeError(f"{type(self).__name__} has no `encoder`: override lc_encoder() to name it")
        return encoder

    def lc_clouds(self, batch: Any) -> tuple[torch.Tensor, torch.Tensor]:
        """Source and reference clouds ``(B, N, 3)``, ``(B, M, 3)`` of a training batch."""
        if hasattr(batch, "points_src"):
            return batch.points_src, batch.points_ref
        if isinstance(batch, dict):
            return batch["points_src"], batch["points_ref"]
        if isinstance(batch, (list, tuple)) and len(batch) >= 2:
            return batch[0], batch[1]
        raise TypeError(f"{type(self).__name__}: override lc_clouds() to get the two clouds from a {type(batch)}")

    def lc_estimate(self, batch: Any) -> torch.Tensor | None:
        """The current estimate ``(B, 4, 4)`` for ``pairing="estimate"`` (default ``None``)."""
        return None

    def local_consistency_loss(self, batch: Any) -> torch.Tensor | None:
        """The unweighted LC value on ``batch`` (``None`` when LC is off)."""
        module = getattr(self, "local_consistency", None)
        if module is None:
            return None
        src, ref = self.lc_clouds(batch)
        return module(self.lc_encoder(), src, ref, self.lc_estimate(batch))


def _adding_local_consistency(step: Callable[..., Any]) -> Callable[..., Any]:
    """Wrap ``training_step`` so the outermost call adds the weighted LC term to the loss it returns."""

    @functools.wraps(step)
    def training_step(self: Any, batch: Any, *args: Any, **kwargs: Any) -> Any:
        if getattr(self, "_lc_step_active", False):  # a subclass's step calling super(): add LC once
            return step(self, batch, *args, **kwargs)
        self._lc_step_active = True
        try:
            out = step(self, batch, *args, **kwargs)
        finally:
            self._lc_step_active = False
        lc = self.local_consistency_loss(batch)
        if lc is None:
            return out
        self.log("train/lc", lc.detach(), prog_bar=False, on_step=True, on_epoch=True)
        if isinstance(out, dict) and "loss" in out:
            return {**out, "loss": out["loss"] + self.lc_weight * lc}
        if isinstance(out, torch.Tensor):
            return out + self.lc_weight * lc
        raise TypeError(f"{type(self).__name__}.training_step must return the loss (a tensor or a dict with 'loss')")

    setattr(training_step, _WRAPPED, True)
    return training_step
