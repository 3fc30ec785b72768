"""Shared base of the descriptor + inverse-compositional LK models: DVDs, PointNetLK and FMR-Net.

All three register with the same two pieces, built once here: a :class:`~lcreg.nn.pointnet.PointNetEncoder`
``psi`` and the :class:`~lcreg.nn.lk.InverseCompositionalLK` solver. They differ only in how ``psi`` is trained
(self-supervised DVDs losses, PointNetLK's supervised pose + residual loss, FMR-Net's reconstruction), so each
subclass adds its losses and nothing else. ``eval_iterations`` lets a model run more LK iterations at
validation/test than in training (PointNetLK: 10 and 20). A ``voxel_grid`` (constructor argument,
``configs/voxelize/lk27.yaml``) switches every evaluation (validation, test, predict, ``register``) to voxelised
IC-LK for large clouds (:mod:`lcreg.nn.voxel_lk`); training always uses the plain solver.

Every training step logs how well the descriptor still sees motion (:func:`lcreg.nn.lk.jacobian_diagnostics` of
the solve's Jacobian): ``train/j_cond``, ``train/j_sensitivity`` and ``train/j_dir_{rx,ry,rz,tx,ty,tz}``. A
collapsing self-supervised descriptor shows there first (issue 12); ``benchmarks/plot_learning_curves.py`` draws them.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

import torch
from lightning.pytorch.utilities import rank_zero_info

from lcreg.checkpoints import CheckpointError, load_submodule
from lcreg.models.base import RegistrationModule
from lcreg.nn.lk import (
    InverseCompositionalLK,
    JacobianMode,
    axis_rotation_starts,
    check_start_margin,
    jacobian_diagnostics,
)
from lcreg.nn.losses import lk_pose_loss
from lcreg.nn.pointnet import PointNetEncoder
from lcreg.nn.voxel_lk import VoxelGrid, voxel_lk
from lcreg.types import RegistrationBatch, RegistrationResult

__all__ = ["LucasKanadeModule", "lk_pose_loss"]  # lk_pose_loss: re-exported from lcreg.nn.losses


class LucasKanadeModule(RegistrationModule):
    """A PointNet descriptor registered by IC-LK; subclasses add their training losses.

    Args:
        encoder_channels: PointNet widths; the last is the descriptor size ``K``.
        batch_norm: BatchNorm in the encoder (IC-LK always runs it with its running statistics).
        max_iterations: IC-LK iterations in training (and at test unless ``eval_iterations`` is set).
        eval_iterations: IC-LK iterations at validation/test/predict (``None``: ``max_iterations``).
        tolerance: Stop an item once ``||dxi|| <`` this.
        damping: Relative damping of ``J^T J`` (keeps a singular Jacobian from producing NaN).
        jacobian: ``"analytic"``, ``"autodiff"`` or ``"finite_difference"`` (PointNetLK/FMR-Net originals).
        fd_step: Twist step of the finite-difference Jacobian (originals: 1e-2).
        differentiable: Keep the graph through the solve in training (PointNetLK's loss back-propagates through
            the Jacobian and the iterations; DVDs holds the estimate fixed).
        voxel_grid: Voxelised IC-LK outside training (:class:`~lcreg.nn.voxel_lk.VoxelGrid`; ``None``: one
            descriptor per cloud). Not a submodule and not saved: any trained checkpoint can be evaluated with it.
        eval_start_angles_deg: Outside training, IC-LK also starts from rotations by ``+-a`` degrees about the x, y
            and z axes for each ``a`` (:func:`~lcreg.nn.lk.axis_rotation_starts`; 6 starts per angle, each item
            keeps the one with the lowest final descriptor residual). ``()``: the identity alone. Not with
            ``voxel_grid``.
        eval_start_margin: With ``eval_start_angles_deg``: another start replaces the identity's answer only if its
            final residual is below ``(1 - eval_start_margin)`` times the identity's
            (:func:`~lcreg.nn.lk.select_start`; 0: the lowest residual wins).
        encoder_from: The encoder's starting weights: a registered name, an exported ``.pt`` or a Lightning
            ``.ckpt`` of any IC-LK model with the same encoder (e.g. FMR-Net's reconstruction-trained PointNet for
            PointNetLK, whose original starts from a classifier's, ``--transfer-from``). Loaded by the model's first
            :meth:`setup` (:func:`lcreg.checkpoints.load_submodule`), unless weights were loaded into it before
            (``load_state_dict``: ``--weights``); a checkpoint Lightning restores (a resumed fit, ``--ckpt_path``)
            comes after and wins. Not kept in exported weights.
        **kwargs: :class:`~lcreg.models.base.RegistrationModule` components (``optimizer``, ``lr_scheduler``,
            ``loss_terms``, ``refiner``).

    Raises:
        ValueError: If ``eval_iterations < 1``, an angle of ``eval_start_angles_deg`` is not finite or
            ``eval_start_margin`` is outside ``[0, 1)``.
        TypeError: If ``voxel_grid`` is not a ``VoxelGrid``.
    """

    def __init__(
        self,
        encoder_channels: Sequence[int] = (64, 64, 64, 128, 1024),
        batch_norm: bool = True,
        max_iterations: int = 10,
        eval_iterations: int | None = None,
        tolerance: float = 1e-7,
        damping: float = 1e-6,
        jacobian: JacobianMode = "analytic",
        fd_step: float = 1e-2,
        differentiable: bool = False,
        voxel_grid: VoxelGrid | None = None,
        eval_start_angles_deg: Sequence[float] = (),
        eval_start_margin: float = 0.0,
        encoder_from: str | None = None,
        **kwargs: Any,
    ) -> None:
        super().__init__(**kwargs)
        self.encoder_from = encoder_from
        self._encoder_pending = encoder_from is not None
        self.eval_start_margin = check_start_margin(eval_start_margin, "eval_start_margin")
        if not all(math.isfinite(a) for a in eval_start_angles_deg):
            raise ValueError(f"`eval_start_angles_deg` must be finite angles in degrees, got {eval_start_angles_deg}")
        self.voxel_grid = voxel_grid  # a plain attribute, checked (_set_voxel_grid): not a submodule, not saved
        if eval_iterations is not None and eval_iterations < 1:
            raise ValueError(f"`eval_iterations` must be >= 1 or None, got {eval_iterations}")
        self.encoder = PointNetEncoder(encoder_channels, batch_norm)
        self.solver = InverseCompositionalLK(
            max_iterations, tolerance, damping, jacobian, fd_step=fd_step, differentiable=differentiable
        )
        self.eval_iterations = eval_iterations
        self.eval_start_angles_deg = tuple(float(a) for a in eval_start_angles_deg)

    inference_hparams: ClassVar[Mapping[str, Any]] = {"encoder_from": None}

    _voxel_grid: VoxelGrid | None = None
    _plain_components: ClassVar[tuple[str, ...]] = ("refiner", "voxel_grid")

    def _set_voxel_grid(self, voxel_grid: Any) -> None:
        """Check and set the voxelisation (``model.voxel_grid = VoxelGrid()`` works after construction too).

        Raises:
            TypeError: Not a :class:`~lcreg.nn.voxel_lk.VoxelGrid` or ``None``.
        """
        if voxel_grid is not None and not isinstance(voxel_grid, VoxelGrid):
            raise TypeError(f"`voxel_grid` must be an lcreg.nn.voxel_lk.VoxelGrid or None, got {type(voxel_grid)}")
        object.__setattr__(self, "_voxel_grid", voxel_grid)

    @property
    def voxel_grid(self) -> VoxelGrid | None:
        """The voxelisation used outside training (``None``: one descriptor per cloud)."""
        return self._voxel_grid

    @voxel_grid.setter
    def voxel_grid(self, voxel_grid: VoxelGrid | None) -> None:
        self._set_voxel_grid(voxel_grid)

    def setup(self, stage: str) -> None:
        """The base checks, then, the first time, the encoder's starting weights (``encoder_from``).

        Raises:
            CheckpointError: ``encoder_from`` is missing or damaged, or its encoder does not fit this one (a
                subclass naming the file, :func:`lcreg.checkpoints.load_submodule`).
        """
        super().setup(stage)
        if self._encoder_pending and self.encoder_from is not None:
            try:
                path = load_submodule(self, "encoder", self.encoder_from)
            except CheckpointError as err:  # the same error, saying which argument named the file
                raise type(err)(err.path or self.encoder_from, f"{err.reason} (the model's `encoder_from`)") from err
            self._encoder_pending = False
            rank_zero_info(f"encoder initialised from {path}")

    def load_state_dict(self, state_dict: Mapping[str, Any], strict: bool = True, assign: bool = False) -> Any:
        """``torch.nn.Module.load_state_dict``; weights loaded before the first ``setup`` win over ``encoder_from``."""
        self._encoder_pending = False
        return super().load_state_dict(state_dict, strict=strict, assign=assign)

    def forward(self, points_src: torch.Tensor, points_ref: torch.Tensor) -> RegistrationResult:
        """IC-LK registration with the current descriptor (``eval_iterations`` and the voxel grid outside training)."""
        if self.training:
            return self.solver(self.encoder, points_src, points_ref)
        if self._voxel_grid is not None:
            if self.eval_start_angles_deg:
                raise ValueError("`eval_start_angles_deg` applies to the whole-cloud solve, not with `voxel_grid`")
            return voxel_lk(self.solver, self.encoder, self._voxel_grid, points_src, points_ref, self.eval_iterations)
        starts = None
        if self.eval_start_angles_deg:
            starts = axis_rotation_starts(self.eval_start_angles_deg, points_src.dtype, points_src.device)
        return self.solver(
            self.encoder,
            points_src,
            points_ref,
            max_iterations=self.eval_iterations,
            starts=starts,
            start_margin=self.eval_start_margin,
        )

    def step_from(
        self, points_src: torch.Tensor, points_ref: torch.Tensor, transform_ref_src: torch.Tensor
    ) -> torch.Tensor:
        """One update of the training solve from ``transform_ref_src (B, 4, 4)``, with the graph kept.

        :meth:`lcreg.nn.lk.InverseCompositionalLK.step_from`, for
        :class:`~lcreg.models.loss_terms.SelfMotionStationarityLoss`.
        """
        return self.solver.step_from(self.encoder, points_src, points_ref, transform_ref_src)

    def differentiable_forward(self, points_src: torch.Tensor, points_ref: torch.Tensor) -> RegistrationResult:
        """The training-mode solve with the graph kept through it, whatever ``differentiable`` says."""
        return self.solver(self.encoder, points_src, points_ref, differentiable=True)

    def training_forward(self, batch: RegistrationBatch) -> RegistrationResult:
        """``forward`` on the batch's clouds; logs the Jacobian diagnostics of the solve."""
        result = self(batch.points_src, batch.points_ref)
        self.log_jacobian_diagnostics(result, len(batch))
        return result

    def log_jacobian_diagnostics(self, result: RegistrationResult, batch_size: int) -> None:
        """Log ``train/j_*`` (:func:`~lcreg.nn.lk.jacobian_diagnostics`) when the result carries a Jacobian."""
        if "jacobian" not in result.aux or self._trainer is None:
            return
        for name, value in jacobian_diagnostics(result.aux["jacobian"], result.aux["feature_ref"]).items():
            self.log(f"train/j_{name}", value.float(), on_step=True, on_epoch=False, batch_size=batch_size)

    def update_norm_statistics(self, batch: RegistrationBatch) -> None:
        """One train-mode encoder pass over both clouds (no graph) so BatchNorm's running statistics follow the data.

        The PointNetLK/FMR-Net originals do this before switching the encoder to eval mode for the solve.
        """
        has_norm = any(isinstance(m, torch.nn.BatchNorm1d) for m in self.encoder.modules())
        if not (self.training and has_norm):
            return
        with torch.no_grad():
            self.encoder(batch.points_src)
            self.encoder(batch.points_ref)
