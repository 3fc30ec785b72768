"""Location of the real data shared by all projects (``<repo_root>/../shared/data``) for the data tests."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = (REPO_ROOT / ".." / "shared" / "data").resolve()
MODELNET40_MINI = SHARED_DATA / "modelnet40_mini"


def shared_data(name: str) -> Path:
    """Path of ``<repo_root>/../shared/data/<name>``, skipping the calling test with a reason when it is absent."""
    path = SHARED_DATA / name
    if not path.is_dir():
        pytest.skip(f"real data {name!r} not found at {path} (expected <repo_root>/../shared/data/{name})")
    return path
