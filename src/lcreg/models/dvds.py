"""DVDs: self-supervised registration with Deep Versatile Descriptors (Liu et al., IEEE T-ITS 2023).

Registration (Section IV, Algorithm 1): a PointNet global descriptor ``psi`` and the inverse-compositional LK solver
(:class:`lcreg.nn.lk.InverseCompositionalLK`, T = 10, stop at ``||dw|| < 1e-7``). Training uses no ground-truth
pose; per batch:

1. ``psi`` frozen (eval mode, no graph): IC-LK estimates ``W`` for each pair.
2. ``psi`` trainable, ``W`` held fixed (one train-mode encoder pass over ``[X, Y, W(X)]``; ``norm_batch``):
   ``L_p = ||psi(W(X)) - psi(Y)||_2 + LC`` (batch mean of the L2 norm, not squared; LC = symmetric KL of
   :class:`lcreg.nn.local_consistency.LocalConsistency`, injected like on every host:
   ``loss_terms=[LocalConsistencyLoss(...)]``, ``configs/lc.yaml``),
   ``L_CD = CD(xi(psi(X)), X) + CD(xi(psi(Y)), Y)`` (FoldingNet decoder ``xi``, Chamfer not squared),
   ``L_n = sum_P (1 - mean_i cos(l([p_i, psi(P)]), n_i))`` (normal head ``l``),
   ``L = L_p + lambda1 L_CD + lambda2 L_n`` (defaults 0.5, 0.1; the LC term's ``weight`` is 1 in the paper;
   ``lambda_global`` scales the descriptor residual of ``L_p``, 1 in the paper).

Normals come from the batch (ModelNet40 provides them). Without normals they are estimated by PCA
(:func:`lcreg.geometry.normals.estimate_normals`) and compared with ``|cos|`` since their sign is arbitrary.
The paper's ablation models: A ``loss_terms=[], lambda_recon=0, lambda_normal=0``; B adds LC; C adds
reconstruction; D is the full model (``configs/ablation/``). Decoder and normal head are unused at test time (not
even built when their weight is 0).

Diagnostics (paper-ambiguity note 1): every ``diagnostics_every_n_steps`` training steps the gradient norms of the
LC and global terms w.r.t. ``psi`` are logged (``train/lc_grad_norm``, ``train/global_grad_norm``), so a collapse of
the LC term is visible.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, ClassVar, Literal

import torch

from lcreg.geometry import se3
from lcreg.geometry.chamfer import chamfer_distance
from lcreg.geometry.normals import estimate_normals
from lcreg.models.lucas_kanade import LucasKanadeModule
from lcreg.nn.decoders import MLPDecoder
from lcreg.nn.folding import FoldingDecoder
from lcreg.nn.heads import NormalHead
from lcreg.nn.lk import JacobianMode
from lcreg.types import RegistrationBatch, RegistrationResult

__all__ = ["DVDs"]


class DVDs(LucasKanadeModule):
    """DVDs model (encoder, solver and ``forward`` from :class:`~lcreg.models.lucas_kanade.LucasKanadeModule`).

    Args:
        encoder_channels: PointNet widths; the last is the descriptor size ``K`` (paper: 1024).
        batch_norm: BatchNorm in the encoder.
        max_iterations: IC-LK iterations ``T``.
        tolerance: IC-LK stopping threshold on ``||dw||``.
        damping: Relative damping of ``J^T J``.
        jacobian: ``"analytic"`` (exact, default), ``"autodiff"`` or ``"finite_difference"``.
        lambda_recon: ``lambda1`` (self-reconstruction; 0 disables it).
        lambda_normal: ``lambda2`` (normal estimation; 0 disables it).
        lambda_global: Weight of the global residual ``L_p``'s descriptor term (paper: 1; 0 keeps it logged but
            unoptimised, e.g. when a :class:`~lcreg.models.loss_terms.SelfMotionLoss` trains the descriptor).
        decoder_grid_size: FoldingNet grid side; ``grid_size**2`` reconstructed points (either decoder).
        decoder_hidden: The decoder's hidden widths (FoldingNet's MLP; FMR-Net's MLP decoder: 1024, 512, 256).
        decoder: ``"folding"`` (the paper's FoldingNet ``xi``) or ``"mlp"`` (FMR-Net's fully connected decoder,
            :class:`~lcreg.nn.decoders.MLPDecoder`, BatchNorm as the encoder's): with the same encoder and the same
            squared-Chamfer reconstruction, FMR-Net's descriptor keeps more pairs at the true pose than DVDs' with
            FoldingNet (``docs/results/converge/``), so the decoder is a lever of the descriptor's bias.
        normal_hidden: Normal-head MLP widths.
        global_loss: ``"l2"`` (paper: ``||psi(W(X)) - psi(Y)||_2``) or ``"normalized_l2"`` (the same divided by the
            RMS norm of the two descriptors; IC-LK is invariant to the descriptor scale, so this removes the trivial
            minimiser "shrink the features" without changing what registration uses).
        squared_chamfer: The reconstruction term's Chamfer distance averages squared nearest-neighbour distances
            (FMR-Net's reconstruction loss) instead of distances (default, the paper's ``L_CD``).
        diagnostics_every_n_steps: Period of the gradient-norm diagnostics (0: never).
        norm_batch: How the loss encodes ``X``, ``Y`` and ``W(X)`` in training: ``"joint"`` (default), one encoder pass
            over ``[X, Y, W(X)]``, so BatchNorm normalises the three with the same batch statistics (the global
            residual compares like with like); ``"per_cloud"``, one pass per cloud, each batch normalised alone as
            FMR-Net does (with FMR-Net's objective and decoder this is FMR-Net's loss and gradients, BatchNorm
            included). The same function without BatchNorm.
        **kwargs: :class:`~lcreg.models.lucas_kanade.LucasKanadeModule` arguments (``eval_iterations``,
            ``voxel_grid``) and components (``optimizer``, ``lr_scheduler``, ``loss_terms`` such as
            ``[LocalConsistencyLoss()]``, ``refiner``).
    """

    training_only_modules: ClassVar[tuple[str, ...]] = ("loss_terms", "decoder", "normal_head")
    inference_hparams: ClassVar[Mapping[str, Any]] = {
        **LucasKanadeModule.inference_hparams,
        "lambda_recon": 0.0,
        "lambda_normal": 0.0,
        "norm_batch": "joint",
    }

    def __init__(
        self,
        encoder_channels: Sequence[int] = (64, 64, 64, 128, 1024),
        batch_norm: bool = True,
        max_iterations: int = 10,
        tolerance: float = 1e-7,
        damping: float = 1e-6,
        jacobian: JacobianMode = "analytic",
        lambda_recon: float = 0.5,
        lambda_normal: float = 0.1,
        lambda_global: float = 1.0,
        decoder_grid_size: int = 32,
        decoder_hidden: Sequence[int] = (256, 256),
        normal_hidden: Sequence[int] = (128, 64),
        global_loss: Literal["l2", "normalized_l2"] = "l2",
        squared_chamfer: bool = False,
        diagnostics_every_n_steps: int = 50,
        decoder: Literal["folding", "mlp"] = "folding",
        norm_batch: Literal["joint", "per_cloud"] = "joint",
        **kwargs: Any,
    ) -> None:
        super().__init__(
            encoder_channels,
            batch_norm,
            max_iterations,
            tolerance=tolerance,
            damping=damping,
            jacobian=jacobian,
            **kwargs,
        )
        if min(lambda_recon, lambda_normal, lambda_global) < 0:
            raise ValueError(
                f"loss weights must be >= 0, got lambda_recon={lambda_recon}, lambda_normal={lambda_normal}, "
                f"lambda_global={lambda_global}"
            )
        if decoder not in ("folding", "mlp"):
            raise ValueError(f"`decoder` must be 'folding' or 'mlp', got {decoder!r}")
        if norm_batch not in ("joint", "per_cloud"):
            raise ValueError(f"`norm_batch` must be 'joint' or 'per_cloud', got {norm_batch!r}")
        self.norm_batch = norm_batch
        k = self.encoder.feature_dim
        self.lambda_recon = lambda_recon
        self.lambda_normal = lambda_normal
        self.lambda_global = lambda_global
        self.decoder: FoldingDecoder | MLPDecoder | None = None
        if lambda_recon > 0 and decoder == "folding":
            self.decoder = FoldingDecoder(k, decoder_grid_size, decoder_hidden)
        elif lambda_recon > 0:
            self.decoder = MLPDecoder(k, decoder_hidden, decoder_grid_size**2, batch_norm)
        self.normal_head = NormalHead(k, normal_hidden) if lambda_normal > 0 else None
        if global_loss not in ("l2", "normalized_l2"):
            raise ValueError(f"`global_loss` must be 'l2' or 'normalized_l2', got {global_loss!r}")
        self.global_loss = global_loss
        self.squared_chamfer = squared_chamfer
        self.diagnostics_every_n_steps = diagnostics_every_n_steps

    def _chamfer(self, decoded: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
        """Batch mean of the Chamfer distance between a reconstruction and its cloud (squared if configured)."""
        return chamfer_distance(decoded, points, squared=self.squared_chamfer).mean()

    def _normal_loss(self, points: torch.Tensor, normals: torch.Tensor | None, code: torch.Tensor) -> torch.Tensor:
        """``1 - mean cos(pred, n)`` per batch (``|cos|`` for PCA-estimated, unoriented normals), batch mean."""
        if self.normal_head is None:
            raise RuntimeError("normal loss requested but lambda_normal == 0")
        oriented = normals is not None
        target = normals if normals is not None else estimate_normals(points.detach())
        cos = torch.nn.functional.cosine_similarity(self.normal_head(points, code), target, dim=-1, eps=1e-8)
        return (1 - (cos if oriented else cos.abs()).mean(dim=1)).mean()

    def _compute_loss(self, result: RegistrationResult, batch: RegistrationBatch) -> dict[str, torch.Tensor]:
        """``L = L_p + lambda1 L_CD + lambda2 L_n``; no ground-truth transform is used."""
        x, y = batch.points_src, batch.points_ref
        b = x.shape[0]
        moved = se3.transform_points(result.transform_ref_src.detach(), x)
        if self.norm_batch == "per_cloud":
            f_x, f_y, f_wx = self.encoder(x), self.encoder(y), self.encoder(moved)
        elif y.shape[1] == x.shape[1]:
            f_x, f_y, f_wx = self.encoder(torch.cat([x, y, moved])).split(b)
        else:
            f_x, f_wx = self.encoder(torch.cat([x, moved])).split(b)
            f_y = self.encoder(y)
        residual = (f_wx - f_y).norm(dim=-1)  # (B,)
        if self.global_loss == "normalized_l2":
            scale = (0.5 * (f_wx.pow(2).sum(-1) + f_y.pow(2).sum(-1))).sqrt()
            residual = residual / scale.clamp_min(torch.finfo(scale.dtype).eps)
        losses = {"global": residual.mean()}
        losses["loss"] = self.lambda_global * losses["global"]
        if self.decoder is not None:
            recon = self._chamfer(self.decoder(f_x), x) + self._chamfer(self.decoder(f_y), y)
            losses["recon"] = recon
            losses["loss"] = losses["loss"] + self.lambda_recon * recon
        if self.normal_head is not None:
            normal = self._normal_loss(x, batch.normals_src, f_x) + self._normal_loss(y, batch.normals_ref, f_y)
            losses["normal"] = normal
            losses["loss"] = losses["loss"] + self.lambda_normal * normal
        return losses

    def _log_loss_diagnostics(self, losses: dict[str, torch.Tensor]) -> None:
        """Log gradient norms of the global and LC terms w.r.t. the encoder (collapse check)."""
        every = self.diagnostics_every_n_steps
        if not (self.training and every > 0 and self.global_step % every == 0 and torch.is_grad_enabled()):
            return
        params = [p for p in self.encoder.parameters() if p.requires_grad]
        for name in ("global", "lc"):
            if name in losses and losses[name].requires_grad:
                grads = torch.autograd.grad(losses[name], params, retain_graph=True, allow_unused=True)
                norm = torch.sqrt(sum((g.pow(2).sum() for g in grads if g is not None), torch.zeros(())))
                self.log(f"train/{name}_grad_norm", norm, on_step=True, on_epoch=False)
