from __future__ import annotations

import lcreg.data
from lcreg.checks import DatasetLayoutError


def test_every_lazy_name_resolves_to_its_object() -> None:
    for name in lcreg.data.__all__:
        assert getattr(lcreg.data, name).__name__ == name, name
    assert lcreg.data.DatasetLayoutError is DatasetLayoutError  # defined in lcreg.checks, part of the data API
