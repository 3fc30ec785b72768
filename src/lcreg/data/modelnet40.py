"""ModelNet40 in the official ``modelnet40_ply_hdf5_2048`` HDF5 layout, and the two registration protocols.

Layout of ``root`` (the folder of the official download, or any folder in the same layout)::

    root/
      train_files.txt    one h5 file per line, e.g. data/modelnet40_ply_hdf5_2048/ply_data_train0.h5
      test_files.txt     (entries are resolved by their basename inside root)
      ply_data_train0.h5 ...  keys: data (S, P, 3) float, label (S,) or (S, 1) int, optional normal (S, P, 3)
      shape_names.txt    optional, the 40 class names, label = line index

Protocols (labels in the official alphabetical order; labels 0-19 = airplane ... lamp):

* ``"unseen_objects"``: train/val objects from the train split of labels 0-19, test objects = the test split of
  labels 0-19 (the held-out objects of the seen categories).
* ``"unseen_categories"``: train/val objects from the train split of labels 0-19; test objects = labels 20-39,
  either of the test split only (``unseen_categories_test="test_split"``, the DCP/PRNet/IDAM choice) or of both
  splits (``"all"``, as PointNetLK Revisited does: no object of labels 20-39 is ever seen in training, so the train
  split's objects of those classes are unseen as well). Report the set and its size with every number.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import h5py
import numpy as np

from lcreg.checks import DatasetLayoutError, dataset_root
from lcreg.data.pairs import ObjectSet

__all__ = [
    "EXPECTED_LAYOUT",
    "NUM_SEEN_CLASSES",
    "load_modelnet40_h5",
    "load_shape_names",
    "modelnet40_objects",
]

Split = Literal["train", "test"]
Protocol = Literal["unseen_objects", "unseen_categories"]
UnseenCategoriesTest = Literal["test_split", "all"]

NUM_SEEN_CLASSES = 20
"""Labels ``0 .. NUM_SEEN_CLASSES - 1`` are the seen (training) categories of both protocols."""
NUM_CLASSES = 40
"""ModelNet40 labels are 0-39 (the line index in ``shape_names.txt``); a file with others is refused."""

EXPECTED_LAYOUT = (
    "expected the official modelnet40_ply_hdf5_2048 layout: <root>/train_files.txt and <root>/test_files.txt "
    "listing h5 files (resolved by basename inside <root>), each h5 with keys 'data' (S, P, 3), 'label' (S,) or "
    "(S, 1) and optionally 'normal' (S, P, 3); optional <root>/shape_names.txt"
)


def _check_root(root: str | Path) -> Path:
    """Return ``root`` as a directory path or raise ``FileNotFoundError`` describing the layout."""
    return dataset_root(root, "ModelNet40", EXPECTED_LAYOUT)


def _resolve_entry(root: Path, entry: str, list_file: Path) -> Path:
    """Find the h5 file named by one line of a ``*_files.txt`` list (by basename in ``root``, else as given)."""
    for candidate in (root / Path(entry).name, root / entry):
        if candidate.is_file():
            return candidate
    raise FileNotFoundError(
        f"{str(list_file)!r} lists {entry!r} but {str(root / Path(entry).name)!r} does not exist; {EXPECTED_LAYOUT}"
    )


def _read_h5(path: Path) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """Read ``data``, optional ``normal`` and ``label`` of one h5 file, checking keys and shapes."""
    try:
        with h5py.File(path, "r") as f:
            missing = [key for key in ("data", "label") if key not in f]
            if missing:
                found = sorted(f)
                raise DatasetLayoutError(f"{str(path)!r} has no key(s) {missing} (found {found}); {EXPECTED_LAYOUT}")
            points = np.asarray(f["data"][...], dtype=np.float32)
            labels = np.asarray(f["label"][...])
            normals = np.asarray(f["normal"][...], dtype=np.float32) if "normal" in f else None
    except OSError as err:
        raise DatasetLayoutError(f"{str(path)!r} is not a readable HDF5 file ({err}); {EXPECTED_LAYOUT}") from err
    if points.ndim != 3 or points.shape[-1] != 3:
        raise DatasetLayoutError(f"{str(path)!r}: 'data' has shape {points.shape}, expected (S, P, 3)")
    if labels.ndim == 2 and labels.shape[1] == 1:
        labels = labels[:, 0]
    if labels.shape != points.shape[:1] or not np.issubdtype(labels.dtype, np.integer):
        raise DatasetLayoutError(
            f"{str(path)!r}: 'label' has shape {labels.shape} and dtype {labels.dtype}, "
            f"expected integers of shape ({points.shape[0]},) or ({points.shape[0]}, 1)"
        )
    if normals is not None and normals.shape != points.shape:
        raise DatasetLayoutError(f"{str(path)!r}: 'normal' has shape {normals.shape}, expected {points.shape}")
    if len(points) == 0:
        raise DatasetLayoutError(f"{str(path)!r} holds no objects ('data' has shape {points.shape})")
    if labels.min() < 0 or labels.max() >= NUM_CLASSES:
        bad = int(((labels < 0) | (labels >= NUM_CLASSES)).sum())
        raise DatasetLayoutError(
            f"{str(path)!r}: {bad} label(s) outside 0-{NUM_CLASSES - 1} (found {labels.min()}..{labels.max()})"
        )
    _check_objects(path, points, normals)
    return points, normals, labels.astype(np.int64)


MIN_OBJECT_POINTS = 3
"""Fewest points per object a file may hold (a rigid pose needs three non-collinear points)."""


def _check_objects(path: Path, points: np.ndarray, normals: np.ndarray | None) -> None:
    """Refuse objects no registration can use, naming the file and the rows (object indices in the file).

    Raises:
        DatasetLayoutError: Too few points per object, NaN/Inf in ``data`` or ``normal``, or an object whose points
            are all identical.
    """
    if points.shape[1] < MIN_OBJECT_POINTS:
        raise DatasetLayoutError(
            f"{str(path)!r}: objects hold {points.shape[1]} point(s), registration needs at least {MIN_OBJECT_POINTS}"
        )
    for key, values in (("data", points), ("normal", normals)):
        if values is None:
            continue
        rows = np.flatnonzero(~np.isfinite(values).all(axis=(1, 2)))
        if len(rows):
            raise DatasetLayoutError(f"{str(path)!r}: objects at rows {_rows(rows)} of {key!r} hold NaN/Inf")
    flat = np.flatnonzero((np.ptp(points, axis=1) == 0).all(axis=1))
    if len(flat):
        message = f"objects at rows {_rows(flat)} of 'data' have all their points identical"
        raise DatasetLayoutError(f"{str(path)!r}: {message}")


def _rows(rows: np.ndarray, shown: int = 5) -> str:
    """``[3, 7, 9]`` or ``[3, 7, 9, 11, 12, ... (14 rows)]``."""
    listed = ", ".join(str(int(r)) for r in rows[:shown])
    return f"[{listed}]" if len(rows) <= shown else f"[{listed}, ... ({len(rows)} rows)]"


def load_shape_names(root: str | Path) -> list[str] | None:
    """Class names from ``<root>/shape_names.txt`` (label = line index), or ``None`` when the file is absent.

    Raises:
        FileNotFoundError: If ``root`` is not a directory.
    """
    path = _check_root(root) / "shape_names.txt"
    if not path.is_file():
        return None
    return [line.strip() for line in path.read_text().splitlines() if line.strip()]


def load_modelnet40_h5(root: str | Path, split: Split) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """Read one split of the official ``modelnet40_ply_hdf5_2048`` layout.

    Args:
        root: Folder with ``{split}_files.txt`` and the h5 files it lists (see the module docstring).
        split: ``"train"`` or ``"test"``.

    Returns:
        ``(points (S, P, 3) float32, normals (S, P, 3) float32 or None, labels (S,) int64)`` with the files
        concatenated in list order (``P = 2048`` in the official files). ``normals`` is ``None`` unless every
        file has a ``normal`` key.

    Raises:
        ValueError: On an unknown ``split``.
        FileNotFoundError: If ``root``, the list file or a listed h5 file is missing (the message names the path).
        DatasetLayoutError: If the list is empty, a file is not HDF5, or keys/shapes are wrong (names the path).

    Example:
        >>> points, normals, labels = load_modelnet40_h5("../shared/data/modelnet40_mini", "test")  # doctest: +SKIP
        >>> points.shape  # doctest: +SKIP
        (178, 2048, 3)
    """
    if split not in ("train", "test"):
        raise ValueError(f"`split` must be 'train' or 'test', got {split!r}")
    base = _check_root(root)
    list_file = base / f"{split}_files.txt"
    if not list_file.is_file():
        raise FileNotFoundError(f"{str(list_file)!r} does not exist; {EXPECTED_LAYOUT}")
    entries = [line.strip() for line in list_file.read_text().splitlines() if line.strip()]
    if not entries:
        raise DatasetLayoutError(f"{str(list_file)!r} lists no h5 file; {EXPECTED_LAYOUT}")
    parts = [_read_h5(_resolve_entry(base, entry, list_file)) for entry in entries]
    if len({p[0].shape[1] for p in parts}) > 1:
        raise DatasetLayoutError(f"the files listed in {str(list_file)!r} have different numbers of points per object")
    points = np.concatenate([p[0] for p in parts])
    has_normals = all(p[1] is not None for p in parts)
    normals = np.concatenate([p[1] for p in parts if p[1] is not None]) if has_normals else None
    return points, normals, np.concatenate([p[2] for p in parts])


def modelnet40_objects(
    root: str | Path,
    protocol: Protocol,
    part: Split,
    unseen_categories_test: UnseenCategoriesTest = "all",
) -> ObjectSet:
    """The objects of one part (``"train"`` pool or ``"test"`` set) of a ModelNet40 registration protocol.

    Args:
        root: Dataset folder (see :func:`load_modelnet40_h5`).
        protocol: ``"unseen_objects"`` or ``"unseen_categories"`` (see the module docstring).
        part: ``"train"`` (the pool that train and validation are drawn from: train split, labels 0-19) or
            ``"test"``.
        unseen_categories_test: For ``"unseen_categories"``: test on labels 20-39 of the test split only
            (``"test_split"``) or of both splits (``"all"``).

    Returns:
        The selected objects. On the real subset ``modelnet40_mini``: train pool 783 objects; unseen-objects test
        164; unseen-categories test 80 (``"all"``) or 14 (``"test_split"``).

    Raises:
        ValueError: On an unknown ``protocol``, ``part`` or ``unseen_categories_test``.
        FileNotFoundError: See :func:`load_modelnet40_h5`.
        DatasetLayoutError: See :func:`load_modelnet40_h5`.
    """
    if protocol not in ("unseen_objects", "unseen_categories"):
        raise ValueError(f"`protocol` must be 'unseen_objects' or 'unseen_categories', got {protocol!r}")
    if unseen_categories_test not in ("test_split", "all"):
        raise ValueError(f"`unseen_categories_test` must be 'test_split' or 'all', got {unseen_categories_test!r}")
    if part not in ("train", "test"):
        raise ValueError(f"`part` must be 'train' or 'test', got {part!r}")
    if part == "train":
        train = ObjectSet(*load_modelnet40_h5(root, "train"))
        return train.subset(train.labels < NUM_SEEN_CLASSES)
    test = ObjectSet(*load_modelnet40_h5(root, "test"))
    if protocol == "unseen_objects":
        return test.subset(test.labels < NUM_SEEN_CLASSES)
    if unseen_categories_test == "all":
        test = ObjectSet.concatenate([ObjectSet(*load_modelnet40_h5(root, "train")), test])
    return test.subset(test.labels >= NUM_SEEN_CLASSES)
