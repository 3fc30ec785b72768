"""Voxelised IC-LK for large clouds (the DVDs paper's 7-Scenes footnote, after PointNetLK Revisited).

One global PointNet descriptor cannot describe a room or a street, so the cloud is cut into ``K = grid^3`` voxels
(``grid = 3``: 27), each voxel gets its own descriptor, and the voxels' Jacobians and residuals are stacked into one
least-squares system for a single rigid transform. Test time only; the encoder is the trained one, unchanged.

Steps for one pair (both clouds centred on their centroids as in :mod:`lcreg.nn.lk`; ``G`` starts at identity, or
at the estimate of ``coarse_iterations`` whole-cloud iterations):

1. The grid spans the centred reference's bounding box; the border voxels extend to infinity, so no point is ever
   dropped (and ``grid = 1`` is exactly the plain solver). Voxel ``v`` enters the system when it holds at least
   ``min_points`` reference points; its local origin ``o_v`` is their centroid and its scale ``s_v`` is 1, or their
   largest distance from ``o_v`` with ``normalize``. The encoder sees ``y = (x - o_v) / s_v``: points keep their
   original relative positions (no resampling onto a grid).
2. Every voxel is fed ``points_per_voxel`` points: a seeded random subset of a fuller voxel, or all its points plus
   repeats of random ones (a repeated point changes neither a max-pooled descriptor nor its Jacobian).
3. ``J_v = d psi(exp(xi_v) Y_v) / d xi_v`` at 0 in voxel coordinates (the model's Jacobian mode). A global twist
   ``xi = [omega, v]`` (about the reference centroid, metres) moves voxel coordinates by ``xi_v = W_v xi`` with
   ``W_v = [[I, 0], [-[o_v]x / s_v, I / s_v]]``, so the stacked system is ``J = [J_1 W_1; ...; J_V W_V]``.
4. Each iteration warps the source by ``G`` and (every ``reassign_every`` iterations) assigns the warped points to
   the *reference's* voxels, so the voxel correspondence never uses the ground truth (PointNetLK Revisited
   voxelises both clouds in the ground-truth-aligned frame instead). It computes ``r_v = psi((G x - o_v) / s_v) -
   psi(Y_v)`` for the voxels holding at least ``min_points`` source points and solves ``dxi = -(J^T J + lambda
   I)^{-1} J^T r`` over those voxels' rows (the damping of :class:`~lcreg.nn.lk.InverseCompositionalLK`);
   ``G <- exp(dxi) G``.

Limits: membership changes as points cross voxel borders, so the objective is piecewise smooth and, unlike the
plain solver, the iteration does not reach the exact optimum even on noise-free copies (tests/nn/test_voxel_lk.py:
0.3 and 2.7 degrees left from 5, where the plain solver reaches 1e-14). The settings of configs/voxelize/lk27.yaml
were chosen on 3DMatch SUN3D validation scenes (docs/results/scenes_tuning.md).
"""

from __future__ import annotations

import torch
from torch import nn

from lcreg.checks import TooFewPointsError, check_points, check_same_batch
from lcreg.geometry import se3, so3
from lcreg.geometry.precision import full_precision
from lcreg.nn.lk import Encoder, InverseCompositionalLK, twist_jacobian
from lcreg.types import RegistrationResult

__all__ = ["VoxelGrid", "voxel_lk"]


class VoxelGrid:
    """Settings of voxelised IC-LK (``voxel_grid`` of an LK model; ``configs/voxelize/lk27.yaml``).

    Args:
        grid: Voxels per axis (``K = grid^3``; paper: 27 voxels, ``grid = 3``).
        points_per_voxel: Points fed to the encoder per voxel (subsampled or padded by repetition).
        min_points: A voxel enters the system only when it holds at least this many points (reference at setup,
            warped source at every iteration).
        normalize: Scale each voxel into the unit sphere (the training scale of ModelNet40 models). Off by default:
            on the validation scenes it was worse (mean RRE 61 vs 38 degrees, docs/results/scenes_tuning.md).
        coarse_iterations: IC-LK iterations on the whole cloud (one voxel, same ``normalize``) before the voxel
            system, which then starts from that estimate (0: none).
        reassign_every: Re-assign the warped source points to the voxels every this many iterations (1: every
            iteration, the default; 0: once, at the start estimate, so the voxel contents move rigidly with ``G``).
        seed: Seed of the per-voxel subsampling (results are deterministic for a given seed).

    Raises:
        ValueError: If an argument is out of range.
    """

    def __init__(
        self,
        grid: int = 3,
        points_per_voxel: int = 512,
        min_points: int = 32,
        normalize: bool = False,
        coarse_iterations: int = 0,
        reassign_every: int = 1,
        seed: int = 0,
    ) -> None:
        if grid < 1 or coarse_iterations < 0 or reassign_every < 0:
            raise ValueError(
                f"need grid >= 1, coarse_iterations >= 0 and reassign_every >= 0, got {grid=}, "
                f"{coarse_iterations=}, {reassign_every=}"
            )
        if points_per_voxel < 1 or not 1 <= min_points <= points_per_voxel:
            raise ValueError(
                f"need points_per_voxel >= 1 and 1 <= min_points <= points_per_voxel, got {points_per_voxel=} "
                f"and {min_points=}"
            )
        self.grid = grid
        self.points_per_voxel = points_per_voxel
        self.min_points = min_points
        self.normalize = normalize
        self.coarse_iterations = coarse_iterations
        self.reassign_every = reassign_every
        self.seed = seed

    def __repr__(self) -> str:
        return (
            f"VoxelGrid(grid={self.grid}, points_per_voxel={self.points_per_voxel}, min_points={self.min_points}, "
            f"normalize={self.normalize}, coarse_iterations={self.coarse_iterations}, "
            f"reassign_every={self.reassign_every}, seed={self.seed})"
        )

    def assign(self, points: torch.Tensor, lower: torch.Tensor, size: torch.Tensor) -> torch.Tensor:
        """Voxel index ``(N,)`` in ``[0, grid^3)`` of points ``(N, 3)``; the border voxels extend to infinity."""
        cell = torch.floor((points - lower) / size).long().clamp(0, self.grid - 1)
        return (cell[:, 0] * self.grid + cell[:, 1]) * self.grid + cell[:, 2]

    def sample(self, indices: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        """``points_per_voxel`` indices drawn from ``indices (n,)``: a random subset, or all plus random repeats."""
        n, m = indices.numel(), self.points_per_voxel
        if n >= m:
            return indices[torch.randperm(n, generator=generator)[:m].to(indices.device)]
        extra = torch.randint(n, (m - n,), generator=generator).to(indices.device)
        return torch.cat([indices, indices[extra]])

    def gather(
        self, voxel_of: torch.Tensor, voxels: torch.Tensor, generator: torch.Generator
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Point indices of each voxel in ``voxels (V,)``: ``(V, points_per_voxel)`` and a mask ``(V,)`` of full ones.

        Args:
            voxel_of: Voxel of every point ``(N,)`` (from :meth:`assign`).
            voxels: The voxel ids to gather.
            generator: CPU generator of the subsampling.

        Voxels below ``min_points`` get index 0 everywhere (masked out by the caller).
        """
        out = torch.zeros(len(voxels), self.points_per_voxel, dtype=torch.long, device=voxel_of.device)
        valid = torch.zeros(len(voxels), dtype=torch.bool, device=voxel_of.device)
        order = torch.argsort(voxel_of)
        counts = torch.bincount(voxel_of, minlength=self.grid**3)
        start = torch.cumsum(counts, 0) - counts
        for row, v in enumerate(voxels.tolist()):
            count = int(counts[v])
            if count < self.min_points:
                continue
            out[row] = self.sample(order[int(start[v]) : int(start[v]) + count], generator)
            valid[row] = True
        return out, valid


def _twist_to_voxel(origins: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """``W_v (V, 6, 6)``: a global twist ``[omega, v]`` seen in voxel coordinates ``(x - o_v) / s_v``."""
    n = origins.shape[0]
    eye = torch.eye(3, dtype=origins.dtype, device=origins.device).expand(n, 3, 3)
    top = torch.cat([eye, torch.zeros_like(eye)], dim=-1)
    bottom = torch.cat([-so3.hat(origins), eye], dim=-1) / scales[:, None, None]
    return torch.cat([top, bottom], dim=-2)


def _reference_voxels(
    grid: VoxelGrid, ref: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Grid of a centred reference ``(M, 3)``: lower corner, voxel size, kept voxel ids, origins and scales."""
    lower, upper = ref.min(0).values, ref.max(0).values
    size = ((upper - lower) / grid.grid).clamp_min(1e-6) * (1 + 1e-6)
    voxel_of = grid.assign(ref, lower, size)
    counts = torch.bincount(voxel_of, minlength=grid.grid**3)
    kept = torch.nonzero(counts >= grid.min_points).squeeze(-1)
    if kept.numel() == 0:
        raise TooFewPointsError(
            f"`points_ref` ({ref.shape[0]} points) has no voxel with at least min_points={grid.min_points} points "
            f"on a {grid.grid}^3 grid; lower `min_points` or `grid`"
        )
    origins = torch.stack([ref[voxel_of == v].mean(0) for v in kept.tolist()])
    if grid.normalize:
        radii = [(ref[voxel_of == v] - o).norm(dim=-1).max() for v, o in zip(kept.tolist(), origins, strict=True)]
        scales = torch.stack(radii).clamp_min(1e-6)
    else:
        scales = torch.ones(len(kept), dtype=ref.dtype, device=ref.device)
    return lower, size, kept, origins, scales


def _solve_one(
    solver: InverseCompositionalLK,
    encoder: Encoder | nn.Module,
    grid: VoxelGrid,
    src: torch.Tensor,
    ref: torch.Tensor,
    max_iterations: int,
    init: torch.Tensor,
) -> tuple[torch.Tensor, bool, int, torch.Tensor, int]:
    """Register one centred pair ``src (N, 3)``, ``ref (M, 3)`` from ``init (1, 4, 4)``.

    Returns:
        ``(G (1, 4, 4), converged, iterations, residual norms (T,), voxels in the system)``.
    """
    generator = torch.Generator().manual_seed(grid.seed)
    lower, size, kept, origins, scales = _reference_voxels(grid, ref)
    ref_idx, _ = grid.gather(grid.assign(ref, lower, size), kept, generator)
    local_ref = (ref[ref_idx] - origins[:, None]) / scales[:, None, None]
    feat_ref, jac = twist_jacobian(encoder, local_ref, solver.jacobian, solver.fd_step)  # (V, K), (V, K, 6)
    jac = jac @ _twist_to_voxel(origins, scales).to(jac.dtype)  # (V, K, 6) in the global twist
    g = init
    history: list[torch.Tensor] = []
    converged, iters = False, 0
    for it in range(max_iterations):
        if it == 0 or (grid.reassign_every > 0 and it % grid.reassign_every == 0):
            warped = se3.transform_points(g, src[None])[0]
            src_idx, valid = grid.gather(grid.assign(warped, lower, size), kept, generator)
        if not bool(valid.any()):
            break  # no voxel holds enough source points: keep the last estimate, not converged
        moved = se3.transform_points(g, src[src_idx].reshape(1, -1, 3)).reshape((*src_idx.shape, 3))
        feat = encoder((moved - origins[:, None]) / scales[:, None, None])
        resid = (feat - feat_ref) * valid[:, None]  # (V, K)
        history.append(resid.norm())
        rows = (jac * valid[:, None, None]).reshape(-1, 6).double()  # stacked (V K, 6) system
        step = torch.linalg.solve(solver.damped((rows.T @ rows)[None]), (rows.T @ resid.reshape(-1, 1).double())[None])
        dxi = -step[..., 0].to(src.dtype)  # (1, 6)
        g = se3.exp(dxi) @ g
        iters += 1
        if float(dxi.norm()) < solver.tolerance:
            converged = True
            break
    empty = src.new_full((1,), float("nan"))
    return g, converged, iters, torch.stack(history) if history else empty, len(kept)


def _register_one(
    solver: InverseCompositionalLK,
    encoder: Encoder | nn.Module,
    grid: VoxelGrid,
    src: torch.Tensor,
    ref: torch.Tensor,
    max_iterations: int,
) -> tuple[torch.Tensor, bool, int, torch.Tensor, int]:
    """The optional whole-cloud stage, then the voxel system (see :func:`_solve_one` for the outputs)."""
    g = se3.identity(1, device=src.device, dtype=src.dtype)
    coarse_iters, coarse_history = 0, src.new_zeros(0)
    if grid.coarse_iterations > 0:
        whole = VoxelGrid(1, grid.points_per_voxel, grid.min_points, grid.normalize, seed=grid.seed, reassign_every=0)
        g, _, coarse_iters, coarse_history, _ = _solve_one(solver, encoder, whole, src, ref, grid.coarse_iterations, g)
    g, converged, iters, history, voxels = _solve_one(solver, encoder, grid, src, ref, max_iterations, g)
    return g[0], converged, coarse_iters + iters, torch.cat([coarse_history, history]), voxels


@full_precision
def voxel_lk(
    solver: InverseCompositionalLK,
    encoder: Encoder | nn.Module,
    grid: VoxelGrid,
    points_src: torch.Tensor,
    points_ref: torch.Tensor,
    max_iterations: int | None = None,
) -> RegistrationResult:
    """Voxelised IC-LK of ``points_src (B, N, 3)`` onto ``points_ref (B, M, 3)`` (no gradients; test time).

    Args:
        solver: Supplies the Jacobian mode, finite-difference step, damping, tolerance and default iterations.
        encoder: The descriptor ``psi`` (run in eval mode).
        grid: Voxel settings.
        points_src: Source clouds ``(B, N, 3)`` (metres or any unit; each voxel is normalised on its own).
        points_ref: Reference clouds ``(B, M, 3)``.
        max_iterations: Overrides ``solver.max_iterations``.

    Returns:
        :class:`RegistrationResult` with ``transform_ref_src (B, 4, 4)``, ``converged``, ``num_iters``,
        ``residual_history (B, T)`` (stacked ``||r||`` per iteration, NaN-padded after an item stops) and
        ``aux["num_voxels"] (B,)``, the reference voxels in the system.

    Raises:
        TooFewPointsError: If a reference has no voxel with ``grid.min_points`` points.
    """
    check_points(points_src, "points_src")
    check_points(points_ref, "points_ref")
    check_same_batch(points_src=points_src, points_ref=points_ref)
    iterations = max_iterations or solver.max_iterations
    was_training = isinstance(encoder, nn.Module) and encoder.training
    if isinstance(encoder, nn.Module):
        encoder.eval()
    try:
        with torch.no_grad():
            mean_src, mean_ref = points_src.mean(1), points_ref.mean(1)
            items = [
                _register_one(solver, encoder, grid, s - ms, r - mr, iterations)
                for s, r, ms, mr in zip(points_src, points_ref, mean_src, mean_ref, strict=True)
            ]
    finally:
        if was_training and isinstance(encoder, nn.Module):
            encoder.train()
    width = max(len(item[3]) for item in items)
    history = points_src.new_full((len(items), width), float("nan"))
    for row, item in enumerate(items):
        history[row, : len(item[3])] = item[3]
    device = points_src.device
    return RegistrationResult(
        transform_ref_src=se3.uncenter(torch.stack([item[0] for item in items]), mean_src, mean_ref),
        converged=torch.tensor([item[1] for item in items], device=device),
        num_iters=torch.tensor([item[2] for item in items], device=device),
        residual_history=history,
        aux={"num_voxels": torch.tensor([item[4] for item in items], device=device)},
    )
