from __future__ import annotations

import time

import numpy as np
import pytest

from lcreg.data.synthetic import PRIMITIVES, primitive_area, sample_primitive, synthetic_shapes

SIZE = np.array([0.5, 0.3, 0.2])


def _implicit(kind: str, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Implicit surface value ``F(p)`` (0 on the surface) and its gradient for the smooth primitives."""
    x, y, z = p.T
    a, b, c = SIZE
    if kind == "ellipsoid":
        value = (x / a) ** 2 + (y / b) ** 2 + (z / c) ** 2 - 1
        grad = np.stack([2 * x / a**2, 2 * y / b**2, 2 * z / c**2], -1)
        return value, grad
    if kind == "torus":
        major, minor = a, min(b, a / 2)
        rho = np.hypot(x, y)
        value = (rho - major) ** 2 + z**2 - minor**2
        grad = np.stack([2 * (rho - major) * x / rho, 2 * (rho - major) * y / rho, 2 * z], -1)
        return value, grad
    raise AssertionError(kind)


@pytest.mark.parametrize("kind", ["ellipsoid", "torus"])
def test_smooth_primitive_normals_are_normalized_gradients(kind: str) -> None:
    points, normals = sample_primitive(kind, SIZE, 2000, np.random.default_rng(0))
    value, grad = _implicit(kind, points)
    np.testing.assert_allclose(value, 0.0, atol=1e-12)
    np.testing.assert_allclose(normals, grad / np.linalg.norm(grad, axis=-1, keepdims=True), atol=1e-12)


def test_box_points_on_faces_with_axis_normals() -> None:
    points, normals = sample_primitive("box", SIZE, 3000, np.random.default_rng(0))
    assert np.all(np.abs(points) <= SIZE + 1e-12)
    axis = np.abs(normals).argmax(axis=-1)
    rows = np.arange(len(points))
    np.testing.assert_allclose(np.abs(normals).sum(-1), 1.0)
    np.testing.assert_allclose(points[rows, axis], normals[rows, axis] * SIZE[axis])  # on the face the normal leaves
    # Area-uniform: face pairs get points in proportion to their areas (bc : ac : ab).
    share = np.bincount(axis, minlength=3) / len(points)
    area = np.array([SIZE[1] * SIZE[2], SIZE[0] * SIZE[2], SIZE[0] * SIZE[1]])
    np.testing.assert_allclose(share, area / area.sum(), atol=0.03)


def test_cylinder_and_cone_surfaces_and_normals() -> None:
    a, _, c = SIZE
    points, normals = sample_primitive("cylinder", SIZE, 2000, np.random.default_rng(0))
    rho = np.hypot(points[:, 0], points[:, 1])
    side = np.abs(normals[:, 2]) < 0.5
    np.testing.assert_allclose(rho[side], a)
    np.testing.assert_allclose(normals[side, :2], points[side, :2] / a)
    np.testing.assert_allclose(np.abs(points[~side, 2]), c)
    assert np.all(rho[~side] <= a + 1e-12) and np.all(points[~side, 2] * normals[~side, 2] > 0)

    points, normals = sample_primitive("cone", SIZE, 2000, np.random.default_rng(0))
    rho = np.hypot(points[:, 0], points[:, 1])
    base = normals[:, 2] < -0.99
    np.testing.assert_allclose(points[base, 2], -c)
    lateral = ~base
    np.testing.assert_allclose(rho[lateral], a * (c - points[lateral, 2]) / (2 * c), atol=1e-12)  # on the slant
    # Lateral normal = normalized gradient of rho - a (c - z) / (2c).
    grad = np.concatenate([points[lateral, :2] / rho[lateral, None], np.full((lateral.sum(), 1), a / (2 * c))], -1)
    np.testing.assert_allclose(normals[lateral], grad / np.linalg.norm(grad, axis=-1, keepdims=True), atol=1e-9)


@pytest.mark.parametrize("kind", PRIMITIVES)
def test_primitive_normals_are_unit_and_outward(kind: str) -> None:
    points, normals = sample_primitive(kind, SIZE, 1000, np.random.default_rng(1))
    np.testing.assert_allclose(np.linalg.norm(normals, axis=-1), 1.0, atol=1e-12)
    # Moving along the normal leaves the solid: the point gets farther from the primitive's centre (or axis circle).
    if kind != "torus":
        assert np.all(np.einsum("ni,ni->n", points, normals) > 0)
    assert primitive_area(kind, SIZE) > 0


def test_primitive_validation() -> None:
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="kind"):
        sample_primitive("sphere", SIZE, 10, rng)
    with pytest.raises(ValueError, match="size"):
        sample_primitive("box", (1.0, -1.0, 1.0), 10, rng)
    with pytest.raises(ValueError, match="num_points"):
        sample_primitive("box", SIZE, -1, rng)


def test_shapes_shapes_dtypes_and_unit_sphere() -> None:
    points, normals, labels = synthetic_shapes(16, 512, seed=0)
    assert points.shape == (16, 512, 3) and normals.shape == (16, 512, 3) and labels.shape == (16,)
    assert points.dtype == np.float32 and normals.dtype == np.float32 and labels.dtype == np.int64
    np.testing.assert_allclose(np.linalg.norm(normals, axis=-1), 1.0, atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(points, axis=-1).max(axis=1), 1.0, atol=1e-6)
    np.testing.assert_allclose(points.mean(axis=1), 0.0, atol=1e-5)
    assert labels.min() >= 0 and labels.max() < len(PRIMITIVES)


def test_shapes_are_deterministic_per_seed() -> None:
    a = synthetic_shapes(8, 256, seed=3)
    b = synthetic_shapes(8, 256, seed=3)
    c = synthetic_shapes(8, 256, seed=4)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    assert not np.allclose(a[0], c[0])


def test_shapes_are_not_rotationally_symmetric() -> None:
    points, _, _ = synthetic_shapes(64, 1024, seed=0)
    cov = np.einsum("spi,spj->sij", points, points) / points.shape[1]
    ev = np.linalg.eigvalsh(cov)  # ascending
    gap = np.minimum(ev[:, 1] - ev[:, 0], ev[:, 2] - ev[:, 1]) / ev[:, 2]
    assert np.all(gap > 1e-3)  # three distinct principal axes: no axis of continuous symmetry


def test_shapes_are_fast_and_validate_arguments() -> None:
    start = time.perf_counter()
    synthetic_shapes(512, 2048, seed=0)
    assert time.perf_counter() - start < 3.0  # about 0.4 s on 2 loaded cores
    assert synthetic_shapes(0, 16)[0].shape == (0, 16, 3)
    with pytest.raises(ValueError, match="num_shapes"):
        synthetic_shapes(-1)
    with pytest.raises(ValueError, match="points_per_shape"):
        synthetic_shapes(2, 0)


def test_posed_shape_normals_are_orthogonal_to_the_local_surface() -> None:
    points, normals, _ = synthetic_shapes(3, 1024, seed=0)
    for p, n in zip(points.astype(np.float64), normals.astype(np.float64)):
        d = ((p[:, None] - p[None]) ** 2).sum(-1)
        np.fill_diagonal(d, np.inf)
        nearest = np.argpartition(d, 4, axis=1)[:, :4]
        chords = p[nearest] - p[:, None]
        cos = np.abs(np.einsum("nki,ni->nk", chords, n)) / np.linalg.norm(chords, axis=-1)
        assert np.median(cos) < 0.15  # random unit normals give about 0.5
