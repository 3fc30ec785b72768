"""Every model's ``forward`` validates its clouds first and blames the right one (issue 14, defect 9).

Before: DCP/PRNet on an unbatched ``(N, 3)`` cloud said "DGCNN needs at least k=20 points per cloud, got 3";
DeepGMR/PCRNet blamed ``points``; IDAM counted NaNs of its features; PRNet could blame ``points_ref`` for a NaN
in the source.
"""

from __future__ import annotations

import pytest
import torch

import lcreg
from lcreg.checks import NonFiniteError, ShapeError, TooFewPointsError

MODELS = ["DVDs", "DCP", "PRNet", "IDAM", "DeepGMR", "PointNetLK", "FMRNet", "PCRNet", "ICP"]


def _clouds() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    src = torch.rand(2, 64, 3, generator=torch.Generator().manual_seed(0))
    nan = src.clone()
    nan[1, 5, 2] = float("nan")
    return src, src + 0.01, nan


@pytest.fixture(scope="module", params=MODELS)
def model(request: pytest.FixtureRequest) -> lcreg.RegistrationModule:
    torch.manual_seed(0)
    return getattr(lcreg, request.param)().eval()


@pytest.mark.parametrize("side", ["points_src", "points_ref"])
def test_nan_is_blamed_on_its_cloud(model: lcreg.RegistrationModule, side: str) -> None:
    src, ref, nan = _clouds()
    args = (nan, ref) if side == "points_src" else (src, nan)
    with pytest.raises(NonFiniteError, match=rf"^`{side}` contains 1 NaN/Inf value"), torch.no_grad():
        model(*args)
    with pytest.raises(NonFiniteError, match=rf"^`{side}` contains 1 NaN/Inf value"), torch.no_grad():
        model(points_src=args[0], points_ref=args[1])


def test_unbatched_cloud_is_a_shape_error(model: lcreg.RegistrationModule) -> None:
    src, ref, _ = _clouds()
    with pytest.raises(ShapeError, match=r"^`points_src` must have shape \(B, N, 3\), got \(64, 3\)"), torch.no_grad():
        model(src[0], ref[0])


def test_too_small_cloud_names_the_argument(model: lcreg.RegistrationModule) -> None:
    src, ref, _ = _clouds()
    with pytest.raises(TooFewPointsError, match=r"^`points_ref` has 2 points"), torch.no_grad():
        model(src, ref[:, :2])


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("normals_src", torch.zeros(2, 10, 3)),
        ("normals_ref", torch.zeros(2, 64, 2)),
        ("transform_ref_src", torch.eye(4).expand(3, 4, 4)),
        ("index", torch.zeros(2, 1, dtype=torch.int64)),
    ],
)
def test_a_batch_field_of_the_wrong_shape_is_named(
    model: lcreg.RegistrationModule, field: str, value: torch.Tensor
) -> None:
    """Before: DVDs trained on normals of another length failed with a broadcast RuntimeError deep in its loss."""
    from lcreg.types import RegistrationBatch

    src, ref, _ = _clouds()
    batch = RegistrationBatch(src, ref, **{field: value})
    with pytest.raises(ShapeError, match=rf"`batch\.{field}`"):
        model.validation_step(batch, 0)
