"""Classical registration through Open3D behind the common interface (no training).

:class:`ICP` runs Open3D's ``registration_icp`` per pair on the CPU (float64), starting from the identity unless
an initial transform is given. Open3D is imported lazily, inside :meth:`ICP.forward`. ``lcreg fit`` refuses these
models with a clear message (``configure_optimizers``); use ``lcreg test``.

Parameters are explicit (no Open3D defaults are relied on):

* ``max_correspondence_distance``: pairs farther apart are ignored (same units as the points; ModelNet40 clouds lie
  in the unit sphere, translations are up to 0.5 per axis);
* ``max_iterations``, ``relative_fitness``, ``relative_rmse``: ``ICPConvergenceCriteria``;
* point-to-plane: reference normals from ``KDTreeSearchParamHybrid(normal_radius, normal_max_nn)``.
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
import torch

from lcreg.models.base import RegistrationModule
from lcreg.types import RegistrationBatch, RegistrationResult

__all__ = ["ICP"]


def _cloud(points: np.ndarray) -> Any:
    import open3d as o3d

    pcd = o3d.geometry.PointCloud()
    pcd.points = o3d.utility.Vector3dVector(points.astype(np.float64))
    return pcd


class ICP(RegistrationModule):
    """Open3D ICP (point-to-point or point-to-plane).

    Nothing to train: ``has_loss = False`` (validation/test only update metrics) and ``configure_optimizers`` raises.

    Args:
        method: ``"point_to_point"`` or ``"point_to_plane"``.
        max_correspondence_distance: Inlier distance of the correspondences.
        max_iterations: Maximum ICP iterations.
        relative_fitness: Convergence threshold on the relative change of fitness.
        relative_rmse: Convergence threshold on the relative change of inlier RMSE.
        normal_radius: Search radius of the reference normals (point-to-plane).
        normal_max_nn: Maximum neighbours of the normal estimation.
    """

    has_loss = False

    def __init__(
        self,
        method: Literal["point_to_point", "point_to_plane"] = "point_to_point",
        max_correspondence_distance: float = 0.2,
        max_iterations: int = 50,
        relative_fitness: float = 1e-6,
        relative_rmse: float = 1e-6,
        normal_radius: float = 0.1,
        normal_max_nn: int = 30,
    ) -> None:
        super().__init__()
        if method not in ("point_to_point", "point_to_plane"):
            raise ValueError(f"`method` must be 'point_to_point' or 'point_to_plane', got {method!r}")
        if max_correspondence_distance <= 0 or max_iterations < 1:
            raise ValueError("`max_correspondence_distance` must be > 0 and `max_iterations` >= 1")
        self.save_hyperparameters()
        self.method = method
        self.max_correspondence_distance = max_correspondence_distance
        self.max_iterations = max_iterations
        self.relative_fitness = relative_fitness
        self.relative_rmse = relative_rmse
        self.normal_radius = normal_radius
        self.normal_max_nn = normal_max_nn

    def _register_one(self, src: np.ndarray, ref: np.ndarray, init: np.ndarray) -> tuple[np.ndarray, bool]:
        import open3d as o3d

        reg = o3d.pipelines.registration
        source, target = _cloud(src), _cloud(ref)
        estimation: Any
        if self.method == "point_to_plane":
            target.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(self.normal_radius, self.normal_max_nn))
            estimation = reg.TransformationEstimationPointToPlane()
        else:
            estimation = reg.TransformationEstimationPointToPoint(False)
        criteria = reg.ICPConvergenceCriteria(self.relative_fitness, self.relative_rmse, self.max_iterations)
        out = reg.registration_icp(source, target, self.max_correspondence_distance, init, estimation, criteria)
        return np.asarray(out.transformation), bool(out.fitness > 0)

    def forward(
        self, points_src: torch.Tensor, points_ref: torch.Tensor, init: torch.Tensor | None = None
    ) -> RegistrationResult:
        """Register each pair with Open3D; ``init (B, 4, 4)`` is the starting estimate (identity by default)."""
        src = points_src.detach().cpu().double().numpy()
        ref = points_ref.detach().cpu().double().numpy()
        inits = np.tile(np.eye(4), (len(src), 1, 1)) if init is None else init.detach().cpu().double().numpy()
        outs = [self._register_one(s, r, i) for s, r, i in zip(src, ref, inits)]
        transform = torch.as_tensor(np.stack([o[0] for o in outs]), dtype=points_src.dtype, device=points_src.device)
        converged = torch.tensor([o[1] for o in outs], device=points_src.device)
        iters = torch.full((len(src),), self.max_iterations, dtype=torch.long, device=points_src.device)
        return RegistrationResult(transform_ref_src=transform, converged=converged, num_iters=iters)

    def compute_loss(self, result: RegistrationResult, batch: RegistrationBatch) -> dict[str, torch.Tensor]:
        """Classical methods have no training objective."""
        raise RuntimeError(f"{type(self).__name__} is a classical method with nothing to train; use `lcreg test`")

    def configure_optimizers(self) -> Any:
        """Refuse training with a clear message."""
        raise RuntimeError(
            f"{type(self).__name__} has no parameters to train: `lcreg fit` does not apply, use `lcreg test`"
        )
