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
from collections.abc import Callable
from typing import Protocol, runtime_checkable

import torch
from torch import nn

from lcreg.geometry import se3
from lcreg.geometry.random_transforms import random_euler_transform
from lcreg.nn.local_consistency import LocalConsistency
from lcreg.nn.losses import lk_pose_loss, weighted_pose_loss
from lcreg.types import RegistrationBatch, RegistrationResult

__all__ = [
    "LocalConsistencyLoss",
    "LossHost",
    "LossTerm",
    "SelfMotionLoss",
    "SelfMotionStationarityLoss",
    "SolveStepHost",
    "random_subsets",
]


class LossHost(Protocol):
    """What a loss term may use of its model (:class:`~lcreg.models.base.RegistrationModule` provides it all)."""

    @property
    def descriptor_dim(self) -> int:
        """Width ``K`` of :meth:`descriptor_encoder`'s features."""
        ...

    def descriptor_encoder(self) -> Callable[[torch.Tensor], torch.Tensor]:
        """The encoder ``psi``: ``(B, n, 3) -> (B, K)`` or ``(B, n, K)``."""
        ...

    def differentiable_forward(self, points_src: torch.Tensor, points_ref: torch.Tensor) -> RegistrationResult:
        """The model's estimate with its autograd graph kept."""
        ...


@runtime_checkable
class SolveStepHost(Protocol):
    """A host whose estimate is an iterative solve that can take one update from a given pose (the IC-LK models)."""

    def step_from(
        self, points_src: torch.Tensor, points_ref: torch.Tensor, transform_ref_src: torch.Tensor
    ) -> torch.Tensor:
        """The pose ``(B, 4, 4)`` one update of the solve moves ``transform_ref_src`` to, with the graph kept."""
        ...


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

    def bind(self, model: LossHost) -> None:
        """Called once by the model's constructor: check (or adapt to) the model; default does nothing."""

    def forward(
        self, model: LossHost, result: RegistrationResult, batch: RegistrationBatch
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

    def bind(self, model: LossHost) -> None:
        """Set (or check) the LC width against the host's descriptor width.

        Raises:
            ValueError: If the LC module was built for another width.
        """
        self.local_consistency.bind(model.descriptor_dim)

    def forward(self, model: LossHost, result: RegistrationResult, batch: RegistrationBatch) -> torch.Tensor:
        """``LocalConsistency(psi, X, Y, estimate)`` (scalar, nats)."""
        return self.local_consistency(
            model.descriptor_encoder(), batch.points_src, batch.points_ref, result.transform_ref_src
        )


def random_subsets(points: torch.Tensor, size: int) -> torch.Tensor:
    """An independent random subset of ``size`` points of every cloud (no repeats), ``(B, size, 3)``.

    Uses the global RNG on the clouds' device (``seed_everything`` makes it reproducible).
    """
    b, n, _ = points.shape
    idx = torch.rand(b, n, device=points.device).argsort(dim=1)[:, :size]
    return points.gather(1, idx[..., None].expand(-1, -1, points.shape[-1]))


class SelfMotionLoss(LossTerm):
    """Label-free pose term on self-generated pairs: one cloud, two samplings, a known random motion.

    For every source cloud ``X`` of the batch two independent random subsets ``A`` and ``B`` of
    ``sample_fraction * N`` points are drawn, a rigid motion ``G`` (Euler angles ``U[0, max_angle_deg]``,
    translation ``U[-max_translation, max_translation]``, the ModelNet40 protocol's ranges) is drawn, and the host
    registers ``A`` to ``G B (+ noise)`` with the graph kept through its solve
    (:meth:`~lcreg.models.base.RegistrationModule.differentiable_forward`). The term is PointNetLK's pose loss
    ``16 MSE(T G^-1, I)`` against the generated ``G``. The motion is made by the term, never read from the
    dataset: the batch's ground-truth pose is not used, so the term works on any unlabeled scans.

    Why DVDs needs it (issue 12): at the IC-LK estimate the paper's residual ``||psi(W X) - psi(Y)||`` carries no
    information about the remaining error, so it can only be lowered by making ``psi`` insensitive to motion; a
    known motion is the label-free signal that rewards seeing motion.

    Args:
        weight: Factor of the term.
        name: Log key (``{stage}/self_motion``).
        max_angle_deg: Bound of each generated Euler angle (degrees).
        max_translation: Bound of each generated translation component (cloud units).
        sample_fraction: Share of the cloud's points in each of the two samplings (``(0, 1]``; 1 gives the same
            points in both clouds, in another order).
        noise_std: Standard deviation of Gaussian noise added to the moved sampling (cloud units).
        translation_weight: Weight ``w`` of the translation error in the pose loss
            (:func:`~lcreg.nn.losses.weighted_pose_loss`); 1 is PointNetLK's loss, about 25 weighs a 0.01 translation
            error like a 2 deg rotation error.

    Raises:
        ValueError: On bounds out of range.
    """

    def __init__(
        self,
        weight: float = 1.0,
        name: str = "self_motion",
        max_angle_deg: float = 45.0,
        max_translation: float = 0.5,
        sample_fraction: float = 0.75,
        noise_std: float = 0.0,
        translation_weight: float = 1.0,
    ) -> None:
        super().__init__(weight, name)
        if not 0 < sample_fraction <= 1:
            raise ValueError(f"`sample_fraction` must be in (0, 1], got {sample_fraction}")
        if min(max_angle_deg, max_translation, noise_std, translation_weight) < 0:
            raise ValueError(
                "`max_angle_deg`, `max_translation`, `noise_std` and `translation_weight` must be >= 0, got "
                f"{max_angle_deg}, {max_translation}, {noise_std}, {translation_weight}"
            )
        self.max_angle_deg = max_angle_deg
        self.max_translation = max_translation
        self.sample_fraction = sample_fraction
        self.noise_std = noise_std
        self.translation_weight = translation_weight

    def make_pairs(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Self-generated pairs from clouds ``(B, N, 3)``: ``(source (B, n, 3), reference (B, n, 3), G (B, 4, 4))``.

        ``reference = G subset_2 + noise``, so ``G`` maps ``source`` into ``reference`` (``transform_ref_src``).
        """
        size = max(1, int(self.sample_fraction * points.shape[1]))
        src, other = random_subsets(points, size), random_subsets(points, size)
        motion = random_euler_transform(len(points), self.max_angle_deg, self.max_translation, dtype=points.dtype)[0]
        motion = motion.to(points.device)
        ref = se3.transform_points(motion, other)
        if self.noise_std > 0:
            ref = ref + self.noise_std * torch.randn_like(ref)
        return src, ref, motion

    def forward(self, model: LossHost, result: RegistrationResult, batch: RegistrationBatch) -> torch.Tensor:
        """The pose loss of the host's differentiable estimate on pairs made from ``batch.points_src``.

        ``16 MSE(T G^-1, I)``, its translation part weighted by ``translation_weight``.
        """
        src, ref, motion = self.make_pairs(batch.points_src.detach())
        estimate = model.differentiable_forward(src, ref).transform_ref_src
        if self.translation_weight == 1.0:  # PointNetLK's loss, computed as the shipped weights were trained
            return lk_pose_loss(estimate, motion)
        return weighted_pose_loss(estimate, motion, self.translation_weight)


class SelfMotionStationarityLoss(SelfMotionLoss):
    """Label-free fixed-point term: one update of the host's solve, started at the known self-motion, should not move.

    Pairs as :class:`SelfMotionLoss` (one cloud, two samplings, a generated motion ``G``); instead of unrolling the
    solve from the identity, the host takes one update from ``G`` itself (``step_from``,
    :meth:`lcreg.nn.lk.InverseCompositionalLK.step_from`) and the term is the pose loss
    (:func:`~lcreg.nn.losses.weighted_pose_loss`) of the pose it reaches against ``G``. It is 0 where ``G`` is a
    fixed point of the solve: the term aims at the bias of the descriptor residual's minimum, which two samplings of
    one surface displace from the true pose (``docs/results/converge/dvds_tw100_1024/test_failures.md``: started at
    the true test pose, the shipped DVDs ends at the same recall as from the identity).

    Args:
        weight: Factor of the term.
        name: Log key (``{stage}/self_motion_stationarity``).
        max_angle_deg: Bound of each generated Euler angle (degrees).
        max_translation: Bound of each generated translation component (cloud units).
        sample_fraction: Share of the cloud's points in each of the two samplings (``(0, 1]``).
        noise_std: Standard deviation of Gaussian noise added to the moved sampling (cloud units).
        translation_weight: Weight of the translation error in the pose loss.

    Raises:
        ValueError: On bounds out of range.
        TypeError: When bound to a host without ``step_from`` (:class:`SolveStepHost`).
    """

    def __init__(
        self,
        weight: float = 1.0,
        name: str = "self_motion_stationarity",
        max_angle_deg: float = 45.0,
        max_translation: float = 0.5,
        sample_fraction: float = 0.75,
        noise_std: float = 0.0,
        translation_weight: float = 1.0,
    ) -> None:
        super().__init__(weight, name, max_angle_deg, max_translation, sample_fraction, noise_std, translation_weight)

    def bind(self, model: LossHost) -> None:
        """Check that the host can step its solve.

        Raises:
            TypeError: If ``model`` has no ``step_from``.
        """
        if not isinstance(model, SolveStepHost):
            raise TypeError(
                f"{type(self).__name__} needs a host with an IC-LK solve (`step_from`), got {type(model).__name__}"
            )

    def forward(self, model: LossHost, result: RegistrationResult, batch: RegistrationBatch) -> torch.Tensor:
        """``weighted_pose_loss(step_from(G), G)`` on pairs made from ``batch.points_src`` (scalar)."""
        if not isinstance(model, SolveStepHost):  # bind checks it; a term used without its model's constructor
            raise TypeError(f"{type(self).__name__} needs a host with `step_from`, got {type(model).__name__}")
        src, ref, motion = self.make_pairs(batch.points_src.detach())
        return weighted_pose_loss(model.step_from(src, ref, motion), motion, self.translation_weight)
