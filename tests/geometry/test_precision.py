"""Geometry under autocast: float32 arithmetic whatever autocast asks for, the same numbers as without it."""

from __future__ import annotations

import inspect
from collections.abc import Callable
from types import ModuleType

import pytest
import torch

from lcreg.geometry import chamfer, euler, neighbors, normals, procrustes, rri, se3, so3
from lcreg.geometry.precision import full_precision, upcast_reduced
from lcreg.geometry.random_transforms import random_rotation

BF16 = torch.bfloat16


def _problem(seed: int = 0) -> dict[str, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    src = torch.randn(3, 40, 3, generator=gen)
    transform = se3.make_transform(random_rotation(3, gen), torch.randn(3, 3, generator=gen))
    ref = se3.transform_points(transform, src) + 0.01 * torch.randn(3, 40, 3, generator=gen)
    weights = torch.rand(3, 40, generator=gen)
    twist = 0.3 * torch.randn(3, 6, generator=gen)
    return {"src": src, "ref": ref, "transform": transform, "weights": weights, "twist": twist}


CALLS: dict[str, Callable[[dict[str, torch.Tensor]], object]] = {
    "weighted_kabsch": lambda p: procrustes.weighted_kabsch(p["src"], p["ref"], p["weights"]),
    "compose": lambda p: se3.compose(p["transform"], se3.inverse(p["transform"])),
    "transform_points": lambda p: se3.transform_points(p["transform"], p["src"]),
    "se3.log": lambda p: se3.log(p["transform"]),
    "se3.exp": lambda p: se3.exp(p["twist"]),
    "euler": lambda p: euler.matrix_to_euler_zyx(p["transform"][:, :3, :3]),
    "chamfer": lambda p: chamfer.chamfer_distance(p["src"], p["ref"]),
    "knn": lambda p: neighbors.knn(p["src"], p["ref"], 4),
    "cdist": lambda p: neighbors.cdist(p["src"], p["ref"]),
    "normals": lambda p: normals.estimate_normals(p["ref"], k=8),
    "rri": lambda p: rri.rri_features(p["src"], k=4),
}


def _flat(value: object) -> list[torch.Tensor]:
    return list(value) if isinstance(value, tuple) else [value]  # type: ignore[list-item]


@pytest.mark.parametrize("name", sorted(CALLS))
def test_under_autocast_float32_inputs_give_exactly_the_float32_result(name: str) -> None:
    """Without the guard, autocast would run their products in bfloat16 (kabsch's covariance, the compositions)."""
    p = _problem()
    plain = _flat(CALLS[name](p))
    with torch.autocast("cpu", dtype=BF16):
        cast = _flat(CALLS[name](p))
    for a, b in zip(plain, cast, strict=True):
        assert b.dtype == a.dtype
        assert torch.equal(a, b)


@pytest.mark.parametrize("name", sorted(CALLS))
def test_under_autocast_bfloat16_inputs_are_computed_in_float32(name: str) -> None:
    p = {k: v.to(BF16) for k, v in _problem().items()}
    with torch.autocast("cpu", dtype=BF16):
        cast = _flat(CALLS[name](p))
    plain = _flat(CALLS[name]({k: v.float() for k, v in p.items()}))
    for a, b in zip(plain, cast, strict=True):
        assert b.dtype == a.dtype
        assert torch.equal(a, b)


def test_without_the_guard_autocast_rounds_a_composition_to_bfloat16() -> None:
    """The guard matters (so the tests above can fail): unguarded, autocast runs the product in bfloat16."""
    p = _problem()
    a, b = p["transform"], se3.inverse(p["transform"])
    with torch.autocast("cpu", dtype=BF16):
        unguarded = se3.compose.__wrapped__(a, b)  # type: ignore[attr-defined]
    assert unguarded.dtype == BF16
    assert (unguarded.float() - se3.compose(a, b)).abs().max() > 1e-4


def test_float64_stays_float64_under_autocast() -> None:
    p = {k: v.double() for k, v in _problem().items()}
    with torch.autocast("cpu", dtype=BF16):
        out = procrustes.weighted_kabsch(p["src"], p["ref"], p["weights"])
    assert out.dtype == torch.float64
    torch.testing.assert_close(out, procrustes.weighted_kabsch(p["src"], p["ref"], p["weights"]), rtol=0, atol=0)


def test_without_autocast_half_precision_is_still_a_type_error() -> None:
    p = _problem()
    with pytest.raises(TypeError, match="points_src"):
        procrustes.weighted_kabsch(p["src"].to(BF16), p["ref"].to(BF16))


def test_gradients_reach_bfloat16_inputs_through_the_float32_solve() -> None:
    p = _problem()
    src = p["src"].to(BF16).requires_grad_()
    with torch.autocast("cpu", dtype=BF16):
        procrustes.weighted_kabsch(src, p["ref"].to(BF16)).sum().backward()
    assert src.grad is not None and src.grad.dtype == BF16
    assert bool(torch.isfinite(src.grad).all()) and bool(src.grad.abs().sum() > 0)


def test_upcast_reduced_walks_containers_and_keeps_other_values() -> None:
    half, full, ints = torch.ones(2, dtype=torch.float16), torch.ones(2, dtype=torch.float64), torch.ones(2).long()
    out = upcast_reduced({"a": (half, [ints, "x"]), "b": full})
    assert out["a"][0].dtype == torch.float32 and out["a"][1][0].dtype == torch.long and out["a"][1][1] == "x"
    assert out["b"] is full


def test_a_function_without_tensor_arguments_is_called_as_is() -> None:
    @full_precision
    def seven(x: int) -> int:
        return x + 1

    with torch.autocast("cpu", dtype=BF16):
        assert seven(6) == 7


# Public functions that lose no precision, or take no tensors: not wrapped (precision.py says why).
NOT_WRAPPED = {"gather_points", "neighbour_max", "split", "identity", "EXACT_MAX_DIM"}
MODULES = (chamfer, euler, neighbors, normals, procrustes, rri, se3, so3)


@pytest.mark.parametrize("module", MODULES, ids=lambda m: m.__name__.rsplit(".", 1)[-1])
def test_every_numerical_geometry_function_is_wrapped(module: ModuleType) -> None:
    """The convention is pinned: a new geometry function must be wrapped or listed above with a reason."""
    for name in module.__all__:
        obj = getattr(module, name)
        if name in NOT_WRAPPED or not inspect.isfunction(obj):
            continue
        assert hasattr(obj, "__wrapped__"), f"{module.__name__}.{name} is not wrapped by full_precision"
