"""Input validation shared by every public entry point.

All checks raise typed errors that name the offending argument, never ``assert``:

* :class:`ShapeError` (a ``ValueError``) for a wrong shape, with ``expected`` and ``actual`` attributes;
* ``TypeError`` for a non-tensor or an unsupported dtype (float32 and float64 are supported);
* :class:`NonFiniteError` (a ``ValueError``) for NaN or Inf values;
* :class:`TooFewPointsError` (a ``ValueError``) for empty clouds or clouds smaller than a module needs, and its
  subclass :class:`DegenerateCloudError` for a cloud whose points all coincide (no rotation can be recovered);
* :class:`PointCloudFileError` (a ``ValueError``) for a point-cloud file that exists but cannot be used;
* :class:`DatasetLayoutError` (a ``ValueError``) for a dataset folder whose files do not follow the expected layout;
* :class:`MissingDependencyError` (an ``ImportError``) for an optional package a method needs (the message says how
  to install it).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import torch

__all__ = [
    "DatasetLayoutError",
    "DegenerateCloudError",
    "MissingDependencyError",
    "NonFiniteError",
    "PointCloudFileError",
    "ShapeError",
    "TooFewPointsError",
    "check_count_or_fraction",
    "check_extent",
    "check_finite",
    "check_float",
    "check_points",
    "check_rigid",
    "check_same_batch",
    "check_shape",
    "check_transform",
    "resolve_count",
]

SUPPORTED_DTYPES = (torch.float32, torch.float64)


class ShapeError(ValueError):
    """A tensor does not have the expected shape.

    Attributes:
        name: The argument name.
        expected: The expected shape, symbolic dimensions as strings.
        actual: The actual shape.
    """

    def __init__(self, name: str, expected: Sequence[int | str], actual: Sequence[int]) -> None:
        self.name = name
        self.expected = tuple(expected)
        self.actual = tuple(actual)
        exp = "(" + ", ".join(str(e) for e in self.expected) + ")"
        super().__init__(f"`{name}` must have shape {exp}, got {tuple(self.actual)}")


class NonFiniteError(ValueError):
    """A tensor contains NaN or Inf values."""


class TooFewPointsError(ValueError):
    """A point cloud has fewer points than an operation needs (including empty clouds)."""


class DegenerateCloudError(TooFewPointsError):
    """Every point of a cloud is at one location (zero extent): a rigid motion cannot be recovered from it."""


class PointCloudFileError(ValueError):
    """A point-cloud file exists but cannot be used: unreadable, corrupt, empty or with non-finite points.

    Attributes:
        path: The file.
    """

    def __init__(self, path: object, reason: str) -> None:
        self.path = str(path)
        super().__init__(f"point-cloud file {self.path!r}: {reason}")


class DatasetLayoutError(ValueError):
    """A dataset folder exists but its files do not follow the expected layout (the message names the path)."""


class MissingDependencyError(ImportError):
    """An optional package a method needs is not installed (one line naming it and the install command)."""


class DatasetNotFoundError(FileNotFoundError):
    """A dataset's root folder does not exist (the message names it, resolved, and how to give another)."""


def dataset_root(root: str | Path, what: str, layout: str, argument: str = "--data.init_args.root") -> Path:
    """``root`` (``~`` expanded) if it is a directory.

    Args:
        root: The dataset folder as configured (a relative path is relative to the working directory).
        what: The dataset or component, for the message (e.g. ``"ModelNet40DataModule"``).
        layout: The expected layout, appended to the message.
        argument: The option that sets the folder, named in the message.

    Raises:
        TypeError: If ``root`` is not a path (``None``, a number).
        DatasetNotFoundError: If it is not a directory; a relative ``root`` is shown resolved against the working
            directory (configs name ``../shared/data/...``, which holds only from a source checkout).
    """
    if not isinstance(root, (str, os.PathLike)):
        message = f"{what}: `root` must be a folder path, got {root!r}; give the dataset's folder with {argument}"
        raise TypeError(message)
    path = Path(root).expanduser()
    if path.is_dir():
        return path
    where = "" if path.is_absolute() else f" (relative to the working directory: {path.resolve()})"
    raise DatasetNotFoundError(
        f"{what}: root {str(root)!r}{where} is not a directory; give the dataset's folder with {argument}; {layout}"
    )


def check_count_or_fraction(value: object, name: str, wrong_type: type[Exception] = TypeError) -> int | float:
    """Check that ``value`` is an int count ``>= 1`` or a float fraction in ``(0, 1]`` and return it.

    Args:
        value: The value to check (a bool is neither).
        name: The argument it was given as, named in the message.
        wrong_type: The error raised for a value of another type.

    Raises:
        ValueError: For a count below 1 or a fraction outside ``(0, 1]``; ``wrong_type`` for another type.
    """
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise wrong_type(f"`{name}` must be an int count or a float fraction, got {value!r}")
    if isinstance(value, int) and value < 1:
        raise ValueError(f"`{name}` as a count must be >= 1, got {value!r}")
    if isinstance(value, float) and not 0.0 < value <= 1.0:
        raise ValueError(f"`{name}` as a fraction must be in (0, 1], got {value!r}")
    return value


def resolve_count(value: int | float, total: int) -> int:
    """A :func:`check_count_or_fraction` value as a count of ``total``: a count as it is, a fraction rounded (>= 1)."""
    return max(1, round(value * total)) if isinstance(value, float) else value


def check_float(x: object, name: str) -> torch.Tensor:
    """Check that ``x`` is a float32/float64 tensor and return it.

    Raises:
        TypeError: If ``x`` is not a tensor or has another dtype.
    """
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"`{name}` must be a torch.Tensor, got {type(x).__name__}")
    if x.dtype not in SUPPORTED_DTYPES:
        raise TypeError(f"`{name}` must be float32 or float64, got {x.dtype}")
    return x


def check_shape(x: torch.Tensor, expected: Sequence[int | str], name: str) -> dict[str, int]:
    """Check ``x.shape`` against ``expected`` where strings are symbolic dimensions.

    Args:
        x: The tensor.
        expected: For example ``("B", "N", 3)``; a repeated symbol must match itself.
        name: The argument name used in the message.

    Returns:
        The values bound to the symbolic dimensions.

    Raises:
        ShapeError: On a rank or size mismatch.
    """
    if x.ndim != len(expected):
        raise ShapeError(name, expected, x.shape)
    bound: dict[str, int] = {}
    for dim, exp in zip(x.shape, expected):
        if isinstance(exp, str):
            if bound.setdefault(exp, dim) != dim:
                raise ShapeError(name, expected, x.shape)
        elif dim != exp:
            raise ShapeError(name, expected, x.shape)
    return bound


def check_finite(x: torch.Tensor, name: str) -> None:
    """Raise :class:`NonFiniteError` if ``x`` has NaN or Inf entries.

    Real floating tensors are checked in one pass: NaN propagates to the minimum and maximum, and an infinite entry
    is one of them (``torch.isfinite(x).all()`` takes several passes over ``x``).
    """
    if x.is_floating_point() and x.numel() > 0:
        low, high = torch.aminmax(x)
        finite = bool(torch.isfinite(low) & torch.isfinite(high))
    else:
        finite = bool(torch.isfinite(x).all())
    if not finite:
        bad = int((~torch.isfinite(x)).sum())
        raise NonFiniteError(f"`{name}` contains {bad} NaN/Inf value(s)")


def check_points(x: object, name: str, min_points: int = 1) -> torch.Tensor:
    """Validate a batched point cloud ``(B, N, 3)``: float dtype, shape, size and finiteness.

    Args:
        x: The candidate tensor.
        name: Argument name for messages.
        min_points: Smallest acceptable ``N``.

    Returns:
        ``x`` unchanged.
    """
    t = check_float(x, name)
    check_shape(t, ("B", "N", 3), name)
    if t.shape[0] == 0:
        raise ShapeError(name, ("B>0", "N", 3), t.shape)
    if t.shape[1] < min_points:
        raise TooFewPointsError(f"`{name}` has {t.shape[1]} points; at least {min_points} are needed")
    check_finite(t, name)
    return t


def check_extent(x: torch.Tensor, name: str) -> None:
    """Raise :class:`DegenerateCloudError` if a cloud of ``x (B, N, 3)`` has all its points at one location.

    Args:
        x: Validated clouds (:func:`check_points`).
        name: Argument name for messages.
    """
    low, high = x.amin(dim=1), x.amax(dim=1)  # (B, 3)
    flat = ((high - low).amax(dim=-1) == 0).nonzero().flatten().tolist()
    if flat:
        raise DegenerateCloudError(
            f"`{name}`: every point of cloud(s) {flat} is at one location; registration needs distinct points"
        )


def check_transform(x: object, name: str) -> torch.Tensor:
    """Validate a batch of homogeneous transforms ``(B, 4, 4)`` (dtype, shape, finiteness)."""
    t = check_float(x, name)
    check_shape(t, ("B", 4, 4), name)
    check_finite(t, name)
    return t


def check_rigid(x: torch.Tensor, name: str, atol: float = 1e-3) -> None:
    """Raise ``ValueError`` unless every ``x[b]`` of ``(B, 4, 4)`` is a rigid motion ``[R t; 0 0 0 1]``.

    ``R`` must be a rotation: ``R^T R = I`` and ``det R = +1`` (no scaling, shear or reflection), each within
    ``atol`` (float32 products of rotations drift by about 1e-6); the last row must be ``[0, 0, 0, 1]``.

    Args:
        x: Finite transforms ``(B, 4, 4)`` (:func:`check_transform`).
        name: Argument name for messages.
        atol: Absolute tolerance of each test.
    """
    rot = x[:, :3, :3].double()
    eye = torch.eye(3, dtype=rot.dtype, device=rot.device)
    orth = (rot.transpose(1, 2) @ rot - eye).abs().amax(dim=(1, 2))
    det = (torch.linalg.det(rot) - 1).abs()
    row = (x[:, 3].double() - eye.new_tensor([0.0, 0.0, 0.0, 1.0])).abs().amax(dim=1)
    bad = ((orth > atol) | (det > atol) | (row > atol)).nonzero().flatten().tolist()
    if bad:
        raise ValueError(
            f"`{name}` must hold rigid motions [R t; 0 0 0 1] with R a rotation (R^T R = I, det R = +1); "
            f"item(s) {bad[:10]} are not (largest |R^T R - I| {float(orth.max()):.3g}, |det R - 1| "
            f"{float(det.max()):.3g}, last-row error {float(row.max()):.3g})"
        )


def check_same_batch(**tensors: torch.Tensor) -> None:
    """Check that all tensors share the batch size (dim 0) and dtype.

    Raises:
        ShapeError: On different batch sizes.
        TypeError: On different dtypes.
    """
    items = list(tensors.items())
    name0, t0 = items[0]
    for name, t in items[1:]:
        if t.shape[0] != t0.shape[0]:
            raise ShapeError(name, (t0.shape[0], *t.shape[1:]), t.shape)
        if t.dtype != t0.dtype:
            raise TypeError(f"`{name}` has dtype {t.dtype} but `{name0}` has {t0.dtype}")
