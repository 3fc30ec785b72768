"""Inputs in the module's dtype: float64 clouds (numpy's default) work with float32 models, and the reverse.

The public entry points accept float32 and float64 clouds (:mod:`lcreg.checks`). A module computes in the dtype of
its floating parameters (float32 unless converted with ``.double()`` or a ``"64-true"`` Lightning precision), so
inputs are cast to it at the boundary, once, here; a module without floating parameters (classical methods) keeps
the input dtype.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import nn

from lcreg.geometry.precision import REDUCED_DTYPES

__all__ = ["check_compute_dtype", "module_dtype", "to_module_dtype"]


def module_dtype(module: nn.Module) -> torch.dtype | None:
    """The dtype of the first floating parameter or buffer of ``module`` (``None`` when it has none)."""
    for tensor in (*module.parameters(), *module.buffers()):
        if tensor.is_floating_point():
            return tensor.dtype
    return None


def check_compute_dtype(module: nn.Module) -> None:
    """Refuse a module whose parameters are float16 or bfloat16: its geometry would compute in half precision.

    Raises:
        TypeError: Naming the module and the way to mixed precision (autocast, :mod:`lcreg.geometry.precision`).
    """
    dtype = module_dtype(module)
    if dtype in REDUCED_DTYPES:
        raise TypeError(
            f"{type(module).__name__} has {dtype} parameters, but lcreg models compute in float32 or float64: for "
            "mixed precision keep float32 weights and use autocast (Lightning's `--trainer.precision bf16-mixed` or "
            "`16-mixed`), not `bf16-true`/`16-true`, `.half()` or `.bfloat16()`"
        )


def to_module_dtype(module: nn.Module, value: Any) -> Any:
    """``value`` with every floating tensor (top level, or inside a tuple/list/dict) cast to ``module``'s dtype.

    Args:
        module: The module that computes.
        value: A tensor, a container of tensors, or anything else (returned unchanged).

    Raises:
        TypeError: If ``module`` computes in float16 or bfloat16 (its geometry would too; autocast is the way to
            mixed precision, :mod:`lcreg.geometry.precision`).
    """
    dtype = module_dtype(module)
    if dtype is None:
        return value
    check_compute_dtype(module)
    return _cast(value, dtype)


def _cast(value: Any, dtype: torch.dtype) -> Any:
    if isinstance(value, torch.Tensor):
        return value.to(dtype) if value.is_floating_point() and value.dtype != dtype else value
    if isinstance(value, (tuple, list)):
        return type(value)(_cast(v, dtype) for v in value)
    if isinstance(value, dict):
        return {k: _cast(v, dtype) for k, v in value.items()}
    return value
