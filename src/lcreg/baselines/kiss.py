"""KISS-Matcher (Lim et al., ICRA 2025) behind the classical interface: an optional dependency.

KISS-Matcher is a global registration pipeline (voxel sampling, Faster-PFH features, ROBIN graph pruning of the
correspondences, a graduated non-convexity solve) in C++ with Python bindings, pip ``kiss-matcher`` (MIT licence;
wheels for Linux x86_64 and macOS arm64 only). lcreg installs it with ``pip install 'lcreg[kiss]'``; where it is
missing, using the method raises :class:`~lcreg.checks.MissingDependencyError` in one line that says how to get it.
Building the class and listing the method need nothing.

Every radius is a multiple of one voxel size ``v``, as for the Open3D methods: KISS-Matcher's own gains are in
voxels too (normals ``normal_factor v``, FPFH ``feature_factor v``), so the scale rule of
:mod:`lcreg.registration.voxel` carries over. KISS-Matcher also has constants in metres (it clamps its noise bounds
to 1 m, and the same clouds in millimetres fail its solve), so both clouds are scaled by a power of ten that puts
``v`` in ``[0.01, 0.1)`` (:func:`unit_factor`; 3DMatch and ModelNet40 voxels are already there) and the translation
is scaled back: the same scans in millimetres and in metres give the same transform. Fitness and inlier RMSE are
Open3D's at the gate ``distance_factor v`` (KISS-Matcher reports inlier counts, not these).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from lcreg.baselines.classical import ClassicalRegistration, PairResult, _check_bool, _check_int, _check_positive
from lcreg.checks import MissingDependencyError

__all__ = ["KISSMatcher", "require_kiss_matcher", "unit_factor"]

INSTALL_HINT = "pip install 'lcreg[kiss]' (kiss-matcher wheels exist for Linux x86_64 and macOS arm64)"


def unit_factor(voxel_size: float) -> float:
    """The power of ten ``k`` with ``k * voxel_size`` in ``[0.01, 0.1)`` (``k(1000 v) = k(v) / 1000``)."""
    return float(10.0 ** (-math.floor(math.log10(voxel_size) + 1e-12) - 2))


def require_kiss_matcher() -> Any:
    """The ``kiss_matcher`` module.

    Raises:
        MissingDependencyError: It is not installed (one line with the install command and the platforms).
    """
    try:
        import kiss_matcher
    except ImportError as err:
        raise MissingDependencyError(
            f"method 'kiss' needs the optional package kiss-matcher, which is not installed: {INSTALL_HINT}"
        ) from err
    return kiss_matcher


class KISSMatcher(ClassicalRegistration):
    """KISS-Matcher global registration (``init`` is ignored: the method is global).

    A pair KISS-Matcher finds no solution for (too few inliers) gets the identity with fitness 0 and
    ``valid=False`` (``lcreg.register`` then runs its fallback, if any).

    Args:
        voxel_size: ``v`` (point units): KISS-Matcher's sampling voxel and the unit of every radius.
        downsample: Voxel-downsample both clouds at ``v`` (Open3D) before KISS-Matcher's own voxel sampling.
        normal_factor: Normal radius in voxels (KISS-Matcher ``normal_r_gain``; its default 3).
        normal_max_nn: Unused by KISS-Matcher (kept for the classical interface).
        feature_factor: FPFH radius in voxels (``fpfh_r_gain``; its default 5).
        robin_noise_bound_gain: ROBIN pruning's noise bound in voxels (its default 1).
        solver_noise_bound_gain: The robust solver's noise bound in voxels (its default 0.75).
        num_max_corr: Most correspondences kept (its default 5000).
        distance_factor: Gate of the reported fitness / inlier RMSE, in voxels (the registration API's 2).

    Raises:
        ValueError: On an invalid argument (the message names it).
    """

    def __init__(
        self,
        voxel_size: float = 0.05,
        downsample: bool = False,
        normal_factor: float = 3.0,
        normal_max_nn: int = 30,
        feature_factor: float = 5.0,
        robin_noise_bound_gain: float = 1.0,
        solver_noise_bound_gain: float = 0.75,
        num_max_corr: int = 5000,
        distance_factor: float = 2.0,
        use_quatro: bool = False,
        **kwargs: Any,
    ) -> None:
        super().__init__(voxel_size, downsample, normal_factor, normal_max_nn, **kwargs)
        for name, value in (
            ("feature_factor", feature_factor),
            ("robin_noise_bound_gain", robin_noise_bound_gain),
            ("solver_noise_bound_gain", solver_noise_bound_gain),
            ("distance_factor", distance_factor),
        ):
            _check_positive(name, value)
        _check_int("num_max_corr", num_max_corr, 3)
        _check_bool("use_quatro", use_quatro)
        self.feature_factor = float(feature_factor)
        self.robin_noise_bound_gain = float(robin_noise_bound_gain)
        self.solver_noise_bound_gain = float(solver_noise_bound_gain)
        self.num_max_corr = num_max_corr
        self.distance_factor = float(distance_factor)
        self.use_quatro = use_quatro

    @property
    def iteration_budget(self) -> int:
        """KISS-Matcher's solve reports no iterations: 1 (one global solve)."""
        return 1

    def config(self, scale: float = 1.0) -> Any:
        """The ``KISSMatcherConfig`` of these settings, for clouds multiplied by ``scale``.

        Raises:
            MissingDependencyError: kiss-matcher is not installed.
        """
        km = require_kiss_matcher()
        return km.KISSMatcherConfig(
            voxel_size=self.voxel_size * scale,
            use_voxel_sampling=True,
            use_quatro=self.use_quatro,
            num_max_corr=self.num_max_corr,
            normal_r_gain=self.normal_factor,
            fpfh_r_gain=self.feature_factor,
            robin_noise_bound_gain=self.robin_noise_bound_gain,
            solver_noise_bound_gain=self.solver_noise_bound_gain,
        )

    def estimate_pair(self, points_src: np.ndarray, points_ref: np.ndarray) -> tuple[np.ndarray, bool]:
        """KISS-Matcher's (4, 4) estimate for ``points_src (N, 3)`` onto ``points_ref (M, 3)`` and validity.

        An invalid solve (too few inliers) gives the identity and ``False``.
        """
        km = require_kiss_matcher()
        scale = unit_factor(self.voxel_size)
        solution = km.KISSMatcher(self.config(scale)).estimate(
            np.ascontiguousarray(points_src * scale, dtype=np.float32),
            np.ascontiguousarray(points_ref * scale, dtype=np.float32),
        )
        transform = np.eye(4)
        if solution.valid:
            transform[:3, :3] = np.asarray(solution.rotation, dtype=np.float64)
            transform[:3, 3] = np.asarray(solution.translation, dtype=np.float64).reshape(3) / scale
        return transform, bool(solution.valid)

    def register_pair(self, source: Any, target: Any, init: np.ndarray | None) -> PairResult:
        """KISS-Matcher on two Open3D clouds, then Open3D's fitness at ``distance_factor * v``."""
        import open3d as o3d

        transform, valid = self.estimate_pair(np.asarray(source.points), np.asarray(target.points))
        if not valid:  # no solution: nothing aligned (fitness 0), so `converged` is False
            return PairResult(transform, 0.0, 0.0, valid=False)
        gate = self.distance_factor * self.voxel_size
        out = o3d.pipelines.registration.evaluate_registration(source, target, gate, transform)
        return PairResult(transform, float(out.fitness), float(out.inlier_rmse))
