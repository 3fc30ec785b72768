"""DeepGMR: Deep Gaussian Mixture Registration (Yuan et al., ECCV 2020), after ``wentaoyuan/deepgmr``.

Pipeline (the original's ``model.py``), for each cloud separately:

1. Input features: RRI descriptors of the ``k = 20`` nearest neighbours (:func:`lcreg.geometry.rri.rri_features`,
   ``4k`` numbers per point, exactly rotation invariant) or, with ``use_rri=False``, the centred coordinates.
2. Encoder ``psi`` (:class:`DeepGMREncoder`, LC uses it): shared PointNet ``d_in -> 64 -> 128 -> 256 -> d_model``
   (bias-free 1x1 convolutions, BatchNorm, ReLU), per-point features ``(B, N, d_model)``.
3. Cluster head: ``[local, global max-pool]`` ``(2 d_model) -> 512 -> 256 -> 128 -> J`` (last layer plain, with
   bias); softmax over the ``J = 16`` clusters gives the point-to-component posteriors ``gamma (B, N, J)``.
4. GMM (:func:`gmm_params`): ``pi_j = mean_i gamma_ij``, ``mu_j = sum_i gamma_ij x_i / (N pi_j)`` and an isotropic
   covariance ``sigma_j^2 I``.
5. Closed-form registration of the two mixtures (:func:`gmm_register`), both ways: ``T12`` (source into reference,
   the estimate) and ``T21``. Loss ``MSE(T12 T_gt^-1, I4) + MSE(T21 T_gt, I4)``.

The backbone runs once per cloud (two BatchNorm batches), as in the original. With RRI the estimate is exactly
equivariant to rigid motions of either cloud, and it is exact for any network weights when the reference is a
rigidly moved, permuted copy of the source (identical posteriors per point): on noise-free "same points" pairs (the
DCP protocol with ``independent_sampling=False``) DeepGMR is exact from initialisation; the original trains with
independent noise on both clouds.

Decisions and deviations:

* **Variance scale.** The original stores ``sum_i gamma_ij ||x_i - mu_j||^2 / (N pi_j)``, the *total* variance of
  the component; the per-axis variance of an isotropic 3-D Gaussian (its maximum-likelihood ``sigma^2``) is that
  divided by 3, which :func:`gmm_params` returns. This does not change any estimate: the variances only enter the
  registration as the per-component weights ``pi_s,j / sigma_t,j^2``, a common factor 1/3 multiplies every weight
  (the *relative* weights are unchanged), so the cross-covariance ``M`` is scaled by 3, its singular vectors (hence
  ``R``) are unchanged, and ``t = c_t - R c_s`` uses the ``pi``-weighted centroids, which do not involve ``sigma``.
  ``T12``, ``T21`` and the loss are identical to the original's (pinned by a test).
* **Centroids.** As in the original, both centroids use the source weights ``pi_s`` (``c_s = sum pi_s,j mu_s,j``,
  ``c_t = sum pi_s,j mu_t,j``) while ``M = sum_j pi_s,j / sigma_t,j^2 (mu_s,j - c_s)(mu_t,j - c_t)^T``. (The exact
  minimiser of ``sum_j pi_s,j / sigma_t,j^2 ||R mu_s,j + t - mu_t,j||^2`` would centre with the precision-weighted
  means; the two agree when the target variances are equal and whenever the mixtures match exactly.)
* **Centred xyz without RRI.** The original's non-RRI input subtracts the mean over the *coordinates* of each point
  (``mean(dim=2)`` on ``(B, N, 3)``), not the cloud centroid; we centre at the cloud centroid, as the RRI path
  does (its features are computed on the centred cloud). The paper's results use RRI.
* No optional T-Net (off in the original's defaults). The SVD runs on the input's device (the original moves it
  to the CPU). ``gamma`` mass and variances are floored at ``eps`` so an empty component cannot divide by zero.
* The original's ReduceLROnPlateau (factor 0.5, min lr 1e-6, patience 10, stepped on the validation loss) is set in
  the configs; :meth:`~lcreg.models.base.RegistrationModule.configure_optimizers` monitors ``val/loss`` for it.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import nn

from lcreg.geometry import se3
from lcreg.geometry.precision import full_precision
from lcreg.geometry.procrustes import weighted_kabsch
from lcreg.geometry.rri import rri_features
from lcreg.models.base import RegistrationModule
from lcreg.nn.losses import transform_mse
from lcreg.nn.mlp import PointwiseMLP
from lcreg.types import RegistrationBatch, RegistrationResult

__all__ = ["DeepGMR", "DeepGMREncoder", "gmm_params", "gmm_register"]


@full_precision
def gmm_params(
    gamma: torch.Tensor, points: torch.Tensor, eps: float = 1e-12
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Isotropic GMM fitted to ``points`` with soft assignments ``gamma`` (one weighted M-step).

    Args:
        gamma: Posteriors ``(B, N, J)``, each row summing to one.
        points: Clouds ``(B, N, 3)``.
        eps: Floor of the component mass ``N pi_j`` and of the variance.

    Returns:
        ``(pi, mu, sigma2)``: weights ``(B, J)``, means ``(B, J, 3)`` and per-axis variances ``(B, J)`` (covariance
        ``sigma2_j I``; the original's value is ``3 sigma2``, see the module docstring).
    """
    mass = gamma.sum(dim=1)  # (B, J) = N pi_j
    pi = mass / gamma.shape[1]
    denom = mass.clamp_min(eps)
    mu = gamma.transpose(1, 2) @ points / denom[..., None]  # (B, J, 3)
    sq_dist = (points[:, :, None, :] - mu[:, None, :, :]).square().sum(-1)  # (B, N, J)
    sigma2 = (gamma * sq_dist).sum(dim=1) / denom / 3.0
    return pi, mu, sigma2.clamp_min(eps)


@full_precision
def gmm_register(pi_s: torch.Tensor, mu_s: torch.Tensor, mu_t: torch.Tensor, sigma2_t: torch.Tensor) -> torch.Tensor:
    """Closed-form rigid transform taking the source mixture onto the target mixture (DeepGMR's formula).

    ``c_s = sum_j pi_j mu_s,j``, ``c_t = sum_j pi_j mu_t,j``, ``M = sum_j pi_j / sigma2_t,j (mu_s,j - c_s)
    (mu_t,j - c_t)^T``, ``R`` from the SVD of ``M`` with the reflection fix, ``t = c_t - R c_s``.

    Args:
        pi_s: Source component weights ``(B, J)`` (normalised here to sum to one).
        mu_s: Source means ``(B, J, 3)``.
        mu_t: Target means ``(B, J, 3)`` (component ``j`` corresponds to source component ``j``).
        sigma2_t: Target isotropic variances ``(B, J)``, positive.

    Returns:
        ``transform_t_s`` ``(B, 4, 4)``: ``mu_t ~ R mu_s + t``.
    """
    pi = pi_s / pi_s.sum(dim=1, keepdim=True)
    c_s = (pi[..., None] * mu_s).sum(dim=1)  # (B, 3)
    c_t = (pi[..., None] * mu_t).sum(dim=1)
    a, b = mu_s - c_s[:, None], mu_t - c_t[:, None]  # (B, J, 3)
    weights = pi / sigma2_t  # (B, J)
    # weighted_kabsch re-centres with its own (precision-weighted) centroids; adding the mirrored pairs (-a, -b)
    # makes those centroids exactly 0, so its cross-covariance is M / (2 sum w) and the rotation is the original's.
    rot = weighted_kabsch(torch.cat([a, -a], dim=1), torch.cat([b, -b], dim=1), torch.cat([weights, weights], 1))
    rot = rot[:, :3, :3]
    trans = c_t - (rot @ c_s[..., None]).squeeze(-1)
    return se3.make_transform(rot, trans)


class DeepGMREncoder(nn.Module):
    """DeepGMR's per-point feature network ``psi``: RRI (or centred xyz) then a shared PointNet.

    Args:
        d_model: Output width ``K`` (original: 1024).
        k: Neighbours of the RRI features (original: 20); inputs need ``N >= k + 1`` points.
        use_rri: RRI inputs (``4k`` channels); ``False``: centred coordinates (3 channels).
    """

    def __init__(self, d_model: int = 1024, k: int = 20, use_rri: bool = True) -> None:
        super().__init__()
        if d_model < 1:
            raise ValueError(f"`d_model` must be >= 1, got {d_model}")
        if use_rri and k < 2:
            raise ValueError(f"`k` must be >= 2, got {k}")
        self.k = k
        self.use_rri = use_rri
        self.mlp = PointwiseMLP((4 * k if use_rri else 3, 64, 128, 256, d_model), bias=False)

    @property
    def out_channels(self) -> int:
        """Feature width ``K = d_model``."""
        return self.mlp.out_channels

    @property
    def feature_dim(self) -> int:
        """Descriptor width ``K`` (the attribute loss terms such as LC read)."""
        return self.mlp.out_channels

    def input_features(self, points: torch.Tensor) -> torch.Tensor:
        """``(B, N, 3)`` -> RRI ``(B, N, 4k)`` or centred coordinates ``(B, N, 3)``."""
        if self.use_rri:
            return rri_features(points, self.k)
        return points - points.mean(dim=1, keepdim=True)

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        """Per-point features ``(B, N, d_model)`` of clouds ``(B, N, 3)``."""
        return self.mlp(self.input_features(points))


class DeepGMR(RegistrationModule):
    """DeepGMR host (module docstring); the LC encoder is :class:`DeepGMREncoder` (``K = d_model``).

    Args:
        d_model: Per-point feature width (original: 1024).
        num_clusters: Mixture components ``J`` (original: 16).
        k: RRI neighbours (original: 20).
        use_rri: RRI input features (needed for the paper's results; exact rotation equivariance).
        **kwargs: :class:`~lcreg.models.base.RegistrationModule` components: ``optimizer`` (original: Adam, lr
            1e-3), ``lr_scheduler`` (none), ``loss_terms`` (e.g. local consistency), ``refiner``.
    """

    def __init__(
        self,
        d_model: int = 1024,
        num_clusters: int = 16,
        k: int = 20,
        use_rri: bool = True,
        **kwargs: Any,
    ) -> None:
        super().__init__(**kwargs)
        if num_clusters < 1:
            raise ValueError(f"`num_clusters` must be >= 1, got {num_clusters}")
        self.encoder = DeepGMREncoder(d_model, k, use_rri)
        self.cluster_head = PointwiseMLP((2 * d_model, 512, 256, 128, num_clusters), bias=False, last_plain=True)
        self.min_points = k + 1 if use_rri else 3

    def posteriors(self, points: torch.Tensor) -> torch.Tensor:
        """Point-to-component posteriors ``gamma (B, N, J)`` (softmax over the clusters)."""
        local = self.encoder(points)  # (B, N, d_model)
        glob = local.amax(dim=1, keepdim=True).expand_as(local)
        return torch.softmax(self.cluster_head(torch.cat([local, glob], dim=-1)), dim=-1)

    def forward(self, points_src: torch.Tensor, points_ref: torch.Tensor) -> RegistrationResult:
        """Register ``points_src (B, N, 3)`` onto ``points_ref (B, M, 3)`` through their mixtures.

        ``aux``: ``transform_21`` (reference into source), ``gamma_src``/``gamma_ref`` and the mixtures
        ``pi_*``, ``mu_*``, ``sigma2_*`` (per-axis variances).
        """
        gamma_src, gamma_ref = self.posteriors(points_src), self.posteriors(points_ref)
        pi_s, mu_s, sigma2_s = gmm_params(gamma_src, points_src)
        pi_r, mu_r, sigma2_r = gmm_params(gamma_ref, points_ref)
        transform_12 = gmm_register(pi_s, mu_s, mu_r, sigma2_r)
        transform_21 = gmm_register(pi_r, mu_r, mu_s, sigma2_s)
        aux = {
            "transform_21": transform_21,
            "gamma_src": gamma_src,
            "gamma_ref": gamma_ref,
            "pi_src": pi_s,
            "mu_src": mu_s,
            "sigma2_src": sigma2_s,
            "pi_ref": pi_r,
            "mu_ref": mu_r,
            "sigma2_ref": sigma2_r,
        }
        return RegistrationResult.fixed_iterations(transform_12, aux=aux)

    def _compute_loss(self, result: RegistrationResult, batch: RegistrationBatch) -> dict[str, torch.Tensor]:
        """``MSE(T12 T_gt^-1, I4) + MSE(T21 T_gt, I4)`` (logged as ``mse_12``/``mse_21``), plus LC when attached."""
        transform_gt = self.ground_truth(batch)
        mse_12 = transform_mse(result.transform_ref_src, se3.inverse(transform_gt))
        mse_21 = transform_mse(result.aux["transform_21"], transform_gt)
        losses = {"loss": mse_12 + mse_21, "mse_12": mse_12, "mse_21": mse_21}
        return losses
