"""Local consistency (LC): the DVDs pretext loss, usable by any registration network.

For a source cloud ``X`` (and its reference ``Y``):

1. Barycenter ``x_b``; the farthest point ``x_f = argmax ||x_i - x_b||`` over points not rejected as outliers
   (distance above ``outlier_threshold`` or above the ``outlier_quantile`` of the cloud's distances), and the
   closest point ``x_c = argmin ||x_i - x_b||``.
2. Local subsets ``X1 = kNN(x_f, N_l)``, ``X2 = kNN(x_c, N_l)``.
3. ``tau(X_k) = FC[psi(X_k) (+) psi(W(X_k))]`` with ``FC: R^{2K} -> R^K`` and ``psi`` the host's encoder.
4. Loss ``1/2 (KL(p1 || p2) + KL(p2 || p1))`` with ``p_k = softmax(tau(X_k) / temperature)`` over the K channels;
   by default each descriptor is standardised over its channels first (``standardize=True``), so the loss does
   not vanish or explode with the encoder's output scale.

What ``W(X_k)`` is (see ``docs/local_consistency.md``):

* ``pairing="target"`` (default): the subset of ``Y`` chosen by the same rule. The barycenter rule is invariant
  to rigid motion, so ``Y``'s subsets correspond to ``W(X_k)`` up to sampling. It needs no estimate, carries the
  real relation between ``X`` and ``Y``, and so plugs into any host without touching its solver.
* ``pairing="estimate"``: ``X_k`` moved by the host's current estimate (held fixed: detached). This is the literal
  reading of the paper's alternating scheme (``W`` is found, then ``psi`` is trained with ``W`` fixed); early in
  training a poor estimate (e.g. identity) reduces the term to comparing the two regions' own descriptors.

The metric ``FC`` is a randomly initialised, **frozen** layer by default: a trainable FC can output a constant and
drive the loss to zero with no gradient left for ``psi`` (Algorithm 1 also lists only ``psi``, the decoder and the
normal head as trained). ``trainable_metric=True`` makes it trainable. A frozen metric is a function of
``metric_seed`` and the width alone, so it is left out of ``state_dict()`` (for DVDs' 1024 channels it is 2.1 M
numbers, 8.4 MB, which made up 42 % of every checkpoint) and rebuilt from the seed when a state dict without it is
loaded; a state dict that holds it (older checkpoints, a trainable metric) loads it as before.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Literal, cast

import torch
from torch import nn

from lcreg.checks import check_points, check_rigid, check_same_batch, check_transform
from lcreg.geometry import se3
from lcreg.geometry.neighbors import gather_points, knn
from lcreg.geometry.precision import full_precision

__all__ = ["LocalConsistency", "barycenter_subsets"]

Pairing = Literal["target", "estimate"]


def barycenter_subsets(
    points: torch.Tensor,
    num_local_points: int,
    outlier_threshold: float | None = None,
    outlier_quantile: float | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Indices of the farthest- and closest-to-barycenter local subsets.

    Args:
        points: Clouds ``(B, N, 3)``.
        num_local_points: Subset size ``N_l`` (``<= N``).
        outlier_threshold: Points farther than this from the barycenter (distance units) cannot be ``x_f``.
        outlier_quantile: Points beyond this quantile (in ``(0, 1]``) of the distances cannot be ``x_f``.

    Returns:
        ``(idx_far, idx_close)``, each ``(B, N_l)`` int64 indices into ``N``.
    """
    dist = (points - points.mean(dim=1, keepdim=True)).norm(dim=-1)  # (B, N)
    cap = torch.full_like(dist[:, 0], float("inf"))
    if outlier_threshold is not None:
        cap = cap.clamp(max=outlier_threshold)
    if outlier_quantile is not None:
        cap = torch.minimum(cap, torch.quantile(dist, outlier_quantile, dim=1))
    # Fall back to the closest point if every point is rejected (threshold below all distances).
    eligible = dist <= cap[:, None]
    far = torch.where(eligible, dist, torch.full_like(dist, -1.0)).argmax(dim=1)  # (B,)
    close = dist.argmin(dim=1)
    anchors = gather_points(points, torch.stack([far, close], dim=1))  # (B, 2, 3)
    _, idx = knn(anchors, points, num_local_points)  # (B, 2, N_l)
    return idx[:, 0], idx[:, 1]


def _descriptor(encoder: Callable[[torch.Tensor], torch.Tensor], points: torch.Tensor) -> torch.Tensor:
    """``(B, K)`` descriptor; a per-point encoder output ``(B, n, K)`` is max-pooled."""
    out = encoder(points)
    if out.ndim == 3:
        out = out.amax(dim=1)
    if out.ndim != 2:
        raise ValueError(f"the encoder must return (B, K) or (B, n, K) features, got shape {tuple(out.shape)}")
    return out


def _frozen_metric_state(module: LocalConsistency) -> dict[str, torch.Tensor]:
    """The metric's tensors under their names in ``module``'s state dict, or ``{}`` when it is trainable or unbuilt."""
    if module.trainable_metric or module.metric is None:
        return {}
    return {f"metric.{name}": tensor for name, tensor in module.metric.state_dict().items()}


def _drop_frozen_metric(module: nn.Module, state_dict: dict[str, Any], prefix: str, local_metadata: Any) -> None:
    """State-dict post-hook: leave a frozen metric out (``metric_seed`` rebuilds it)."""
    for name in _frozen_metric_state(cast(LocalConsistency, module)):
        state_dict.pop(prefix + name, None)


def _fill_frozen_metric(module: nn.Module, state_dict: dict[str, Any], prefix: str, *_: Any) -> None:
    """Load pre-hook: a state dict without the frozen metric gets the seeded one, so strict loading accepts it."""
    for name, tensor in _frozen_metric_state(cast(LocalConsistency, module)).items():
        state_dict.setdefault(prefix + name, tensor)


class LocalConsistency(nn.Module):
    """Symmetric-KL local-consistency loss between the far and close barycenter subsets.

    Args:
        feature_dim: Descriptor size ``K`` of the encoder it will be used with; ``None``: set later by
            :meth:`bind` (hosts bind it to their encoder's width when built).
        num_local_points: ``N_l = |X1| = |X2|`` (paper default 64).
        pairing: ``"target"`` or ``"estimate"`` (module docstring).
        outlier_threshold: Absolute outlier distance ``c`` for ``x_f``; ``None`` disables it.
        outlier_quantile: Alternative robust cap: quantile of the barycenter distances (e.g. 0.98 on real scans).
        temperature: Softmax temperature turning ``tau`` into a distribution.
        trainable_metric: Train the FC metric (default frozen, see module docstring).
        standardize: Standardise each descriptor over its K channels (zero mean, unit variance) before the FC, so
            the loss does not depend on the encoder's output scale (an untrained PointNet without BatchNorm outputs
            values ~1e-2, which makes both softmaxes uniform and the loss ~1e-6).
        metric_seed: Seed of the FC metric's initialisation (a private generator: building the module does not
            consume the global RNG, so a host initialised after it gets the same weights with and without LC).

    Example:
        >>> from lcreg import LocalConsistency
        >>> from lcreg.nn.pointnet import PointNetEncoder
        >>> lc = LocalConsistency(feature_dim=64, num_local_points=16)
        >>> enc = PointNetEncoder(channels=(32, 64))
        >>> loss = lc(enc, torch.randn(2, 100, 3), torch.randn(2, 100, 3))
        >>> loss.shape
        torch.Size([])
    """

    def __init__(
        self,
        feature_dim: int | None = None,
        num_local_points: int = 64,
        pairing: Pairing = "target",
        outlier_threshold: float | None = None,
        outlier_quantile: float | None = None,
        temperature: float = 1.0,
        trainable_metric: bool = False,
        standardize: bool = True,
        metric_seed: int = 0,
    ) -> None:
        super().__init__()
        if (feature_dim is not None and feature_dim < 1) or num_local_points < 1:
            raise ValueError(
                f"`feature_dim` and `num_local_points` must be >= 1, got {feature_dim}, {num_local_points}"
            )
        if pairing not in ("target", "estimate"):
            raise ValueError(f"`pairing` must be 'target' or 'estimate', got {pairing!r}")
        if outlier_quantile is not None and not 0 < outlier_quantile <= 1:
            raise ValueError(f"`outlier_quantile` must be in (0, 1], got {outlier_quantile}")
        if temperature <= 0:
            raise ValueError(f"`temperature` must be > 0, got {temperature}")
        self.feature_dim: int | None = None
        self.num_local_points = num_local_points
        self.pairing = pairing
        self.outlier_threshold = outlier_threshold
        self.outlier_quantile = outlier_quantile
        self.temperature = temperature
        self.standardize = standardize
        self.trainable_metric = trainable_metric
        self.metric_seed = metric_seed
        self.metric: nn.Linear | None = None
        self.register_state_dict_post_hook(_drop_frozen_metric)
        self.register_load_state_dict_pre_hook(_fill_frozen_metric)
        if feature_dim is not None:
            self.bind(feature_dim)

    def bind(self, feature_dim: int) -> None:
        """Build the FC metric for descriptors of width ``feature_dim`` (a no-op when already built for it).

        Raises:
            ValueError: If the module was built for another width, or ``feature_dim < 1``.
        """
        if self.feature_dim is not None:
            if feature_dim != self.feature_dim:
                raise ValueError(
                    f"LocalConsistency was built for {self.feature_dim} features, the encoder has {feature_dim} "
                    "(leave `feature_dim` unset to take the host's width)"
                )
            return
        if feature_dim < 1:
            raise ValueError(f"`feature_dim` must be >= 1, got {feature_dim}")
        with torch.random.fork_rng(devices=[]):  # Linear's own init must not advance the global RNG
            metric = nn.Linear(2 * feature_dim, feature_dim)
        self._init_metric(metric, self.metric_seed)
        metric.requires_grad_(self.trainable_metric)
        self.feature_dim, self.metric = feature_dim, metric

    def _metric_for(self, feats: torch.Tensor) -> nn.Linear:
        """The FC metric for descriptors ``feats (.., K)``, built on first use when ``feature_dim`` was left unset."""
        if self.metric is None:
            if self.trainable_metric:
                raise ValueError("a trainable LC metric needs `feature_dim` (or bind()) before the optimiser is built")
            self.bind(feats.shape[-1])
            self.to(feats.device)
        if self.metric is None or feats.shape[-1] != self.feature_dim:
            raise ValueError(f"encoder returns {feats.shape[-1]} features, LocalConsistency expects {self.feature_dim}")
        return self.metric

    @staticmethod
    @torch.no_grad()
    def _init_metric(metric: nn.Linear, seed: int) -> None:
        """PyTorch's default ``Linear`` initialisation (uniform in ``+-1/sqrt(fan_in)``), from a private generator."""
        gen = torch.Generator().manual_seed(seed)
        bound = 1.0 / metric.in_features**0.5
        for param in (metric.weight, metric.bias):
            param.copy_(torch.rand(param.shape, generator=gen) * 2 * bound - bound)

    def subsets(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Far and close subsets ``(B, N_l, 3)`` each of ``points (B, N, 3)``."""
        idx_far, idx_close = barycenter_subsets(
            points, self.num_local_points, self.outlier_threshold, self.outlier_quantile
        )
        return gather_points(points, idx_far), gather_points(points, idx_close)

    def _paired_subsets(
        self, points_src: torch.Tensor, points_ref: torch.Tensor | None, transform_ref_src: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """``X1, X2, W(X1), W(X2)``, each ``(B, N_l, 3)``."""
        x1, x2 = self.subsets(points_src)
        if self.pairing == "target":
            if points_ref is None:
                raise ValueError("pairing='target' needs `points_ref`")
            check_points(points_ref, "points_ref", min_points=self.num_local_points)
            check_same_batch(points_src=points_src, points_ref=points_ref)
            w1, w2 = self.subsets(points_ref)
        else:
            if transform_ref_src is None:
                raise ValueError("pairing='estimate' needs `transform_ref_src` (the current estimate)")
            transform = check_transform(transform_ref_src, "transform_ref_src").detach()
            check_rigid(transform, "transform_ref_src")
            w1, w2 = se3.transform_points(transform, x1), se3.transform_points(transform, x2)
        return x1, x2, w1, w2

    def forward(
        self,
        encoder: Callable[[torch.Tensor], torch.Tensor],
        points_src: torch.Tensor,
        points_ref: torch.Tensor | None = None,
        transform_ref_src: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Batch-mean symmetric KL between ``softmax(tau(X1))`` and ``softmax(tau(X2))``.

        Args:
            encoder: The host's ``psi``: ``(B, n, 3) -> (B, K)`` or ``(B, n, K)`` (max-pooled here).
            points_src: Source clouds ``(B, N, 3)``, ``N >= num_local_points``.
            points_ref: Reference clouds ``(B, M, 3)`` (``pairing="target"``).
            transform_ref_src: Current estimates ``(B, 4, 4)`` (``pairing="estimate"``).

        Returns:
            Scalar loss (nats).

        Raises:
            TooFewPointsError: A cloud has fewer than ``num_local_points`` points.
            ValueError: ``transform_ref_src`` is not a batch of rigid motions.
        """
        check_points(points_src, "points_src", min_points=self.num_local_points)
        x1, x2, w1, w2 = self._paired_subsets(points_src, points_ref, transform_ref_src)
        feats = _descriptor(encoder, torch.cat([x1, x2, w1, w2]))  # (4B, K), one encoder pass
        return self._symmetric_kl(feats)

    @full_precision
    def _symmetric_kl(self, feats: torch.Tensor) -> torch.Tensor:
        """The loss from the descriptors ``(4B, K)`` of ``X1, X2, W(X1), W(X2)``, in float32 under autocast.

        A KL of two close distributions is a small difference, which bfloat16 would round away.
        """
        metric = self._metric_for(feats)
        if self.standardize:
            feats = (feats - feats.mean(-1, keepdim=True)) / feats.std(-1, keepdim=True).clamp_min(1e-6)
        f1, f2, g1, g2 = feats.chunk(4)
        tau1 = metric(torch.cat([f1, g1], dim=-1)) / self.temperature
        tau2 = metric(torch.cat([f2, g2], dim=-1)) / self.temperature
        logp, logq = torch.log_softmax(tau1, dim=-1), torch.log_softmax(tau2, dim=-1)
        sym_kl = 0.5 * ((logp.exp() - logq.exp()) * (logp - logq)).sum(-1)  # (B,)
        return sym_kl.mean()
