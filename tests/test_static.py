"""Lint, format and type checks as tests (ruff and mypy from the same environment as the interpreter)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent


def _tool(name: str) -> Path:
    path = BIN / name
    if not path.is_file():
        pytest.skip(f"{name} is not installed next to {sys.executable} (pip install -e '.[dev]')")
    return path


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(args, cwd=REPO_ROOT, capture_output=True, text=True, timeout=300, check=False)


def test_ruff_check() -> None:
    proc = _run(str(_tool("ruff")), "check", "--no-cache", "src", "tests", "benchmarks", "examples")
    assert proc.returncode == 0, proc.stdout + proc.stderr


def test_ruff_format() -> None:
    proc = _run(str(_tool("ruff")), "format", "--check", "--no-cache", "src", "tests", "benchmarks", "examples")
    assert proc.returncode == 0, proc.stdout + proc.stderr


def test_mypy() -> None:
    proc = _run(str(_tool("mypy")))  # configuration (files = ["src/lcreg"]) in pyproject.toml
    assert proc.returncode == 0, proc.stdout + proc.stderr
