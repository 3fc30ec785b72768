"""DCP: Deep Closest Point (Wang & Solomon, ICCV 2019), DCP-v1 and DCP-v2 behind the common interface.

Pipeline (``transform_ref_src`` in one shot, no iterations):

1. Embedding ``F = DGCNN(points)`` per point (static k-NN graph on the input coordinates, ``k = 20``, 512 channels,
   ReLU), computed separately for the source and the reference (shared weights).
2. Pointer: ``"transformer"`` (DCP-v2) adds the attention residuals of
   :class:`~lcreg.nn.transformer.PointerTransformer` (1 block, 4 heads, FFN 1024); ``"identity"`` (DCP-v1) keeps
   ``F`` as it is.
3. SVD head: ``p_ij = softmax_j(F_src,i . F_ref,j / sqrt(d))``, soft correspondences ``y_hat_i = sum_j p_ij y_j``
   and the differentiable Kabsch fit :func:`~lcreg.nn.correspondence.soft_correspondence_transform`.

Loss (as in the original): ``MSE(R^T R_gt, I) + MSE(t, t_gt)``
(:func:`~lcreg.nn.losses.rotation_translation_mse`). With ``cycle=True`` a second head pass estimates the reverse
transform ``T_src_ref`` from the transposed scores and ``0.1 * [MSE(R_ba R_ab, I) + MSE(R_ba t_ab + t_ba, 0)]`` is
added.

Deviations from the original code (``WangYueFt/dcp``):

* Known bug fixed: the original cycle term uses ``R_ba^T t_ab + t_ba`` in its translation part; the exact identity
  of ``T_ba T_ab = I`` is ``R_ba t_ab + t_ba = 0``, which is what is used here (off by default, as in the original).
* Only the DGCNN embedding and the SVD head of the README's DCP-v1/v2 are implemented (not the PointNet embedding
  or the MLP head options).
* The Kabsch reflection fix multiplies the last column of ``V`` by ``sign det(V U^T)`` (same result as the
  original's recomputation) and the SVD is batched instead of a per-sample loop.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Literal

import torch

from lcreg.models.base import RegistrationModule
from lcreg.nn.correspondence import similarity_scores, soft_correspondence_transform
from lcreg.nn.dgcnn import DGCNN
from lcreg.nn.losses import cycle_consistency_mse, rotation_translation_mse
from lcreg.nn.transformer import PointerTransformer
from lcreg.types import RegistrationBatch, RegistrationResult

__all__ = ["CYCLE_WEIGHT", "DCP"]

Pointer = Literal["transformer", "identity"]

CYCLE_WEIGHT = 0.1
"""Weight of the optional cycle-consistency term (the original's constant)."""


class DCP(RegistrationModule):
    """Deep Closest Point (DCP-v2 with ``pointer="transformer"``, DCP-v1 with ``pointer="identity"``).

    ``result.aux`` holds ``"matched"`` (soft correspondences ``(B, N, 3)`` in the reference frame), with
    ``cycle=True`` also ``"transform_src_ref"`` ``(B, 4, 4)``, and with ``return_probabilities=True`` the matching
    ``"probabilities"`` ``(B, N, M)`` (large: ``N x M`` per pair, off by default).

    Args:
        emb_dims: Per-point embedding width (512).
        k: Neighbours of the static DGCNN graph (20); clouds need at least ``k`` points.
        pointer: ``"transformer"`` (DCP-v2) or ``"identity"`` (DCP-v1).
        heads: Attention heads of the transformer (4).
        ff_dims: FFN width of the transformer (1024).
        cycle: Add the reverse head pass and the cycle-consistency term (weight :data:`CYCLE_WEIGHT`).
        edge_channels: Widths of the DGCNN edge layers (64, 64, 128, 256); smaller only for tests.
        return_probabilities: Keep the ``(B, N, M)`` matching probabilities in ``result.aux``.
        batch_norm: BatchNorm in the DGCNN embedding (the original). ``False`` is a deviation, for the question of
            what BatchNorm does at small batches: in training each cloud batch is normalised by its own statistics
            (the reference batch's carry the batch's mean translation), in eval mode by running averages, so the
            network evaluated is not the one trained (``benchmarks/overfit.py``).
        **kwargs: :class:`~lcreg.models.base.RegistrationModule` components: ``optimizer`` (original: Adam, lr
            1e-3, weight decay 1e-4), ``lr_scheduler`` (original: MultiStepLR [75, 150, 200], gamma 0.1),
            ``loss_terms`` (e.g. local consistency), ``refiner``.

    Raises:
        ValueError: On an unknown ``pointer`` or an injected loss term built for another width than ``emb_dims``.
    """

    def __init__(
        self,
        emb_dims: int = 512,
        k: int = 20,
        pointer: Pointer = "transformer",
        heads: int = 4,
        ff_dims: int = 1024,
        cycle: bool = False,
        edge_channels: Sequence[int] = (64, 64, 128, 256),
        return_probabilities: bool = False,
        batch_norm: bool = True,
        **kwargs: Any,
    ) -> None:
        super().__init__(**kwargs)
        if pointer not in ("transformer", "identity"):
            raise ValueError(f"`pointer` must be 'transformer' or 'identity', got {pointer!r}")
        self.encoder = DGCNN(emb_dims, k, "static", channels=tuple(edge_channels), act="relu", batch_norm=batch_norm)
        self.pointer = PointerTransformer(emb_dims, heads, ff_dims, "relu") if pointer == "transformer" else None
        self.cycle = cycle
        self.return_probabilities = return_probabilities
        self.min_points = k

    def embed(self, points_src: torch.Tensor, points_ref: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Final per-point embeddings ``(B, N, emb_dims)``, ``(B, M, emb_dims)`` (after the pointer)."""
        feat_src, feat_ref = self.encoder(points_src), self.encoder(points_ref)
        if self.pointer is not None:
            feat_src, feat_ref = self.pointer(feat_src, feat_ref)
        return feat_src, feat_ref

    @staticmethod
    def head(
        points_src: torch.Tensor, points_ref: torch.Tensor, probabilities: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """SVD head on given matching probabilities ``(B, N, M)``: ``(transform_ref_src (B, 4, 4), matched)``."""
        return soft_correspondence_transform(points_src, points_ref, probabilities)

    def forward(self, points_src: torch.Tensor, points_ref: torch.Tensor) -> RegistrationResult:
        """Estimate ``transform_ref_src`` for ``points_src (B, N, 3)`` and ``points_ref (B, M, 3)``."""
        feat_src, feat_ref = self.embed(points_src, points_ref)
        scores = similarity_scores(feat_src, feat_ref)  # (B, N, M)
        probabilities = scores.softmax(dim=-1)
        transform, matched = self.head(points_src, points_ref, probabilities)
        aux: dict[str, torch.Tensor] = {"matched": matched}
        if self.cycle:
            aux["transform_src_ref"] = self.head(points_ref, points_src, scores.transpose(1, 2).softmax(dim=-1))[0]
        if self.return_probabilities:
            aux["probabilities"] = probabilities
        return RegistrationResult.fixed_iterations(transform, aux=aux)

    def _compute_loss(self, result: RegistrationResult, batch: RegistrationBatch) -> dict[str, torch.Tensor]:
        """``pose`` (rotation/translation MSE), optional ``cycle`` (weight 0.1) and the total ``loss``."""
        pose = rotation_translation_mse(result.transform_ref_src, self.ground_truth(batch))
        losses = {"pose": pose, "loss": pose}
        if self.cycle:
            cycle = cycle_consistency_mse(result.aux["transform_src_ref"], result.transform_ref_src)  # T_ba T_ab
            losses["cycle"] = cycle
            losses["loss"] = pose + CYCLE_WEIGHT * cycle
        return losses
