"""Inverse-compositional Lucas-Kanade (IC-LK) registration on global descriptors (PointNetLK lineage).

Given an encoder ``psi`` and clouds ``X`` (source) and ``Y`` (reference), find ``G`` with ``psi(G X) = psi(Y)``:

1. Centre both clouds (``X0 = X - mean X``, ``Y0 = Y - mean Y``) so rotations act about the centroids.
2. ``J = d psi(exp(xi) Y0) / d xi`` at ``xi = 0`` (``(B, K, 6)``, twist ``[omega, v]``), computed once.
3. Repeat up to ``max_iterations``: ``r = psi(G X0) - psi(Y0)``,
   ``dxi = -(J^T J + lambda I)^{-1} J^T r`` and ``G <- exp(dxi) G`` (inverse composition: ``G X0 ~ exp(eta) Y0``
   with ``eta = J^+ r``, hence the minus sign); an item stops once ``||dxi|| < tolerance``.
4. Undo the centring: ``T = Trans(mean Y) G Trans(-mean X)``.

Several starts (``starts``, e.g. :func:`axis_rotation_starts`): the loop runs from each initial ``G`` at once (the
starts stacked along the batch) and each item keeps the start whose final residual ``||psi(G X0) - psi(Y0)||`` is
lowest (:func:`select_start`; with ``start_margin`` the identity's answer stays unless another start's residual is
lower by that fraction). A descriptor's IC-LK converges to the nearest minimum of the residual; a failed pair often
has a lower minimum farther away, which a rotated start reaches.

The damping ``lambda = damping * mean(diag(J^T J)) + tiny`` keeps a singular ``J^T J`` (e.g. dead ReLUs)
from producing NaN: a zero Jacobian gives ``dxi = 0``. The 6x6 systems are solved in float64.

Under autocast (mixed-precision training) the solve, encoder passes included, runs in float32
(:func:`lcreg.geometry.precision.full_precision`): it drives a difference of two descriptors to zero, which bfloat16's
8-bit mantissa would round away; the training passes of the encoder outside the solve keep autocast.

Jacobians: ``"analytic"`` (exact, via the encoder's ``twist_jacobian``; PointNet provides it),
``"autodiff"`` (forward-mode AD through any encoder, exact, 6 JVPs) and ``"finite_difference"``
(``(psi(exp(delta e_k) Y0) - psi(Y0)) / delta`` as PointNetLK, ``delta = 1e-2``).
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Iterator, Sequence
from typing import Literal

import torch
from torch import nn

from lcreg.checks import check_points, check_same_batch, check_transform
from lcreg.geometry import se3
from lcreg.geometry.precision import full_precision
from lcreg.nn.dtypes import to_module_dtype
from lcreg.types import RegistrationResult

__all__ = [
    "TWIST_NAMES",
    "InverseCompositionalLK",
    "JacobianMode",
    "axis_rotation_starts",
    "jacobian_diagnostics",
    "select_start",
    "twist_jacobian",
]

JacobianMode = Literal["analytic", "autodiff", "finite_difference"]
Encoder = Callable[[torch.Tensor], torch.Tensor]
TWIST_NAMES = ("rx", "ry", "rz", "tx", "ty", "tz")  # order of the twist ``[omega, v]``


def _generators(points: torch.Tensor) -> torch.Tensor:
    """Point velocities ``d(exp(xi) p)/d xi_k`` for the 6 twist directions, ``(6, B, N, 3)``: ``e_k x p``, ``e_k``."""
    eye = torch.eye(3, dtype=points.dtype, device=points.device)
    rot = [torch.cross(eye[k].expand_as(points), points, dim=-1) for k in range(3)]
    trans = [eye[k].expand_as(points) for k in range(3)]
    return torch.stack(rot + trans)


@full_precision
def twist_jacobian(
    encoder: Encoder | nn.Module, points: torch.Tensor, mode: JacobianMode = "analytic", fd_step: float = 1e-2
) -> tuple[torch.Tensor, torch.Tensor]:
    """Descriptor ``psi(P) (B, K)`` and ``d psi(exp(xi) P) / d xi`` at 0, ``(B, K, 6)``.

    Args:
        encoder: Maps ``(B, N, 3)`` to ``(B, K)``; for ``"analytic"`` it must define ``twist_jacobian``.
        points: Clouds ``(B, N, 3)``.
        mode: ``"analytic"``, ``"autodiff"`` or ``"finite_difference"``.
        fd_step: Twist step ``delta`` of the finite differences (radians / distance units).

    Raises:
        ValueError: Unknown mode, or ``"analytic"`` for an encoder without ``twist_jacobian``.
    """
    if mode == "analytic":
        method = getattr(encoder, "twist_jacobian", None)
        if method is None:
            raise ValueError(f"{type(encoder).__name__} has no `twist_jacobian`; use 'autodiff' or 'finite_difference'")
        return method(points)
    if mode == "autodiff":
        psi = encoder(points)
        cols = [torch.func.jvp(encoder, (points,), (g,))[1] for g in _generators(points)]
        return psi, torch.stack(cols, dim=-1)
    if mode == "finite_difference":
        b = points.shape[0]
        steps = fd_step * torch.eye(6, dtype=points.dtype, device=points.device)  # (6, 6)
        moved = se3.transform_points(se3.exp(steps).repeat_interleave(b, 0), points.repeat(6, 1, 1))
        feats = encoder(torch.cat([points, moved]))  # ((1 + 6) B, K)
        psi, pert = feats[:b], feats[b:].reshape(6, b, -1)
        return psi, ((pert - psi) / fd_step).permute(1, 2, 0)
    raise ValueError(f"unknown Jacobian mode {mode!r}; expected 'analytic', 'autodiff' or 'finite_difference'")


@full_precision
def jacobian_diagnostics(jacobian: torch.Tensor, feature: torch.Tensor) -> dict[str, torch.Tensor]:
    """How well the descriptor still sees motion: conditioning of the IC-LK Jacobian, batch medians.

    A self-supervised objective can lower its residual by making ``psi`` insensitive to motion; these numbers show
    it (issue 12): ``cond`` = smallest / largest singular value of ``J`` (1: every twist direction seen equally,
    0: one direction invisible), ``sensitivity`` = smallest singular value over ``||psi||`` (how far the
    descriptor moves, relative to its size, under the least-seen unit twist), ``dir_<k>`` = ``||J e_k|| / ||psi||``
    per twist direction (``rx ry rz``: per radian, ``tx ty tz``: per distance unit).

    Args:
        jacobian: ``d psi / d xi`` at the reference, ``(B, K, 6)``.
        feature: The reference descriptors ``psi (B, K)``.

    Returns:
        Scalars (float64, no graph): ``"cond"``, ``"sensitivity"`` and ``"dir_rx"`` ... ``"dir_tz"``.
    """
    jac = jacobian.detach().double()
    norm = feature.detach().double().norm(dim=-1).clamp_min(torch.finfo(torch.float64).tiny)  # (B,)
    sv = torch.linalg.svdvals(jac)  # (B, 6), descending
    out = {
        "cond": (sv[:, -1] / sv[:, 0].clamp_min(torch.finfo(torch.float64).tiny)).median(),
        "sensitivity": (sv[:, -1] / norm).median(),
    }
    columns = jac.norm(dim=1) / norm[:, None]  # (B, 6)
    out.update({f"dir_{name}": columns[:, k].median() for k, name in enumerate(TWIST_NAMES)})
    return out


def axis_rotation_starts(
    angles_deg: Sequence[float], dtype: torch.dtype | None = None, device: torch.device | None = None
) -> torch.Tensor:
    """The identity and rotations by ``+-a`` about the x, y and z axes for each ``a`` of ``angles_deg``.

    Args:
        angles_deg: Rotation angles in degrees (``[]``: the identity alone).
        dtype: Dtype of the result.
        device: Device of the result.

    Returns:
        ``(1 + 6 len(angles_deg), 4, 4)`` transforms, the identity first, then for each angle
        ``+x, -x, +y, -y, +z, -z``.
    """
    twists = torch.zeros(1 + 6 * len(angles_deg), 6, dtype=torch.float64)
    for i, angle in enumerate(angles_deg):
        for axis in range(3):
            for k, sign in enumerate((1.0, -1.0)):
                twists[1 + 6 * i + 2 * axis + k, axis] = sign * math.radians(angle)
    return se3.exp(twists).to(dtype=dtype or torch.get_default_dtype(), device=device)


def select_start(final_residual: torch.Tensor, margin: float = 0.0) -> torch.Tensor:
    """The start each item keeps, from the final residuals ``||psi(G X0) - psi(Y0)||`` of every start ``(S, B)``.

    Start 0 is the identity. An item keeps the start with the lowest residual if that residual is below
    ``(1 - margin)`` times the identity's, else the identity: ``margin = 0`` keeps the lowest residual; a positive
    margin moves only pairs that another start fits clearly better (a wrong pose of almost equal residual, e.g. on a
    symmetric object, does not replace the identity's answer).

    Args:
        final_residual: ``(S, B)`` residual norms, the identity's first.
        margin: Fraction in ``[0, 1)``.

    Returns:
        ``(B,)`` int64 start indices.
    """
    best = final_residual.argmin(0)
    if margin <= 0:
        return best
    lowest = final_residual.gather(0, best[None])[0]
    return torch.where(lowest < (1 - margin) * final_residual[0], best, torch.zeros_like(best))


def check_start_margin(margin: float, name: str = "start_margin") -> float:
    """``margin`` as a float after checking it is in ``[0, 1)``.

    Raises:
        ValueError: Not a finite fraction in ``[0, 1)``.
    """
    if not (math.isfinite(margin) and 0.0 <= margin < 1.0):
        raise ValueError(f"`{name}` must be in [0, 1), got {margin}")
    return float(margin)


@contextlib.contextmanager
def _eval_mode(encoder: Encoder | nn.Module) -> Iterator[None]:
    """The encoder in eval mode inside the block (the solve sees the function tested), its mode restored after."""
    was_training = isinstance(encoder, nn.Module) and encoder.training
    if isinstance(encoder, nn.Module):
        encoder.eval()
    try:
        yield
    finally:
        if was_training and isinstance(encoder, nn.Module):
            encoder.train()


class InverseCompositionalLK(nn.Module):
    """IC-LK solver; holds hyper-parameters only, the encoder is passed at call time.

    Args:
        max_iterations: Maximum number of updates ``T`` (paper: 10).
        tolerance: Stop an item once ``||dxi||_2 <`` this (paper: 1e-7).
        damping: Relative Levenberg damping of ``J^T J``.
        jacobian: ``"analytic"``, ``"autodiff"`` or ``"finite_difference"``.
        fd_step: Step of the finite-difference Jacobian.
        center: Centre the clouds before solving (recommended; rotations then act about the centroids).
        differentiable: Keep the autograd graph through the solve (off for DVDs, where ``psi`` is frozen while
            the transform is estimated).
    """

    def __init__(
        self,
        max_iterations: int = 10,
        tolerance: float = 1e-7,
        damping: float = 1e-6,
        jacobian: JacobianMode = "analytic",
        fd_step: float = 1e-2,
        center: bool = True,
        differentiable: bool = False,
    ) -> None:
        super().__init__()
        if max_iterations < 1:
            raise ValueError(f"`max_iterations` must be >= 1, got {max_iterations}")
        if tolerance < 0 or damping < 0 or fd_step <= 0:
            raise ValueError("`tolerance` and `damping` must be >= 0 and `fd_step` > 0")
        if jacobian not in ("analytic", "autodiff", "finite_difference"):
            raise ValueError(f"unknown `jacobian` {jacobian!r}")
        self.max_iterations = max_iterations
        self.tolerance = tolerance
        self.damping = damping
        self.jacobian = jacobian
        self.fd_step = fd_step
        self.center = center
        self.differentiable = differentiable

    def damped(self, jtj: torch.Tensor) -> torch.Tensor:
        """``J^T J + lambda I`` for ``J^T J (B, 6, 6)`` (float64), ``lambda = damping * mean(diag) + tiny``."""
        diag_mean = jtj.diagonal(dim1=1, dim2=2).mean(-1)
        lam = self.damping * diag_mean + torch.finfo(torch.float64).tiny ** 0.5
        return jtj + lam[:, None, None] * torch.eye(6, dtype=jtj.dtype, device=jtj.device)

    def pseudo_inverse(self, jac: torch.Tensor) -> torch.Tensor:
        """Damped ``(J^T J + lambda I)^{-1} J^T``, ``(B, 6, K)``, solved in float64."""
        j64 = jac.double()
        return torch.linalg.solve(self.damped(j64.transpose(1, 2) @ j64), j64.transpose(1, 2)).to(jac.dtype)

    @full_precision
    def forward(
        self,
        encoder: Encoder | nn.Module,
        points_src: torch.Tensor,
        points_ref: torch.Tensor,
        max_iterations: int | None = None,
        differentiable: bool | None = None,
        starts: torch.Tensor | None = None,
        start_margin: float = 0.0,
    ) -> RegistrationResult:
        """Estimate ``transform_ref_src`` for ``points_src (B, N, 3)`` and ``points_ref (B, M, 3)``.

        Args:
            encoder: The descriptor ``psi``.
            points_src: Source clouds ``(B, N, 3)``.
            points_ref: Reference clouds ``(B, M, 3)``.
            max_iterations: Overrides the solver's ``max_iterations`` for this call (PointNetLK: 10 in training,
                20 at test).
            differentiable: Overrides the solver's ``differentiable`` for this call (a loss term that trains
                through the solve of a model whose own loss holds the estimate fixed).
            starts: Initial transforms of the centred source ``(S, 4, 4)`` (``None``: the identity alone); each item
                keeps the start with the lowest final residual (see the module docstring).
            start_margin: With ``starts``: another start replaces the identity only if its final residual is below
                ``(1 - start_margin)`` times the identity's (:func:`select_start`; 0: the lowest residual).

        Returns:
            :class:`RegistrationResult` with ``residual_history (B, iterations)`` (``||r||`` before each update),
            ``aux["feature_ref"] (B, K)``, ``aux["jacobian"] (B, K, 6)`` at the centred reference and
            ``aux["residual"] (B, K)``, the last residual ``r`` (before the last update; differentiable when the
            solve is); with ``starts`` also ``aux["start"] (B,)``, the index of the start kept, and
            ``aux["final_residual"] (B,)``, its ``||r||`` after the last update.

        Raises:
            ValueError: ``max_iterations < 1``, ``starts`` not ``(S, 4, 4)`` with ``S >= 1`` or ``start_margin``
                outside ``[0, 1)``.
        """
        check_start_margin(start_margin)
        if max_iterations is not None and max_iterations < 1:
            raise ValueError(f"`max_iterations` must be >= 1, got {max_iterations}")
        check_points(points_src, "points_src")
        check_points(points_ref, "points_ref")
        check_same_batch(points_src=points_src, points_ref=points_ref)
        if starts is not None and (starts.ndim != 3 or starts.shape[0] < 1 or starts.shape[1:] != (4, 4)):
            raise ValueError(f"`starts` must have shape (S>=1, 4, 4), got {tuple(starts.shape)}")
        dtype = points_src.dtype
        if isinstance(encoder, nn.Module):  # float64 clouds, float32 encoder (or the reverse): compute in its dtype
            points_src, points_ref = to_module_dtype(encoder, (points_src, points_ref))
        grad = self.differentiable if differentiable is None else differentiable
        with _eval_mode(encoder), torch.set_grad_enabled(grad and torch.is_grad_enabled()):
            iterations = max_iterations or self.max_iterations
            result = self._solve(encoder, points_src, points_ref, iterations, starts, start_margin)
        result.transform_ref_src = result.transform_ref_src.to(dtype)  # the caller's dtype
        return result

    @full_precision
    def step_from(
        self,
        encoder: Encoder | nn.Module,
        points_src: torch.Tensor,
        points_ref: torch.Tensor,
        transform_ref_src: torch.Tensor,
    ) -> torch.Tensor:
        """The transform one update of the solve moves ``transform_ref_src`` to, with the autograd graph kept.

        At a fixed point of the solve the update is zero: started at the true pose, the distance of the result from
        it is the bias of the descriptor's residual minimum (two samplings of one surface have different
        descriptors at the true pose), which a training term can penalise without unrolling the solve.

        Args:
            encoder: The descriptor ``psi``.
            points_src: Source clouds ``(B, N, 3)``.
            points_ref: Reference clouds ``(B, M, 3)``.
            transform_ref_src: The poses to step from ``(B, 4, 4)`` (uncentred, as the solve returns them).

        Returns:
            ``(B, 4, 4)`` ``Trans(mean Y) exp(dxi) G0 Trans(-mean X)``, ``G0`` the start in the centred frame and
            ``dxi`` the update at it, in the dtype of ``points_src``.
        """
        check_points(points_src, "points_src")
        check_points(points_ref, "points_ref")
        check_transform(transform_ref_src, "transform_ref_src")
        check_same_batch(points_src=points_src, points_ref=points_ref, transform_ref_src=transform_ref_src)
        dtype = points_src.dtype
        if isinstance(encoder, nn.Module):
            points_src, points_ref = to_module_dtype(encoder, (points_src, points_ref))
        with _eval_mode(encoder):
            src0, ref0, mean_src, mean_ref = self._centred(points_src, points_ref)
            start = se3.uncenter(transform_ref_src.to(src0.dtype), -mean_src, -mean_ref)  # into the centred frame
            feat_ref, jac = twist_jacobian(encoder, ref0, self.jacobian, self.fd_step)
            resid = encoder(se3.transform_points(start, src0)) - feat_ref  # (B, K)
            dxi = -(self.pseudo_inverse(jac) @ resid[..., None]).squeeze(-1)  # (B, 6)
            return se3.uncenter(se3.exp(dxi) @ start, mean_src, mean_ref).to(dtype)

    def _centred(
        self, points_src: torch.Tensor, points_ref: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(X0, Y0, mean X, mean Y)``: both clouds centred (means ``(B, 3)``; zeros when ``center`` is off)."""
        b = points_src.shape[0]
        mean_src = points_src.mean(1) if self.center else points_src.new_zeros(b, 3)
        mean_ref = points_ref.mean(1) if self.center else points_ref.new_zeros(b, 3)
        return points_src - mean_src[:, None], points_ref - mean_ref[:, None], mean_src, mean_ref

    def _solve(
        self,
        encoder: Encoder | nn.Module,
        points_src: torch.Tensor,
        points_ref: torch.Tensor,
        max_iterations: int,
        starts: torch.Tensor | None = None,
        start_margin: float = 0.0,
    ) -> RegistrationResult:
        b = points_src.shape[0]
        src0, ref0, mean_src, mean_ref = self._centred(points_src, points_ref)
        feat_ref, jac = twist_jacobian(encoder, ref0, self.jacobian, self.fd_step)
        pinv = self.pseudo_inverse(jac)
        n = 1 if starts is None else starts.shape[0]  # the starts are stacked along the batch, start-major
        if starts is None:
            g = se3.identity(b, device=points_src.device, dtype=points_src.dtype)
        else:
            g = starts.to(points_src)[:, None].expand(n, b, 4, 4).reshape(n * b, 4, 4)
        src_n, feat_n, pinv_n = src0.repeat(n, 1, 1), feat_ref.repeat(n, 1), pinv.repeat(n, 1, 1)
        active = torch.ones(n * b, dtype=torch.bool, device=points_src.device)
        iters = torch.zeros(n * b, dtype=torch.long, device=points_src.device)
        history = []
        for _ in range(max_iterations):
            resid = encoder(se3.transform_points(g, src_n)) - feat_n  # (S B, K)
            history.append(resid.norm(dim=-1))
            dxi = -(pinv_n @ resid[..., None]).squeeze(-1) * active[:, None]  # (S B, 6)
            g = se3.exp(dxi) @ g
            iters = iters + active.long()
            active = active & (dxi.norm(dim=-1) >= self.tolerance)
            if not bool(active.any()):
                break
        aux = {"feature_ref": feat_ref, "jacobian": jac}
        if starts is not None:
            final = (encoder(se3.transform_points(g, src_n)) - feat_n).norm(dim=-1).reshape(n, b)
            best = select_start(final, start_margin)  # (B,)
            pick = best * b + torch.arange(b, device=best.device)  # rows of the kept starts
            g, active, iters, resid = g[pick], active[pick], iters[pick], resid[pick]
            history = [h[pick] for h in history]
            aux.update(start=best, final_residual=final.gather(0, best[None])[0])
        return RegistrationResult(
            transform_ref_src=se3.uncenter(g, mean_src, mean_ref),
            converged=~active,
            num_iters=iters,
            residual_history=torch.stack(history, dim=1),
            aux={**aux, "residual": resid},
        )
