"""PointNet global descriptor (shared per-point MLP + max pool) with an exact analytic twist Jacobian.

The encoder follows PointNetLK: every layer is ``Linear -> BatchNorm -> ReLU`` (a 1x1 Conv1d), default widths
``3 -> 64 -> 64 -> 64 -> 128 -> 1024`` and max pooling, so ``psi: (B, N, 3) -> (B, K)``.

:meth:`PointNetEncoder.twist_jacobian` returns ``d psi(exp(xi) P) / d xi`` at ``xi = 0`` (twist ``[omega, v]``).
Because of the max pool only the arg-max point of each channel contributes, and the derivative of a point
moved by a small twist is ``[p x g, g]`` for the point gradient ``g``. The hidden layers are differentiated in
forward mode on the 3 coordinate directions for all points (cheap: widths <= 128); the wide last layer is
differentiated only at each channel's arg-max point. This costs about one forward pass, against 6 for finite
differences. Batch norm enters with its running statistics (eval-mode semantics), which is how the IC-LK
solver runs the encoder.

The training-mode forward uses the same fact for the backward pass: when the last layer has no BatchNorm, its
arg-max points are found without autograd (chunk by chunk) and the graph holds the last layer at those ``K`` points
only, instead of the ``(B, N, K)`` activations and their dense backward (forward + backward over ``[X, Y, W(X)]``
at ``B = 16``, ``N = 1024``: 3.5x faster, ``benchmarks/bench_dvds_step.py --breakdown``). The plain versions stay as
``_..._reference`` methods (:mod:`lcreg.reference`).
"""

from __future__ import annotations

from collections.abc import Sequence
from itertools import pairwise
from typing import cast

import torch
from torch import nn

from lcreg.checks import check_points
from lcreg.nn.dtypes import to_module_dtype
from lcreg.reference import reference_active

__all__ = ["PointNetEncoder"]

_SPARSE_MIN_POINTS = 128
"""Fewest points per cloud for the sparse training backward (crossover measured on a 2-core CPU at ``K = 1024``:
64-128 points; LC's 64-point subsets run 1.3-1.7x faster dense, 512-1024-point clouds about 3x faster sparse)."""


class PointNetEncoder(nn.Module):
    """Vanilla PointNet feature extractor ``psi`` (no T-Net).

    Args:
        channels: Output widths of the shared layers; the last one is the descriptor size ``K``.
        batch_norm: Use BatchNorm after each linear layer (PointNet/PointNetLK) or not.
        chunk_size: Points per chunk of the pooled wide last layer (eval-mode forward, arg-max searches of the
            training forward and of the Jacobian). Memory/speed only, same result; with 128 a chunk's product stays
            small enough for the cache at ``B = 16-48``, ``K = 1024`` (arg-max search at ``B = 48`` on a 2-core CPU:
            1.2-1.4x faster than with 256 points).
    """

    def __init__(
        self, channels: Sequence[int] = (64, 64, 64, 128, 1024), batch_norm: bool = True, chunk_size: int = 128
    ) -> None:
        super().__init__()
        self.chunk_size = chunk_size
        if len(channels) < 1 or any(c <= 0 for c in channels):
            raise ValueError(f"`channels` must be positive widths, got {list(channels)}")
        widths = [3, *channels]
        self.linears = nn.ModuleList(nn.Linear(a, b) for a, b in pairwise(widths))
        self.norms = nn.ModuleList(nn.BatchNorm1d(c) if batch_norm else nn.Identity() for c in channels)

    @property
    def feature_dim(self) -> int:
        """Descriptor size ``K``."""
        return self._linear(len(self.linears) - 1).out_features

    def _linear(self, i: int) -> nn.Linear:
        """Linear layer ``i`` (typed access into the ModuleList)."""
        return cast(nn.Linear, self.linears[i])

    def _block(self, i: int, h: torch.Tensor) -> torch.Tensor:
        """Layer ``i`` (linear, norm, ReLU) on ``(B, N, C)`` features, training-mode normalisation."""
        z = self.linears[i](h)
        b, n, c = z.shape
        return torch.relu(self.norms[i](z.reshape(b * n, c)).reshape(b, n, c))

    def _folded(self, i: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Layer ``i`` with its eval-mode norm folded in: ``relu(h @ W.T + b)`` equals the block. Differentiable."""
        scale, shift = self._affine(i)
        lin = self._linear(i)
        bias = lin.bias if lin.bias is not None else 0.0
        return lin.weight * scale[:, None], bias * scale + shift

    def point_features(self, points: torch.Tensor) -> torch.Tensor:
        """Per-point features ``(B, N, K)`` before pooling."""
        h = points
        for i in range(len(self.linears)):
            if self.training:
                h = self._block(i, h)
            else:
                weight, bias = self._folded(i)
                h = torch.relu(nn.functional.linear(h, weight, bias))
        return h

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        """Global descriptor ``(B, K)`` of ``points (B, N, 3)`` (float32 or float64: computed in the weights' dtype)."""
        points = to_module_dtype(self, check_points(points, "points"))
        if self.training:
            if reference_active() or not self._pools_sparsely(points.shape[1]):
                return self._forward_train_reference(points)
            return self._forward_train(points)
        h = points
        for i in range(len(self.linears) - 1):
            weight, bias = self._folded(i)
            h = torch.relu(nn.functional.linear(h, weight, bias))
        weight, bias = self._folded(len(self.linears) - 1)
        if torch.is_grad_enabled() and not reference_active() and points.shape[1] >= _SPARSE_MIN_POINTS:
            # A graph through an eval-mode solve (a loss term training through IC-LK): as in training, differentiate
            # the wide last layer at the arg-max points only; autograd through the chunked max below would keep and
            # scatter every (B, chunk, K) block.
            return torch.relu(_dot_at(h, self._pooled_argmax(h, weight), weight, bias))
        # max and ReLU commute and the bias is per channel: pool the wide last layer chunk by chunk (cache-friendly).
        pooled = torch.stack([nn.functional.linear(c, weight).amax(1) for c in h.split(self.chunk_size, dim=1)])
        return torch.relu(pooled.amax(0) + bias)

    def _pools_sparsely(self, num_points: int) -> bool:
        """Whether the training forward differentiates the last layer at the arg-max points only.

        It needs a plain last layer (BatchNorm's batch statistics need every point's output), and pays off from about
        ``_SPARSE_MIN_POINTS`` points per cloud: below, the dense backward costs less than gathering ``K`` rows per
        cloud.
        """
        return isinstance(self.norms[-1], nn.Identity) and num_points >= _SPARSE_MIN_POINTS

    def _forward_train_reference(self, points: torch.Tensor) -> torch.Tensor:
        """Training-mode descriptor ``(B, K)``: every layer on every point, then max (its backward is sparse)."""
        return self.point_features(points).max(dim=1).values

    def _forward_train(self, points: torch.Tensor) -> torch.Tensor:
        """Training-mode descriptor ``(B, K)`` with the wide last layer differentiated at the arg-max points only.

        Needs a plain last layer (no BatchNorm). Max and ReLU commute and the bias is per channel, so
        ``max_i relu(w_k . h_i + b_k) = relu(w_k . h_a + b_k)`` with ``a`` the arg-max of ``w_k . h_i``; the max
        routes the gradient to ``a`` alone, so the last layer only needs a graph at the ``K`` arg-max points. The
        arg-max is found without autograd, chunk by chunk; values and gradients are those of
        :meth:`_forward_train_reference` (up to float rounding).
        """
        h = points
        last = len(self.linears) - 1
        for i in range(last):
            h = self._block(i, h)
        lin = self._linear(last)
        arg = self._pooled_argmax(h, lin.weight)
        return torch.relu(_dot_at(h, arg, lin.weight, lin.bias))

    def _pooled_argmax(self, h: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
        """Arg-max over the points of ``h @ weight.T``, ``(B, K)``, for ``h (B, N, C)``; no autograd.

        The same arg-max as with a per-channel bias. The full ``(B, N, K)`` product is never held: ``chunk_size``
        points at a time, as ``(B, K, chunk)`` so that the max runs over contiguous memory; ties go to the first point.
        """
        size = self.chunk_size
        weights = weight.detach().expand(h.shape[0], -1, -1)  # (B, K, C), a view
        with torch.no_grad():
            best_val, best_idx = torch.bmm(weights, h[:, :size].transpose(1, 2)).max(dim=-1)  # (B, K)
            for start in range(size, h.shape[1], size):
                val, idx = torch.bmm(weights, h[:, start : start + size].transpose(1, 2)).max(dim=-1)
                better = val > best_val
                best_val = torch.where(better, val, best_val)
                best_idx = torch.where(better, idx + start, best_idx)
        return best_idx

    def _affine(self, i: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Eval-mode norm of layer ``i`` as ``scale * z + shift`` (identity without BatchNorm)."""
        norm = self.norms[i]
        weight = self._linear(i).weight
        if isinstance(norm, nn.BatchNorm1d):
            if norm.running_var is None or norm.running_mean is None:
                raise RuntimeError("PointNetEncoder needs BatchNorm running statistics (track_running_stats=True)")
            scale = torch.rsqrt(norm.running_var + norm.eps)
            if norm.weight is not None:
                scale = scale * norm.weight
            shift = -norm.running_mean * scale + (norm.bias if norm.bias is not None else 0.0)
            return scale, shift
        return weight.new_ones(weight.shape[0]), weight.new_zeros(weight.shape[0])

    def twist_jacobian(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Descriptor and its exact Jacobian w.r.t. a twist applied to the cloud, at identity.

        The hidden layers carry the 3 coordinate derivatives of every point forward; the wide last layer is
        evaluated without a graph, chunk by chunk, only to find each channel's arg-max point, and then differentiated
        (and its value recomputed, differentiably) at those ``K`` points.

        Args:
            points: Clouds ``(B, N, 3)``.

        Returns:
            ``(psi (B, K), jacobian (B, K, 6))`` with columns ordered ``[omega, v]``; eval-mode normalisation.
        """
        points = to_module_dtype(self, check_points(points, "points"))
        if reference_active():
            return self._twist_jacobian_reference(points)
        b = points.shape[0]
        h, dh = self._hidden_forward_mode(points)
        weight, bias = self._folded(len(self.linears) - 1)
        arg = self._pooled_argmax(h, weight)  # (B, K)
        psi = torch.relu(_dot_at(h, arg, weight, bias))  # (B, K)
        k = psi.shape[1]
        dh_arg = torch.gather(dh, 1, arg[:, :, None, None].expand(b, k, 3, dh.shape[-1]))  # (B, K, 3, C)
        grad = (dh_arg * weight[:, None, :]).sum(-1) * (psi > 0).to(psi.dtype)[..., None]  # (B, K, 3)
        p_arg = torch.gather(points, 1, arg[..., None].expand(b, k, 3))  # (B, K, 3)
        return psi, torch.cat([torch.cross(p_arg, grad, dim=-1), grad], dim=-1)

    def _hidden_forward_mode(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Hidden layers (eval-mode norms) on ``points (B, N, 3)`` with their derivatives along the 3 coordinates.

        Returns:
            ``(h (B, N, C), dh (B, N, 3, C))``: the input of the last layer and ``dh[b, i, d] = d h[b, i] / d p_id``.
        """
        h, dh = points, None
        for i in range(len(self.linears) - 1):
            weight, bias = self._folded(i)
            z = nn.functional.linear(h, weight, bias)
            mask = (z > 0).to(z.dtype)
            jac_in = weight.T.contiguous() if dh is None else dh @ weight.T  # (3, C) or (B, N, 3, C)
            dh = jac_in * mask[:, :, None, :]  # (B, N, 3, C), contiguous
            h = z * mask
        if dh is None:  # a single-layer encoder: the points' own derivatives
            b, n, _ = points.shape
            dh = torch.eye(3, dtype=points.dtype, device=points.device).expand(b, n, 3, 3)
        return h, dh

    def _twist_jacobian_reference(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`twist_jacobian` with the full ``(B, N, K)`` last layer and its max (validated input)."""
        b, n, _ = points.shape
        h = points
        dh = torch.eye(3, dtype=points.dtype, device=points.device).expand(b, n, 3, 3)  # (B, N, dir, C)
        last = len(self.linears) - 1
        for i in range(last):
            weight, bias = self._folded(i)
            z = nn.functional.linear(h, weight, bias)
            mask = (z > 0).to(z.dtype)
            dh = (dh @ weight.T) * mask[:, :, None, :]  # (B, N, 3, C)
            h = z * mask
        weight, bias = self._folded(last)
        feats = torch.relu(nn.functional.linear(h, weight, bias))  # (B, N, K)
        psi, arg = feats.max(dim=1)  # (B, K)
        k = psi.shape[1]
        dh_arg = torch.gather(dh, 1, arg[:, :, None, None].expand(b, k, 3, dh.shape[-1]))  # (B, K, 3, C)
        grad = torch.einsum("bkdc,kc->bkd", dh_arg, weight)  # (B, K, 3)
        grad = grad * (psi > 0).to(psi.dtype)[..., None]
        p_arg = torch.gather(points, 1, arg[..., None].expand(b, k, 3))  # (B, K, 3)
        return psi, torch.cat([torch.cross(p_arg, grad, dim=-1), grad], dim=-1)


def _dot_at(h: torch.Tensor, idx: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None) -> torch.Tensor:
    """``z[b, k] = weight[k] . h[b, idx[b, k]] + bias[k]``, ``(B, K)``, for ``h (B, N, C)`` and ``idx (B, K)``.

    One output channel of a linear layer, evaluated at one point per channel; differentiable in ``h`` (the gather's
    backward scatters into the chosen points), ``weight`` and ``bias``.
    """
    h_at = torch.gather(h, 1, idx[..., None].expand(-1, -1, h.shape[-1]))  # (B, K, C)
    z = (h_at * weight).sum(-1)
    return z if bias is None else z + bias
