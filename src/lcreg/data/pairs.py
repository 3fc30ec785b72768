"""The one registration-pair protocol shared by every object dataset (ModelNet40, synthetic shapes, ...).

A pair is made from one object (``P`` surface points, optional normals) as follows; every random draw comes from
the ``torch.Generator`` passed to :func:`make_pair`, so a seeded generator gives the same pair on any machine:

1. ``normalize``: the whole object is centred on its centroid and divided by its largest norm (unit sphere), before
   any sampling, so both clouds share one frame.
2. Two samplings of ``num_points`` points without replacement: independent ones (``independent_sampling``, the DVDs
   protocol: "sample N = 1024 points twice") or the same points in another order.
3. A DCP-protocol transform :func:`lcreg.geometry.random_transforms.random_euler_transform`: Euler angles
   ``[z, y, x]`` each ``U[0, max_angle_deg]``, translation ``U[-max_translation, max_translation]^3``.
   The reference is the transformed second sampling: ``points_ref = R @ second + t`` (``transform_ref_src``).
4. Partial visibility (optional) is decided here (directions drawn), applied in step 6.
5. Gaussian noise ``N(0, noise_sigma^2)`` clipped to ``±noise_clip``, drawn independently for each cloud and added
   after the transform (PRNet/IDAM style, never in place on the object). Noise is drawn last, so the same seed
   gives the same sampling, transform and crop with or without noise.
6. Crop: ``"prnet"`` keeps the ``partial_keep`` points of each cloud nearest to one shared far anchor
   (random unit direction × 500, the same anchor for the source and the already transformed reference, so the
   overlap is partial, as in PRNet/IDAM); ``"viewpoint"`` keeps, for an independent random direction per cloud,
   the points with the largest projection onto it (PointNetLK-style half-visibility). Kept points keep their
   sampling order.

Normals follow their points: the object's normals are renormalized to unit length and the reference normals are
rotated by ``R``. Outputs are CPU float32 tensors. With ``with_indices`` a pair also names the object row of each
kept point, from which :func:`true_correspondences` gives the exact point-to-point matches of a same-points pair
(what a correspondence-based method could find at best).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, get_args

import numpy as np
import torch

from lcreg.checks import (
    ShapeError,
    TooFewPointsError,
    check_count_or_fraction,
    check_finite,
    check_float,
    check_shape,
    resolve_count,
)
from lcreg.geometry.random_transforms import random_euler_transform
from lcreg.geometry.se3 import transform_normals, transform_points

__all__ = [
    "ANCHOR_DISTANCE",
    "ObjectSet",
    "PairProtocol",
    "PartialMode",
    "make_pair",
    "normalize_object",
    "true_correspondences",
]

PartialMode = Literal["none", "prnet", "viewpoint"]
_PARTIAL_MODES: tuple[str, ...] = get_args(PartialMode)

ANCHOR_DISTANCE = 500.0
"""Distance of the PRNet crop anchor from the origin (PRNet/IDAM use ``500 * (±1, ±1, ±1)`` plus ``U[0, 1)``)."""


@dataclass
class PairProtocol:
    """How registration pairs are generated from one object (see the module docstring for the steps).

    Attributes:
        num_points: Points ``N`` in each sampled cloud (before any partial crop).
        max_angle_deg: Each Euler angle is ``U[0, max_angle_deg]`` degrees.
        max_translation: Each translation component is ``U[-max_translation, max_translation]``.
        independent_sampling: Source and reference are two independent samplings of the object; ``False`` uses
            the same points (shuffled) for both.
        normalize: Centre the object on its centroid and scale it into the unit sphere before sampling.
        noise_sigma: Standard deviation of the Gaussian noise added to both clouds (0 disables it).
        noise_clip: Noise is clipped to ``[-noise_clip, noise_clip]`` per coordinate.
        partial: ``"none"``, ``"prnet"`` (shared far anchor) or ``"viewpoint"`` (one direction per cloud).
        partial_keep: Points kept per cloud by a crop: an ``int`` count or a ``float`` fraction in ``(0, 1]`` of
            ``num_points``. Ignored (but type-checked) when ``partial == "none"``.

    Raises:
        ValueError: On an invalid field; the message names it.
        TypeError: When ``partial_keep`` is neither an int nor a float.

    Example:
        >>> PairProtocol(num_points=1024, partial="prnet", partial_keep=0.75).num_kept
        768
    """

    num_points: int = 1024
    max_angle_deg: float = 45.0
    max_translation: float = 0.5
    independent_sampling: bool = True
    normalize: bool = True
    noise_sigma: float = 0.0
    noise_clip: float = 0.05
    partial: PartialMode = "none"
    partial_keep: int | float = 768

    def __post_init__(self) -> None:
        if isinstance(self.num_points, bool) or not isinstance(self.num_points, int) or self.num_points < 1:
            raise ValueError(f"`num_points` must be a positive int, got {self.num_points!r}")
        for name in ("max_angle_deg", "max_translation", "noise_sigma", "noise_clip"):
            value = getattr(self, name)
            if not math.isfinite(value) or value < 0:
                raise ValueError(f"`{name}` must be finite and >= 0, got {value!r}")
        if self.max_angle_deg > 180:
            raise ValueError(f"`max_angle_deg` must be <= 180, got {self.max_angle_deg!r}")
        if self.partial not in _PARTIAL_MODES:
            raise ValueError(f"`partial` must be one of {_PARTIAL_MODES}, got {self.partial!r}")
        keep = check_count_or_fraction(self.partial_keep, "partial_keep")
        if self.partial != "none" and isinstance(keep, int) and keep > self.num_points:
            raise ValueError(f"`partial_keep` ({keep}) must be <= `num_points` ({self.num_points}) for a crop")

    @property
    def num_kept(self) -> int:
        """Points in each output cloud: ``num_points`` without a crop, else the resolved ``partial_keep``."""
        if self.partial == "none":
            return self.num_points
        return resolve_count(self.partial_keep, self.num_points)


@dataclass
class ObjectSet:
    """Objects that pairs are drawn from (CPU arrays, one row per object).

    Attributes:
        points: ``(S, P, 3)`` float32 surface points.
        normals: ``(S, P, 3)`` unit normals or ``None``.
        labels: ``(S,)`` int64 class labels.

    Raises:
        ValueError: When the shapes disagree.
    """

    points: np.ndarray
    normals: np.ndarray | None
    labels: np.ndarray

    def __post_init__(self) -> None:
        if self.points.ndim != 3 or self.points.shape[-1] != 3:
            raise ShapeError("points", ("S", "P", 3), self.points.shape)
        if self.normals is not None and self.normals.shape != self.points.shape:
            raise ShapeError("normals", self.points.shape, self.normals.shape)
        if self.labels.shape != self.points.shape[:1]:
            raise ShapeError("labels", self.points.shape[:1], self.labels.shape)

    def __len__(self) -> int:
        return int(self.points.shape[0])

    def subset(self, indices: np.ndarray) -> ObjectSet:
        """The objects at ``indices`` (an int array or a boolean mask over ``S``)."""
        normals = None if self.normals is None else self.normals[indices]
        return ObjectSet(self.points[indices], normals, self.labels[indices])

    @staticmethod
    def concatenate(sets: list[ObjectSet]) -> ObjectSet:
        """Stack several sets (normals are kept only if every set has them)."""
        if not sets:
            raise ValueError("`sets` must not be empty")
        has_normals = all(s.normals is not None for s in sets)
        normals = np.concatenate([s.normals for s in sets if s.normals is not None]) if has_normals else None
        return ObjectSet(np.concatenate([s.points for s in sets]), normals, np.concatenate([s.labels for s in sets]))


def _validate_object(points: object, normals: object, num_points: int) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Check an object's points ``(P, 3)`` and normals and return them in float64."""
    pts = check_float(points, "points")
    check_shape(pts, ("P", 3), "points")
    check_finite(pts, "points")
    if pts.shape[0] < num_points:
        raise TooFewPointsError(
            f"`points` has {pts.shape[0]} points but the protocol samples num_points={num_points} without "
            "replacement; lower `num_points` or use denser objects"
        )
    if normals is None:
        return pts.double(), None
    nrm = check_float(normals, "normals")
    check_shape(nrm, (pts.shape[0], 3), "normals")
    check_finite(nrm, "normals")
    return pts.double(), nrm.double()


def normalize_object(points: torch.Tensor) -> torch.Tensor:
    """Centre ``(P, 3)`` points on their centroid and scale them so that the largest norm is 1 (the pairs' frame)."""
    centred = points - points.mean(dim=0, keepdim=True)
    scale = centred.norm(dim=-1).max()
    if not bool(scale > 0):
        raise ValueError("`points` are all identical; the object cannot be normalized")
    return centred / scale


def _unit(normals: torch.Tensor) -> torch.Tensor:
    """Rescale rows of ``(P, 3)`` to unit length (zero rows stay zero)."""
    return normals / normals.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def _random_direction(generator: torch.Generator) -> torch.Tensor:
    """A uniformly distributed unit vector ``(3,)`` (float64)."""
    d = torch.randn(3, generator=generator, dtype=torch.float64)
    return d / d.norm().clamp_min(1e-12)


def _crop_to_anchor(points: torch.Tensor, anchor: torch.Tensor, keep: int) -> torch.Tensor:
    """Indices ``(keep,)`` of the points ``(N, 3)`` nearest to ``anchor (3,)``, in their original order."""
    dist = (points - anchor).norm(dim=-1)
    return dist.topk(keep, largest=False).indices.sort().values


def _crop_to_view(points: torch.Tensor, direction: torch.Tensor, keep: int) -> torch.Tensor:
    """Indices ``(keep,)`` of the points ``(N, 3)`` with the largest projection on ``direction (3,)``, in order."""
    return (points @ direction).topk(keep).indices.sort().values


def _clipped_noise(shape: tuple[int, ...], sigma: float, clip: float, generator: torch.Generator) -> torch.Tensor:
    """Gaussian noise of ``shape`` with std ``sigma`` clipped to ``[-clip, clip]`` (float64)."""
    noise = torch.randn(shape, generator=generator, dtype=torch.float64) * sigma
    return noise.clamp(-clip, clip)


def make_pair(
    points: torch.Tensor,
    normals: torch.Tensor | None,
    protocol: PairProtocol,
    generator: torch.Generator,
    with_indices: bool = False,
) -> dict[str, torch.Tensor]:
    """Make one registration pair from one object following ``protocol``.

    Args:
        points: Object surface points ``(P, 3)`` (float32/float64, CPU), ``P >= protocol.num_points``.
        normals: Object normals ``(P, 3)`` or ``None``; they are renormalized to unit length.
        protocol: The pair protocol.
        generator: CPU generator that supplies every random draw.
        with_indices: Also return ``point_index_src`` / ``point_index_ref`` ``(K,)`` int64: the row of ``points``
            each kept point was sampled from (the random draws, hence the pair, are the same either way).

    Returns:
        A dict of CPU float32 tensors with ``K = protocol.num_kept``:

        * ``points_src`` ``(K, 3)``: the first sampling (normalized object frame);
        * ``points_ref`` ``(K, 3)``: the second sampling mapped by the ground truth, ``R p + t``;
        * ``normals_src`` / ``normals_ref`` ``(K, 3)`` (only when ``normals`` is given; the reference normals are
          rotated by ``R``);
        * ``transform_ref_src`` ``(4, 4)``: ``[R t; 0 1]``, maps source coordinates into the reference frame;
        * ``angles_zyx`` ``(3,)``: its Euler angles ``[z, y, x]`` in radians (DCP convention).

    Raises:
        TypeError: If ``points``/``normals`` are not float tensors.
        ShapeError: If they are not ``(P, 3)`` or disagree.
        NonFiniteError: On NaN/Inf input.
        TooFewPointsError: If ``P < protocol.num_points``.
        ValueError: If ``generator`` is not a CPU generator or the object is a single repeated point.

    Example:
        >>> g = torch.Generator().manual_seed(0)
        >>> pair = make_pair(torch.rand(2048, 3), None, PairProtocol(), g)
        >>> pair["points_src"].shape, pair["transform_ref_src"].shape
        (torch.Size([1024, 3]), torch.Size([4, 4]))
    """
    if generator.device.type != "cpu":
        raise ValueError(f"`generator` must be a CPU generator (pairs are built on the CPU), got {generator.device}")
    pts, nrm = _validate_object(points, normals, protocol.num_points)
    if protocol.normalize:
        pts = normalize_object(pts)
    if nrm is not None:
        nrm = _unit(nrm)

    # 1. Two samplings without replacement (the second is a reshuffle of the first when not independent).
    n = protocol.num_points
    idx_src = torch.randperm(pts.shape[0], generator=generator)[:n]
    if protocol.independent_sampling:
        idx_ref = torch.randperm(pts.shape[0], generator=generator)[:n]
    else:
        idx_ref = idx_src[torch.randperm(n, generator=generator)]

    # 2. Ground-truth transform; the reference is the transformed second sampling.
    transform, angles = random_euler_transform(
        1, protocol.max_angle_deg, protocol.max_translation, generator=generator, dtype=torch.float64
    )
    src = pts[idx_src]
    ref = transform_points(transform, pts[idx_ref][None])[0]
    nrm_src = nrm[idx_src] if nrm is not None else None
    nrm_ref = transform_normals(transform, nrm[idx_ref][None])[0] if nrm is not None else None

    # 3. Crop geometry (drawn before the noise so that noise does not change the rest of the pair).
    crop_src = crop_ref = None
    if protocol.partial == "prnet":
        crop_src = crop_ref = _random_direction(generator) * ANCHOR_DISTANCE
    elif protocol.partial == "viewpoint":
        crop_src, crop_ref = _random_direction(generator), _random_direction(generator)

    # 4. Independent clipped noise on both clouds, after the transform.
    if protocol.noise_sigma > 0:
        src = src + _clipped_noise(src.shape, protocol.noise_sigma, protocol.noise_clip, generator)
        ref = ref + _clipped_noise(ref.shape, protocol.noise_sigma, protocol.noise_clip, generator)

    # 5. Partial crop (noise first, then cut, as PRNet/IDAM).
    if crop_src is not None and crop_ref is not None:
        crop = _crop_to_anchor if protocol.partial == "prnet" else _crop_to_view
        keep_src = crop(src, crop_src, protocol.num_kept)
        keep_ref = crop(ref, crop_ref, protocol.num_kept)
        src, ref = src[keep_src], ref[keep_ref]
        idx_src, idx_ref = idx_src[keep_src], idx_ref[keep_ref]
        if nrm_src is not None and nrm_ref is not None:
            nrm_src, nrm_ref = nrm_src[keep_src], nrm_ref[keep_ref]

    out = {
        "points_src": src.float(),
        "points_ref": ref.float(),
        "transform_ref_src": transform[0].float(),
        "angles_zyx": angles[0].float(),
    }
    if nrm_src is not None and nrm_ref is not None:
        out["normals_src"] = nrm_src.float()
        out["normals_ref"] = nrm_ref.float()
    if with_indices:
        out["point_index_src"], out["point_index_ref"] = idx_src.long(), idx_ref.long()
    return out


def true_correspondences(index_src: torch.Tensor, index_ref: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The exact matches of a pair: the positions ``(i, j)`` where both clouds hold the same object point.

    Args:
        index_src: ``point_index_src`` of :func:`make_pair` (``with_indices=True``), ``(N,)`` int64.
        index_ref: ``point_index_ref``, ``(M,)`` int64.

    Returns:
        ``(rows_src (C,), rows_ref (C,))``: ``points_src[rows_src[c]]`` and ``points_ref[rows_ref[c]]`` are one
        object point before noise (``points_ref = R p + t``), ordered by ``rows_src``. ``C = 0`` for independent
        samplings that share no point.

    Raises:
        ShapeError: If either is not 1-D. TypeError: If either is not an integer tensor.
    """
    for name, value in (("index_src", index_src), ("index_ref", index_ref)):
        if value.dtype.is_floating_point or value.dtype == torch.bool:
            raise TypeError(f"`{name}` must be an integer tensor, got {value.dtype}")
        if value.ndim != 1:
            raise ShapeError(name, ("N",), value.shape)
    match = index_src[:, None] == index_ref[None, :]  # (N, M): rows of a sampling without replacement are unique
    rows_src, rows_ref = match.nonzero(as_tuple=True)
    return rows_src, rows_ref
