from __future__ import annotations

import numpy as np
import pytest
import torch

from lcreg.checks import (
    DatasetLayoutError,
    NonFiniteError,
    ShapeError,
    TooFewPointsError,
    check_count_or_fraction,
    check_finite,
    check_float,
    check_points,
    check_same_batch,
    check_shape,
    check_transform,
    resolve_count,
)


def test_error_hierarchy() -> None:
    assert issubclass(ShapeError, ValueError)
    assert issubclass(NonFiniteError, ValueError)
    assert issubclass(TooFewPointsError, ValueError)
    assert issubclass(DatasetLayoutError, ValueError)


@pytest.mark.parametrize("value", [1, 768, 0.25, 1.0])
def test_check_count_or_fraction_returns_a_count_or_a_fraction_as_given(value: int | float) -> None:
    assert check_count_or_fraction(value, "keep") is value


@pytest.mark.parametrize(
    ("value", "error", "message"),
    [
        (0, ValueError, "`keep` as a count must be >= 1, got 0"),
        (-3, ValueError, "`keep` as a count must be >= 1"),
        (0.0, ValueError, r"`keep` as a fraction must be in \(0, 1\], got 0.0"),
        (1.5, ValueError, r"`keep` as a fraction must be in \(0, 1\]"),
        (float("nan"), ValueError, "as a fraction"),
        (True, TypeError, "`keep` must be an int count or a float fraction, got True"),
        ("3", TypeError, "got '3'"),
        (None, TypeError, "got None"),
    ],
)
def test_check_count_or_fraction_names_the_argument(value: object, error: type[Exception], message: str) -> None:
    with pytest.raises(error, match=message):
        check_count_or_fraction(value, "keep")
    with pytest.raises(ValueError, match="`keep`"):  # a caller may want a ValueError for every bad value
        check_count_or_fraction(value, "keep", wrong_type=ValueError)


def test_resolve_count_rounds_a_fraction_of_the_total_and_keeps_a_count() -> None:
    assert [resolve_count(v, 705) for v in (0.5, 0.25, 1.0, 1e-9, 176)] == [352, 176, 705, 1, 176]
    assert resolve_count(0.75, 512) == 384 and resolve_count(0.75, 1024) == 768


def test_shape_error_attributes_and_message() -> None:
    err = ShapeError("points_src", ("B", "N", 3), (2, 5, 4))
    assert err.name == "points_src"
    assert err.expected == ("B", "N", 3)
    assert err.actual == (2, 5, 4)
    assert "points_src" in str(err) and "(B, N, 3)" in str(err) and "(2, 5, 4)" in str(err)


def test_check_float_accepts_supported(dtype: torch.dtype) -> None:
    x = torch.zeros(2, dtype=dtype)
    assert check_float(x, "x") is x


@pytest.mark.parametrize("bad", [torch.zeros(2, dtype=torch.int64), torch.zeros(2, dtype=torch.float16), np.zeros(2)])
def test_check_float_rejects(bad: object) -> None:
    with pytest.raises(TypeError, match="`my_arg`"):
        check_float(bad, "my_arg")


def test_check_shape_binds_symbols() -> None:
    assert check_shape(torch.zeros(2, 5, 3), ("B", "N", 3), "x") == {"B": 2, "N": 5}
    assert check_shape(torch.zeros(4, 4), ("K", "K"), "x") == {"K": 4}


@pytest.mark.parametrize(
    ("shape", "expected"),
    [((2, 5), ("B", "N", 3)), ((2, 5, 4), ("B", "N", 3)), ((4, 3), ("K", "K")), ((2, 5, 3, 1), ("B", "N", 3))],
)
def test_check_shape_rejects(shape: tuple[int, ...], expected: tuple[int | str, ...]) -> None:
    with pytest.raises(ShapeError, match="`cloud`") as info:
        check_shape(torch.zeros(shape), expected, "cloud")
    assert info.value.actual == shape
    assert info.value.expected == expected


@pytest.mark.parametrize("value", [float("nan"), float("inf"), -float("inf")])
def test_check_finite(value: float) -> None:
    check_finite(torch.zeros(3), "x")
    x = torch.zeros(3)
    x[1] = value
    with pytest.raises(NonFiniteError, match="`weights` contains 1"):
        check_finite(x, "weights")


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float32, torch.float64])
@pytest.mark.parametrize("values", [[float("nan")], [float("inf")], [-float("inf")], [float("nan"), float("inf")]])
def test_check_finite_finds_every_non_finite_kind_in_every_float_dtype(dtype: torch.dtype, values: list[float]) -> None:
    x = torch.linspace(-2, 2, 40, dtype=dtype).reshape(2, 20)
    check_finite(x, "x")
    check_finite(x[:0], "empty")
    for i, value in enumerate(values):
        x[1, 3 * i + 1] = value
    with pytest.raises(NonFiniteError, match=f"`x` contains {len(values)}"):
        check_finite(x, "x")


def test_check_finite_accepts_integer_and_bool_tensors() -> None:
    check_finite(torch.arange(4), "i")
    check_finite(torch.zeros(3, dtype=torch.bool), "b")


def test_check_points() -> None:
    pts = torch.zeros(2, 5, 3)
    assert check_points(pts, "points_src") is pts
    with pytest.raises(ShapeError, match="points_src"):
        check_points(torch.zeros(2, 5, 2), "points_src")
    with pytest.raises(ShapeError, match="points_src"):
        check_points(torch.zeros(0, 5, 3), "points_src")
    with pytest.raises(TooFewPointsError, match="points_src"):
        check_points(torch.zeros(2, 0, 3), "points_src")
    with pytest.raises(TooFewPointsError, match=r"points_src.*at least 6"):
        check_points(pts, "points_src", min_points=6)
    with pytest.raises(TypeError, match="points_src"):
        check_points(pts.long(), "points_src")
    pts[0, 0, 0] = float("nan")
    with pytest.raises(NonFiniteError, match="points_src"):
        check_points(pts, "points_src")


def test_check_transform() -> None:
    t = torch.eye(4).expand(3, 4, 4)
    assert check_transform(t, "transform_ref_src") is t
    with pytest.raises(ShapeError, match="transform_ref_src"):
        check_transform(torch.eye(4), "transform_ref_src")
    with pytest.raises(TypeError, match="transform_ref_src"):
        check_transform(torch.eye(4, dtype=torch.int32)[None], "transform_ref_src")
    bad = t.clone()
    bad[1, 0, 3] = float("nan")
    with pytest.raises(NonFiniteError, match="transform_ref_src"):
        check_transform(bad, "transform_ref_src")


def test_check_same_batch() -> None:
    check_same_batch(a=torch.zeros(2, 3), b=torch.zeros(2, 7, 3))
    with pytest.raises(ShapeError, match="`b`"):
        check_same_batch(a=torch.zeros(2, 3), b=torch.zeros(3, 3))
    with pytest.raises(TypeError, match=r"`b`.*`a`"):
        check_same_batch(a=torch.zeros(2, 3), b=torch.zeros(2, 3, dtype=torch.float64))


def test_check_extent_names_the_cloud_whose_points_coincide() -> None:
    from lcreg.checks import DegenerateCloudError, TooFewPointsError, check_extent

    clouds = torch.rand(3, 10, 3)
    check_extent(clouds, "points")
    clouds[1] = torch.tensor([1.0, 2.0, 3.0])
    with pytest.raises(DegenerateCloudError, match=r"`points`.*\[1\]") as info:
        check_extent(clouds, "points")
    assert isinstance(info.value, TooFewPointsError)
