"""The NaN/Inf policy of :mod:`lcreg.geometry` (stated in its docstring and ``docs/architecture.md``).

Element-wise batched transforms check dtype and shape only and propagate NaN/Inf row by row: a non-finite item
gives a non-finite result for that item and leaves every other item exactly as without it, with no error (they run
inside loops where a finiteness check would cost a host sync each call; their callers validate at the boundary).
Functions that take whole clouds (neighbours, Chamfer, Procrustes, normals) refuse them with a typed error naming
the argument.
"""

from __future__ import annotations

from collections.abc import Callable

import pytest
import torch

import lcreg.geometry as geometry
from lcreg.checks import NonFiniteError
from lcreg.geometry import chamfer, euler, neighbors, normals, procrustes, se3, so3

G = torch.Generator().manual_seed(0)
W = torch.randn(3, 3, generator=G, dtype=torch.float64) * 0.5
T = se3.exp(torch.randn(3, 6, generator=G, dtype=torch.float64) * 0.3)
P = torch.randn(3, 20, 3, generator=G, dtype=torch.float64)

PROPAGATING: dict[str, tuple[Callable[..., torch.Tensor], tuple[torch.Tensor, ...]]] = {
    "so3.exp": (so3.exp, (W,)),
    "so3.log": (so3.log, (so3.exp(W),)),
    "so3.quaternion_to_matrix": (so3.quaternion_to_matrix, (torch.randn(3, 4, generator=G, dtype=torch.float64),)),
    "euler.euler_zyx_to_matrix": (euler.euler_zyx_to_matrix, (W,)),
    "euler.matrix_to_euler_zyx": (euler.matrix_to_euler_zyx, (so3.exp(W),)),
    "se3.exp": (se3.exp, (torch.randn(3, 6, generator=G, dtype=torch.float64),)),
    "se3.log": (se3.log, (T,)),
    "se3.inverse": (se3.inverse, (T,)),
    "se3.compose": (se3.compose, (T, T)),
    "se3.transform_points": (se3.transform_points, (T, P)),
    "se3.transform_normals": (se3.transform_normals, (T, P)),
    "neighbors.pairwise_sq_distances": (neighbors.pairwise_sq_distances, (P, P)),
    "neighbors.cdist": (neighbors.cdist, (P, P)),
}


def _poisoned(x: torch.Tensor, value: float) -> torch.Tensor:
    out = x.clone()
    out[1].view(-1)[0] = value
    return out


@pytest.mark.parametrize("value", [float("nan"), float("inf")], ids=["nan", "inf"])
@pytest.mark.parametrize("name", list(PROPAGATING))
def test_elementwise_ops_propagate_non_finite_items_row_by_row(name: str, value: float) -> None:
    fn, args = PROPAGATING[name]
    clean = fn(*args)
    for position in range(len(args)):
        poisoned = [_poisoned(a, value) if i == position else a for i, a in enumerate(args)]
        out = fn(*poisoned)
        assert not torch.isfinite(out[1]).all(), f"{name}: argument {position}'s bad item vanished"
        assert torch.equal(out[[0, 2]], clean[[0, 2]]), f"{name}: a bad item changed the other items"


VALIDATING: dict[str, tuple[Callable[..., object], str]] = {
    "neighbors.knn": (lambda p: neighbors.knn(p, P, 4), "query"),
    "chamfer.chamfer_distance": (lambda p: chamfer.chamfer_distance(p, P), "points_a"),
    "procrustes.weighted_kabsch": (lambda p: procrustes.weighted_kabsch(p, P, torch.ones(3, 20, dtype=P.dtype)), ""),
    "normals.estimate_normals": (lambda p: normals.estimate_normals(p, k=4), "points"),
}


@pytest.mark.parametrize("name", list(VALIDATING))
def test_cloud_functions_refuse_non_finite_clouds_naming_the_argument(name: str) -> None:
    fn, argument = VALIDATING[name]
    with pytest.raises(NonFiniteError, match=f"`{argument}" if argument else "NaN/Inf"):
        fn(_poisoned(P, float("nan")))


def test_the_policy_is_stated_where_the_functions_live() -> None:
    doc = geometry.__doc__ or ""
    assert "propagate NaN/Inf" in doc and "validate" in doc
