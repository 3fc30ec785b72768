"""Procedural asymmetric shapes with analytic normals: the embedded default dataset (no files, seed-determined).

Each shape is a union of 2 to 4 primitives, each an ellipsoid, box, cylinder, cone or torus with random sizes, a
uniformly random rotation and a random offset, so shapes have no rotational symmetry (generically). Points are
sampled uniformly by area on every primitive surface (rejection sampling for the ellipsoid and the torus), and
each point carries the analytic outward normal of its primitive. Points of one primitive that lie inside another
are kept (the union's interior surfaces are not removed), which does not matter for registration. Every shape is
then centred on its centroid and scaled into the unit sphere (normals are unchanged by this).

Primitive parameters ``size = (a, b, c)`` (local frame, before the pose):

* ``ellipsoid``: semi-axes ``a, b, c``;
* ``box``: half extents ``a, b, c``;
* ``cylinder``: radius ``a``, axis ``z`` from ``-c`` to ``c`` (``b`` unused), with both caps;
* ``cone``: base radius ``a`` at ``z = -c``, apex at ``z = c`` (``b`` unused), with the base disc;
* ``torus``: major radius ``a`` around ``z``, minor radius ``min(b, a / 2)`` (``c`` unused).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

__all__ = ["PRIMITIVES", "primitive_area", "sample_primitive", "synthetic_shapes"]

PRIMITIVES = ("ellipsoid", "box", "cylinder", "cone", "torus")
"""Primitive kinds; a shape's label is the index of its first primitive's kind in this tuple."""

_Sampler = Callable[[np.ndarray, np.random.Generator], tuple[np.ndarray, np.ndarray]]


def _unit(v: np.ndarray) -> np.ndarray:
    """Rows of ``(n, 3)`` scaled to unit length."""
    return v / np.maximum(np.sqrt(np.einsum("...i,...i->...", v, v)), 1e-12)[..., None]


def _unit_sphere(n: int, rng: np.random.Generator) -> np.ndarray:
    """``(n, 3)`` uniform points on the unit sphere."""
    return _unit(rng.normal(size=(n, 3)))


def _torus_radii(sizes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Major and minor radii ``(n,)`` of tori with parameters ``(n, 3)``."""
    return sizes[:, 0], np.minimum(sizes[:, 1], sizes[:, 0] / 2)


def _sample_ellipsoid(sizes: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Area-uniform points and normals on ellipsoids with semi-axes ``sizes (n, 3)`` (one point per row)."""
    n = sizes.shape[0]
    u = np.empty((n, 3))
    todo = np.arange(n)
    while todo.size:
        cand = _unit_sphere(todo.size, rng)
        axes = sizes[todo]
        # The map u -> axes * u stretches the sphere's area by abc * |u / axes|; accept proportionally.
        ratio = np.linalg.norm(cand / axes, axis=-1) * axes.min(axis=-1)
        ok = rng.random(todo.size) < ratio
        u[todo[ok]] = cand[ok]
        todo = todo[~ok]
    return u * sizes, _unit(u / sizes)  # gradient of sum (x_i / a_i)^2 is 2 x_i / a_i^2 = 2 u_i / a_i


def _sample_box(sizes: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Area-uniform points and normals on boxes with half extents ``sizes (n, 3)``."""
    n = sizes.shape[0]
    face_area = sizes[:, [1, 0, 0]] * sizes[:, [2, 2, 1]]  # area of the faces orthogonal to x, y, z
    cum = np.cumsum(face_area, axis=-1)
    pick = rng.random(n) * cum[:, -1]
    axis = (pick > cum[:, 0]).astype(int) + (pick > cum[:, 1]).astype(int)
    sign = np.where(rng.random(n) < 0.5, -1.0, 1.0)
    rows = np.arange(n)
    points = rng.uniform(-1.0, 1.0, size=(n, 3)) * sizes
    points[rows, axis] = sign * sizes[rows, axis]
    normals = np.zeros((n, 3))
    normals[rows, axis] = sign
    return points, normals


def _sample_cylinder(sizes: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Area-uniform points and normals on closed cylinders (radius ``a``, half height ``c``)."""
    n = sizes.shape[0]
    a, c = sizes[:, 0], sizes[:, 2]
    side = rng.random(n) < (2 * c) / (2 * c + a)  # side 4 pi a c vs. caps 2 pi a^2
    theta = rng.uniform(0, 2 * np.pi, n)
    cos, sin = np.cos(theta), np.sin(theta)
    rho = np.where(side, a, a * np.sqrt(rng.random(n)))
    cap_sign = np.where(rng.random(n) < 0.5, -1.0, 1.0)
    z = np.where(side, rng.uniform(-1.0, 1.0, n) * c, cap_sign * c)
    points = np.stack([rho * cos, rho * sin, z], axis=-1)
    normals = np.where(side[:, None], np.stack([cos, sin, 0 * z], -1), np.stack([0 * z, 0 * z, cap_sign], -1))
    return points, normals


def _sample_cone(sizes: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Area-uniform points and normals on closed cones (base radius ``a`` at ``z=-c``, apex at ``z=c``)."""
    n = sizes.shape[0]
    a, c = sizes[:, 0], sizes[:, 2]
    height = 2 * c
    slant = np.sqrt(a**2 + height**2)
    lateral = rng.random(n) < slant / (slant + a)  # lateral pi a L vs. base pi a^2
    theta = rng.uniform(0, 2 * np.pi, n)
    cos, sin = np.cos(theta), np.sin(theta)
    frac = np.sqrt(rng.random(n))  # area grows linearly with the distance from the apex (or the base centre)
    rho = a * frac
    z = np.where(lateral, c - height * frac, -c)
    points = np.stack([rho * cos, rho * sin, z], axis=-1)
    side_normal = np.stack([height * cos, height * sin, a], axis=-1) / slant[:, None]
    base_normal = np.stack([0 * z, 0 * z, -np.ones(n)], axis=-1)
    return points, np.where(lateral[:, None], side_normal, base_normal)


def _sample_torus(sizes: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Area-uniform points and normals on tori (major radius ``a`` around ``z``, minor ``min(b, a/2)``)."""
    n = sizes.shape[0]
    major, minor = _torus_radii(sizes)
    phi = np.empty(n)
    todo = np.arange(n)
    while todo.size:
        cand = rng.uniform(0, 2 * np.pi, todo.size)
        # The area element is proportional to R + r cos(phi).
        ok = rng.random(todo.size) * (major[todo] + minor[todo]) < major[todo] + minor[todo] * np.cos(cand)
        phi[todo[ok]] = cand[ok]
        todo = todo[~ok]
    theta = rng.uniform(0, 2 * np.pi, n)
    normals = np.stack([np.cos(phi) * np.cos(theta), np.cos(phi) * np.sin(theta), np.sin(phi)], axis=-1)
    centre = np.stack([major * np.cos(theta), major * np.sin(theta), 0 * theta], axis=-1)
    return centre + minor[:, None] * normals, normals


_SAMPLERS: dict[str, _Sampler] = {
    "ellipsoid": _sample_ellipsoid,
    "box": _sample_box,
    "cylinder": _sample_cylinder,
    "cone": _sample_cone,
    "torus": _sample_torus,
}


def _areas(kinds: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """Surface areas ``(m,)`` of primitives with kind indices ``(m,)`` and parameters ``(m, 3)``."""
    a, b, c = sizes[:, 0], sizes[:, 1], sizes[:, 2]
    p = 1.6075  # Knud Thomsen's approximation of the ellipsoid area (relative error < 1.1 %)
    ellipsoid = 4 * np.pi * (((a * b) ** p + (a * c) ** p + (b * c) ** p) / 3) ** (1 / p)
    box = 8 * (a * b + b * c + a * c)
    cylinder = 4 * np.pi * a * c + 2 * np.pi * a**2
    cone = np.pi * a * np.sqrt(a**2 + 4 * c**2) + np.pi * a**2
    major, minor = _torus_radii(sizes)
    torus = 4 * np.pi**2 * major * minor
    return np.choose(kinds, [ellipsoid, box, cylinder, cone, torus])


def primitive_area(kind: str, size: np.ndarray | tuple[float, float, float]) -> float:
    """Surface area of one primitive (the ellipsoid uses Thomsen's approximation, within 1.1 %).

    Args:
        kind: One of :data:`PRIMITIVES`.
        size: Its parameters ``(3,)`` (see the module docstring).

    Returns:
        The area.

    Raises:
        ValueError: On an unknown ``kind`` or a ``size`` that is not three positive numbers.
    """
    sizes = _check_primitive(kind, size)
    return float(_areas(np.array([PRIMITIVES.index(kind)]), sizes[None])[0])


def _check_primitive(kind: str, size: np.ndarray | tuple[float, float, float]) -> np.ndarray:
    """Validate a primitive kind and its ``(3,)`` parameters, returned as float64."""
    if kind not in _SAMPLERS:
        raise ValueError(f"`kind` must be one of {PRIMITIVES}, got {kind!r}")
    sizes = np.asarray(size, dtype=np.float64)
    if sizes.shape != (3,) or not bool(np.all(sizes > 0)) or not bool(np.all(np.isfinite(sizes))):
        raise ValueError(f"`size` must be three positive finite numbers, got {size!r}")
    return sizes


def sample_primitive(
    kind: str, size: np.ndarray | tuple[float, float, float], num_points: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Sample one primitive surface in its local frame, uniformly by area.

    Args:
        kind: One of :data:`PRIMITIVES`.
        size: Its parameters ``(3,)`` (see the module docstring).
        num_points: Number of points ``n``.
        rng: NumPy generator.

    Returns:
        ``(points (n, 3), normals (n, 3))`` float64, normals are unit and point outwards.

    Raises:
        ValueError: On an unknown ``kind``, a bad ``size`` or a negative ``num_points``.

    Example:
        >>> pts, nrm = sample_primitive("ellipsoid", (0.5, 0.3, 0.2), 100, np.random.default_rng(0))
        >>> pts.shape, bool(np.allclose(np.linalg.norm(nrm, axis=1), 1.0))
        ((100, 3), True)
    """
    sizes = _check_primitive(kind, size)
    if num_points < 0:
        raise ValueError(f"`num_points` must be >= 0, got {num_points}")
    return _SAMPLERS[kind](np.broadcast_to(sizes, (num_points, 3)).copy(), rng)


def _random_rotations(m: int, rng: np.random.Generator) -> np.ndarray:
    """``(m, 3, 3)`` uniformly random rotations (normalised Gaussian quaternions)."""
    w, x, y, z = _unit(rng.normal(size=(m, 4))).T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=-2,
    )


def synthetic_shapes(
    num_shapes: int, points_per_shape: int = 2048, seed: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Generate random asymmetric shapes (unions of 2-4 posed primitives), deterministically from ``seed``.

    Args:
        num_shapes: Number of shapes ``S``.
        points_per_shape: Points ``P`` per shape.
        seed: Seed of the NumPy generator; the same arguments always give the same arrays.

    Returns:
        ``(points (S, P, 3) float32, normals (S, P, 3) float32, labels (S,) int64)``: points in the unit sphere
        (centred, largest norm 1) in random order, unit outward normals of their primitive, and the label of each
        shape (the :data:`PRIMITIVES` index of its first primitive).

    Raises:
        ValueError: If ``num_shapes < 0`` or ``points_per_shape < 1``.

    Example:
        >>> points, normals, labels = synthetic_shapes(4, 256, seed=0)
        >>> points.shape, normals.shape, labels.shape
        ((4, 256, 3), (4, 256, 3), (4,))
    """
    if num_shapes < 0:
        raise ValueError(f"`num_shapes` must be >= 0, got {num_shapes}")
    if points_per_shape < 1:
        raise ValueError(f"`points_per_shape` must be >= 1, got {points_per_shape}")
    rng = np.random.default_rng(seed)
    s, p = num_shapes, points_per_shape

    # Shape structure: primitives per shape, kinds, sizes, poses (the first primitive sits at the origin).
    counts = rng.integers(2, 5, size=s)
    m = int(counts.sum())
    first = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(int) if s else np.zeros(0, dtype=int)
    kinds = rng.integers(0, len(PRIMITIVES), size=m)
    sizes = rng.uniform(0.15, 0.6, size=(m, 3))
    rotations = _random_rotations(m, rng)
    offsets = rng.uniform(-0.4, 0.4, size=(m, 3))
    offsets[first] = 0.0

    # Points per primitive proportional to its area (padded to 4 primitives per shape).
    slot = np.arange(m) - np.repeat(first, counts)
    area = np.zeros((s, 4))
    area[np.repeat(np.arange(s), counts), slot] = _areas(kinds, sizes)
    per_slot = rng.multinomial(p, area / area.sum(axis=-1, keepdims=True)) if s else np.zeros((0, 4), int)
    prim = np.repeat(np.arange(m), per_slot[np.repeat(np.arange(s), counts), slot])  # primitive of each point
    prim = rng.permuted(prim.reshape(s, p), axis=1).reshape(-1)  # random point order within each shape

    # Sample every kind at once, then pose the local points.
    local = np.empty((s * p, 3))
    local_normals = np.empty((s * p, 3))
    for k, name in enumerate(PRIMITIVES):
        sel = np.flatnonzero(kinds[prim] == k)
        local[sel], local_normals[sel] = _SAMPLERS[name](sizes[prim[sel]], rng)
    rot = rotations.astype(np.float32)[prim]
    points = (np.einsum("nij,nj->ni", rot, local.astype(np.float32)) + offsets[prim]).reshape(s, p, 3)
    normals = np.einsum("nij,nj->ni", rot, local_normals.astype(np.float32)).reshape(s, p, 3)

    # Unit sphere (normals are invariant).
    points = points - points.mean(axis=1, keepdims=True)
    radius = np.sqrt(np.einsum("spi,spi->sp", points, points)).max(axis=1, initial=0.0)
    points = points / np.maximum(radius, 1e-12)[:, None, None]
    labels = kinds[first].astype(np.int64)
    return points.astype(np.float32), _unit(normals).astype(np.float32), labels
