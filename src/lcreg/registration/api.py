"""``lcreg.register(src, ref)``: register two clouds of any size, unit and container in one call.

>>> import lcreg
>>> result = lcreg.register("scan_a.ply", "scan_b.ply")          # doctest: +SKIP
>>> result.transform            # (4, 4) float64, maps scan_a's points into scan_b's frame
>>> result.fitness, result.inlier_rmse, result.time_s
>>> moved = result.apply(points_of_scan_a)

Steps: read or convert both clouds (:mod:`lcreg.registration.inputs`: NaN rows dropped with a warning), pick the
voxel size from the clouds (:mod:`lcreg.registration.voxel`) unless given, apply the initial guess to the source,
run the method (:mod:`lcreg.registration.methods`), compose the result with the initial guess, and score it
(fitness: share of the source's points within ``2v`` of the reference after alignment; inlier RMSE of those).
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import torch

from lcreg.checks import check_rigid, check_transform
from lcreg.registration.inputs import Cloud, CloudLike, as_cloud
from lcreg.registration.methods import (
    GLOBAL_STEPS,
    Method,
    Prepared,
    PreparedCache,
    evaluate,
    global_step,
    icp_step,
    learned_model,
    learned_step,
    parse_method,
)
from lcreg.registration.methods import threads as threads_limit
from lcreg.registration.voxel import TARGET_POINTS, auto_voxel_size

__all__ = [
    "DEFAULT",
    "DEFAULT_METHOD",
    "DEFAULT_WITHOUT_KISS",
    "LEARNED_MIN_FITNESS",
    "DefaultPipeline",
    "LowFitnessWarning",
    "Registration",
    "default_pipeline",
    "register",
    "register_clouds",
    "resolve_methods",
]


@dataclass(frozen=True)
class DefaultPipeline:
    """What ``method="default"`` runs: a method, a fallback below a fitness, another method for small clouds.

    Attributes:
        method: The method for clouds with more than ``target_points`` points (scans: downsampled).
        fallback: Method run when ``method``'s result has a fitness below ``min_fitness`` or no solution.
        min_fitness: See ``fallback``.
        small: The method when both clouds have at most ``target_points`` points (objects), ``None``: ``method``.
        fallback_ransac_iterations: RANSAC's iteration limit in the fallback (``None``: the methods' default).
    """

    method: str
    fallback: str | None = None
    min_fitness: float | None = None
    small: str | None = None
    fallback_ransac_iterations: int | None = None

    def describe(self) -> str:
        """``"kiss+icp, then ransac+icp (25,000 RANSAC iterations) below fitness 0.1; ransac+icp for ..."``."""
        limit = self.fallback_ransac_iterations
        fallback = f"{self.fallback} ({limit:,} RANSAC iterations)" if limit is not None else self.fallback
        tail = "" if self.fallback is None else f", then {fallback} below fitness {self.min_fitness:g}"
        small = "" if self.small is None else f"; {self.small} when both clouds have at most --target-points points"
        return self.method + tail + small


DEFAULT = DefaultPipeline("kiss+icp", "ransac+icp", 0.1, small="ransac+icp", fallback_ransac_iterations=25_000)
"""``method="default"``: chosen on the validation pairs (``docs/results/register.md``): KISS-Matcher fails on small
objects (1,024 points: 64 % recall against RANSAC's 99 %), where RANSAC is fast anyway; the pairs KISS-Matcher fails
on are hard for RANSAC too, and 25,000 iterations there cost 0.5 points of validation recall against 100,000 at a
quarter of the fallback's RANSAC time."""
DEFAULT_WITHOUT_KISS = DefaultPipeline("ransac+icp")
"""The default where the optional kiss-matcher is not installed (no wheel for the platform)."""


def default_pipeline() -> DefaultPipeline:
    """:data:`DEFAULT`, or :data:`DEFAULT_WITHOUT_KISS` when kiss-matcher cannot be imported."""
    try:
        import kiss_matcher  # noqa: F401
    except ImportError:
        return DEFAULT_WITHOUT_KISS
    return DEFAULT


def resolve_methods(
    method: str,
    refine: str | None,
    fallback: str | None,
    min_fitness: float | None,
    ransac_iterations: int | None = None,
) -> tuple[Method, Method | None, float | None, Method | None]:
    """``(method, fallback, min_fitness, small)`` parsed; ``"default"`` is :func:`default_pipeline`.

    The default brings its fallback (unless one is given, with its RANSAC iterations) and its method for small
    clouds (else ``None``). ``ransac_iterations`` sets RANSAC's iteration limit in all of them.

    Raises:
        MethodError: An unknown method or fallback.
        ValueError: ``min_fitness`` outside [0, 1], ``ransac_iterations`` not an int >= 1.
    """
    if min_fitness is not None and not (isinstance(min_fitness, (int, float)) and 0 <= min_fitness <= 1):
        raise ValueError(f"`min_fitness` must be a number in [0, 1] or None, got {min_fitness!r}")
    if ransac_iterations is not None and (
        isinstance(ransac_iterations, bool) or not isinstance(ransac_iterations, int) or ransac_iterations < 1
    ):
        raise ValueError(f"`ransac_iterations` must be an int >= 1 or None, got {ransac_iterations!r}")
    small, fallback_iterations = None, None
    if method == "default":
        policy = default_pipeline()
        method, small = policy.method, None if policy.small is None else parse_method(policy.small)
        if fallback is None:  # the default's fallback, at the default's level unless one is given
            fallback, min_fitness = policy.fallback, policy.min_fitness if min_fitness is None else min_fitness
            fallback_iterations = policy.fallback_ransac_iterations
    second = (
        None if fallback is None else parse_method(default_pipeline().method if fallback == "default" else fallback)
    )
    first = parse_method(method, refine)
    if ransac_iterations is not None:
        first = replace(first, ransac_iterations=ransac_iterations)
        small = None if small is None else replace(small, ransac_iterations=ransac_iterations)
    limit = ransac_iterations if ransac_iterations is not None else fallback_iterations
    if second is not None and limit is not None:
        second = replace(second, ransac_iterations=limit)
    return first, second, min_fitness, small


DEFAULT_METHOD = DEFAULT.method
"""The method of :data:`DEFAULT` (kept for scripts that read the name)."""
LEARNED_MIN_FITNESS = 0.5
"""A learned object method's result below this fitness is flagged (:class:`LowFitnessWarning`): those networks were
trained on complete objects that overlap fully, where a correct result has a fitness near 1."""


class LowFitnessWarning(UserWarning):
    """A result's fitness says the registration probably failed (the message says what to use instead)."""


@dataclass
class Registration:
    """The result of :func:`register`.

    Attributes:
        transform: ``(4, 4)`` float64 ``[R t; 0 1]`` mapping source points into the reference frame
            (``p_ref = R p_src + t``), in the inputs' unit.
        method: The method that ran (``"ransac+icp"``).
        voxel_size: ``v`` used by the steps (input unit).
        fitness: Share of the (downsampled) source points within ``2v`` of the reference after alignment.
        inlier_rmse: RMSE of those points' distances (input unit).
        time_s: Wall time of the registration (reading the files excluded), seconds.
        num_points: Points of source and reference as given (after dropping NaN rows).
        used_points: Points of source and reference the steps used (after downsampling).
        dropped: NaN/Inf rows dropped from source and reference.
        coarse_transform: The coarse step's estimate before refinement (``None`` without refinement).
        coarse_time_s: Wall time up to the end of the coarse step (``None`` without refinement).
        sources: Labels of the two clouds (file paths, or ``points_src``/``points_ref``).
    """

    transform: np.ndarray
    method: str
    voxel_size: float
    fitness: float
    inlier_rmse: float
    time_s: float
    num_points: tuple[int, int]
    used_points: tuple[int, int]
    dropped: tuple[int, int] = (0, 0)
    coarse_transform: np.ndarray | None = None
    coarse_time_s: float | None = None
    sources: tuple[str, str] = ("points_src", "points_ref")
    extra: dict[str, Any] = field(default_factory=dict)

    def apply(self, points: CloudLike) -> np.ndarray:
        """``(N, 3)`` points moved by :attr:`transform` (float64; NaN rows pass through as NaN)."""
        array = points.detach().cpu().numpy() if isinstance(points, torch.Tensor) else np.asarray(points)
        array = np.asarray(array, dtype=np.float64).reshape(-1, 3)
        return array @ self.transform[:3, :3].T + self.transform[:3, 3]

    def to_dict(self) -> dict[str, Any]:
        """Plain values (JSON-ready): the transform as 4 rows of 4 numbers, the diagnostics."""
        out = {
            "transform_ref_src": self.transform.tolist(),
            "method": self.method,
            "voxel_size": self.voxel_size,
            "fitness": self.fitness,
            "inlier_rmse": self.inlier_rmse,
            "time_s": self.time_s,
            "num_points": list(self.num_points),
            "used_points": list(self.used_points),
            "dropped_nonfinite": list(self.dropped),
            "source": self.sources[0],
            "reference": self.sources[1],
        }
        if self.coarse_transform is not None:
            out["coarse_transform_ref_src"] = self.coarse_transform.tolist()
        if "fallback" in self.extra:
            out["fallback"] = dict(self.extra["fallback"])
        return out


def _check_init(init: Any) -> np.ndarray:
    """``init`` as a ``(4, 4)`` float64 rigid motion (typed errors naming ``init``)."""
    array = init.detach().cpu().numpy() if isinstance(init, torch.Tensor) else init
    tensor = torch.as_tensor(np.asarray(array, dtype=np.float64))
    check_transform(tensor.reshape(1, 4, 4) if tensor.numel() == 16 else tensor, "init")  # typed: shape, NaN
    check_rigid(tensor.reshape(1, 4, 4), "init")
    return tensor.reshape(4, 4).numpy()


def register_clouds(
    src: Cloud,
    ref: Cloud,
    method: Method,
    *,
    weights: str | None = None,
    voxel_size: float | None = None,
    init: np.ndarray | None = None,
    target_points: int = TARGET_POINTS,
    learned_points: int = 1024,
    seed: int = 0,
    cache: PreparedCache | None = None,
    fallback: Method | None = None,
    min_fitness: float | None = None,
    small: Method | None = None,
) -> Registration:
    """Register two validated clouds (the work of :func:`register`; ``cache`` reuses files' features across pairs).

    With ``small``, clouds of at most ``target_points`` points each (objects) are registered by ``small`` alone.

    A result whose fitness is below ``min_fitness`` (for learned methods, by default :data:`LEARNED_MIN_FITNESS`), or
    whose coarse step reports no solution (KISS-Matcher), is run again with ``fallback`` when one is given (the result
    with the higher fitness is kept, both recorded in ``extra["fallback"]``, the times added); without a fallback, a
    learned method's low fitness or a step's missing solution comes with a :class:`LowFitnessWarning`.

    Args:
        src: Source cloud.
        ref: Reference cloud.
        method: Parsed method.
        weights: Learned methods: a shipped name, an exported ``.pt`` or a ``.ckpt`` (``None``: shipped weights).
        voxel_size: ``v`` in the clouds' unit (``None``: automatic).
        init: ``(4, 4)`` initial guess applied to the source first (``None``: identity).
        target_points: Points kept per cloud by downsampling (and by the automatic voxel size).
        learned_points: Points per cloud fed to a network.
        seed: Seed of the networks' point samples.
        cache: Prepared clouds shared by pairs (files only; keys are the file paths).
        fallback: Method run when the fitness is below ``min_fitness``.
        min_fitness: Fitness below which the result counts as failed (``None``: :data:`LEARNED_MIN_FITNESS` for
            learned methods, no check for classical ones).
        small: Method for two clouds of at most ``target_points`` points (``None``: ``method``).

    Returns:
        The :class:`Registration`.
    """
    if small is not None and max(len(src.points), len(ref.points)) <= target_points:
        method, fallback, min_fitness = small, None, None
    _import_steps(method, fallback)  # module loading is not registration time
    start = time.perf_counter()
    v = auto_voxel_size(src.points, ref.points, target_points) if voxel_size is None else float(voxel_size)
    points_src = src.points
    src_key = None if src.path is None else str(src.path)
    if init is not None:
        points_src = points_src @ init[:3, :3].T + init[:3, 3]
        src_key = None
    cache = cache or PreparedCache()
    ref_key = None if ref.path is None else str(ref.path)
    clouds = (cache.get(src_key, points_src, v, target_points), cache.get(ref_key, ref.points, v, target_points))
    steps = (weights, init, learned_points, seed)
    first = _run_method(method, src, ref, clouds, steps, start)
    threshold = min_fitness if min_fitness is not None else (LEARNED_MIN_FITNESS if method.learned else None)
    no_solution = first.extra.get("coarse_valid") is False  # the coarse step says it found none (KISS-Matcher)
    if not no_solution and (threshold is None or first.fitness >= threshold):
        return first
    if fallback is None:
        if no_solution or method.learned:
            warnings.warn(LowFitnessWarning(_failure_message(first, threshold, no_solution)), stacklevel=3)
        return first
    second = _run_method(fallback, src, ref, clouds, steps, time.perf_counter())  # same prepared clouds
    kept = second if second.fitness > first.fitness else first
    kept.extra["fallback"] = {
        "first": first.method, "first_fitness": first.fitness, "min_fitness": threshold,
        "ran": second.method, "ran_fitness": second.fitness, "kept": kept.method, "no_solution": no_solution,
    }  # fmt: skip
    kept.time_s = first.time_s + second.time_s
    return kept


def _import_steps(*methods: Method | None) -> None:
    """Import what the steps of ``methods`` run on (Open3D, the classical baselines, KISS-Matcher), untimed.

    Raises:
        lcreg.checks.MissingDependencyError: A ``kiss`` step without the optional package kiss-matcher.
    """
    import open3d  # noqa: F401

    import lcreg.baselines.classical  # noqa: F401

    if any(m is not None and m.coarse == "kiss" for m in methods):
        from lcreg.baselines.kiss import require_kiss_matcher

        require_kiss_matcher()


def _failure_message(result: Registration, threshold: float | None, no_solution: bool) -> str:
    coarse = result.method.partition("+")[0]
    if no_solution:
        return (
            f"{result.method}: {coarse} found no solution (too few consistent correspondences), the result is the "
            "identity refined; use ransac+icp, or ask for a fallback (fallback='ransac+icp', --fallback ransac+icp)"
        )
    return (
        f"{result.method}: fitness {result.fitness:.2f} is below {threshold:g}, the registration probably failed; "
        f"{coarse} is an object model trained on complete objects that overlap fully: for partial scans use "
        "ransac+icp or kiss+icp, or ask for a fallback (fallback='ransac+icp', --fallback ransac+icp)"
    )


def _run_method(
    method: Method,
    src: Cloud,
    ref: Cloud,
    clouds: tuple[Prepared, Prepared],
    steps: tuple[str | None, np.ndarray | None, int, int],
    start: float,
) -> Registration:
    """One method on a pair's prepared clouds (``steps``: weights, init, learned points, seed); timed from ``start``."""
    weights, init, learned_points, seed = steps
    p_src, p_ref = clouds
    model = learned_model(method.coarse, weights) if method.learned else None
    coarse, valid = _coarse(method, p_src, p_ref, model, learned_points, seed)
    coarse_time = time.perf_counter() - start
    transform = coarse if method.refine is None else icp_step(p_src, p_ref, coarse).transform
    fitness, rmse = evaluate(p_src, p_ref, transform)
    if init is not None:
        transform, coarse = transform @ init, coarse @ init
    return Registration(
        transform=transform,
        method=method.name,
        voxel_size=p_src.voxel_size,
        fitness=fitness,
        inlier_rmse=rmse,
        time_s=time.perf_counter() - start,
        num_points=(len(src.points), len(ref.points)),
        used_points=(len(p_src.points), len(p_ref.points)),
        dropped=(src.dropped, ref.dropped),
        coarse_transform=None if method.refine is None else coarse,
        coarse_time_s=None if method.refine is None else coarse_time,
        sources=(src.label, ref.label),
        extra={} if valid else {"coarse_valid": False},
    )


def _coarse(method: Method, src: Any, ref: Any, model: Any, learned_points: int, seed: int) -> tuple[np.ndarray, bool]:
    """The coarse step's ``(4, 4)`` estimate, and whether the step reports a solution (KISS-Matcher may not)."""
    name = method.coarse
    if name == "icp":
        return icp_step(src, ref, np.eye(4)).transform, True
    if name in GLOBAL_STEPS:
        out = global_step(name, src, ref, method.ransac_iterations)
        return out.transform, out.valid
    return learned_step(model, src.points, ref.points, learned_points, seed), True


def register(
    src: CloudLike,
    ref: CloudLike,
    method: str = "default",
    *,
    weights: str | None = None,
    refine: str | None = None,
    voxel_size: float | None = None,
    init: Any = None,
    target_points: int = TARGET_POINTS,
    learned_points: int = 1024,
    seed: int = 0,
    fallback: str | None = None,
    min_fitness: float | None = None,
    threads: int | None = None,
    ransac_iterations: int | None = None,
) -> Registration:
    """Register ``src`` onto ``ref``: the rigid motion mapping the source's points into the reference's frame.

    Args:
        src: Source cloud: a file path (``.ply``, ``.pcd``, ``.xyz``, ``.pts``, ``.npy``, KITTI ``.bin``, ...), an
            ``(N, 3)`` numpy array (float32/float64/int) or torch tensor, or an Open3D ``PointCloud``.
        ref: Reference cloud, same kinds.
        method: ``"default"`` (:data:`DEFAULT`: ``kiss+icp``, then ``ransac+icp`` below fitness 0.1; ``ransac+icp``
            where kiss-matcher is not installed), or a name of
            :func:`lcreg.registration.methods.available_methods` (``"icp"``, ``"ransac"``, ``"fgr"``, ``"dvds"``,
            ``"ransac+icp"``, ``"dvds+icp"``, ...).
        weights: Learned methods only: a shipped name (``lcreg.pretrained_names()``), an exported ``.pt`` file or a
            ``.ckpt`` of ``lcreg fit``; ``None`` takes the method's shipped weights.
        refine: ``"icp"`` adds ICP refinement to a single-step method (``"none"``/``None``: as named).
        voxel_size: ``v`` in the clouds' unit; ``None`` picks it from the clouds (about ``target_points`` points
            after downsampling, never below 1.5 point spacings).
        init: Initial guess ``(4, 4)`` (numpy or torch), applied to the source before the method; the result
            includes it.
        target_points: Points per cloud after downsampling.
        learned_points: Points per cloud given to a network.
        seed: Seed of the networks' point samples (classical steps are seeded too: results are reproducible).
        fallback: A method run when the result's fitness is below ``min_fitness`` (e.g. ``"ransac+icp"`` after a
            learned object method on partial scans); the result with the higher fitness is returned.
        min_fitness: Fitness below which a result counts as failed (``None``: 0.5 for learned methods, whose
            result below it also comes with a :class:`LowFitnessWarning` when no fallback is given; no check for
            classical methods, whose correct results on partial scans can have any fitness).
        threads: CPU threads of Open3D and torch during the call (``None``: their defaults); RANSAC always runs on
            one thread, so results do not depend on it.
        ransac_iterations: RANSAC's iteration limit in every step that runs it (``None``: 100,000, and the
            default's own limit in its fallback: :data:`DEFAULT`).

    Returns:
        :class:`Registration`: ``transform (4, 4)``, ``fitness``, ``inlier_rmse``, ``time_s`` and diagnostics.

    Raises:
        FileNotFoundError, lcreg.checks.PointCloudFileError: A missing, empty or damaged file (named).
        TypeError, lcreg.checks.ShapeError, lcreg.checks.TooFewPointsError: Bad clouds (the argument is named).
        lcreg.registration.methods.MethodError: Unknown method, or a learned method without weights.
        ValueError: A bad ``init``, ``voxel_size`` or count.
    """
    chosen, second, min_fitness, small = resolve_methods(method, refine, fallback, min_fitness, ransac_iterations)
    _check_options(voxel_size, target_points, learned_points)
    init_matrix = None if init is None else _check_init(init)
    cloud_src, cloud_ref = as_cloud(src, "points_src"), as_cloud(ref, "points_ref")
    with threads_limit(threads):
        return register_clouds(
            cloud_src,
            cloud_ref,
            chosen,
            weights=weights,
            voxel_size=voxel_size,
            init=init_matrix,
            target_points=target_points,
            learned_points=learned_points,
            seed=seed,
            fallback=second,
            min_fitness=min_fitness,
            small=small,
        )


def _check_options(voxel_size: float | None, target_points: int, learned_points: int) -> None:
    """Typed errors naming the option."""
    if voxel_size is not None and not (isinstance(voxel_size, (int, float)) and 0 < voxel_size < float("inf")):
        raise ValueError(f"`voxel_size` must be a finite number > 0 or None, got {voxel_size!r}")
    for name, value in (("target_points", target_points), ("learned_points", learned_points)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 16:
            raise ValueError(f"`{name}` must be an int >= 16, got {value!r}")
