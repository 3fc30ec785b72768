"""PRNet: Partial Registration Network (Wang & Solomon, NeurIPS 2019), reimplemented behind the common interface.

Upstream: https://github.com/WangYueFt/prnet (commit 82d466a9, ``model.py``/``main.py``); facts in
``/work/shared/reference/baselines.md`` section 2. One PRNet iteration on ``points_src (B, N, 3)`` and
``points_ref (B, M, 3)``:

1. Per-point embeddings: dynamic DGCNN (k = 20, LeakyReLU 0.2, 512 channels), run separately on each cloud (so
   BatchNorm sees each cloud's own statistics, as upstream), then the DCP transformer (FFN with LeakyReLU) with the
   residual ``F + phi``.
2. Keypoints: the ``num_keypoints`` points of each cloud with the largest L2 norm of their embedding (upstream keeps
   512 of 768; here the count is clamped to the cloud size).
3. TemperatureNet: ``|mean_i F_src,i - mean_j F_ref,j|`` over the keypoints (the "feature disparity", also the
   feature-alignment loss) -> MLP 512-128-128-128-1 (BatchNorm + ReLU, output ReLU) clamped to ``[1/100, 100]``.
4. Head, run A->B and B->A: scores ``F_src F_ref^T / sqrt(d)``; ``sampler="gumbel_softmax"`` (upstream default) draws
   a hard straight-through Gumbel-softmax sample with ``tau`` = the per-pair temperature, ``sampler="softmax"``
   uses ``softmax(temperature * scores)`` (upstream multiplies by the temperature in this mode and divides by it in
   the Gumbel mode; both kept). The transform is the SVD fit of the keypoints to their matched points
   (:func:`lcreg.nn.correspondence.soft_correspondence_transform`, reflection fixed).

``num_iterations`` (3) iterations run; after each the source is moved by the A->B estimate and the cumulative
transform is composed, ``T_cum <- T_i T_cum``, without detaching (gradients flow through the moved source). The loss
sums over iterations ``i`` with the discount ``0.9^i``: the pose loss ``MSE(R_cum^T R_gt, I) + MSE(t_cum, t_gt)`` of
the cumulative estimate, ``0.1 x`` the mean feature disparity and ``0.1 x`` the cycle consistency of the
per-iteration A->B and B->A estimates.

Deviations from upstream (all deliberate):

* **Cycle consistency uses the exact identity.** ``T_ab T_ba = I`` means ``R_ab R_ba = I`` and
  ``t_ab + R_ab t_ba = 0``; upstream's translation term is ``MSE(t_ab, -t_ba)``, which is not zero for an exact
  inverse pair in general (there ``t_ab + t_ba = (I - R_ab^T) t_ab``). Here the loss is
  ``MSE(R_ab R_ba, I) + MSE(t_ab + R_ab t_ba, 0)`` (the rotation and translation blocks of ``T_ab T_ba - I``, with
  the column-vector convention ``p_ref = R p_src + t``).
* **Optional deterministic evaluation.** Upstream samples Gumbel noise at test time too, so its test numbers are
  random. ``deterministic_eval=False`` (default) keeps that; ``True`` replaces the Gumbel sample in eval mode by the
  one-hot of ``argmax`` of the scores, the mode of the Gumbel-max distribution (the softmax sampler is already
  deterministic). All randomness comes from torch's RNG, so ``torch.manual_seed`` (or ``seed_everything``) fixes it.
* The SVD runs on the tensors' own device (upstream moves it to the CPU); upstream's "scale consensus" term (always
  0) is omitted. Keypoints are returned ordered by decreasing norm (upstream: ``topk(sorted=False)``; the fit does
  not depend on the order).
* ``converged`` is ``True`` for every pair: PRNet runs a fixed number of iterations and has no stopping test.
"""

from __future__ import annotations

from typing import Any, Literal

import torch
import torch.nn.functional as F
from torch import nn

from lcreg.geometry import se3
from lcreg.geometry.neighbors import gather_points
from lcreg.models.base import RegistrationModule
from lcreg.nn.correspondence import similarity_scores, soft_correspondence_transform
from lcreg.nn.dgcnn import DGCNN
from lcreg.nn.losses import cycle_consistency_mse, rotation_translation_mse
from lcreg.nn.mlp import PointwiseMLP
from lcreg.nn.transformer import PointerTransformer
from lcreg.types import RegistrationBatch, RegistrationResult

__all__ = ["PRNet", "TemperatureNet", "sample_correspondences", "select_keypoints"]

Sampler = Literal["gumbel_softmax", "softmax"]


def select_keypoints(
    points: torch.Tensor, features: torch.Tensor, num_keypoints: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Keep the points whose embeddings have the largest L2 norm (PRNet's ``KeyPointNet``).

    Args:
        points: Coordinates ``(B, N, 3)``.
        features: Per-point embeddings ``(B, N, d)``.
        num_keypoints: Points to keep; clamped to ``N``.

    Returns:
        ``(keypoints (B, K, 3), keypoint_features (B, K, d), indices (B, K))`` with ``K = min(num_keypoints, N)``,
        ordered by decreasing norm.
    """
    k = min(num_keypoints, points.shape[1])
    idx = features.norm(dim=-1).topk(k, dim=1).indices  # (B, K)
    return gather_points(points, idx), gather_points(features, idx), idx


def sample_correspondences(
    scores: torch.Tensor,
    temperature: torch.Tensor,
    sampler: Sampler = "gumbel_softmax",
    deterministic: bool = False,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """Row-stochastic matching matrix from similarity scores.

    Args:
        scores: ``(B, N, M)`` similarity logits.
        temperature: Per-pair temperature ``(B,)`` (positive).
        sampler: ``"gumbel_softmax"``: hard straight-through Gumbel-softmax with ``tau = temperature`` (forward: a
            one-hot sample, ``argmax_j (s_ij + g_ij)``; backward: the gradient of ``softmax((s + g) / tau)``).
            ``"softmax"``: ``softmax(temperature * scores)`` over ``M``.
        deterministic: For the Gumbel sampler, return the one-hot of ``argmax_j s_ij`` (no noise, no gradient).
        generator: Optional torch generator for the Gumbel noise (default: the global torch RNG).

    Returns:
        ``(B, N, M)``, rows summing to one.
    """
    tau = temperature[:, None, None].to(scores.dtype)
    if sampler == "softmax":
        return torch.softmax(tau * scores, dim=-1)
    if sampler != "gumbel_softmax":
        raise ValueError(f"`sampler` must be 'gumbel_softmax' or 'softmax', got {sampler!r}")
    if deterministic:
        return F.one_hot(scores.argmax(dim=-1), scores.shape[-1]).to(scores.dtype)
    # Standard Gumbel noise -log(E), E ~ Exp(1), from torch's RNG.
    gumbel = -torch.empty_like(scores).exponential_(generator=generator).log()
    soft = torch.softmax((scores + gumbel) / tau, dim=-1)
    hard = F.one_hot(soft.argmax(dim=-1), scores.shape[-1]).to(scores.dtype)
    return hard - soft.detach() + soft


class TemperatureNet(nn.Module):
    """PRNet's temperature from the feature disparity of two clouds.

    Args:
        emb_dims: Embedding width ``d``.
        hidden: Hidden width (128).
        temp_factor: Output clamped to ``[1 / temp_factor, temp_factor]`` (100).
        batch_norm: BatchNorm in the hidden layers (upstream), over the pairs of the batch.
    """

    def __init__(
        self, emb_dims: int = 512, hidden: int = 128, temp_factor: float = 100.0, batch_norm: bool = True
    ) -> None:
        super().__init__()
        if temp_factor < 1:
            raise ValueError(f"`temp_factor` must be >= 1, got {temp_factor}")
        self.temp_factor = temp_factor
        self.mlp = PointwiseMLP([emb_dims, hidden, hidden, hidden], batch_norm=batch_norm, bias=True, act="relu")
        self.out = nn.Sequential(nn.Linear(hidden, 1), nn.ReLU())

    def forward(self, feat_src: torch.Tensor, feat_ref: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Temperature and feature disparity.

        Args:
            feat_src: Source (keypoint) embeddings ``(B, N, d)``.
            feat_ref: Reference (keypoint) embeddings ``(B, M, d)``.

        Returns:
            ``(temperature (B,), disparity (B, d))`` with ``disparity = |mean F_src - mean F_ref|``.
        """
        disparity = (feat_src.mean(dim=1) - feat_ref.mean(dim=1)).abs()
        temperature = self.out(self.mlp(disparity)).squeeze(-1)
        return temperature.clamp(1.0 / self.temp_factor, self.temp_factor), disparity


class PRNet(RegistrationModule):
    """PRNet (see the module docstring); defaults are upstream's.

    Args:
        emb_dims: Embedding width of the DGCNN and the transformer (512).
        k: Neighbours of the dynamic DGCNN graph (20); clouds need at least ``k`` points.
        num_heads: Transformer heads (4).
        ff_dims: Transformer FFN width (1024).
        num_keypoints: Keypoints kept per cloud (512; clamped to the cloud size).
        num_iterations: Registration iterations (3).
        sampler: ``"gumbel_softmax"`` (upstream default) or ``"softmax"``.
        deterministic_eval: In eval mode, use the argmax instead of a Gumbel sample (default ``False``, upstream).
        discount: Per-iteration loss discount (0.9).
        feature_alignment_weight: Weight of the feature-disparity term (0.1).
        cycle_weight: Weight of the cycle-consistency term (0.1).
        temp_factor: Temperature range ``[1/temp_factor, temp_factor]`` (100).
        batch_norm: BatchNorm in the DGCNN and the TemperatureNet (upstream). ``False`` is a deviation, for the
            question of what BatchNorm does at small batches (training mode normalises by the batch's statistics, eval
            mode by running averages; see :class:`lcreg.baselines.dcp.DCP`).
        temperature_batch_norm: BatchNorm in the TemperatureNet alone (``None``: as ``batch_norm``). Without it the
            TemperatureNet's output ReLU can start dead, holding the temperature at its floor (``benchmarks/
            overfit.py``: PRNet without any BatchNorm did not fit 8 fixed pairs).
        **kwargs: :class:`~lcreg.models.base.RegistrationModule` components: ``optimizer`` (upstream: Adam lr
            1e-3, weight decay 1e-4), ``lr_scheduler`` (upstream: MultiStepLR at 30/60/80 % of the epochs, gamma
            0.1), ``loss_terms`` (e.g. local consistency), ``refiner``.
    """

    def __init__(
        self,
        emb_dims: int = 512,
        k: int = 20,
        num_heads: int = 4,
        ff_dims: int = 1024,
        num_keypoints: int = 512,
        num_iterations: int = 3,
        sampler: Sampler = "gumbel_softmax",
        deterministic_eval: bool = False,
        discount: float = 0.9,
        feature_alignment_weight: float = 0.1,
        cycle_weight: float = 0.1,
        temp_factor: float = 100.0,
        batch_norm: bool = True,
        temperature_batch_norm: bool | None = None,
        **kwargs: Any,
    ) -> None:
        super().__init__(**kwargs)
        if sampler not in ("gumbel_softmax", "softmax"):
            raise ValueError(f"`sampler` must be 'gumbel_softmax' or 'softmax', got {sampler!r}")
        if num_keypoints < 3:
            raise ValueError(f"`num_keypoints` must be >= 3 (a rigid fit needs 3 points), got {num_keypoints}")
        if num_iterations < 1:
            raise ValueError(f"`num_iterations` must be >= 1, got {num_iterations}")
        self.encoder = DGCNN(emb_dims, k, "dynamic", act="leaky_relu", batch_norm=batch_norm)
        self.pointer = PointerTransformer(emb_dims, num_heads, ff_dims, "leaky_relu")
        temperature_bn = batch_norm if temperature_batch_norm is None else temperature_batch_norm
        self.temperature_net = TemperatureNet(emb_dims, temp_factor=temp_factor, batch_norm=temperature_bn)
        self.num_keypoints = num_keypoints
        self.num_iterations = num_iterations
        self.sampler: Sampler = sampler
        self.deterministic_eval = deterministic_eval
        self.discount = discount
        self.feature_alignment_weight = feature_alignment_weight
        self.cycle_weight = cycle_weight
        self.min_points = max(k, 3)

    def head(
        self,
        keypoints_src: torch.Tensor,
        keypoints_ref: torch.Tensor,
        feat_src: torch.Tensor,
        feat_ref: torch.Tensor,
        temperature: torch.Tensor,
    ) -> torch.Tensor:
        """SVD head (one direction): match keypoints by their embeddings, then fit the rigid transform.

        Args:
            keypoints_src: Source keypoints ``(B, N, 3)``.
            keypoints_ref: Reference keypoints ``(B, M, 3)``.
            feat_src: Their embeddings ``(B, N, d)``.
            feat_ref: Their embeddings ``(B, M, d)``.
            temperature: Per-pair temperature ``(B,)``.

        Returns:
            ``transform_ref_src (B, 4, 4)``.
        """
        scores = similarity_scores(feat_src, feat_ref)  # (B, N, M)
        deterministic = self.deterministic_eval and not self.training
        probabilities = sample_correspondences(scores, temperature, self.sampler, deterministic)
        transform, _ = soft_correspondence_transform(keypoints_src, keypoints_ref, probabilities)
        return transform

    def iteration(
        self, points_src: torch.Tensor, points_ref: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """One PRNet pass: ``(transform_ab (B, 4, 4), transform_ba (B, 4, 4), temperature (B,), disparity (B, d))``."""
        feat_src, feat_ref = self.pointer(self.encoder(points_src), self.encoder(points_ref))
        kp_src, kf_src, _ = select_keypoints(points_src, feat_src, self.num_keypoints)
        kp_ref, kf_ref, _ = select_keypoints(points_ref, feat_ref, self.num_keypoints)
        temperature, disparity = self.temperature_net(kf_src, kf_ref)
        transform_ab = self.head(kp_src, kp_ref, kf_src, kf_ref, temperature)
        transform_ba = self.head(kp_ref, kp_src, kf_ref, kf_src, temperature)
        return transform_ab, transform_ba, temperature, disparity

    def forward(self, points_src: torch.Tensor, points_ref: torch.Tensor) -> RegistrationResult:
        """Register ``points_src (B, N, 3)`` to ``points_ref (B, M, 3)`` with ``num_iterations`` PRNet passes.

        ``aux`` holds, stacked over the iterations ``T``: ``transform_ab`` and ``transform_ba`` ``(B, T, 4, 4)``
        (per-iteration A->B / B->A estimates between the moved source and the reference), ``transform_cumulative``
        ``(B, T, 4, 4)`` (``T_i ... T_0``), ``temperature`` ``(B, T)`` and ``feature_disparity`` ``(B, T, d)``.
        """
        batch = points_src.shape[0]
        cumulative = se3.identity(batch, device=points_src.device, dtype=points_src.dtype)
        src = points_src
        history: dict[str, list[torch.Tensor]] = {
            k: [] for k in ("transform_ab", "transform_ba", "transform_cumulative", "temperature", "feature_disparity")
        }
        for _ in range(self.num_iterations):
            transform_ab, transform_ba, temperature, disparity = self.iteration(src, points_ref)
            cumulative = se3.compose(transform_ab, cumulative)
            src = se3.transform_points(transform_ab, src)  # not detached: gradients flow through the moved source
            for key, value in zip(history, (transform_ab, transform_ba, cumulative, temperature, disparity)):
                history[key].append(value)
        aux = {key: torch.stack(values, dim=1) for key, values in history.items()}
        return RegistrationResult.fixed_iterations(cumulative, self.num_iterations, aux)

    def training_forward(self, batch: RegistrationBatch) -> RegistrationResult:
        """``forward``, logging the TemperatureNet's output (``train/temperature_min``, ``_mean``: pairs, iterations).

        In the Gumbel sampler it is ``tau``: a temperature near its floor ``1 / temp_factor`` makes the samples hard
        and the straight-through gradient ``1 / tau`` times larger (a lead when training diverges).
        """
        result = self(batch.points_src, batch.points_ref)
        if self._trainer is not None:
            temperature = result.aux["temperature"].detach()
            for name, value in (("min", temperature.min()), ("mean", temperature.mean())):
                self.log(f"train/temperature_{name}", value, on_step=True, on_epoch=False, batch_size=len(batch))
        return result

    def _compute_loss(self, result: RegistrationResult, batch: RegistrationBatch) -> dict[str, torch.Tensor]:
        """Discounted sum over iterations of the pose, feature-alignment and cycle-consistency terms (+ LC)."""
        gt = self.ground_truth(batch)
        aux = result.aux
        zero = gt.new_zeros(())
        pose, alignment, cycle = zero, zero, zero
        for i in range(aux["transform_cumulative"].shape[1]):
            weight = self.discount**i
            pose = pose + weight * rotation_translation_mse(aux["transform_cumulative"][:, i], gt)
            alignment = alignment + weight * aux["feature_disparity"][:, i].mean()
            cycle = cycle + weight * cycle_consistency_mse(aux["transform_ab"][:, i], aux["transform_ba"][:, i])
        alignment = self.feature_alignment_weight * alignment
        cycle = self.cycle_weight * cycle
        losses = {"loss": pose + alignment + cycle, "pose": pose, "feature_alignment": alignment, "cycle": cycle}
        return losses
