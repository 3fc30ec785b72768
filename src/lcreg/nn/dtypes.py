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

__all__ = ["module_dtype", "to_module_dtype"]


def module_dtype(module: nn.Module) -> torch.dtype | None:
    """The dtype of the first floating parameter or buffer of ``module`` (``None`` when it has none)."""
    for tensor in (*module.parameters(), *module.buffers()):
        if tensor.is_floating_point():
            return tensor.dtype
    return None


def to_module_dtype(module: nn.Module, value: Any) -> Any:
    """``value`` with every floating tensor (top level, or inside a tuple/list/dict) cast to ``module``'s dtype.

    Args:
        module: The module that computes.
        value: A tensor, a container of tensors, or anything else (returned unchanged).
    """
    dtype = module_dtype(module)
    if dtype is None:
        return value
    return _cast(value, dtype)


def _cast(value: Any, dtype: torch.dtype) -> Any:
    if isinstance(value, torch.Tensor):
        return value.to(dtype) if value.is_floating_point() and value.dtype != dtype else value
    if isinstance(value, (tuple, list)):
        return type(value)(_cast(v, dtype) for v in value)
    if isinstance(value, dict):
        return {k: _cast(v, dtype) for k, v in value.items()}
    return value
