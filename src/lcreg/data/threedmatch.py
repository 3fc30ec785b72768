"""3DMatch / 3DLoMatch / 7-Scenes fragment pairs in the official geometric-registration benchmark layout.

Layout of ``root`` (the folder of the official test-set download, or any folder in the same layout)::

    root/
      fragments/<scene>/cloud_bin_<k>.ply          fused RGB-D fragment k of the scene (xyz, metres)
      benchmarks/3DMatch/<scene>/gt.log            ground truth of the pairs with more than 30 % overlap
      benchmarks/3DMatch/<scene>/gt_overlap.log    ``i,j,overlap`` for fragment pairs of the scene
      benchmarks/3DLoMatch/<scene>/...             the low-overlap (10-30 %) pairs, same format

``gt.log`` is a list of blocks of five lines: a header ``i j n`` (two fragment indices and the number of fragments
of the scene) then the rows of a 4x4 matrix ``[R t; 0 1]`` that maps the points of fragment ``j`` into the frame of
fragment ``i``. A pair therefore has source = fragment ``j``, reference = fragment ``i`` and
``transform_ref_src`` = the matrix as written. The scene ``7-scenes-redkitchen`` is Microsoft 7-Scenes redkitchen;
the other seven test scenes come from SUN3D.

The listed overlap agrees with the fraction of the reference fragment's points (fragment ``i``) that have a point of
the mapped source fragment within 5 cm (measured on the 197 3DMatch pairs above 70 %: that fraction is 0.02 below
to 0.13 above the listed value); the fraction of the source points covered by the reference can be much lower.

Pair selection (:func:`threedmatch_pairs`): a gt.log pair is kept when its listed overlap is strictly more than
``min_overlap`` (the "more than 70 %" of the 7-Scenes protocol). ``gt_overlap.log`` is needed for that: when it is
missing, or lacks a gt.log pair, a :class:`~lcreg.checks.DatasetLayoutError` /
:class:`FileNotFoundError` is raised instead of silently dropping pairs, unless ``min_overlap <= 0`` (no filter;
the overlap is then filled in when known and ``None`` otherwise). Every pair of the 3DLoMatch lists has an overlap
of at most 30 %, so select them with ``min_overlap=0`` (or ``0.1``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np

from lcreg.checks import DatasetLayoutError, dataset_root
from lcreg.data.scenes import ScenePair, ScenePairDataModule, Split

__all__ = [
    "BENCHMARKS",
    "EXPECTED_LAYOUT",
    "SEVEN_SCENES_REDKITCHEN",
    "Block",
    "GtLog",
    "SevenScenesDataModule",
    "fragment_path",
    "list_scenes",
    "pair_paths",
    "read_blocks",
    "read_gt_log",
    "read_gt_overlap",
    "threedmatch_pairs",
]

Benchmark = Literal["3DMatch", "3DLoMatch"]

BENCHMARKS: tuple[Benchmark, ...] = ("3DMatch", "3DLoMatch")
"""Names of the benchmark folders under ``<root>/benchmarks``."""

SEVEN_SCENES_REDKITCHEN = "7-scenes-redkitchen"
"""The 3DMatch test scene that is Microsoft 7-Scenes redkitchen (60 fragments)."""

EXPECTED_LAYOUT = (
    "expected the official 3DMatch geometric-registration layout: <root>/fragments/<scene>/cloud_bin_<k>.ply and "
    "<root>/benchmarks/{3DMatch,3DLoMatch}/<scene>/gt.log (blocks 'i j n' + 4x4 matrix mapping fragment j into "
    "fragment i) with gt_overlap.log ('i,j,overlap' lines) beside it"
)

_BOTTOM_ROW = np.array([0.0, 0.0, 0.0, 1.0])
_BOTTOM_ROW_TOL = 1e-6


@dataclass(frozen=True)
class GtLog:
    """Content of one ``gt.log``.

    Attributes:
        transforms: ``(i, j) -> (4, 4)`` float64 ``[R t; 0 1]`` mapping fragment ``j`` into the frame of fragment
            ``i``, in file order.
        num_fragments: ``n`` of the block headers (number of fragments of the scene).
    """

    transforms: dict[tuple[int, int], np.ndarray] = field(repr=False)
    num_fragments: int


def _numbered_lines(path: Path) -> list[tuple[int, list[str]]]:
    """Non-blank lines of ``path`` as ``(1-based line number, whitespace-split tokens)``."""
    if not path.is_file():
        raise FileNotFoundError(f"{str(path)!r} does not exist or is not a file; {EXPECTED_LAYOUT}")
    try:
        with path.open(encoding="utf-8") as handle:
            return [(number, line.split()) for number, line in enumerate(handle, start=1) if line.strip()]
    except UnicodeDecodeError as err:
        raise DatasetLayoutError(f"{str(path)!r} is not a text file ({err}); {EXPECTED_LAYOUT}") from err


def _layout_error(path: Path, line: int, message: str) -> DatasetLayoutError:
    return DatasetLayoutError(f"{str(path)!r}, line {line}: {message}")


def _parse_header(path: Path, line: int, tokens: list[str]) -> tuple[int, int, int]:
    """Parse a gt.log block header ``i j n``."""
    if len(tokens) != 3:
        raise _layout_error(path, line, f"expected a block header 'i j n' (3 integers), got {' '.join(tokens)!r}")
    try:
        i, j, n = (int(token) for token in tokens)
    except ValueError:
        raise _layout_error(path, line, f"block header 'i j n' must hold integers, got {' '.join(tokens)!r}") from None
    if n <= 0 or not (0 <= i < n and 0 <= j < n):
        raise _layout_error(path, line, f"header {' '.join(tokens)!r} needs n > 0 and 0 <= i, j < n")
    return i, j, n


def _parse_row(path: Path, line: int, tokens: list[str], size: int) -> list[float]:
    """Parse one row of a ``size x size`` matrix: ``size`` finite numbers."""
    if len(tokens) != size:
        raise _layout_error(path, line, f"expected a matrix row of {size} numbers, got {' '.join(tokens)!r}")
    try:
        row = [float(token) for token in tokens]
    except ValueError:
        raise _layout_error(path, line, f"matrix row must hold numbers, got {' '.join(tokens)!r}") from None
    if not all(math.isfinite(value) for value in row):
        raise _layout_error(path, line, f"matrix row holds a non-finite value: {' '.join(tokens)!r}")
    return row


def read_gt_log(path: str | Path) -> GtLog:
    """Read a 3DMatch ``gt.log`` (blocks of a header ``i j n`` and a 4x4 matrix; tabs and blank lines allowed).

    Args:
        path: The ``gt.log`` file.

    Returns:
        :class:`GtLog` with ``transforms[(i, j)]`` the ``(4, 4)`` float64 matrix mapping fragment ``j`` into the
        frame of fragment ``i`` (metres), and the scene's ``num_fragments``.

    Raises:
        FileNotFoundError: ``path`` is not a file.
        DatasetLayoutError: A malformed or truncated block, a non-finite value, a last row other than ``0 0 0 1``,
            headers disagreeing on ``n``, an index outside ``[0, n)``, a repeated pair, or no block at all (the
            message names the file and the line).
    """
    path = Path(path).expanduser()
    blocks, num_fragments = read_blocks(path, 4)
    for block in blocks:
        if np.abs(block.matrix[3] - _BOTTOM_ROW).max() > _BOTTOM_ROW_TOL:
            raise _layout_error(
                path, block.row_lines[3], f"last matrix row must be 0 0 0 1, got {block.matrix[3].tolist()}"
            )
    return GtLog(transforms={(b.i, b.j): b.matrix for b in blocks}, num_fragments=num_fragments)


@dataclass(frozen=True)
class Block:
    """One block of a 3DMatch ``gt.log``/``gt.info``: header ``i j n`` (at ``line``) and its matrix."""

    line: int
    i: int
    j: int
    matrix: np.ndarray = field(repr=False)
    row_lines: list[int] = field(repr=False)


def read_blocks(path: Path, size: int) -> tuple[list[Block], int]:
    """The blocks of a ``gt.log`` (``size`` 4) or ``gt.info`` (6) file and the headers' ``n``, structure checked.

    Raises:
        FileNotFoundError: ``path`` is not a file.
        DatasetLayoutError: No block, a truncated block, a row that is not ``size`` finite numbers, headers
            disagreeing on ``n`` or a repeated pair (naming the file and line).
    """
    lines = _numbered_lines(path)
    if not lines:
        raise DatasetLayoutError(f"{str(path)!r} holds no block ('i j n' + {size}x{size} matrix); {EXPECTED_LAYOUT}")
    blocks: list[Block] = []
    seen: set[tuple[int, int]] = set()
    num_fragments: int | None = None
    for start in range(0, len(lines), size + 1):
        header_line, header_tokens = lines[start]
        i, j, n = _parse_header(path, header_line, header_tokens)
        if num_fragments is not None and n != num_fragments:
            raise _layout_error(path, header_line, f"header says n = {n}, earlier headers say n = {num_fragments}")
        num_fragments = n
        rows = lines[start + 1 : start + 1 + size]
        if len(rows) < size:
            raise _layout_error(path, header_line, f"block '{i} {j} {n}' has {len(rows)} matrix rows, expected {size}")
        matrix = np.array([_parse_row(path, number, tokens, size) for number, tokens in rows], dtype=np.float64)
        if (i, j) in seen:
            raise _layout_error(path, header_line, f"pair ({i}, {j}) is listed twice")
        seen.add((i, j))
        blocks.append(Block(header_line, i, j, matrix, [number for number, _ in rows]))
    if num_fragments is None:  # pragma: no cover - lines is non-empty, so a header was parsed
        raise DatasetLayoutError(f"{str(path)!r} holds no block; {EXPECTED_LAYOUT}")
    return blocks, num_fragments


def read_gt_overlap(path: str | Path) -> dict[tuple[int, int], float]:
    """Read a 3DMatch ``gt_overlap.log`` (``i,j,overlap`` lines; spaces around commas and blank lines allowed).

    Args:
        path: The ``gt_overlap.log`` file.

    Returns:
        ``(i, j) -> overlap`` ratio in ``[0, 1]``, in file order.

    Raises:
        FileNotFoundError: ``path`` is not a file.
        DatasetLayoutError: A line that is not ``i,j,overlap`` with integer indices and an overlap in ``[0, 1]``,
            or a repeated pair (the message names the file and the line).
    """
    path = Path(path).expanduser()
    overlaps: dict[tuple[int, int], float] = {}
    for number, tokens in _numbered_lines(path):
        text = " ".join(tokens)
        fields = [part.strip() for part in text.split(",")] if "," in text else tokens
        if len(fields) != 3:
            raise _layout_error(path, number, f"expected 'i,j,overlap', got {text!r}")
        try:
            i, j, overlap = int(fields[0]), int(fields[1]), float(fields[2])
        except ValueError:
            raise _layout_error(path, number, f"expected integers i, j and a number overlap, got {text!r}") from None
        if not 0.0 <= overlap <= 1.0:  # also rejects NaN
            raise _layout_error(path, number, f"overlap must be in [0, 1], got {fields[2]!r}")
        if (i, j) in overlaps:
            raise _layout_error(path, number, f"pair ({i}, {j}) is listed twice")
        overlaps[(i, j)] = overlap
    return overlaps


def _check_benchmark(benchmark: str) -> None:
    if benchmark not in BENCHMARKS:
        raise ValueError(f"benchmark must be one of {BENCHMARKS}, got {benchmark!r}")


def _benchmark_dir(root: str | Path, benchmark: str) -> Path:
    """``<root>/benchmarks/<benchmark>``, or ``FileNotFoundError`` describing the layout."""
    _check_benchmark(benchmark)
    path = dataset_root(root, "3DMatch", EXPECTED_LAYOUT)
    bench = path / "benchmarks" / benchmark
    if not bench.is_dir():
        raise FileNotFoundError(f"benchmark folder {str(bench)!r} is not a directory; {EXPECTED_LAYOUT}")
    return bench


def list_scenes(root: str | Path, benchmark: Benchmark = "3DMatch") -> list[str]:
    """Scenes of a benchmark: the folders of ``<root>/benchmarks/<benchmark>`` that hold a ``gt.log``, sorted.

    Args:
        root: Dataset root (holds ``fragments/`` and ``benchmarks/``).
        benchmark: ``"3DMatch"`` or ``"3DLoMatch"``.

    Returns:
        Scene names, sorted.

    Raises:
        ValueError: Unknown ``benchmark``.
        FileNotFoundError: ``root`` or ``<root>/benchmarks/<benchmark>`` is not a directory.
    """
    bench = _benchmark_dir(root, benchmark)
    return sorted(child.name for child in bench.iterdir() if (child / "gt.log").is_file())


def fragment_path(root: str | Path, scene: str, index: int) -> Path:
    """Path of fragment ``index`` of ``scene``: ``<root>/fragments/<scene>/cloud_bin_<index>.ply`` (not checked)."""
    return Path(root).expanduser() / "fragments" / scene / f"cloud_bin_{index}.ply"


def pair_paths(root: str | Path, scene: str, i: int, j: int) -> tuple[Path, Path]:
    """``(source = fragment j, reference = fragment i)`` of gt.log pair ``(i, j)``, both checked to exist.

    Raises:
        FileNotFoundError: A fragment is missing (named, with the pair).
    """
    path_src, path_ref = fragment_path(root, scene, j), fragment_path(root, scene, i)
    for path in (path_ref, path_src):
        if not path.is_file():
            raise FileNotFoundError(
                f"fragment {str(path)!r} of gt.log pair ({i}, {j}) does not exist; {EXPECTED_LAYOUT}"
            )
    return path_src, path_ref


def _check_min_overlap(min_overlap: float) -> float:
    value = float(min_overlap)
    if not math.isfinite(value) or value >= 1.0:
        raise ValueError(f"min_overlap must be a finite number below 1 (<= 0 disables the filter), got {min_overlap}")
    return value


def _resolve_scenes(root: str | Path, scenes: list[str] | None, benchmark: Benchmark) -> list[str]:
    """The sorted, de-duplicated scenes to read; every named one must have a gt.log."""
    available = list_scenes(root, benchmark)
    if scenes is None:
        return available
    if isinstance(scenes, str):
        raise ValueError(f"scenes must be a list of scene names or None, got the string {scenes!r}")
    unknown = sorted(set(scenes) - set(available))
    if unknown:
        bench = Path(root).expanduser() / "benchmarks" / benchmark
        raise FileNotFoundError(
            f"no gt.log for scene(s) {unknown} under {str(bench)!r} (expected <scene>/gt.log); available: {available}"
        )
    return sorted(set(scenes))


def _scene_overlaps(scene_dir: Path, min_overlap: float) -> dict[tuple[int, int], float] | None:
    """The scene's overlaps, ``None`` when ``gt_overlap.log`` is absent and no filter needs it."""
    overlap_file = scene_dir / "gt_overlap.log"
    if overlap_file.is_file() or min_overlap > 0.0:
        if not overlap_file.is_file():
            raise FileNotFoundError(
                f"{str(overlap_file)!r} does not exist but min_overlap={min_overlap} needs the listed overlaps "
                f"(pass min_overlap=0 to keep every gt.log pair); {EXPECTED_LAYOUT}"
            )
        return read_gt_overlap(overlap_file)
    return None


def _lookup_overlap(overlaps: dict[tuple[int, int], float] | None, i: int, j: int) -> float | None:
    """Overlap of pair ``(i, j)`` (or ``(j, i)``), ``None`` when not listed."""
    if overlaps is None:
        return None
    if (i, j) in overlaps:
        return overlaps[(i, j)]
    return overlaps.get((j, i))


def _scene_pairs(root: str | Path, scene: str, benchmark: Benchmark, min_overlap: float) -> list[ScenePair]:
    """The selected pairs of one scene, sorted by ``(i, j)``."""
    scene_dir = Path(root).expanduser() / "benchmarks" / benchmark / scene
    gt = read_gt_log(scene_dir / "gt.log")
    overlaps = _scene_overlaps(scene_dir, min_overlap)
    pairs = []
    for i, j in sorted(gt.transforms):
        overlap = _lookup_overlap(overlaps, i, j)
        if min_overlap > 0.0:
            if overlap is None:
                raise DatasetLayoutError(
                    f"{str(scene_dir / 'gt_overlap.log')!r} lists no overlap for gt.log pair ({i}, {j}); "
                    f"min_overlap={min_overlap} needs it (pass min_overlap=0 to keep every gt.log pair)"
                )
            if overlap <= min_overlap:
                continue
        path_src, path_ref = pair_paths(root, scene, i, j)
        pairs.append(
            ScenePair(
                path_src=path_src,
                path_ref=path_ref,
                transform_ref_src=gt.transforms[(i, j)],
                name=f"{scene}/{i}-{j}",
                overlap=overlap,
            )
        )
    return pairs


def threedmatch_pairs(
    root: str | Path,
    scenes: list[str] | None = None,
    min_overlap: float = 0.7,
    benchmark: Benchmark = "3DMatch",
) -> list[ScenePair]:
    """The fragment pairs of a 3DMatch / 3DLoMatch benchmark whose listed overlap is more than ``min_overlap``.

    Pair ``(i, j)`` of ``gt.log`` becomes ``ScenePair(path_src=fragment j, path_ref=fragment i,
    transform_ref_src=the gt.log matrix, name="<scene>/<i>-<j>", overlap=the gt_overlap.log value)``.

    Args:
        root: Dataset root (holds ``fragments/`` and ``benchmarks/``).
        scenes: Scene names (e.g. ``[SEVEN_SCENES_REDKITCHEN]`` for 7-Scenes); ``None`` = every scene of the
            benchmark (:func:`list_scenes`).
        min_overlap: Keep the pairs whose listed overlap is strictly more than this ratio; ``<= 0`` keeps every
            gt.log pair and makes ``gt_overlap.log`` optional. 3DLoMatch pairs all lie in 10-30 %: use 0 there.
        benchmark: ``"3DMatch"`` or ``"3DLoMatch"``.

    Returns:
        The pairs sorted by scene name, then ``(i, j)``.

    Raises:
        ValueError: Unknown ``benchmark``, ``scenes`` given as a string, or ``min_overlap`` not finite or ``>= 1``.
        FileNotFoundError: Missing root, benchmark folder, scene gt.log, gt_overlap.log (when ``min_overlap > 0``)
            or fragment file of a selected pair (the message names it).
        DatasetLayoutError: Malformed gt.log / gt_overlap.log, or a gt.log pair absent from gt_overlap.log when
            ``min_overlap > 0``.
    """
    min_overlap = _check_min_overlap(min_overlap)
    _check_benchmark(benchmark)
    pairs: list[ScenePair] = []
    for scene in _resolve_scenes(root, scenes, benchmark):
        pairs.extend(_scene_pairs(root, scene, benchmark, min_overlap))
    return pairs


class SevenScenesDataModule(ScenePairDataModule):
    """7-Scenes (and any 3DMatch scene) fragment pairs under the DVDs paper's protocol, for evaluation.

    Defaults follow the paper's 7-Scenes section: pairs with more than 70 % overlap, 2048 points per fragment, the
    source aligned to the reference with the ground truth and the pair then displaced by a random rigid transform
    (Euler angles ``U[0, 45]`` degrees, translations ``U[-0.5, 0.5]`` metres, about the reference centroid). Models
    are trained on ModelNet40, so only a test split is configured by default; ``train_scenes``/``val_scenes``
    make the other splits (e.g. SUN3D scenes) when wanted.

    Args:
        root: Dataset root with ``fragments/`` and ``benchmarks/`` (checked in :meth:`setup`).
        test_scenes: Scenes of the test split (default: 7-Scenes redkitchen; ``None``: every scene of the benchmark).
        val_scenes: Scenes of the validation split.
        train_scenes: Scenes of the training split.
        min_overlap: Keep pairs with a listed overlap strictly above this.
        benchmark: ``"3DMatch"`` or ``"3DLoMatch"`` (use ``min_overlap: 0`` with the latter).
        **kwargs: Options of :class:`~lcreg.data.scenes.ScenePairDataModule` (``num_points``, ``voxel_size``, ...).
    """

    recall_thresholds: ClassVar[tuple[tuple[float, float], ...]] = ((15.0, 0.3),)
    """The 3DMatch / 7-Scenes recall (FCGF, DGR): RRE < 15 degrees and RTE < 0.3 m (``recall_r15_t0p3``)."""

    def __init__(
        self,
        root: str,
        test_scenes: Sequence[str] | None = (SEVEN_SCENES_REDKITCHEN,),
        val_scenes: Sequence[str] = (),
        train_scenes: Sequence[str] = (),
        min_overlap: float = 0.7,
        benchmark: Benchmark = "3DMatch",
        **kwargs: Any,
    ) -> None:
        super().__init__(**kwargs)
        _check_min_overlap(min_overlap)
        _check_benchmark(benchmark)
        self.root = root
        if isinstance(test_scenes, str) or isinstance(val_scenes, str) or isinstance(train_scenes, str):
            raise ValueError("`test_scenes`, `val_scenes` and `train_scenes` are lists of scene names, not a string")
        self.scenes: dict[str, list[str] | None] = {
            "train": list(train_scenes),
            "val": list(val_scenes),
            "test": None if test_scenes is None else list(test_scenes),
        }
        self.min_overlap = min_overlap
        self.benchmark: Benchmark = benchmark

    def pairs(self, split: Split) -> list[ScenePair]:
        """The pairs of the scenes of ``split`` (``None``: every scene; an empty list: no pair)."""
        scenes = self.scenes[split]
        if scenes is not None and not scenes:
            return []
        return threedmatch_pairs(self.root, scenes, self.min_overlap, self.benchmark)
