"""Pair lists for registering many pairs: one reader for CSV lists, 3DMatch benchmarks and KITTI json lists.

:func:`read_pair_list` turns a path into a list of :class:`ListedPair` (source file, reference file, optional ground
truth, name, group, optional 3DMatch covariance and whether the pair counts for the official recall). The kind of
list is detected from the path:

* a CSV file (``.csv`` or ``.txt``): one pair a row, ``src,ref`` or ``src,ref,gt`` where ``gt`` is the 4x4
  ``transform_ref_src`` in row-major order, either as 16 space-separated numbers in the third column or as 16 more
  columns. ``#`` comments, blank lines and a header row whose first field is ``src`` are skipped; relative paths are
  relative to the CSV's folder. A pair counts for the recall when it has a ground truth.
* a 3DMatch scene folder holding ``gt.log`` (``<root>/benchmarks/<benchmark>/<scene>``), the ``gt.log`` file itself,
  or a benchmark folder holding scene folders (``<root>/benchmarks/3DMatch``: every scene, sorted). Pair ``(i, j)``
  of ``gt.log`` has source = fragment ``j``, reference = fragment ``i`` (:func:`~lcreg.data.threedmatch.fragment_path`),
  the matrix as ground truth, the ``gt.info`` covariance when the file is present, the ``gt_overlap.log`` overlap when
  present, ``name = "<scene>/<i>-<j>"`` and ``group = <scene>``. As in the official protocol, only non-consecutive
  fragments (``j - i > 1``) count for the recall.
* a KITTI json pair list (``<kitti root>/pairs/<split>.json``, entries ``seq_id, frame0, frame1, transform``): source
  = scan of ``frame1``, reference = scan of ``frame0`` (:func:`~lcreg.data.kitti.layout.scan_path`), the json
  transform as ground truth, ``name = "NN/frame0-frame1"``, ``group = "NN"``. Pairs whose scans are missing are
  skipped with a ``UserWarning``.
"""

from __future__ import annotations

import csv
import warnings
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from lcreg.checks import DatasetLayoutError, check_rigid
from lcreg.data.kitti.io import read_json_pairs
from lcreg.data.kitti.layout import EXPECTED_LAYOUT as KITTI_LAYOUT
from lcreg.data.kitti.layout import describe_missing, raise_if_no_pair, scan_frames, scan_path
from lcreg.data.scenes import ScenePair
from lcreg.data.threedmatch import (
    EXPECTED_LAYOUT,
    _layout_error,
    pair_paths,
    read_blocks,
    read_gt_log,
    read_gt_overlap,
)

__all__ = ["ACCEPTED_KINDS", "ListedPair", "read_gt_info", "read_pair_list"]

ACCEPTED_KINDS = (
    "a CSV pair list (.csv/.txt: rows 'src,ref' or 'src,ref,gt' with gt = 16 numbers, row-major 4x4), "
    "a 3DMatch scene folder holding gt.log (<root>/benchmarks/<benchmark>/<scene>), its gt.log file, "
    "a 3DMatch benchmark folder holding scene folders (<root>/benchmarks/3DMatch), "
    "or a KITTI json pair list (<kitti root>/pairs/<split>.json)"
)
"""The kinds of pair list :func:`read_pair_list` accepts (used in its error messages)."""

_CSV_SUFFIXES = (".csv", ".txt")
_HEADER_NAMES = ("src", "source", "path_src")
_SYMMETRY_RTOL = 1e-6


@dataclass(frozen=True)
class ListedPair:
    """One pair of a pair list: two point-cloud files, their ground truth when known, and how it is scored.

    Attributes:
        path_src: Source cloud file (any format of :func:`lcreg.data.io.read_points`).
        path_ref: Reference cloud file.
        transform_ref_src: ``(4, 4)`` float64 ``[R t; 0 1]`` mapping source points into the reference frame
            (metres), or ``None`` when the list gives no ground truth.
        name: Identifier, unique within a list (e.g. ``"7-scenes-redkitchen/0-2"``, ``"00/11-0"``).
        group: Scene (3DMatch) or sequence (KITTI, ``"00"``); ``""`` for CSV lists.
        info: ``(6, 6)`` float64 covariance of the 3DMatch ``gt.info`` (for
            :func:`lcreg.metrics.functional.correspondence_rmse_sq`), or ``None``.
        scored: Whether the pair counts for the official recall (3DMatch: ``j - i > 1``; others: a ground truth is
            given). Always ``False`` without a ground truth.
        overlap: Overlap ratio of the 3DMatch ``gt_overlap.log`` when listed, else ``None``.

    Raises:
        ValueError: ``transform_ref_src`` is not ``(4, 4)``, ``info`` is not ``(6, 6)``, or ``scored`` without a
            ground truth.
    """

    path_src: Path
    path_ref: Path
    transform_ref_src: np.ndarray | None = field(default=None, repr=False, compare=False)
    name: str = ""
    group: str = ""
    info: np.ndarray | None = field(default=None, repr=False, compare=False)
    scored: bool = False
    overlap: float | None = None

    def __post_init__(self) -> None:
        if self.transform_ref_src is not None and np.shape(self.transform_ref_src) != (4, 4):
            raise ValueError(
                f"pair {self.name!r}: transform_ref_src must be (4, 4), got {np.shape(self.transform_ref_src)}"
            )
        if self.info is not None and np.shape(self.info) != (6, 6):
            raise ValueError(f"pair {self.name!r}: info must be (6, 6), got {np.shape(self.info)}")
        if self.scored and self.transform_ref_src is None:
            raise ValueError(f"pair {self.name!r} is scored but has no ground truth")

    def to_scene_pair(self) -> ScenePair:
        """This pair as a :class:`~lcreg.data.scenes.ScenePair` (for :class:`~lcreg.data.scenes.ScenePairDataset`).

        Raises:
            ValueError: The pair has no ground truth.
        """
        if self.transform_ref_src is None:
            raise ValueError(f"pair {self.name!r} has no ground truth; a ScenePair needs one")
        return ScenePair(self.path_src, self.path_ref, self.transform_ref_src, self.name, self.overlap)


# ----------------------------------------------------------------------------------------------------- 3DMatch


def _check_info(path: Path, line: int, matrix: np.ndarray) -> None:
    """A usable covariance: symmetric (relative ``1e-6``) with a positive ``[0, 0]`` (the number of points)."""
    if np.abs(matrix - matrix.T).max() > _SYMMETRY_RTOL * np.abs(matrix).max():
        raise _layout_error(path, line, "the 6x6 matrix of this block is not symmetric")
    if not matrix[0, 0] > 0:
        raise _layout_error(path, line, f"the 6x6 matrix needs a positive [0, 0] entry, got {matrix[0, 0]}")


def read_gt_info(path: str | Path) -> dict[tuple[int, int], np.ndarray]:
    """Read a 3DMatch ``gt.info`` (blocks of a header ``i j n`` and a 6x6 matrix; tabs and blank lines allowed).

    Args:
        path: The ``gt.info`` file (beside ``gt.log``).

    Returns:
        ``(i, j) -> (6, 6)`` float64 covariance of pair ``(i, j)`` (the ``info`` argument of
        :func:`lcreg.metrics.functional.correspondence_rmse_sq`), in file order.

    Raises:
        FileNotFoundError: ``path`` is not a file.
        DatasetLayoutError: A malformed or truncated block, a non-finite value, a matrix that is not symmetric or
            has ``[0, 0] <= 0``, headers disagreeing on ``n``, a repeated pair, or no block at all (the message names
            the file and the line).
    """
    path = Path(path).expanduser()
    blocks, _ = read_blocks(path, 6)
    for block in blocks:
        _check_info(path, block.line, block.matrix)
    return {(b.i, b.j): b.matrix for b in blocks}


def _scene_root(scene_dir: Path) -> Path:
    """The dataset root of ``<root>/benchmarks/<benchmark>/<scene>``, or a layout error."""
    if scene_dir.parent.parent.name != "benchmarks":
        raise DatasetLayoutError(
            f"{str(scene_dir)!r} holds a gt.log but is not a folder <root>/benchmarks/<benchmark>/<scene>, so its "
            f"fragments cannot be found; {EXPECTED_LAYOUT}"
        )
    return scene_dir.parent.parent.parent


def _optional_info(scene_dir: Path, keys: list[tuple[int, int]]) -> dict[tuple[int, int], np.ndarray] | None:
    """The scene's ``gt.info`` when present; it must then cover every gt.log pair."""
    info_file = scene_dir / "gt.info"
    if not info_file.is_file():
        return None
    infos = read_gt_info(info_file)
    missing = [key for key in keys if key not in infos]
    if missing:
        raise DatasetLayoutError(
            f"{str(info_file)!r} has no block for {len(missing)} gt.log pair(s), e.g. {missing[:3]}; {EXPECTED_LAYOUT}"
        )
    return infos


def _threedmatch_scene(scene_dir: Path) -> list[ListedPair]:
    """Every pair of one scene's ``gt.log``, in file order, with fragments checked to exist."""
    root, scene = _scene_root(scene_dir), scene_dir.name
    gt = read_gt_log(scene_dir / "gt.log")
    infos = _optional_info(scene_dir, list(gt.transforms))
    overlap_file = scene_dir / "gt_overlap.log"
    overlaps = read_gt_overlap(overlap_file) if overlap_file.is_file() else {}
    pairs = []
    for (i, j), transform in gt.transforms.items():
        path_src, path_ref = pair_paths(root, scene, i, j)
        pairs.append(
            ListedPair(
                path_src=path_src,
                path_ref=path_ref,
                transform_ref_src=transform,
                name=f"{scene}/{i}-{j}",
                group=scene,
                info=None if infos is None else infos[(i, j)],
                scored=j - i > 1,
                overlap=overlaps.get((i, j), overlaps.get((j, i))),
            )
        )
    return pairs


def _threedmatch_benchmark(bench_dir: Path) -> list[ListedPair]:
    """The pairs of every scene folder (with a gt.log) of a benchmark folder, scenes sorted by name."""
    scenes = sorted(child for child in bench_dir.iterdir() if (child / "gt.log").is_file())
    return [pair for scene_dir in scenes for pair in _threedmatch_scene(scene_dir)]


# ----------------------------------------------------------------------------------------------------- CSV


def _csv_error(path: Path, line: int, message: str) -> DatasetLayoutError:
    return DatasetLayoutError(f"CSV pair list {str(path)!r}, line {line}: {message}")


def _csv_transform(path: Path, line: int, values: list[str]) -> np.ndarray:
    """Sixteen numbers (row-major 4x4) as a checked rigid ``(4, 4)`` float64 transform."""
    if len(values) != 16:
        raise _csv_error(path, line, f"the ground truth needs 16 numbers (row-major 4x4), got {len(values)}")
    try:
        matrix = np.array([float(value) for value in values], dtype=np.float64).reshape(4, 4)
    except ValueError:
        raise _csv_error(path, line, f"the ground truth must hold numbers, got {' '.join(values)!r}") from None
    if not np.all(np.isfinite(matrix)):
        raise _csv_error(path, line, "the ground truth holds a non-finite value")
    try:
        check_rigid(torch.from_numpy(matrix)[None], "gt")
    except ValueError as err:
        raise _csv_error(path, line, f"the ground truth is not a rigid motion: {err}") from None
    return matrix


def _csv_point_file(path: Path, line: int, field_text: str, role: str) -> Path:
    """The ``role`` file of a row, resolved against the CSV's folder; it must exist."""
    if not field_text:
        raise _csv_error(path, line, f"the {role} path is empty")
    file = Path(field_text).expanduser()
    file = file if file.is_absolute() else path.parent / file
    if not file.is_file():
        raise FileNotFoundError(f"CSV pair list {str(path)!r}, line {line}: {role} file {str(file)!r} does not exist")
    return file


def _csv_row(path: Path, line: int, fields: list[str]) -> tuple[Path, Path, np.ndarray | None]:
    """Source, reference and optional ground truth of one row of 2, 3 or 18 fields."""
    if len(fields) not in (2, 3, 18):
        raise _csv_error(
            path, line, f"expected 2 columns (src,ref), 3 (src,ref,gt) or 18 (src,ref + 16 numbers), got {len(fields)}"
        )
    src = _csv_point_file(path, line, fields[0], "source")
    ref = _csv_point_file(path, line, fields[1], "reference")
    if len(fields) == 2:
        return src, ref, None
    return src, ref, _csv_transform(path, line, fields[2].split() if len(fields) == 3 else fields[2:])


def _csv_rows(path: Path) -> list[tuple[int, list[str]]]:
    """``(line number, stripped fields)`` of the data rows: no blank, ``#`` comment or leading header line."""
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as err:
        raise DatasetLayoutError(f"CSV pair list {str(path)!r} is not a text file ({err})") from err
    rows: list[tuple[int, list[str]]] = []
    header_allowed = True
    for number, line in enumerate(text.splitlines(), start=1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        fields = [value.strip() for value in next(csv.reader([line]))]
        if header_allowed and fields[0].lower() in _HEADER_NAMES:
            header_allowed = False
            continue
        header_allowed = False
        rows.append((number, fields))
    return rows


def _unique_names(stems: list[str]) -> list[str]:
    """``stems`` with the 2nd, 3rd... repeat of a name suffixed ``-2``, ``-3``..."""
    seen: Counter[str] = Counter()
    names = []
    for stem in stems:
        seen[stem] += 1
        names.append(stem if seen[stem] == 1 else f"{stem}-{seen[stem]}")
    return names


def _csv_pairs(path: Path) -> list[ListedPair]:
    """The pairs of a CSV list, in row order (see the module docstring for the format)."""
    parsed = [_csv_row(path, number, fields) for number, fields in _csv_rows(path)]
    if not parsed:
        raise DatasetLayoutError(f"CSV pair list {str(path)!r} holds no pair; {ACCEPTED_KINDS}")
    names = _unique_names([f"{src.stem}-{ref.stem}" for src, ref, _ in parsed])
    return [
        ListedPair(path_src=src, path_ref=ref, transform_ref_src=gt, name=name, scored=gt is not None)
        for (src, ref, gt), name in zip(parsed, names)
    ]


# ----------------------------------------------------------------------------------------------------- KITTI


def _default_kitti_root(json_file: Path) -> Path:
    """The parent of the json's ``pairs/`` folder (the json's own folder when that is not named ``pairs``)."""
    return json_file.parent.parent if json_file.parent.name == "pairs" else json_file.parent


def _kitti_json_pairs(json_file: Path, kitti_root: Path) -> list[ListedPair]:
    """The json pairs whose two scans exist under ``kitti_root``; a warning counts the skipped ones."""
    rows = read_json_pairs(json_file)
    found = {seq_id: scan_frames(kitti_root, seq_id) for seq_id in sorted({row[0] for row in rows})}
    pairs = [
        ListedPair(
            path_src=scan_path(kitti_root, seq_id, frame1),
            path_ref=scan_path(kitti_root, seq_id, frame0),
            transform_ref_src=transform,
            name=f"{seq_id:02d}/{frame0}-{frame1}",
            group=f"{seq_id:02d}",
            scored=True,
        )
        for seq_id, frame0, frame1, transform in rows
        if {frame0, frame1} <= (found[seq_id] or set())
    ]
    needed: dict[int, set[int]] = {seq_id: set() for seq_id in found}
    for seq_id, frame0, frame1, _ in rows:
        needed[seq_id] |= {frame0, frame1}
    source = f"{str(json_file)!r} lists {len(rows)} pairs in sequences {sorted(found)}"
    raise_if_no_pair(pairs, source, kitti_root, needed, found)
    if len(pairs) < len(rows):
        warnings.warn(
            f"{len(rows) - len(pairs)} of the {len(rows)} pairs of {str(json_file)!r} are skipped: their scans are "
            f"missing under {str(kitti_root / 'sequences')!r} (looked for NN/velodyne/FFFFFF.bin; "
            f"{describe_missing(kitti_root, needed, found)}); {len(pairs)} pair(s) remain",
            UserWarning,
            stacklevel=3,
        )
    return pairs


# ----------------------------------------------------------------------------------------------------- public


def read_pair_list(path: str | Path, *, kitti_root: str | Path | None = None) -> list[ListedPair]:
    """Read a pair list of any accepted kind (detected from ``path``; see the module docstring).

    Args:
        path: A CSV file (``.csv``/``.txt``), a 3DMatch scene folder or its ``gt.log``, a 3DMatch benchmark folder,
            or a KITTI json pair list (``.json``).
        kitti_root: KITTI only: the folder holding ``sequences/`` (default: the parent of the json's ``pairs/``
            folder, or the json's folder when it is not named ``pairs``).

    Returns:
        The pairs, in list order (3DMatch: scenes sorted, then ``gt.log`` order). CSV rows, 3DMatch pairs and the
        remaining KITTI pairs all have existing files.

    Raises:
        FileNotFoundError: ``path`` does not exist; a CSV row names a missing file (the message names the CSV line
            and the file); a 3DMatch fragment is missing; no KITTI pair has both scans.
        DatasetLayoutError: ``path`` is no accepted kind (the message lists them), or a malformed file: a CSV row
            with a wrong column count or a non-numeric, non-finite or non-rigid ground truth, an empty list, a
            malformed ``gt.log``/``gt.info``/``gt_overlap.log``/json (each names the file, and the line where known).

    Warns:
        UserWarning: KITTI pairs were skipped because their scans are missing (how many, and where they were
            looked for).

    Example:
        >>> pairs = read_pair_list("../shared/data/3dmatch/benchmarks/3DMatch")  # doctest: +SKIP
        >>> pairs[0].name, pairs[0].scored  # doctest: +SKIP
        ('7-scenes-redkitchen/0-1', False)
    """
    file = Path(path).expanduser()
    if not file.exists():
        raise FileNotFoundError(f"pair list {str(file)!r} does not exist; expected {ACCEPTED_KINDS}")
    if file.is_dir():
        if (file / "gt.log").is_file():
            return _threedmatch_scene(file)
        if any((child / "gt.log").is_file() for child in file.iterdir()):
            return _threedmatch_benchmark(file)
    elif file.name == "gt.log":
        return _threedmatch_scene(file.parent)
    elif file.suffix.lower() in _CSV_SUFFIXES:
        return _csv_pairs(file)
    elif file.suffix.lower() == ".json":
        root = _default_kitti_root(file) if kitti_root is None else Path(kitti_root).expanduser()
        if not root.is_dir():
            raise FileNotFoundError(f"KITTI root {str(root)!r} is not a directory; {KITTI_LAYOUT}")
        return _kitti_json_pairs(file, root)
    raise DatasetLayoutError(f"{str(file)!r} is not a pair list; expected {ACCEPTED_KINDS}")
