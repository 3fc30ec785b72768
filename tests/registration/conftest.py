"""Fixtures of the register tests."""

from __future__ import annotations

import numpy as np
import pytest

from _register_pairs import make_pair  # type: ignore[import-not-found]


@pytest.fixture(scope="session")
def pair() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(source (3000, 3), reference (3000, 3), ground truth (4, 4))`` float64: the reference = the moved source."""
    return make_pair()
