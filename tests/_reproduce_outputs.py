"""Helpers of the ``lcreg reproduce`` tests: JSONL rows, a drawn-PNG check, counting calls of a patched function."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest


def read_jsonl(path: Path) -> list[dict[str, Any]]:
    """Every row of a JSONL file."""
    return [json.loads(line) for line in path.read_text().splitlines()]


def assert_png_drawn(path: Path) -> None:
    """``path`` is a PNG taller than 300 pixels with visible contrast (not a blank canvas)."""
    from matplotlib.image import imread

    image = imread(path)[..., :3]
    assert image.shape[0] > 300 and image.std() > 0.05, path


def count_calls(monkeypatch: pytest.MonkeyPatch, module: Any, name: str) -> list[str]:
    """Patch ``module.name`` to record its first argument (a name, or the argument's type name) on every call."""
    calls: list[str] = []
    real = getattr(module, name)

    def counting(first: Any, *args: Any, **kwargs: Any) -> Any:
        calls.append(first if isinstance(first, str) else type(first).__name__)
        return real(first, *args, **kwargs)

    monkeypatch.setattr(module, name, counting)
    return calls
