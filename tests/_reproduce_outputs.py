"""Reading what ``lcreg reproduce`` wrote: JSONL rows and a check that a PNG is a drawn figure."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any


def read_jsonl(path: Path) -> list[dict[str, Any]]:
    """Every row of a JSONL file."""
    return [json.loads(line) for line in path.read_text().splitlines()]


def assert_png_drawn(path: Path) -> None:
    """``path`` is a PNG taller than 300 pixels with visible contrast (not a blank canvas)."""
    from matplotlib.image import imread

    image = imread(path)[..., :3]
    assert image.shape[0] > 300 and image.std() > 0.05, path
