"""``lcreg.figures``: Agg figures without pyplot, PNGs written where asked at the figure's size."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from lcreg.figures import agg_figure, save_png

pytest.importorskip("matplotlib")


def test_agg_figure_draws_and_saves_a_png_of_its_size_in_a_new_folder(tmp_path: Path) -> None:
    from matplotlib.image import imread

    fig = agg_figure(4.0, 2.5, 50, "a test")
    fig.subplots().plot([0, 1], [1, 0])
    path = save_png(fig, tmp_path / "new" / "folder" / "plot.png")
    image = imread(path)
    assert image.shape[:2] == (125, 200) and image[..., :3].std() > 0.01
    assert save_png(fig, tmp_path / "big.png", dpi=100) and imread(tmp_path / "big.png").shape[:2] == (250, 400)


def test_neither_importing_nor_drawing_loads_pyplot() -> None:
    code = (
        "import sys; import lcreg.figures as f; a = 'matplotlib' in sys.modules; "
        "f.agg_figure(2, 2, 30, 'x').subplots(); print(a, 'matplotlib.pyplot' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["False", "False"]  # matplotlib is imported on the first figure, pyplot never
