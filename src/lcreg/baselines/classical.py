"""Classical registration through Open3D behind the common interface (nothing to train).

Four methods share :class:`ClassicalRegistration` and the same ``forward(points_src, points_ref)`` contract, so
``lcreg test`` evaluates them with the same pairs and metrics as the learned models (``lcreg fit`` refuses them
with a clear message):

* :class:`ICP`: ``registration_icp``, point-to-point or point-to-plane, from the identity or from an initial
  transform (``forward(..., init=T)``: ICP refinement after any model);
* :class:`RANSAC`: FPFH features + ``registration_ransac_based_on_feature_matching``;
* :class:`FGR`: FPFH features + ``registration_fgr_based_on_feature_matching`` (Fast Global Registration).

Every pair runs on the CPU in float64 (one pair at a time); transforms come back on the input's device and dtype.
Open3D is imported lazily, inside the methods that need it. Nothing relies on an Open3D default: every value below
is a constructor argument, passed to Open3D explicitly.

Parameters are scaled by one ``voxel_size`` ``v`` (point units; ModelNet40 clouds lie in the unit sphere). With
``downsample=True`` both clouds are ``voxel_down_sample``-d at ``v`` before normals, features and the solver; the
transform is a rigid motion, so it applies unchanged to the original clouds. Defaults were chosen on the ModelNet40
*validation* pairs (never test) by ``benchmarks/tune_classical.py``; see ``docs/results/tune_classical.md``.
"Open3D example" means ``isl-org/Open3D : examples/python/pipelines/registration_{ransac,fgr}.py`` (the values
collected in the project's ``ecosystem.md`` section 3.2).

=======================  ===================  ==============================================  ==========================
parameter                default (absolute)   what it does                                    source
=======================  ===================  ==============================================  ==========================
**all methods**
``voxel_size`` (v)       ICP 0.05, RANSAC     unit of every radius and gate below; the        tuned on validation
                         0.05, FGR 0.08       downsampling cell
``downsample``           False                ``voxel_down_sample(v)`` both clouds first      tuned on validation
                                                                                              (lowered recall: 1024
                                                                                              points are sparse)
``normal_factor``        2.0 (ICP 0.1,        normal radius (``KDTreeSearchParamHybrid``);    Open3D example (2v)
                         RANSAC 0.1, FGR      ICP point-to-plane: reference only;
                         0.16)                RANSAC/FGR: both clouds
``normal_max_nn``        30                   maximum neighbours of a normal                  Open3D example
**ICP**
``method``               point_to_point       ``...PointToPoint(with_scaling=False)`` or      classic ICP (plane:
                                              ``...PointToPlane()``                           icp_plane.yaml)
``distance_factor``      8.0 (0.4)            correspondence gate                             tuned on validation
                                              ``max_correspondence_distance``                 (identity start)
``max_iterations``       100                  ``ICPConvergenceCriteria.max_iteration``        explicit (Open3D default
                                                                                              30)
``relative_fitness``     1e-6                 stop when the fitness changes less              Open3D default value
``relative_rmse``        1e-6                 stop when the inlier RMSE changes less          Open3D default value
**RANSAC, FGR**
``feature_factor``       5.0 (RANSAC 0.25,    FPFH radius                                     Open3D example (5v)
                         FGR 0.4)
``feature_max_nn``       100                  maximum neighbours of FPFH                      Open3D example
``open3d_seed``          0                    ``o3d.utility.random.seed(open3d_seed)``        lcreg (batch-independent)
                                              before each pair
**RANSAC**
``distance_factor``      0.75 (0.0375)        inlier distance of RANSAC and of the distance   tuned on validation
                                              checker                                         (Open3D example 1.5v)
``mutual_filter``        True                 keep mutual nearest feature matches only        Open3D example
``ransac_n``             3                    correspondences per hypothesis                  Open3D example
``edge_length``          0.9                  ``CorrespondenceCheckerBasedOnEdgeLength``      Open3D example
``max_iterations``       100000               ``RANSACConvergenceCriteria.max_iteration``     Open3D example
``confidence``           0.999                ``RANSACConvergenceCriteria.confidence``        Open3D example
``deterministic``        True                 run RANSAC on one Open3D thread (reproducible)  lcreg (see
                                                                                              :class:`RANSAC`)
**FGR**
``distance_factor``      0.25 (0.02)          ``maximum_correspondence_distance``             tuned on validation
                                                                                              (Open3D example 0.5v)
``division_factor``      1.4                  graduated non-convexity: ``mu /=                FGR paper / Open3D value
                                              division_factor``
``use_absolute_scale``   False                False: FGR centres both clouds and divides      FGR paper / Open3D value
                                              them by their largest radius, so distances are
                                              relative to it (~1 for ModelNet40: the same as
                                              point units); True: point units
``decrease_mu``          True                 anneal ``mu`` (graduated non-convexity)         tuned on validation
                                                                                              (Open3D constructor:
                                                                                              False)
``iteration_number``     64                   FGR iterations                                  Open3D example / FGR paper
``tuple_scale``          0.95                 tuple test: edge-length ratio threshold         FGR paper / Open3D value
``maximum_tuple_count``  1000                 tuple test: maximum tuples kept                 Open3D example
``tuple_test``           True                 run the tuple consistency test                  FGR paper / Open3D value
=======================  ===================  ==============================================  ==========================

``configs/models/icp_plane.yaml`` runs point-to-plane ICP with its own validation choice, ``voxel_size=0.08`` (gate
0.64, normal radius 0.16); the :class:`ICP` defaults are the point-to-point choice.

``result.aux`` holds Open3D's ``"fitness"`` and ``"inlier_rmse"`` ``(B,)`` per pair. ``converged`` is
``fitness > 0`` (at least one inlier under the method's gate). ``num_iters`` is the iteration *budget*
(``max_iterations`` / ``iteration_number``): Open3D 0.20 does not report the iterations actually run.

Too-small inputs raise :class:`~lcreg.checks.TooFewPointsError`: clouds need :data:`MIN_POINTS` points (FPFH,
normals and 3-point RANSAC hypotheses need neighbours), before and after downsampling.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import torch

from lcreg.checks import ShapeError, TooFewPointsError, check_rigid, check_transform
from lcreg.models.base import RegistrationModule
from lcreg.types import RegistrationBatch, RegistrationResult

__all__ = ["FGR", "ICP", "MIN_POINTS", "RANSAC", "ClassicalRegistration", "FeatureRegistration", "PairResult"]

MIN_POINTS = 16
"""Smallest cloud (before and after downsampling) accepted by the classical methods: normals use up to 30
neighbours and FPFH up to 100; below ~16 points both are degenerate and 3-point RANSAC has few hypotheses."""

IcpMethod = Literal["point_to_point", "point_to_plane"]


def _check_positive(name: str, value: float) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        raise ValueError(f"`{name}` must be a finite number > 0, got {value!r}")


def _check_non_negative(name: str, value: float) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
        raise ValueError(f"`{name}` must be a finite number >= 0, got {value!r}")


def _check_int(name: str, value: int, minimum: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ValueError(f"`{name}` must be an int >= {minimum}, got {value!r}")


def _check_bool(name: str, value: bool) -> None:
    if not isinstance(value, bool):
        raise ValueError(f"`{name}` must be a bool, got {value!r}")


def _cloud(points: np.ndarray) -> Any:
    """An Open3D ``PointCloud`` of ``points (N, 3)`` (float64)."""
    import open3d as o3d

    pcd = o3d.geometry.PointCloud()
    pcd.points = o3d.utility.Vector3dVector(np.ascontiguousarray(points, dtype=np.float64))
    return pcd


def estimate_normals(pcd: Any, radius: float, max_nn: int) -> None:
    """Estimate ``pcd``'s normals in place with ``KDTreeSearchParamHybrid(radius, max_nn)`` (unoriented)."""
    import open3d as o3d

    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=max_nn))


def compute_fpfh(pcd: Any, radius: float, max_nn: int) -> Any:
    """FPFH features (``Feature``, data ``(33, N)``) of a cloud that has normals."""
    import open3d as o3d

    search = o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=max_nn)
    # No `indices`: every point (an explicit [] selects none in Open3D 0.20; its stub omits the default).
    return o3d.pipelines.registration.compute_fpfh_feature(pcd, search)  # type: ignore[call-arg]


@contextmanager
def _open3d_threads(limit: int | None) -> Iterator[None]:
    """Limit Open3D's CPU threads to ``limit`` inside the block (no change for ``None``), then restore it."""
    if limit is None:
        yield
        return
    import open3d as o3d

    previous = o3d.utility.get_max_threads()
    o3d.utility.set_max_threads(limit)
    try:
        yield
    finally:
        o3d.utility.set_max_threads(previous)


@dataclass
class PairResult:
    """The answer for one pair: ``transform (4, 4)`` float64, ``fitness`` in [0, 1], ``inlier_rmse``, ``valid``.

    ``valid`` is ``False`` when the method itself reports that it found no solution (KISS-Matcher: too few inliers).
    """

    transform: np.ndarray
    fitness: float
    inlier_rmse: float
    valid: bool = True


class ClassicalRegistration(RegistrationModule):
    """Base of the Open3D methods: per-pair CPU loop, voxel scaling, normals, refusal to train.

    Subclasses implement :meth:`register_pair` on Open3D clouds and define :attr:`iteration_budget`.

    Nothing to train: ``has_loss = False`` (validation/test only update metrics); ``_compute_loss`` and
    ``configure_optimizers`` raise ``RuntimeError`` pointing to ``lcreg test``.

    Args:
        voxel_size: ``v`` in point units (> 0): the unit of every radius and gate, and the downsampling cell.
        downsample: ``voxel_down_sample(voxel_size)`` both clouds before the method runs.
        normal_factor: Normal search radius in voxels (radius ``normal_factor * v``).
        normal_max_nn: Maximum neighbours of the normal estimate.
        **kwargs: :class:`~lcreg.models.base.RegistrationModule` components (``refiner``: e.g. RANSAC then ICP).

    Raises:
        ValueError: On an invalid argument (the message names it).
    """

    has_loss = False

    def __init__(
        self, voxel_size: float, downsample: bool, normal_factor: float, normal_max_nn: int, **kwargs: Any
    ) -> None:
        super().__init__(**kwargs)
        self.min_points = MIN_POINTS
        _check_positive("voxel_size", voxel_size)
        _check_bool("downsample", downsample)
        _check_positive("normal_factor", normal_factor)
        _check_int("normal_max_nn", normal_max_nn, 1)
        self.voxel_size = float(voxel_size)
        self.downsample = downsample
        self.normal_factor = float(normal_factor)
        self.normal_max_nn = normal_max_nn

    # --- per-pair work ----------------------------------------------------------------------------------------
    @property
    def normal_radius(self) -> float:
        """Normal search radius ``normal_factor * voxel_size`` (point units)."""
        return self.normal_factor * self.voxel_size

    @property
    def iteration_budget(self) -> int:
        """Iterations reported in ``num_iters`` (Open3D does not report the iterations actually run)."""
        raise NotImplementedError

    def prepare(self, points: np.ndarray, name: str) -> Any:
        """Open3D cloud of ``points (N, 3)``, voxel-downsampled when ``downsample``.

        Raises:
            TooFewPointsError: If downsampling leaves fewer than :data:`MIN_POINTS` points.
        """
        pcd = _cloud(points)
        if self.downsample:
            pcd = pcd.voxel_down_sample(self.voxel_size)
            if len(pcd.points) < MIN_POINTS:
                raise TooFewPointsError(
                    f"`{name}` has {len(pcd.points)} points after voxel_down_sample({self.voxel_size}); at least "
                    f"{MIN_POINTS} are needed: lower `voxel_size` or set `downsample` to False"
                )
        return pcd

    def with_normals(self, pcd: Any) -> Any:
        """``pcd`` with normals estimated at ``normal_radius`` / ``normal_max_nn`` (in place, returned)."""
        estimate_normals(pcd, self.normal_radius, self.normal_max_nn)
        return pcd

    def register_pair(self, source: Any, target: Any, init: np.ndarray | None) -> PairResult:
        """Register one prepared pair of Open3D clouds (``init (4, 4)`` or ``None``)."""
        raise NotImplementedError

    def _run(self, points_src: torch.Tensor, points_ref: torch.Tensor, init: torch.Tensor | None) -> RegistrationResult:
        src = points_src.detach().cpu().double().numpy()
        ref = points_ref.detach().cpu().double().numpy()
        inits: list[np.ndarray | None] = [None] * len(src)
        if init is not None:
            check_transform(init, "init")
            check_rigid(init, "init")
            if init.shape[0] != len(src):
                raise ShapeError("init", (len(src), 4, 4), init.shape)
            inits = list(init.detach().cpu().double().numpy())
        outs = [
            self.register_pair(self.prepare(s, "points_src"), self.prepare(r, "points_ref"), i)
            for s, r, i in zip(src, ref, inits)
        ]
        device, dtype = points_src.device, points_src.dtype
        transform = torch.as_tensor(np.stack([o.transform for o in outs]), dtype=dtype, device=device)
        fitness = torch.tensor([o.fitness for o in outs], dtype=dtype, device=device)
        rmse = torch.tensor([o.inlier_rmse for o in outs], dtype=dtype, device=device)
        return RegistrationResult(
            transform_ref_src=transform,
            converged=fitness > 0,
            num_iters=torch.full((len(src),), self.iteration_budget, dtype=torch.int64, device=device),
            aux={"fitness": fitness, "inlier_rmse": rmse},
        )

    def forward(self, points_src: torch.Tensor, points_ref: torch.Tensor) -> RegistrationResult:
        """Register each pair with Open3D.

        Args:
            points_src: Source clouds ``(B, N, 3)``.
            points_ref: Reference clouds ``(B, M, 3)``.

        Returns:
            ``transform_ref_src (B, 4, 4)`` on the input's device/dtype; ``aux`` has ``fitness``/``inlier_rmse``.

        Raises:
            TypeError, ShapeError, NonFiniteError, TooFewPointsError, DegenerateCloudError: Bad clouds (the message
                names the argument); batches of different sizes.
        """
        return self._run(points_src, points_ref, None)

    # --- no training ------------------------------------------------------------------------------------------
    def _compute_loss(self, result: RegistrationResult, batch: RegistrationBatch) -> dict[str, torch.Tensor]:
        """Classical methods have no training objective."""
        raise RuntimeError(f"{type(self).__name__} is a classical method with nothing to train; use `lcreg test`")

    def configure_optimizers(self) -> Any:
        """Refuse training with a clear message."""
        raise RuntimeError(
            f"{type(self).__name__} has no parameters to train: `lcreg fit` does not apply, use `lcreg test`"
        )


class ICP(ClassicalRegistration):
    """Open3D ICP, point-to-point or point-to-plane (reference normals), from the identity or a given start.

    ``forward(points_src, points_ref, init=T)`` refines an initial estimate ``T (B, 4, 4)`` (e.g. a learned model's
    output or :class:`RANSAC`'s); without ``init`` every pair starts from the identity.

    Args:
        voxel_size: ``v`` (point units): unit of the gate and normal radius, downsampling cell.
        downsample: Voxel-downsample both clouds at ``v`` first.
        method: ``"point_to_point"`` or ``"point_to_plane"``.
        distance_factor: Correspondence gate in voxels: ``max_correspondence_distance = distance_factor * v``.
        max_iterations: Maximum ICP iterations.
        relative_fitness: Stop when the fitness changes by less than this (relative).
        relative_rmse: Stop when the inlier RMSE changes by less than this (relative).
        normal_factor: Reference normal radius in voxels (point-to-plane only).
        normal_max_nn: Maximum neighbours of the normal estimate (point-to-plane only).

    Raises:
        ValueError: On an invalid argument (the message names it).

    Example:
        >>> icp = ICP(voxel_size=0.03, method="point_to_point", distance_factor=8.0)
        >>> icp.max_correspondence_distance
        0.24
    """

    def __init__(
        self,
        voxel_size: float = 0.05,
        downsample: bool = False,
        method: IcpMethod = "point_to_point",
        distance_factor: float = 8.0,
        max_iterations: int = 100,
        relative_fitness: float = 1e-6,
        relative_rmse: float = 1e-6,
        normal_factor: float = 2.0,
        normal_max_nn: int = 30,
        **kwargs: Any,
    ) -> None:
        super().__init__(voxel_size, downsample, normal_factor, normal_max_nn, **kwargs)
        if method not in ("point_to_point", "point_to_plane"):
            raise ValueError(f"`method` must be 'point_to_point' or 'point_to_plane', got {method!r}")
        _check_positive("distance_factor", distance_factor)
        _check_int("max_iterations", max_iterations, 1)
        _check_non_negative("relative_fitness", relative_fitness)
        _check_non_negative("relative_rmse", relative_rmse)
        self.method = method
        self.distance_factor = float(distance_factor)
        self.max_iterations = max_iterations
        self.relative_fitness = float(relative_fitness)
        self.relative_rmse = float(relative_rmse)

    @property
    def max_correspondence_distance(self) -> float:
        """The correspondence gate ``distance_factor * voxel_size`` (point units)."""
        return self.distance_factor * self.voxel_size

    @property
    def iteration_budget(self) -> int:
        """``max_iterations``."""
        return self.max_iterations

    def register_pair(self, source: Any, target: Any, init: np.ndarray | None) -> PairResult:
        """ICP on one prepared pair, from ``init (4, 4)`` (identity when ``None``)."""
        import open3d as o3d

        reg = o3d.pipelines.registration
        estimation: Any
        if self.method == "point_to_plane":
            self.with_normals(target)
            estimation = reg.TransformationEstimationPointToPlane()
        else:
            estimation = reg.TransformationEstimationPointToPoint(with_scaling=False)
        criteria = reg.ICPConvergenceCriteria(
            relative_fitness=self.relative_fitness,
            relative_rmse=self.relative_rmse,
            max_iteration=self.max_iterations,
        )
        start = np.eye(4) if init is None else init
        out = reg.registration_icp(source, target, self.max_correspondence_distance, start, estimation, criteria)
        return PairResult(np.asarray(out.transformation), float(out.fitness), float(out.inlier_rmse))

    def forward(
        self, points_src: torch.Tensor, points_ref: torch.Tensor, init: torch.Tensor | None = None
    ) -> RegistrationResult:
        """Register each pair with Open3D ICP.

        Args:
            points_src: Source clouds ``(B, N, 3)``.
            points_ref: Reference clouds ``(B, M, 3)``.
            init: Starting estimates ``(B, 4, 4)`` mapping source into reference; identity when ``None``.

        Returns:
            ``transform_ref_src (B, 4, 4)`` on the input's device/dtype.

        Raises:
            TypeError, ShapeError, NonFiniteError, TooFewPointsError, DegenerateCloudError: Bad clouds (the message
                names the argument); batches of different sizes.
            ShapeError: If ``init`` is not ``(B, 4, 4)``.
            NonFiniteError: If ``init`` has NaN/Inf values.
            ValueError: If ``init`` is not a batch of rigid motions.
        """
        return self._run(points_src, points_ref, init)

    def refine(self, points_src: torch.Tensor, points_ref: torch.Tensor, init: torch.Tensor) -> RegistrationResult:
        """ICP from ``init (B, 4, 4)``: the refiner step of any model (``configs/refine/icp.yaml``)."""
        return self(points_src, points_ref, init=init)


class FeatureRegistration(ClassicalRegistration):
    """Base of the global methods on FPFH features (:class:`RANSAC`, :class:`FGR`).

    Both clouds get normals (``normal_factor * v``) and FPFH features (``feature_factor * v``); Open3D's random
    generator is seeded with ``open3d_seed`` before each pair, so a pair's result does not depend on its batch.

    Args:
        voxel_size: ``v`` (point units).
        downsample: Voxel-downsample both clouds at ``v`` first.
        normal_factor: Normal radius in voxels.
        normal_max_nn: Maximum neighbours of the normal estimate.
        feature_factor: FPFH radius in voxels.
        feature_max_nn: Maximum neighbours of FPFH.
        open3d_seed: Value passed to ``o3d.utility.random.seed`` before each pair (>= 0). Not named ``seed``:
            Lightning merges model and datamodule hyperparameters, and the datamodule's ``seed`` differs.
    """

    def __init__(
        self,
        voxel_size: float,
        downsample: bool,
        normal_factor: float,
        normal_max_nn: int,
        feature_factor: float,
        feature_max_nn: int,
        open3d_seed: int,
        **kwargs: Any,
    ) -> None:
        super().__init__(voxel_size, downsample, normal_factor, normal_max_nn, **kwargs)
        _check_positive("feature_factor", feature_factor)
        _check_int("feature_max_nn", feature_max_nn, 1)
        _check_int("open3d_seed", open3d_seed, 0)
        self.feature_factor = float(feature_factor)
        self.feature_max_nn = feature_max_nn
        self.open3d_seed = open3d_seed

    @property
    def feature_radius(self) -> float:
        """FPFH search radius ``feature_factor * voxel_size`` (point units)."""
        return self.feature_factor * self.voxel_size

    def features(self, pcd: Any) -> Any:
        """Normals (in place) then FPFH features ``(33, N)`` of ``pcd``."""
        self.with_normals(pcd)
        return compute_fpfh(pcd, self.feature_radius, self.feature_max_nn)

    def match(self, source: Any, target: Any, feat_src: Any, feat_ref: Any) -> Any:
        """The Open3D global registration call on featured clouds (an Open3D ``RegistrationResult``)."""
        raise NotImplementedError

    def register_featured(self, source: Any, target: Any, feat_src: Any, feat_ref: Any) -> PairResult:
        """Seed Open3D's generator with ``open3d_seed``, then :meth:`match` (features already computed)."""
        import open3d as o3d

        o3d.utility.random.seed(self.open3d_seed)
        out = self.match(source, target, feat_src, feat_ref)
        return PairResult(np.asarray(out.transformation), float(out.fitness), float(out.inlier_rmse))

    def register_pair(self, source: Any, target: Any, init: np.ndarray | None) -> PairResult:
        """Features of both clouds, then :meth:`register_featured` (``init`` is ignored: these methods are global)."""
        return self.register_featured(source, target, self.features(source), self.features(target))


class RANSAC(FeatureRegistration):
    """FPFH + RANSAC (``registration_ransac_based_on_feature_matching``, point-to-point estimation).

    Args:
        voxel_size: ``v`` (point units).
        downsample: Voxel-downsample both clouds at ``v`` first.
        normal_factor: Normal radius in voxels.
        normal_max_nn: Maximum neighbours of the normal estimate.
        feature_factor: FPFH radius in voxels.
        feature_max_nn: Maximum neighbours of FPFH.
        distance_factor: Inlier distance in voxels, for RANSAC and for the distance checker.
        mutual_filter: Keep only mutual nearest-neighbour feature matches.
        ransac_n: Correspondences per hypothesis (>= 3).
        edge_length: Threshold of ``CorrespondenceCheckerBasedOnEdgeLength`` in ``(0, 1)``.
        max_iterations: ``RANSACConvergenceCriteria.max_iteration``.
        confidence: ``RANSACConvergenceCriteria.confidence`` in ``(0, 1]``.
        open3d_seed: ``o3d.utility.random.seed`` value, set before each pair.
        deterministic: Run the RANSAC call on one Open3D thread (``o3d.utility.set_max_threads(1)``, the previous
            limit is restored afterwards). Open3D's parallel RANSAC consumes the seeded generator in thread
            scheduling order, so with several threads the same pair can give another transform from run to run
            (seen on this project's 2-core machine under load); one thread makes the result a function of the
            pair and ``open3d_seed`` only.

    Raises:
        ValueError: On an invalid argument (the message names it).
    """

    def __init__(
        self,
        voxel_size: float = 0.05,
        downsample: bool = False,
        normal_factor: float = 2.0,
        normal_max_nn: int = 30,
        feature_factor: float = 5.0,
        feature_max_nn: int = 100,
        distance_factor: float = 0.75,
        mutual_filter: bool = True,
        ransac_n: int = 3,
        edge_length: float = 0.9,
        max_iterations: int = 100_000,
        confidence: float = 0.999,
        open3d_seed: int = 0,
        deterministic: bool = True,
        **kwargs: Any,
    ) -> None:
        super().__init__(
            voxel_size, downsample, normal_factor, normal_max_nn, feature_factor, feature_max_nn, open3d_seed, **kwargs
        )
        _check_positive("distance_factor", distance_factor)
        _check_bool("mutual_filter", mutual_filter)
        _check_bool("deterministic", deterministic)
        _check_int("ransac_n", ransac_n, 3)
        if not isinstance(edge_length, (int, float)) or isinstance(edge_length, bool) or not 0 < edge_length < 1:
            raise ValueError(f"`edge_length` must be in (0, 1), got {edge_length!r}")
        _check_int("max_iterations", max_iterations, 1)
        if not isinstance(confidence, (int, float)) or isinstance(confidence, bool) or not 0 < confidence <= 1:
            raise ValueError(f"`confidence` must be in (0, 1], got {confidence!r}")
        self.distance_factor = float(distance_factor)
        self.mutual_filter = mutual_filter
        self.ransac_n = ransac_n
        self.edge_length = float(edge_length)
        self.max_iterations = max_iterations
        self.confidence = float(confidence)
        self.deterministic = deterministic

    @property
    def max_correspondence_distance(self) -> float:
        """Inlier distance ``distance_factor * voxel_size`` (point units)."""
        return self.distance_factor * self.voxel_size

    @property
    def iteration_budget(self) -> int:
        """``max_iterations`` (RANSAC trials; it usually stops earlier on ``confidence``)."""
        return self.max_iterations

    def match(self, source: Any, target: Any, feat_src: Any, feat_ref: Any) -> Any:
        """Feature-matching RANSAC with the edge-length and distance checkers."""
        import open3d as o3d

        reg = o3d.pipelines.registration
        dist = self.max_correspondence_distance
        checkers = [
            reg.CorrespondenceCheckerBasedOnEdgeLength(self.edge_length),
            reg.CorrespondenceCheckerBasedOnDistance(dist),
        ]
        criteria = reg.RANSACConvergenceCriteria(max_iteration=self.max_iterations, confidence=self.confidence)
        with _open3d_threads(1 if self.deterministic else None):
            return reg.registration_ransac_based_on_feature_matching(
                source,
                target,
                feat_src,
                feat_ref,
                self.mutual_filter,
                dist,
                reg.TransformationEstimationPointToPoint(with_scaling=False),
                self.ransac_n,
                checkers,
                criteria,
            )


class FGR(FeatureRegistration):
    """FPFH + Fast Global Registration (``registration_fgr_based_on_feature_matching``).

    Every field of ``FastGlobalRegistrationOption`` is passed explicitly. Note that Open3D's constructor default
    is ``decrease_mu=False`` while the function signature's documented default repr says ``True``; here it is a
    constructor argument (default chosen on validation).

    Args:
        voxel_size: ``v`` (point units).
        downsample: Voxel-downsample both clouds at ``v`` first.
        normal_factor: Normal radius in voxels.
        normal_max_nn: Maximum neighbours of the normal estimate.
        feature_factor: FPFH radius in voxels.
        feature_max_nn: Maximum neighbours of FPFH.
        distance_factor: ``maximum_correspondence_distance`` in voxels.
        division_factor: Graduated non-convexity: ``mu`` is divided by this (> 1).
        use_absolute_scale: Interpret the distance in absolute units (else relative to the cloud's scale).
        decrease_mu: Anneal ``mu`` (graduated non-convexity).
        iteration_number: FGR iterations.
        tuple_scale: Edge-length ratio threshold of the tuple test, in ``(0, 1)``.
        maximum_tuple_count: Maximum tuples kept by the tuple test.
        tuple_test: Run the tuple consistency test.
        open3d_seed: ``o3d.utility.random.seed`` value, set before each pair (the tuple test samples at random).

    Raises:
        ValueError: On an invalid argument (the message names it).
    """

    def __init__(
        self,
        voxel_size: float = 0.08,
        downsample: bool = False,
        normal_factor: float = 2.0,
        normal_max_nn: int = 30,
        feature_factor: float = 5.0,
        feature_max_nn: int = 100,
        distance_factor: float = 0.25,
        division_factor: float = 1.4,
        use_absolute_scale: bool = False,
        decrease_mu: bool = True,
        iteration_number: int = 64,
        tuple_scale: float = 0.95,
        maximum_tuple_count: int = 1000,
        tuple_test: bool = True,
        open3d_seed: int = 0,
        **kwargs: Any,
    ) -> None:
        super().__init__(
            voxel_size, downsample, normal_factor, normal_max_nn, feature_factor, feature_max_nn, open3d_seed, **kwargs
        )
        _check_positive("distance_factor", distance_factor)
        _check_positive("division_factor", division_factor)
        if division_factor <= 1:
            raise ValueError(f"`division_factor` must be > 1, got {division_factor!r}")
        _check_bool("use_absolute_scale", use_absolute_scale)
        _check_bool("decrease_mu", decrease_mu)
        _check_int("iteration_number", iteration_number, 1)
        if not isinstance(tuple_scale, (int, float)) or isinstance(tuple_scale, bool) or not 0 < tuple_scale < 1:
            raise ValueError(f"`tuple_scale` must be in (0, 1), got {tuple_scale!r}")
        _check_int("maximum_tuple_count", maximum_tuple_count, 1)
        _check_bool("tuple_test", tuple_test)
        self.distance_factor = float(distance_factor)
        self.division_factor = float(division_factor)
        self.use_absolute_scale = use_absolute_scale
        self.decrease_mu = decrease_mu
        self.iteration_number = iteration_number
        self.tuple_scale = float(tuple_scale)
        self.maximum_tuple_count = maximum_tuple_count
        self.tuple_test = tuple_test

    @property
    def max_correspondence_distance(self) -> float:
        """``maximum_correspondence_distance = distance_factor * voxel_size`` (point units)."""
        return self.distance_factor * self.voxel_size

    @property
    def iteration_budget(self) -> int:
        """``iteration_number``."""
        return self.iteration_number

    def option(self) -> Any:
        """The ``FastGlobalRegistrationOption`` with every field set from the constructor arguments."""
        import open3d as o3d

        return o3d.pipelines.registration.FastGlobalRegistrationOption(
            division_factor=self.division_factor,
            use_absolute_scale=self.use_absolute_scale,
            decrease_mu=self.decrease_mu,
            maximum_correspondence_distance=self.max_correspondence_distance,
            iteration_number=self.iteration_number,
            tuple_scale=self.tuple_scale,
            maximum_tuple_count=self.maximum_tuple_count,
            tuple_test=self.tuple_test,
        )

    def match(self, source: Any, target: Any, feat_src: Any, feat_ref: Any) -> Any:
        """FGR on the feature matches."""
        import open3d as o3d

        return o3d.pipelines.registration.registration_fgr_based_on_feature_matching(
            source, target, feat_src, feat_ref, self.option()
        )
