"""The methods of :func:`lcreg.register` by short name, and the steps they are made of.

A method is a coarse step, optionally followed by ICP refinement (``"ransac+icp"``):

==============  =======================================================================================
``icp``         point-to-plane ICP from the identity (or the initial guess): a local method
``ransac``      FPFH features + RANSAC (global: any initial pose)
``fgr``         FPFH features + Fast Global Registration (global)
``kiss``        KISS-Matcher (global; the optional package kiss-matcher, :mod:`lcreg.baselines.kiss`)
learned         ``dvds``, ``pointnetlk``, ``fmr``, ``dcp``, ``prnet``, ``idam``, ``deepgmr``, ``pcrnet``:
                the package's models with pretrained weights (a shipped name or a file): object-level
                models trained on unit-sphere objects with limited rotations; the clouds are centred on
                the reference's centroid, scaled to the unit sphere (``unit_scale``) and sampled to
                ``learned_points`` points, the transform is mapped back to the input's unit
==============  =======================================================================================

Every radius and gate is a multiple of one voxel size ``v`` (:mod:`lcreg.registration.voxel`), with the Open3D
registration example's factors: normals ``2v`` (30 neighbours), FPFH ``5v`` (100 neighbours), RANSAC inlier
distance ``1.5v`` (mutual filter, edge-length check 0.9, 100,000 iterations, confidence 0.999, seeded, one thread:
reproducible), FGR correspondence distance ``0.5v`` (absolute scale, annealed), ICP gate ``2v`` (point-to-plane,
at most 100 iterations), KISS-Matcher its own gains in voxels (normals ``3v``, FPFH ``5v``, sampling at ``v``).
Clouds with more than the target number of points are voxel-downsampled at ``v`` first.
"""

from __future__ import annotations

import contextlib
import functools
from collections import OrderedDict
from collections.abc import Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from lcreg.methods import METHODS

if TYPE_CHECKING:
    from lcreg.baselines.classical import FGR, ICP, RANSAC, PairResult
    from lcreg.baselines.kiss import KISSMatcher
    from lcreg.models.base import RegistrationModule

__all__ = [
    "CLASSICAL",
    "LEARNED",
    "RANSAC_ITERATIONS",
    "Method",
    "MethodError",
    "Prepared",
    "PreparedCache",
    "available_methods",
    "parse_method",
]

CLASSICAL: dict[str, str] = {name: info.summary for name, info in METHODS.items() if not info.learned}
"""The classical methods: name -> one line (from :data:`lcreg.methods.METHODS`)."""
LEARNED: dict[str, str] = {name: info.class_path for name, info in METHODS.items() if info.learned}
"""The learned methods: name -> class path (from :data:`lcreg.methods.METHODS`)."""
REFINERS = ("icp",)
GLOBAL_STEPS = ("ransac", "fgr", "kiss")
"""Coarse steps that need no initial pose."""
NORMAL_FACTOR, FEATURE_FACTOR = 2.0, 5.0
RANSAC_DISTANCE, FGR_DISTANCE, ICP_DISTANCE = 1.5, 0.5, 2.0
FITNESS_DISTANCE = 2.0
"""Fitness / inlier RMSE gate of the result, in voxels."""


class MethodError(ValueError):
    """An unknown method name, or a learned method without usable weights."""


RANSAC_ITERATIONS = 100_000
"""RANSAC's iteration limit unless a method says otherwise (``Method.ransac_iterations``, ``--ransac-iterations``)."""


@dataclass(frozen=True)
class Method:
    """A parsed method: ``coarse`` step and optional ``refine`` step (``"icp"``).

    Attributes:
        coarse: A key of :data:`CLASSICAL` or :data:`LEARNED`.
        refine: ``"icp"`` or ``None``.
        ransac_iterations: RANSAC's iteration limit (``None``: :data:`RANSAC_ITERATIONS`); other steps ignore it.
    """

    coarse: str
    refine: str | None = None
    ransac_iterations: int | None = None

    @property
    def name(self) -> str:
        """``coarse`` or ``coarse+refine``."""
        return self.coarse if self.refine is None else f"{self.coarse}+{self.refine}"

    @property
    def learned(self) -> bool:
        """The coarse step is a network."""
        return self.coarse in LEARNED


def available_methods() -> list[str]:
    """Every accepted method name (single steps and ``+icp`` pipelines)."""
    singles = [*CLASSICAL, *LEARNED]
    return [*singles, *(f"{m}+icp" for m in singles if m != "icp")]


def parse_method(name: str, refine: str | None = None) -> Method:
    """``"ransac+icp"`` → ``Method("ransac", "icp")``; ``refine`` adds a refinement to a single step.

    Raises:
        MethodError: An unknown name or refinement (the message lists the valid ones).
    """
    coarse, _, tail = str(name).strip().lower().partition("+")
    step = tail or (None if refine in (None, "none") else refine)
    if coarse not in CLASSICAL and coarse not in LEARNED:
        raise MethodError(f"unknown method {name!r}; available: {', '.join(available_methods())}")
    if step is not None and (step not in REFINERS or coarse == "icp"):
        raise MethodError(f"unknown refinement {step!r} for {coarse!r}; available: icp (after any step but icp)")
    return Method(coarse, step)


@dataclass
class Prepared:
    """One cloud made ready at one voxel size: an Open3D cloud (downsampled when large), normals and FPFH on demand.

    Attributes:
        points: ``(N', 3)`` float64 points used by the steps (downsampled or all).
        voxel_size: ``v``.
    """

    points: np.ndarray
    voxel_size: float
    _pcd: Any = None
    _normals: bool = False
    _features: Any = None

    @classmethod
    def make(cls, points: np.ndarray, voxel_size: float, target: int) -> Prepared:
        """Keep ``points`` when there are at most ``target``, else their voxel grid at ``voxel_size``."""
        from lcreg.data.io import voxel_downsample

        kept = points if len(points) <= target else voxel_downsample(points, voxel_size)
        return cls(np.ascontiguousarray(kept, dtype=np.float64), voxel_size)

    @property
    def pcd(self) -> Any:
        """The Open3D cloud of :attr:`points`."""
        if self._pcd is None:
            import open3d as o3d

            self._pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(self.points))
        return self._pcd

    def with_normals(self) -> Any:
        """:attr:`pcd` with normals at ``2v`` (computed once)."""
        if not self._normals:
            from lcreg.baselines.classical import estimate_normals

            estimate_normals(self.pcd, NORMAL_FACTOR * self.voxel_size, 30)
            self._normals = True
        return self.pcd

    def features(self) -> Any:
        """FPFH features at ``5v`` (computed once)."""
        if self._features is None:
            from lcreg.baselines.classical import compute_fpfh

            self._features = compute_fpfh(self.with_normals(), FEATURE_FACTOR * self.voxel_size, 100)
        return self._features


class PreparedCache:
    """Prepared clouds by ``(key, voxel size)``, least recently used dropped beyond ``size`` (many pairs share files).

    Args:
        size: Clouds kept.
    """

    def __init__(self, size: int = 64) -> None:
        self.size = size
        self._items: OrderedDict[tuple[str, float], Prepared] = OrderedDict()

    def get(self, key: str | None, points: np.ndarray, voxel_size: float, target: int) -> Prepared:
        """The prepared cloud of ``points`` (cached under ``key`` unless it is ``None``)."""
        if key is None:
            return Prepared.make(points, voxel_size, target)
        item = self._items.get((key, voxel_size))
        if item is None:
            item = Prepared.make(points, voxel_size, target)
            self._items[(key, voxel_size)] = item
            while len(self._items) > self.size:
                self._items.popitem(last=False)
        self._items.move_to_end((key, voxel_size))
        return item


@contextlib.contextmanager
def threads(count: int | None) -> Iterator[None]:
    """Open3D's and torch's CPU threads set to ``count`` inside the block (``None``: unchanged), then restored.

    Normals, FPFH, ICP, FGR and the networks use them; RANSAC keeps one thread (reproducible, ``deterministic``);
    KISS-Matcher schedules its own threads (TBB).

    Raises:
        ValueError: ``count`` is not an int >= 1.
    """
    if count is None:
        yield
        return
    if isinstance(count, bool) or not isinstance(count, int) or count < 1:
        raise ValueError(f"`threads` must be an int >= 1 or None, got {count!r}")
    import open3d as o3d

    previous = (o3d.utility.get_max_threads(), torch.get_num_threads())
    o3d.utility.set_max_threads(count)
    torch.set_num_threads(count)
    try:
        yield
    finally:
        o3d.utility.set_max_threads(previous[0])
        torch.set_num_threads(previous[1])


@functools.lru_cache(maxsize=16)
def _ransac(voxel_size: float, iterations: int = RANSAC_ITERATIONS) -> RANSAC:
    from lcreg.baselines.classical import RANSAC

    return RANSAC(voxel_size=voxel_size, distance_factor=RANSAC_DISTANCE, max_iterations=iterations)


@functools.lru_cache(maxsize=16)
def _fgr(voxel_size: float) -> FGR:
    from lcreg.baselines.classical import FGR

    return FGR(voxel_size=voxel_size, distance_factor=FGR_DISTANCE, use_absolute_scale=True)


@functools.lru_cache(maxsize=16)
def _icp(voxel_size: float) -> ICP:
    from lcreg.baselines.classical import ICP

    return ICP(voxel_size=voxel_size, method="point_to_plane", distance_factor=ICP_DISTANCE)


@functools.lru_cache(maxsize=16)
def _kiss(voxel_size: float) -> KISSMatcher:
    from lcreg.baselines.kiss import KISSMatcher

    return KISSMatcher(voxel_size=voxel_size, distance_factor=FITNESS_DISTANCE)


def global_step(name: str, src: Prepared, ref: Prepared, ransac_iterations: int | None = None) -> PairResult:
    """RANSAC or FGR on two prepared clouds (their FPFH features are computed once and cached), or KISS-Matcher.

    Args:
        name: ``"ransac"``, ``"fgr"`` or ``"kiss"``.
        src: Prepared source.
        ref: Prepared reference.
        ransac_iterations: RANSAC's iteration limit (``None``: :data:`RANSAC_ITERATIONS`).

    Raises:
        lcreg.checks.MissingDependencyError: ``kiss`` without the optional package kiss-matcher.
    """
    if name == "kiss":
        return _kiss(src.voxel_size).register_pair(src.pcd, ref.pcd, None)
    iterations = RANSAC_ITERATIONS if ransac_iterations is None else ransac_iterations
    solver = _ransac(src.voxel_size, iterations) if name == "ransac" else _fgr(src.voxel_size)
    return solver.register_featured(src.pcd, ref.pcd, src.features(), ref.features())


def icp_step(src: Prepared, ref: Prepared, init: np.ndarray) -> PairResult:
    """Point-to-plane ICP from ``init (4, 4)``."""
    ref.with_normals()
    return _icp(src.voxel_size).register_pair(src.pcd, ref.pcd, init)


def evaluate(src: Prepared, ref: Prepared, transform: np.ndarray) -> tuple[float, float]:
    """``(fitness, inlier RMSE)`` of ``transform`` at the gate ``FITNESS_DISTANCE * v`` (Open3D)."""
    import open3d as o3d

    gate = FITNESS_DISTANCE * src.voxel_size
    out = o3d.pipelines.registration.evaluate_registration(src.pcd, ref.pcd, gate, transform)
    return float(out.fitness), float(out.inlier_rmse)


@functools.lru_cache(maxsize=8)
def learned_model(method: str, weights: str | None) -> RegistrationModule:
    """The network of ``method`` with ``weights`` (a shipped name, an exported ``.pt`` or a ``.ckpt``), eval mode.

    ``weights=None`` uses the shipped weights of that class when there are some.

    Raises:
        MethodError: No weights given and none shipped for this method.
        lcreg.checkpoints.CheckpointError: Unusable weights (naming the file).
    """
    from lcreg import weights as registry

    class_path = LEARNED[method]
    if weights is None:
        shipped = [n for n in registry.shipped_names() if registry.REGISTRY[n].class_path == class_path]
        if not shipped:
            names = ", ".join(registry.shipped_names()) or "none"
            raise MethodError(
                f"method {method!r} has no shipped weights (shipped: {names}); pass weights (`--weights`, "
                "`weights=`): the path of a checkpoint of `lcreg fit` (.ckpt) or of an exported .pt file"
            )
        weights = shipped[0]
    model = registry.pretrained(weights, unit_scale=1.0)  # a name, an exported .pt or a .ckpt: one loader
    if registry.class_path_of(model) != class_path:
        found = registry.class_path_of(model)
        raise MethodError(f"weights {weights!r} hold a {found}, method {method!r} needs {class_path}")
    return model.eval()


def learned_step(model: RegistrationModule, src: np.ndarray, ref: np.ndarray, num_points: int, seed: int) -> np.ndarray:
    """The network's ``(4, 4)`` estimate on ``num_points`` points of each cloud, centred on the reference centroid.

    Args:
        model: A learned model with ``unit_scale`` set (it scales the pair to its training scale).
        src: ``(N, 3)`` source points.
        ref: ``(M, 3)`` reference points.
        num_points: Points sampled per cloud (without replacement; repeated when a cloud has fewer).
        seed: Seed of the samples.

    Returns:
        ``(4, 4)`` float64 mapping ``src`` into ``ref``'s frame.
    """
    rng = np.random.default_rng(seed)
    centre = ref.mean(axis=0)

    def sample(points: np.ndarray) -> torch.Tensor:
        idx = rng.permutation(len(points))[:num_points]
        if len(idx) < num_points:
            idx = np.concatenate([idx, rng.integers(len(points), size=num_points - len(idx))])
        return torch.from_numpy(points[idx] - centre).float()[None]

    with torch.no_grad():
        out = model.register(sample(src), sample(ref)).transform_ref_src[0].double().cpu().numpy()
    shift = np.eye(4)
    shift[:3, 3] = centre
    back = np.eye(4)
    back[:3, 3] = -centre
    return shift @ out @ back
