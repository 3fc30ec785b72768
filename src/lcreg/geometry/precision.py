"""Geometry in full precision under autocast (mixed-precision training: Lightning's ``bf16-mixed`` or ``16-mixed``).

Autocast runs matrix products and convolutions in bfloat16 or float16, whose 8- and 11-bit mantissas are too coarse
for geometry: a Procrustes cross-covariance rounded to bfloat16 moves the rotation by a fraction of a degree, and an
IC-LK normal matrix or a nearest-neighbour search loses its meaning. Every numerical function of
:mod:`lcreg.geometry` is therefore wrapped by :func:`full_precision`, and so are the parts built on them that compute
geometry or compare two close quantities: the IC-LK solve (``lcreg.nn.lk``, its encoder passes included), the
Procrustes and GMM heads, the pose losses, local consistency's KL and the per-pair metrics:

* under an active autocast (of the first tensor argument's device type) it casts bfloat16/float16 tensor arguments
  (also inside tuples, lists and dicts) to float32 and runs the function with autocast off, so the result is float32
  (float64 arguments stay float64) and equal to what the same float32 call gives without autocast;
* without autocast it calls the function unchanged: half-precision inputs are a ``TypeError`` there, as the dtype
  policy of :mod:`lcreg.checks` says, since nothing asked for mixed precision.

Gradients flow through the casts, so a network that runs in bfloat16 still trains through the float32 geometry.
The guard covers autocast only: TF32 (``torch.set_float32_matmul_precision("high")``, ``allow_tf32``) rounds every
float32 product to a 10-bit mantissa, geometry's included, so lcreg leaves torch's default ("highest") alone.
Indexing and pooling helpers (``gather_points``, ``neighbour_max``) are not wrapped: they lose no precision, and
casting their (large) feature tensors would only cost memory.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping
from typing import Any, ParamSpec, TypeVar

import torch

__all__ = ["REDUCED_DTYPES", "full_precision", "upcast_reduced"]

REDUCED_DTYPES = (torch.float16, torch.bfloat16)
"""The dtypes autocast computes in, cast to float32 by :func:`full_precision`."""

P = ParamSpec("P")
R = TypeVar("R")


def upcast_reduced(value: Any) -> Any:
    """``value`` with every bfloat16/float16 tensor (top level, or in a tuple, list or dict) cast to float32."""
    if isinstance(value, torch.Tensor):
        return value.float() if value.dtype in REDUCED_DTYPES else value
    if isinstance(value, (tuple, list)):
        return type(value)(upcast_reduced(v) for v in value)
    if isinstance(value, dict):
        return {k: upcast_reduced(v) for k, v in value.items()}
    return value


def _first_tensor(args: tuple[Any, ...], kwargs: Mapping[str, Any]) -> torch.Tensor | None:
    """The first tensor among the positional, then the keyword arguments (one level into tuples and lists)."""
    for value in (*args, *kwargs.values()):
        if isinstance(value, torch.Tensor):
            return value
        if isinstance(value, (tuple, list)):
            found = next((v for v in value if isinstance(v, torch.Tensor)), None)
            if found is not None:
                return found
    return None


def full_precision(fn: Callable[P, R]) -> Callable[P, R]:
    """Decorate ``fn`` to compute in float32 or float64 under autocast (the module docstring says how).

    Example:
        >>> a = torch.randn(2, 8, 3)
        >>> @full_precision
        ... def gram(x: torch.Tensor) -> torch.Tensor:
        ...     return x.transpose(1, 2) @ x
        >>> with torch.autocast("cpu", dtype=torch.bfloat16):
        ...     bool(torch.equal(gram(a.bfloat16()), gram(a.bfloat16().float())))
        True
        >>> with torch.autocast("cpu", dtype=torch.bfloat16):
        ...     gram(a).dtype
        torch.float32
    """

    @functools.wraps(fn)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
        tensor = _first_tensor(args, kwargs)
        if tensor is None or not torch.is_autocast_enabled(tensor.device.type):
            return fn(*args, **kwargs)
        with torch.autocast(tensor.device.type, enabled=False):
            return fn(*upcast_reduced(args), **upcast_reduced(dict(kwargs)))

    return wrapper
