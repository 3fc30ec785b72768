from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch
from matplotlib.colors import to_rgb
from matplotlib.figure import Figure
from scipy.ndimage import binary_dilation
from scipy.spatial.transform import Rotation

from lcreg.checks import NonFiniteError, ShapeError, TooFewPointsError
from lcreg.viz import (
    COLOR_REF,
    COLOR_SRC,
    DisplayUnavailableError,
    _open3d_geometries,
    plot_registration,
    show_registration,
)

COLOR_TOL = 0.12
"""Largest RGB distance (0-1 scale) of a pixel counted as one of the two cloud colours."""
DPI = 100
"""Resolution of the figures whose pixels are read (the default 150 is slower to draw)."""
ALIGNED, APART = 0.85, 0.25
"""Overlap (:func:`_overlap`) of a panel whose clouds coincide is above ``ALIGNED``; of one where they do not, below
``APART``."""


def _shape(num: int, seed: int) -> np.ndarray:
    """Points ``(num, 3)`` along a widening helix (two turns, 1.5 high): thin curves in every projection."""
    gen = np.random.default_rng(seed)
    t = gen.random(num)
    radius = 0.3 + 0.7 * t
    curve = np.stack([radius * np.cos(4 * np.pi * t), radius * np.sin(4 * np.pi * t), 1.5 * t - 0.75], axis=1)
    return curve + 0.005 * gen.standard_normal((num, 3))


def _transform() -> np.ndarray:
    """``transform_ref_src (4, 4)``: a 60° rotation about an oblique axis and a translation of about half the size."""
    transform = np.eye(4)
    transform[:3, :3] = Rotation.from_rotvec(np.radians(60) * np.array([1.0, 2.0, 3.0]) / np.sqrt(14)).as_matrix()
    transform[:3, 3] = [0.6, -0.3, 0.4]
    return transform


def _inverse(transform: np.ndarray) -> np.ndarray:
    inv = np.eye(4)
    inv[:3, :3] = transform[:3, :3].T
    inv[:3, 3] = -transform[:3, :3].T @ transform[:3, 3]
    return inv


def _pair(num: int = 3000) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(points_src, points_ref, transform_ref_src)``: two independent samplings, the source in its own frame."""
    transform = _transform()
    ref = _shape(num, seed=1)
    inv = _inverse(transform)
    src = _shape(num, seed=2) @ inv[:3, :3].T + inv[:3, 3]
    return src, ref, transform


def _pixels(fig: Figure) -> np.ndarray:
    """RGB ``(H, W, 3)`` in [0, 1] of the figure drawn on its Agg canvas."""
    fig.canvas.draw()
    return np.asarray(fig.canvas.buffer_rgba())[..., :3] / 255.0


def _panels(fig: Figure, image: np.ndarray) -> list[np.ndarray]:
    """The inside of the 6 panels (row-major: before top/front/side, after top/front/side), spines cut off."""
    height = image.shape[0]
    crops = []
    for ax in fig.axes:
        box = ax.get_window_extent()
        x0, x1 = round(box.x0) + 3, round(box.x1) - 3
        y0, y1 = height - round(box.y1) + 3, height - round(box.y0) - 3
        crops.append(image[y0:y1, x0:x1])
    return crops


def _mask(pixels: np.ndarray, color: str) -> np.ndarray:
    return np.linalg.norm(pixels - np.array(to_rgb(color)), axis=-1) < COLOR_TOL


def _near(mask: np.ndarray, other: np.ndarray) -> float:
    """Fraction of the pixels of ``mask`` within 4 pixels of a pixel of ``other`` (masks of one shape)."""
    return float((mask & binary_dilation(other, iterations=4)).sum() / max(int(mask.sum()), 1))


def _overlap(panel: np.ndarray) -> float:
    """Fraction of source-coloured pixels within 4 pixels of a reference-coloured pixel."""
    return _near(_mask(panel, COLOR_SRC), _mask(panel, COLOR_REF))


def _row_overlaps(fig: Figure) -> tuple[list[float], list[float]]:
    overlaps = [_overlap(panel) for panel in _panels(fig, _pixels(fig))]
    return overlaps[:3], overlaps[3:]


# --------------------------------------------------------------------------------------------------- the picture


def test_png_is_written_valid_and_shows_both_clouds(tmp_path: Path) -> None:
    from matplotlib.image import imread

    src, ref, transform = _pair()
    path = tmp_path / "reg.png"
    fig = plot_registration(src, ref, transform, path, title="a pair", dpi=DPI)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    image = imread(path)[..., :3]
    width, height = fig.get_size_inches() * DPI
    assert abs(image.shape[0] - height) <= 1 and abs(image.shape[1] - width) <= 1  # Agg truncates
    assert _mask(image, COLOR_SRC).sum() > 2000
    assert _mask(image, COLOR_REF).sum() > 2000
    assert image.std() > 0.05
    assert [ax.get_title() for ax in fig.axes] == ["top (x-y)", "front (x-z)", "side (y-z)"] * 2
    assert [ax.get_xlabel() + ax.get_ylabel() for ax in fig.axes] == ["xy", "xz", "yz"] * 2
    assert fig.get_suptitle() == "a pair"
    assert len(fig.legends) == 1


def test_ground_truth_aligns_the_after_row_and_the_inverse_does_not() -> None:
    src, ref, transform = _pair()
    before, after = _row_overlaps(plot_registration(src, ref, transform, dpi=DPI))
    _, after_inverse = _row_overlaps(plot_registration(src, ref, _inverse(transform), dpi=DPI))
    assert min(after) > ALIGNED, after  # about 0.95 (at DPI)
    assert max(before) < APART, before  # below 0.11
    assert max(after_inverse) < APART, after_inverse  # below 0.04: the transform applied the wrong way round


def test_after_row_equals_before_row_only_for_the_identity() -> None:
    src, ref, transform = _pair()

    def source_in_both_rows(transform_ref_src: np.ndarray) -> list[float]:
        """Per column: how much of the after row's source lies where the before row's source is."""
        fig = plot_registration(src, ref, transform_ref_src, dpi=DPI)
        masks = [_mask(panel, COLOR_SRC) for panel in _panels(fig, _pixels(fig))]
        near = []
        for before, after in zip(masks[:3], masks[3:]):
            rows, cols = min(before.shape[0], after.shape[0]), min(before.shape[1], after.shape[1])
            near.append(_near(after[:rows, :cols], before[:rows, :cols]))
        return near

    assert min(source_in_both_rows(np.eye(4))) > 0.99
    assert max(source_in_both_rows(transform)) < APART


def test_panels_of_a_column_share_limits_and_equal_aspect() -> None:
    src, ref, transform = _pair()
    fig = plot_registration(src, ref, transform)
    for top, bottom in zip(fig.axes[:3], fig.axes[3:]):
        assert top.get_xlim() == bottom.get_xlim() and top.get_ylim() == bottom.get_ylim()
        assert top.get_aspect() == bottom.get_aspect() == 1.0
    moved = src @ transform[:3, :3].T + transform[:3, 3]
    union = np.concatenate([src, moved, ref])
    for ax, (i, j) in zip(fig.axes, [(0, 1), (0, 2), (1, 2)] * 2):
        (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
        assert x0 <= union[:, i].min() and union[:, i].max() <= x1
        assert y0 <= union[:, j].min() and union[:, j].max() <= y1


def test_limits_ignore_a_far_outlier() -> None:
    src, ref, transform = _pair()
    ref[0] = [1000.0, 1000.0, 1000.0]
    fig = plot_registration(src, ref, transform)
    assert all(ax.get_xlim()[1] < 5 and ax.get_ylim()[1] < 5 for ax in fig.axes)


# --------------------------------------------------------------------------------------------------- inputs


@pytest.mark.parametrize(
    "convert",
    [
        pytest.param(lambda x: x, id="numpy-float64"),
        pytest.param(lambda x: x.astype(np.float32), id="numpy-float32"),
        pytest.param(lambda x: torch.from_numpy(x.astype(np.float32)), id="torch-float32"),
        pytest.param(torch.from_numpy, id="torch-float64"),
    ],
)
def test_numpy_and_torch_inputs_of_both_dtypes(convert: Callable[[np.ndarray], object]) -> None:
    src, ref, transform = _pair()
    before, after = _row_overlaps(plot_registration(convert(src), convert(ref), convert(transform), dpi=DPI))
    assert min(after) > ALIGNED and max(before) < APART


def test_torch_and_numpy_give_the_same_pixels() -> None:
    src, ref, transform = _pair()
    numpy_pixels = _pixels(plot_registration(src, ref, transform, dpi=DPI))
    src_t = torch.from_numpy(src).requires_grad_()
    torch_pixels = _pixels(plot_registration(src_t, torch.from_numpy(ref), torch.from_numpy(transform), dpi=DPI))
    np.testing.assert_array_equal(numpy_pixels, torch_pixels)


def test_subsampling_is_bounded_and_deterministic() -> None:
    src, ref, transform = _pair(5000)
    fig = plot_registration(src, ref, transform, max_points=1000, seed=3, dpi=DPI)
    assert all(len(ax.collections[0].get_offsets()) == 2000 for ax in fig.axes)
    labels = [text.get_text() for text in fig.legends[0].get_texts()]
    assert labels == ["source (1,000 of 5,000 points shown)", "reference (1,000 of 5,000 points shown)"]
    same = plot_registration(src, ref, transform, max_points=1000, seed=3, dpi=DPI)
    np.testing.assert_array_equal(_pixels(fig), _pixels(same))
    other = plot_registration(src, ref, transform, max_points=1000, seed=4, dpi=DPI)
    shown, shown_other = (set(map(tuple, f.axes[0].collections[0].get_offsets().tolist())) for f in (fig, other))
    assert len(shown & shown_other) < 1000  # about 200 of the 2000 points drawn by both seeds


def test_small_clouds_are_not_subsampled() -> None:
    src, ref, transform = _pair(300)
    fig = plot_registration(src[:200], ref, transform, max_points=250)
    assert all(len(ax.collections[0].get_offsets()) == 450 for ax in fig.axes)
    labels = [text.get_text() for text in fig.legends[0].get_texts()]
    assert labels == ["source (200 points)", "reference (250 of 300 points shown)"]


def test_pyplot_is_never_imported_and_the_backend_is_unchanged(tmp_path: Path) -> None:
    script = f"""
import json, sys
import matplotlib
import numpy as np
import lcreg.viz
points = np.random.default_rng(0).random((500, 3))
raw = dict.__getitem__(matplotlib.rcParams, "backend")  # reading rcParams["backend"] could resolve it
lcreg.viz.plot_registration(points, points, np.eye(4), {str(tmp_path / "auto.png")!r})
report = {{"auto": dict.__getitem__(matplotlib.rcParams, "backend") == raw}}
matplotlib.use("svg")
lcreg.viz.plot_registration(points, points, np.eye(4), {str(tmp_path / "svg.png")!r})
report.update(svg=matplotlib.get_backend(), pyplot="matplotlib.pyplot" in sys.modules)
print(json.dumps(report))
"""
    env = {key: value for key, value in os.environ.items() if key != "MPLBACKEND"}
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120, env=env)
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout.strip().splitlines()[-1]) == {"auto": True, "svg": "svg", "pyplot": False}
    assert all((tmp_path / name).read_bytes()[:4] == b"\x89PNG" for name in ("auto.png", "svg.png"))


# --------------------------------------------------------------------------------------------------- errors


def _bad(**change: object) -> dict[str, object]:
    src, ref, transform = _pair(100)
    args: dict[str, object] = {"points_src": src, "points_ref": ref, "transform_ref_src": transform}
    args.update(change)
    return args


def _with(x: np.ndarray, index: tuple[int, ...], value: float) -> np.ndarray:
    x = x.copy()
    x[index] = value
    return x


SRC, REF, TRANSFORM = _pair(100)
SCALED = _with(TRANSFORM, (0, 0), 2.0 * TRANSFORM[0, 0])
REFLECTION = TRANSFORM @ np.diag([-1.0, 1.0, 1.0, 1.0])
ERRORS = [
    ({"points_src": _with(SRC, (3, 1), np.nan)}, NonFiniteError, "points_src"),
    ({"points_ref": _with(REF, (0, 2), np.inf)}, NonFiniteError, "points_ref"),
    ({"points_src": SRC[:, :2]}, ShapeError, "points_src"),
    ({"points_ref": REF[None]}, ShapeError, "points_ref"),
    ({"points_src": SRC[:0]}, TooFewPointsError, "points_src"),
    ({"points_ref": torch.zeros(0, 3)}, TooFewPointsError, "points_ref"),
    ({"points_src": SRC.astype(np.int64)}, TypeError, "points_src"),
    ({"points_ref": REF.tolist()}, TypeError, "points_ref"),
    ({"transform_ref_src": TRANSFORM[:3]}, ShapeError, "transform_ref_src"),
    ({"transform_ref_src": _with(TRANSFORM, (1, 3), np.nan)}, NonFiniteError, "transform_ref_src"),
    ({"transform_ref_src": SCALED}, ValueError, "transform_ref_src"),
    ({"transform_ref_src": REFLECTION}, ValueError, "transform_ref_src"),
    ({"transform_ref_src": _with(TRANSFORM, (3, 0), 0.5)}, ValueError, "transform_ref_src"),
    ({"max_points": 0}, ValueError, "max_points"),
]


@pytest.mark.parametrize(("change", "error", "name"), ERRORS)
def test_invalid_inputs_raise_typed_errors_naming_the_argument(
    change: dict[str, object], error: type[Exception], name: str
) -> None:
    with pytest.raises(error, match=f"`{name}`") as info:
        plot_registration(**_bad(**change))
    if error is ValueError:
        assert type(info.value) is ValueError


def test_path_must_be_a_png(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"\.png"):
        plot_registration(SRC, REF, TRANSFORM, tmp_path / "out.jpg")
    assert list(tmp_path.iterdir()) == []


def test_missing_parent_folder_is_refused_not_created(tmp_path: Path) -> None:
    missing = tmp_path / "no" / "such"
    with pytest.raises(FileNotFoundError, match=str(missing)):
        plot_registration(SRC, REF, TRANSFORM, missing / "out.png")
    assert not (tmp_path / "no").exists()


# --------------------------------------------------------------------------------------------------- Open3D


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the no-display rule is for Linux")
def test_show_without_a_display_raises_before_importing_open3d(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setitem(sys.modules, "open3d", None)  # an import would raise ImportError
    with pytest.raises(DisplayUnavailableError, match=r"--plot out\.png"):
        show_registration(SRC, REF, TRANSFORM)
    assert issubclass(DisplayUnavailableError, RuntimeError)


def test_show_with_a_display_draws_both_clouds(monkeypatch: pytest.MonkeyPatch) -> None:
    import open3d as o3d

    calls = []
    monkeypatch.setenv("DISPLAY", ":99")
    monkeypatch.setattr(o3d.visualization, "draw_geometries", lambda geoms, **kw: calls.append((geoms, kw)))
    show_registration(SRC, REF, TRANSFORM, window_name="pair 0")
    ((geometries, kwargs),) = calls
    assert kwargs == {"window_name": "pair 0"}
    assert [len(g.points) for g in geometries] == [len(SRC), len(REF)]


def test_open3d_geometries_hold_the_moved_source_and_the_reference() -> None:
    src32 = torch.from_numpy(SRC.astype(np.float32))
    moved, ref = _open3d_geometries(src32, REF, torch.from_numpy(TRANSFORM))
    expected = SRC.astype(np.float32).astype(np.float64) @ TRANSFORM[:3, :3].T + TRANSFORM[:3, 3]
    np.testing.assert_allclose(np.asarray(moved.points), expected, atol=1e-12)
    np.testing.assert_array_equal(np.asarray(ref.points), REF)
    np.testing.assert_allclose(np.asarray(moved.colors), np.tile(to_rgb(COLOR_SRC), (len(SRC), 1)), atol=1e-12)
    np.testing.assert_allclose(np.asarray(ref.colors), np.tile(to_rgb(COLOR_REF), (len(REF), 1)), atol=1e-12)


def test_open3d_geometries_validate_their_inputs() -> None:
    with pytest.raises(NonFiniteError, match="`points_ref`"):
        _open3d_geometries(SRC, _with(REF, (0, 0), np.nan), TRANSFORM)
    with pytest.raises(ValueError, match="`transform_ref_src`"):
        _open3d_geometries(SRC, REF, SCALED)
