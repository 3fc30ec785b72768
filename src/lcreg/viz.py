"""Pictures of one registration: a source cloud, a reference cloud and ``transform_ref_src``.

* :func:`plot_registration` draws a 2 x 3 grid of orthogonal projections (columns: top ``x-y``, front ``x-z``, side
  ``y-z``; rows: the source as given and the source moved by the transform, each over the reference) and optionally
  writes it as a PNG. It never imports ``matplotlib.pyplot`` and never calls ``matplotlib.use``: the figure is a
  plain :class:`matplotlib.figure.Figure` on an Agg canvas, so it works without a display and leaves the caller's
  backend alone. Each cloud is subsampled to at most ``max_points`` points by a seeded generator (millions of points
  plot in about a second, and the same seed gives the same pixels).
* :func:`show_registration` opens an interactive Open3D window with the reference and the moved source; without a
  display it raises :class:`DisplayUnavailableError` before trying.

The transform follows the package convention: ``p_ref = R p_src + t`` (``lcreg.geometry.se3``). matplotlib (the
``plot`` extra) and Open3D are imported inside the functions that need them.
"""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from lcreg.checks import TooFewPointsError, check_finite, check_float, check_rigid, check_shape
from lcreg.figures import agg_figure
from lcreg.geometry import se3

if TYPE_CHECKING:
    import open3d as o3d
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

__all__ = [
    "COLOR_REF",
    "COLOR_SRC",
    "VIEWS",
    "DisplayUnavailableError",
    "check_display",
    "plot_registration",
    "show_registration",
]

COLOR_SRC = "#e6550d"
"""Source points (orange)."""
COLOR_REF = "#3182bd"
"""Reference points (blue)."""
VIEWS = (("top", 0, 1), ("front", 0, 2), ("side", 1, 2))
"""Columns of :func:`plot_registration`: view name and the two coordinates it shows (0 = x, 1 = y, 2 = z)."""
ROWS = (("before", "source as given"), ("after", "source moved by transform_ref_src"))
"""Rows of :func:`plot_registration`: label and caption."""
AXIS_NAMES = "xyz"
FIGURE_WIDTH = 13.0
"""Figure width in inches; the height follows the panels' aspect."""
MAX_PANEL_HEIGHT = 4.5
"""Largest panel height in inches."""
LIMIT_PERCENTILES = (0.5, 99.5)
"""Panel limits are set from these percentiles of the shown points (a few far outliers do not shrink the data)."""
OUTLIER_REACH = 0.25
"""Points up to this fraction of the percentile span beyond the percentiles stay inside the limits."""
LIMIT_MARGIN = 0.03
"""Extra space on each side of the limits, as a fraction of the largest extent."""

PointsLike = np.ndarray | torch.Tensor


class DisplayUnavailableError(RuntimeError):
    """An interactive window was asked for where no display exists (Linux without ``DISPLAY``/``WAYLAND_DISPLAY``)."""


# --------------------------------------------------------------------------------------------------- validation


def _as_float_tensor(x: object, name: str) -> torch.Tensor:
    """Return ``x`` (a numpy array or torch tensor, float32/float64) as a detached tensor, sharing memory.

    Raises:
        TypeError: For another type or dtype.
    """
    if isinstance(x, np.ndarray):
        if x.dtype.kind != "f" or x.dtype.itemsize not in (4, 8):
            raise TypeError(f"`{name}` must be float32 or float64, got {x.dtype}")
        x = torch.from_numpy(np.ascontiguousarray(x, dtype=np.float32 if x.dtype.itemsize == 4 else np.float64))
    elif not isinstance(x, torch.Tensor):
        raise TypeError(f"`{name}` must be a numpy array or a torch.Tensor, got {type(x).__name__}")
    return check_float(x, name).detach()


def _check_cloud(x: object, name: str) -> torch.Tensor:
    """Validate one cloud ``(N, 3)``, ``N >= 1``, finite; returns it as a tensor.

    Raises:
        TypeError: Not a float32/float64 array or tensor.
        ShapeError: Not ``(N, 3)``.
        TooFewPointsError: ``N == 0``.
        NonFiniteError: NaN or Inf coordinates.
    """
    points = _as_float_tensor(x, name)
    check_shape(points, ("N", 3), name)
    if points.shape[0] == 0:
        raise TooFewPointsError(f"`{name}` is empty; at least 1 point is needed")
    check_finite(points, name)
    return points


def _check_transform(x: object, name: str) -> torch.Tensor:
    """Validate a rigid ``(4, 4)`` transform; returns it as a float64 CPU tensor.

    Raises:
        TypeError: Not a float32/float64 array or tensor.
        ShapeError: Not ``(4, 4)``.
        NonFiniteError: NaN or Inf entries.
        ValueError: Not a rigid motion ``[R t; 0 0 0 1]`` (:func:`lcreg.checks.check_rigid`).
    """
    transform = _as_float_tensor(x, name)
    check_shape(transform, (4, 4), name)
    check_finite(transform, name)
    transform = transform.cpu().double()
    check_rigid(transform[None], name)
    return transform


def _check_png_path(path: str | os.PathLike[str]) -> Path:
    """Return ``path`` as a :class:`Path` if it names a ``.png`` file in an existing folder.

    Raises:
        ValueError: Another suffix.
        FileNotFoundError: The parent folder does not exist (it is not created).
    """
    out = Path(path)
    if out.suffix.lower() != ".png":
        raise ValueError(f"`path` must end with .png, got {str(out)!r}")
    if not out.parent.is_dir():
        raise FileNotFoundError(f"`path`: folder {str(out.parent)!r} does not exist (it is not created)")
    return out


def _check_positive_int(value: int, name: str) -> None:
    """Raise ``ValueError`` unless ``value`` is an integer >= 1 (``bool`` excluded)."""
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
        raise ValueError(f"`{name}` must be an integer >= 1, got {value!r}")


# --------------------------------------------------------------------------------------------------- geometry


def _subsample(points: torch.Tensor, max_points: int, rng: np.random.Generator) -> np.ndarray:
    """At most ``max_points`` rows of ``points (N, 3)``, drawn without replacement, as float64 ``(K, 3)``."""
    if points.shape[0] > max_points:
        keep = np.sort(rng.choice(points.shape[0], size=max_points, replace=False))
        points = points[torch.from_numpy(keep).to(points.device)]
    return points.cpu().double().numpy()


def _move(transform_ref_src: torch.Tensor, points: np.ndarray) -> np.ndarray:
    """``R p + t`` for float64 ``points (K, 3)`` and a float64 ``(4, 4)`` transform (``lcreg.geometry.se3``)."""
    moved = se3.transform_points(transform_ref_src[None], torch.from_numpy(points)[None])
    return moved[0].numpy()


def _limits(*clouds: np.ndarray) -> np.ndarray:
    """Shared ``(3, 2)`` axis limits of ``clouds``, robust to a few far outliers, never an empty interval.

    The 0.5-99.5 percentiles set the scale; the limits reach the extreme points unless these lie more than
    :data:`OUTLIER_REACH` of that span beyond the percentiles (then they stop there), plus :data:`LIMIT_MARGIN`.
    """
    stacked = np.concatenate(clouds, axis=0)
    low, high = np.percentile(stacked, LIMIT_PERCENTILES, axis=0)  # (3,), (3,)
    reach = OUTLIER_REACH * (high - low)
    low = np.maximum(stacked.min(axis=0), low - reach)
    high = np.minimum(stacked.max(axis=0), high + reach)
    largest = float((high - low).max()) or max(float(np.abs(stacked).max()), 1.0)
    half = np.maximum(high - low, 0.02 * largest) / 2 + LIMIT_MARGIN * largest
    center = (low + high) / 2
    return np.stack([center - half, center + half], axis=1)


def _marker_size(num_points: int) -> float:
    """Scatter marker area in points^2: 2 for a few thousand points, down to 0.5 for tens of thousands."""
    return float(np.clip(2.0 * np.sqrt(2000.0 / max(num_points, 1)), 0.5, 2.0))


# --------------------------------------------------------------------------------------------------- drawing


def _width_ratios(limits: np.ndarray) -> list[float]:
    """Width / height of each column's equal-aspect panel, clipped to [0.4, 2.5] (a flat scan keeps a top view)."""
    extents = limits[:, 1] - limits[:, 0]
    return [float(np.clip(extents[i] / extents[j], 0.4, 2.5)) for _, i, j in VIEWS]


def _figure_size(ratios: list[float]) -> tuple[float, float]:
    """Figure inches: :data:`FIGURE_WIDTH` wide, two rows of panels as tall as the column ratios allow."""
    panel_height = min((FIGURE_WIDTH - 1.8) / sum(ratios), MAX_PANEL_HEIGHT)
    return FIGURE_WIDTH, 2 * panel_height + 1.8


@dataclass(frozen=True)
class _Layer:
    """The points of one row, source and reference interleaved in a random order (neither hides the other).

    Attributes:
        points: ``(N + M, 3)`` coordinates.
        colors: ``(N + M, 4)`` RGBA, :data:`COLOR_SRC` for source points and :data:`COLOR_REF` for reference points.
        size: Marker area of every point (:func:`_marker_size` of the larger cloud).
    """

    points: np.ndarray
    colors: np.ndarray
    size: float


def _layers(src: np.ndarray, after: np.ndarray, ref: np.ndarray, rng: np.random.Generator) -> tuple[_Layer, _Layer]:
    """The ``before`` (``src``) and ``after`` (``after``) rows over ``ref``, in one random drawing order."""
    from matplotlib.colors import to_rgba

    order = rng.permutation(len(src) + len(ref))
    colors = np.array([to_rgba(COLOR_SRC)] * len(src) + [to_rgba(COLOR_REF)] * len(ref))[order]
    size = _marker_size(max(len(src), len(ref)))
    before, moved = (np.concatenate([cloud, ref])[order] for cloud in (src, after))
    return _Layer(before, colors, size), _Layer(moved, colors, size)


def _draw_panel(ax: Axes, view: tuple[str, int, int], layer: _Layer, limits: np.ndarray) -> None:
    """Scatter ``layer``'s points projected on ``view``'s two coordinates, with shared ``limits`` and equal aspect."""
    _, i, j = view
    ax.scatter(layer.points[:, i], layer.points[:, j], s=layer.size, c=layer.colors, linewidths=0, rasterized=True)
    ax.set_xlim(*limits[i])
    ax.set_ylim(*limits[j])
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel(AXIS_NAMES[i])
    ax.set_ylabel(AXIS_NAMES[j])
    ax.tick_params(labelsize=7)


def _legend_label(name: str, shown: int, total: int) -> str:
    """``"source (12,000 of 250,000 points shown)"`` or ``"source (3,000 points)"``."""
    return f"{name} ({shown:,} of {total:,} points shown)" if shown < total else f"{name} ({total:,} points)"


def _legend(fig: Figure, labels: tuple[str, str]) -> None:
    """One legend below the panels (outside the data), large round markers of both colours."""
    from matplotlib.lines import Line2D

    handles = [
        Line2D([], [], linestyle="none", marker="o", markersize=8, color=color, label=label)
        for color, label in zip((COLOR_SRC, COLOR_REF), labels)
    ]
    fig.legend(handles=handles, loc="outside lower center", ncols=2, frameon=False)


def _draw(fig: Figure, layers: tuple[_Layer, _Layer], limits: np.ndarray) -> None:
    """Fill ``fig`` with two rows (sub-figures ``before`` and ``after``) of the three :data:`VIEWS`."""
    grid = fig.add_gridspec(2, 1)
    rows = [fig.add_subfigure(grid[row]) for row in range(2)]
    ratios = _width_ratios(limits)
    for subfig, layer, (label, caption) in zip(rows, layers, ROWS):
        subfig.suptitle(f"{label}: {caption}", fontweight="bold", fontsize=11)
        for ax, view in zip(subfig.subplots(1, 3, width_ratios=ratios), VIEWS):
            _draw_panel(ax, view, layer, limits)
            name, i, j = view
            ax.set_title(f"{name} ({AXIS_NAMES[i]}-{AXIS_NAMES[j]})", fontsize=10)


def plot_registration(
    points_src: PointsLike,
    points_ref: PointsLike,
    transform_ref_src: PointsLike,
    path: str | os.PathLike[str] | None = None,
    *,
    title: str | None = None,
    max_points: int = 20000,
    seed: int = 0,
    dpi: int = 150,
) -> Figure:
    """Draw a source and a reference cloud before and after moving the source by ``transform_ref_src``.

    A 2 x 3 grid of orthogonal projections: columns top (``x-y``), front (``x-z``) and side (``y-z``); the first row
    shows the source as given over the reference, the second the source moved into the reference frame
    (``p_ref = R p_src + t``). Source points are orange (:data:`COLOR_SRC`), reference points blue
    (:data:`COLOR_REF`), drawn in one random order so that neither cloud hides the other. The panels of a column
    share their limits (every shown point but far outliers beyond the 0.5-99.5 percentiles, plus a margin) and have
    an equal aspect. ``matplotlib.pyplot`` is not used:
    the figure has an Agg canvas and the backend is left unchanged.

    Args:
        points_src: Source cloud ``(N, 3)``, numpy array or torch tensor, float32 or float64.
        points_ref: Reference cloud ``(M, 3)``, same types.
        transform_ref_src: Rigid transform ``(4, 4)`` mapping source coordinates into the reference frame.
        path: If given, the PNG written (its folder must exist); the suffix must be ``.png``.
        title: Title above the grid.
        max_points: Each cloud is subsampled to at most this many points (without replacement).
        seed: Seed of the subsampling generator: the same seed draws the same points.
        dpi: Resolution of the figure and the PNG.

    Returns:
        The figure (a :class:`matplotlib.figure.Figure` on a ``FigureCanvasAgg``).

    Raises:
        TypeError: A cloud or the transform is not a float32/float64 numpy array or torch tensor.
        ShapeError: A cloud is not ``(N, 3)`` or the transform is not ``(4, 4)``.
        TooFewPointsError: A cloud is empty.
        NonFiniteError: A cloud or the transform has NaN/Inf entries.
        ValueError: The transform is not rigid, ``path`` does not end with ``.png``, or ``max_points``/``dpi`` are
            not integers >= 1.
        FileNotFoundError: The folder of ``path`` does not exist.
        ImportError: matplotlib is not installed (``pip install 'lcreg[plot]'``).
    """
    src_all = _check_cloud(points_src, "points_src")
    ref_all = _check_cloud(points_ref, "points_ref")
    transform = _check_transform(transform_ref_src, "transform_ref_src")
    _check_positive_int(max_points, "max_points")
    _check_positive_int(dpi, "dpi")
    out = None if path is None else _check_png_path(path)
    rng = np.random.default_rng(seed)
    src, ref = _subsample(src_all, max_points, rng), _subsample(ref_all, max_points, rng)
    after = _move(transform, src)
    limits = _limits(src, after, ref)
    fig = agg_figure(*_figure_size(_width_ratios(limits)), dpi, "plot_registration")
    _draw(fig, _layers(src, after, ref, rng), limits)
    labels = (_legend_label("source", len(src), len(src_all)), _legend_label("reference", len(ref), len(ref_all)))
    _legend(fig, labels)
    if title is not None:
        fig.suptitle(title)
    if out is not None:
        fig.savefig(out, dpi=dpi, format="png")
    return fig


# --------------------------------------------------------------------------------------------------- Open3D window


def _hex_rgb(color: str) -> np.ndarray:
    """``"#rrggbb"`` as float64 RGB ``(3,)`` in ``[0, 1]``."""
    return np.array([int(color[k : k + 2], 16) for k in (1, 3, 5)], dtype=np.float64) / 255.0


def check_display() -> None:
    """Raise :class:`DisplayUnavailableError` on Linux without ``DISPLAY`` and ``WAYLAND_DISPLAY``."""
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise DisplayUnavailableError(
            "no display to open a window on (neither DISPLAY nor WAYLAND_DISPLAY is set); "
            "write a picture instead, e.g. `--plot out.png` (lcreg.viz.plot_registration)"
        )


def _open3d_geometries(
    points_src: PointsLike, points_ref: PointsLike, transform_ref_src: PointsLike
) -> tuple[o3d.geometry.PointCloud, o3d.geometry.PointCloud]:
    """The moved source (orange) and the reference (blue) as coloured Open3D clouds, every point kept.

    Returns:
        ``(source moved by transform_ref_src, reference)``, float64 points.
    """
    import open3d as o3d

    src = _check_cloud(points_src, "points_src").cpu().double().numpy()
    ref = _check_cloud(points_ref, "points_ref").cpu().double().numpy()
    moved = _move(_check_transform(transform_ref_src, "transform_ref_src"), src)
    clouds = []
    for points, color in ((moved, COLOR_SRC), (ref, COLOR_REF)):
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(points)))
        cloud.paint_uniform_color(_hex_rgb(color))
        clouds.append(cloud)
    return clouds[0], clouds[1]


def show_registration(
    points_src: PointsLike,
    points_ref: PointsLike,
    transform_ref_src: PointsLike,
    *,
    window_name: str = "lcreg register",
) -> None:
    """Open an Open3D window with the reference (blue) and the source moved into its frame (orange).

    Blocks until the window is closed.

    Args:
        points_src: Source cloud ``(N, 3)``, numpy array or torch tensor, float32 or float64.
        points_ref: Reference cloud ``(M, 3)``, same types.
        transform_ref_src: Rigid transform ``(4, 4)`` mapping source coordinates into the reference frame.
        window_name: Title of the window.

    Raises:
        DisplayUnavailableError: Linux without ``DISPLAY``/``WAYLAND_DISPLAY`` (checked before anything else).
        TypeError, ShapeError, TooFewPointsError, NonFiniteError, ValueError: As :func:`plot_registration`.
    """
    check_display()
    geometries = _open3d_geometries(points_src, points_ref, transform_ref_src)
    import open3d as o3d

    o3d.visualization.draw_geometries(list(geometries), window_name=window_name)
