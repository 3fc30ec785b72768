"""ScanObjectNN (real indoor object scans) in the official ``h5_files`` layout, and its registration DataModule.

**No copy of ScanObjectNN exists on the development machine** (its terms of use require a request form); this
reader follows the layout of the official download and is tested on small files of that layout written by the
tests. Layout facts (source: ``hkust-vgd/scanobjectnn``, ``README.md``, ``training_data/README.md`` (FAQ),
``data_utils.py`` and the training scripts' default ``--train_file``)::

    <dataset>/h5_files/
      main_split/        objects with their background points (OBJ_BG, PB_*)
        training_objectdataset{suffix}.h5   test_objectdataset{suffix}.h5
      main_split_nobg/   the background filtered out before sampling (OBJ_ONLY, ...)
        training_objectdataset{suffix}.h5   test_objectdataset{suffix}.h5
      split1/ ... split4/                   additional splits of the supplementary material (not read here)

* keys: ``data`` ``(S, 2048, 3)`` float points, ``label`` ``(S,)`` class index, ``mask`` ``(S, 2048)`` per point:
  ``-1`` marks a background point, any other value a point of the object instance (FAQ 5 and
  ``data_utils.convert_to_binary_mask``);
* ``suffix`` per variant (:data:`VARIANT_SUFFIXES`): ``""`` (OBJ_BG with background, OBJ_ONLY without),
  ``"_augmented25_norot"`` (PB_T25), ``"_augmented25rot"`` (PB_T25_R), ``"_augmentedrot"`` (PB_T50_R),
  ``"_augmentedrot_scale75"`` (PB_T50_RS, the "hardest" variant: 11416 training / 2882 test objects, as
  ``guochengqian/PointNeXt`` reports). The official code only names ``main_split`` files; that ``main_split_nobg``
  holds the same five variants comes from third-party loaders (e.g. ``rubenwiersma/deltaconv``), so a missing file
  is reported by name rather than assumed;
* labels follow :data:`SCANOBJECTNN_CLASSES` (FAQ 4: bag 0, bin 1, ..., toilet 14; *not* alphabetical);
* every object had at least 2048 object points before its 2048 points (object and background) were drawn, so the
  object points of an OBJ_BG/PB object number at most 2048 and may be fewer.

``root`` may be the dataset folder (containing ``h5_files/``), the ``h5_files`` folder itself, or the split folder
(``main_split`` or ``main_split_nobg``, which must then match ``background``); the first of
``root/h5_files/<split folder>``, ``root/<split folder>`` and ``root`` (when its name is the split folder) that is a
directory is used.

Registration (:class:`ScanObjectNNDataModule`): the pair protocol of :mod:`lcreg.data.pairs` (the ModelNet40 one:
``num_points`` 1024, Euler angles ``U[0, 45]`` degrees, translation ``U[-0.5, 0.5]``, objects scaled into the unit
sphere); train/validation objects come from the training file (validation carved with ``val_fraction``), test
objects from the test file. Background points, when kept, are part of the object that is registered.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

import h5py
import numpy as np

from lcreg.checks import DatasetLayoutError, NonFiniteError, ShapeError, dataset_root
from lcreg.data.datamodule import PairDataModule
from lcreg.data.pairs import ObjectSet

__all__ = [
    "BACKGROUND_LABEL",
    "EXPECTED_LAYOUT",
    "SCANOBJECTNN_CLASSES",
    "VARIANT_SUFFIXES",
    "ScanObjectNNDataModule",
    "drop_background",
    "load_scanobjectnn_h5",
    "scanobjectnn_file",
    "scanobjectnn_objects",
]

Split = Literal["train", "test"]
Variant = Literal["OBJ", "PB_T25", "PB_T25_R", "PB_T50_R", "PB_T50_RS"]

SCANOBJECTNN_CLASSES = (
    "bag",
    "bin",
    "box",
    "cabinet",
    "chair",
    "desk",
    "display",
    "door",
    "shelf",
    "table",
    "bed",
    "pillow",
    "sink",
    "sofa",
    "toilet",
)
"""The 15 class names, label = index (official FAQ 4, ``hkust-vgd/scanobjectnn : training_data/README.md``)."""

VARIANT_SUFFIXES: dict[str, str] = {
    "OBJ": "",
    "PB_T25": "_augmented25_norot",
    "PB_T25_R": "_augmented25rot",
    "PB_T50_R": "_augmentedrot",
    "PB_T50_RS": "_augmentedrot_scale75",
}
"""File-name suffix of each variant (``"OBJ"`` is OBJ_BG in ``main_split`` and OBJ_ONLY in ``main_split_nobg``)."""

BACKGROUND_LABEL = -1
"""Value of ``mask`` that marks a background point (every other value is a point of the object)."""

_SPLIT_PREFIXES = {"train": "training", "test": "test"}
_FOLDERS = {True: "main_split", False: "main_split_nobg"}

EXPECTED_LAYOUT = (
    "expected the official ScanObjectNN layout: <root>/h5_files/{main_split,main_split_nobg}/"
    "{training,test}_objectdataset{suffix}.h5 (root = the dataset folder, the h5_files folder or the split folder), "
    "each h5 with keys 'data' (S, P, 3) float, 'label' (S,) and 'mask' (S, P) (-1 = background)"
)


def _split_folder(root: Path, background: bool) -> Path:
    """The split folder (``main_split`` or ``main_split_nobg``) that ``root`` designates."""
    name = _FOLDERS[background]
    for candidate in (root / "h5_files" / name, root / name):
        if candidate.is_dir():
            return candidate
    if root.name == name and root.is_dir():
        return root
    other = _FOLDERS[not background]
    hint = f" (root is the {other!r} folder but background={background})" if root.name == other else ""
    raise FileNotFoundError(f"ScanObjectNN root {str(root)!r} has no {name!r} folder{hint}; {EXPECTED_LAYOUT}")


def scanobjectnn_file(root: str | Path, split: Split, variant: Variant = "OBJ", background: bool = True) -> Path:
    """Path of one official ScanObjectNN h5 file (see the module docstring for the accepted ``root`` folders).

    Args:
        root: Dataset folder, its ``h5_files`` folder, or the split folder.
        split: ``"train"`` (``training_*.h5``) or ``"test"`` (``test_*.h5``).
        variant: ``"OBJ"``, ``"PB_T25"``, ``"PB_T25_R"``, ``"PB_T50_R"`` or ``"PB_T50_RS"``.
        background: ``True`` reads ``main_split`` (with background), ``False`` ``main_split_nobg``.

    Returns:
        The existing file, e.g. ``<root>/h5_files/main_split/training_objectdataset_augmentedrot_scale75.h5``.

    Raises:
        ValueError: On an unknown ``split`` or ``variant``.
        FileNotFoundError: If the split folder or the file does not exist (the message names the path).

    Example:
        >>> scanobjectnn_file("data/ScanObjectNN", "test", "PB_T50_RS")  # doctest: +SKIP
        PosixPath('data/ScanObjectNN/h5_files/main_split/test_objectdataset_augmentedrot_scale75.h5')
    """
    if split not in _SPLIT_PREFIXES:
        raise ValueError(f"`split` must be 'train' or 'test', got {split!r}")
    if variant not in VARIANT_SUFFIXES:
        raise ValueError(f"`variant` must be one of {tuple(VARIANT_SUFFIXES)}, got {variant!r}")
    folder = _split_folder(Path(root).expanduser(), background)
    path = folder / f"{_SPLIT_PREFIXES[split]}_objectdataset{VARIANT_SUFFIXES[variant]}.h5"
    if not path.is_file():
        raise FileNotFoundError(f"ScanObjectNN file {str(path)!r} does not exist; {EXPECTED_LAYOUT}")
    return path


def _read_arrays(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Raw ``data``, ``label`` and optional ``mask`` of one h5 file (HDF5 errors become DatasetLayoutError)."""
    try:
        with h5py.File(path, "r") as f:
            missing = [key for key in ("data", "label") if key not in f]
            if missing:
                raise DatasetLayoutError(
                    f"{str(path)!r} has no key(s) {missing} (found {sorted(f)}); {EXPECTED_LAYOUT}"
                )
            points = np.asarray(f["data"][...])
            labels = np.asarray(f["label"][...])
            mask = np.asarray(f["mask"][...]) if "mask" in f else None
    except OSError as err:
        raise DatasetLayoutError(f"{str(path)!r} is not a readable HDF5 file ({err}); {EXPECTED_LAYOUT}") from err
    return points, labels, mask


def _check_labels(path: Path, labels: np.ndarray, num_objects: int) -> np.ndarray:
    """Labels as int64 ``(S,)``: ``(S,)`` or ``(S, 1)`` integral values in ``[0, 15)``."""
    if labels.ndim == 2 and labels.shape[1] == 1:
        labels = labels[:, 0]
    numeric = np.issubdtype(labels.dtype, np.integer) or np.issubdtype(labels.dtype, np.floating)
    if labels.shape != (num_objects,) or not numeric:
        raise DatasetLayoutError(
            f"{str(path)!r}: 'label' has shape {labels.shape} and dtype {labels.dtype}, "
            f"expected numbers of shape ({num_objects},) or ({num_objects}, 1)"
        )
    bad = ~np.isfinite(labels) | (labels != np.round(labels)) | (labels < 0) | (labels >= len(SCANOBJECTNN_CLASSES))
    if bad.any():
        index = int(np.flatnonzero(bad)[0])
        raise DatasetLayoutError(
            f"{str(path)!r}: 'label'[{index}] = {labels[index].item()!r} is not a class index in [0, "
            f"{len(SCANOBJECTNN_CLASSES)})"
        )
    return labels.astype(np.int64)


def load_scanobjectnn_h5(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Read and check one official ScanObjectNN h5 file.

    Args:
        path: The h5 file.

    Returns:
        ``(points (S, P, 3) float32, labels (S,) int64, mask (S, P) int64 or None)``; ``P = 2048`` in the official
        files; ``mask`` is ``None`` when the file has no ``mask`` key (``-1`` = background point).

    Raises:
        FileNotFoundError: If ``path`` does not exist.
        DatasetLayoutError: If the file is not HDF5, lacks ``data``/``label``, or a shape, dtype or label value is
            wrong (the message names the file).
        NonFiniteError: If ``data`` holds NaN or Inf (the message names the file and the first bad object).
    """
    path = Path(path).expanduser()
    if not path.is_file():
        raise FileNotFoundError(f"ScanObjectNN file {str(path)!r} does not exist; {EXPECTED_LAYOUT}")
    points, labels, mask = _read_arrays(path)
    if points.ndim != 3 or points.shape[-1] != 3 or not np.issubdtype(points.dtype, np.number):
        raise DatasetLayoutError(
            f"{str(path)!r}: 'data' has shape {points.shape} and dtype {points.dtype}, expected numbers of shape "
            "(S, P, 3)"
        )
    points = points.astype(np.float32)
    finite = np.isfinite(points).all(axis=(1, 2))
    if not finite.all():
        raise NonFiniteError(f"{str(path)!r}: 'data' of object {int(np.flatnonzero(~finite)[0])} has NaN or Inf values")
    labels = _check_labels(path, labels, points.shape[0])
    if mask is not None:
        if mask.shape != points.shape[:2] or not np.issubdtype(mask.dtype, np.number):
            raise DatasetLayoutError(
                f"{str(path)!r}: 'mask' has shape {mask.shape} and dtype {mask.dtype}, expected numbers of shape "
                f"{points.shape[:2]}"
            )
        mask = mask.astype(np.int64)
    return points, labels, mask


def drop_background(points: np.ndarray, mask: np.ndarray, seed: int = 0, source: str = "points") -> np.ndarray:
    """Keep the object points of every object, refilled to the original size by repeating object points.

    Object ``i`` keeps its ``F_i`` object points (``mask != -1``) in file order, followed by ``P - F_i`` of them drawn
    uniformly with replacement by ``numpy.random.default_rng([seed, i])`` (``i`` = row in ``points``, the file row
    when called by :func:`scanobjectnn_objects`, so object ``i``'s refill does not depend on the other objects).
    Repeated points change neither a nearest neighbour nor a max-pooled descriptor; a pair sampled without
    replacement from a refilled object may contain a point twice.

    Args:
        points: ``(S, P, 3)`` points.
        mask: ``(S, P)`` mask, ``-1`` = background.
        seed: Seed of the refill draws.
        source: Name used in error messages (the file).

    Returns:
        ``(S, P, 3)`` points, every one an object point of its object, every object point present at least once.

    Raises:
        ShapeError: If ``mask`` is not ``(S, P)`` for ``points (S, P, 3)``.
        DatasetLayoutError: If an object has no object point (the message names ``source`` and the object).
    """
    if points.ndim != 3 or points.shape[-1] != 3:
        raise ShapeError("points", ("S", "P", 3), points.shape)
    if mask.shape != points.shape[:2]:
        raise ShapeError("mask", points.shape[:2], mask.shape)
    out = np.empty_like(points)
    num = points.shape[1]
    for i, (obj, keep) in enumerate(zip(points, mask != BACKGROUND_LABEL)):
        fg = obj[keep]
        if fg.shape[0] == 0:
            raise DatasetLayoutError(f"{source!r}: object {i} has no object point (its 'mask' is -1 everywhere)")
        extra = np.random.default_rng([seed, i]).integers(0, fg.shape[0], size=num - fg.shape[0])
        out[i] = np.concatenate([fg, fg[extra]])
    return out


def scanobjectnn_objects(
    root: str | Path,
    split: Split,
    variant: Variant = "OBJ",
    background: bool = True,
    drop_background_points: bool = False,
    seed: int = 0,
) -> ObjectSet:
    """The objects of one ScanObjectNN split file.

    Args:
        root: Dataset folder, its ``h5_files`` folder or the split folder (see the module docstring).
        split: ``"train"`` or ``"test"``.
        variant: ``"OBJ"`` (OBJ_BG / OBJ_ONLY), ``"PB_T25"``, ``"PB_T25_R"``, ``"PB_T50_R"`` or ``"PB_T50_RS"``.
        background: Read ``main_split`` (``True``, objects with background) or ``main_split_nobg`` (``False``).
        drop_background_points: Remove the points whose ``mask`` is ``-1`` and refill each object to ``P`` points
            by repeating its object points (:func:`drop_background`). A ``main_split_nobg`` file without a ``mask``
            key is taken as background-free (the official ``*_nobg`` files were filtered before sampling).
        seed: Seed of the refill draws of ``drop_background_points``.

    Returns:
        :class:`~lcreg.data.pairs.ObjectSet` with ``points (S, P, 3)`` float32 (``P = 2048`` officially),
        ``normals=None`` and ``labels (S,)`` int64 (names in :data:`SCANOBJECTNN_CLASSES`).

    Raises:
        ValueError: On an unknown ``split`` or ``variant``.
        FileNotFoundError: If the folder or file is missing (the message names it and the expected layout).
        DatasetLayoutError: On a corrupt file, missing keys, wrong shapes or labels, a missing ``mask`` needed by
            ``drop_background_points``, or an object without object points (the message names the file).
        NonFiniteError: On NaN/Inf points (the message names the file).

    Example:
        >>> objs = scanobjectnn_objects("data/ScanObjectNN", "test", "PB_T50_RS")  # doctest: +SKIP
        >>> objs.points.shape  # doctest: +SKIP
        (2882, 2048, 3)
    """
    path = scanobjectnn_file(root, split, variant, background)
    points, labels, mask = load_scanobjectnn_h5(path)
    if drop_background_points:
        if mask is not None:
            points = drop_background(points, mask, seed=seed, source=str(path))
        elif background:
            raise DatasetLayoutError(
                f"{str(path)!r} has no 'mask' key, needed by drop_background_points=True; {EXPECTED_LAYOUT}"
            )
    return ObjectSet(points, None, labels)


class ScanObjectNNDataModule(PairDataModule):
    """ScanObjectNN (official ``h5_files`` layout) as registration pairs under the ModelNet40 pair protocol.

    Train and validation objects come from the training file of the chosen variant (validation carved with
    ``val_fraction``, never from the test file); test objects are the test file. Validation and test pairs are
    deterministic per index.

    Args:
        root: Dataset folder, its ``h5_files`` folder or the split folder (checked in :meth:`setup`, not here, so
            configs can be built without the data).
        variant: ``"OBJ"`` (OBJ_BG / OBJ_ONLY), ``"PB_T25"``, ``"PB_T25_R"``, ``"PB_T50_R"`` or ``"PB_T50_RS"``.
        background: ``True`` reads ``main_split`` (objects with background), ``False`` ``main_split_nobg``.
        drop_background_points: Remove background points (``mask == -1``) and refill every object by repeating its
            object points (see :func:`scanobjectnn_objects`).
        **kwargs: Options of :class:`~lcreg.data.datamodule.PairDataModule` (``num_points``, ``batch_size``,
            ``max_angle_deg``, ``seed``, ...); ``seed`` also seeds the refill draws.

    Raises:
        ValueError: On an unknown ``variant`` or invalid pair-protocol options.

    Example:
        >>> dm = ScanObjectNNDataModule(root="data/ScanObjectNN", variant="PB_T50_RS")  # no file is read here
        >>> dm.pair_protocol.num_points, dm.pair_protocol.max_angle_deg
        (1024, 45.0)
    """

    def __init__(
        self,
        root: str,
        variant: Variant = "OBJ",
        background: bool = True,
        drop_background_points: bool = False,
        **kwargs: Any,
    ) -> None:
        if variant not in VARIANT_SUFFIXES:
            raise ValueError(f"`variant` must be one of {tuple(VARIANT_SUFFIXES)}, got {variant!r}")
        super().__init__(**kwargs)
        self.root = root
        self.variant: Variant = variant
        self.background = background
        self.drop_background_points = drop_background_points

    def class_names(self) -> list[str]:
        """:data:`SCANOBJECTNN_CLASSES` (label = index)."""
        return list(SCANOBJECTNN_CLASSES)

    def _load_objects(self, stage: Literal["fit", "test"]) -> dict[str, ObjectSet]:
        dataset_root(self.root, type(self).__name__, EXPECTED_LAYOUT)
        split: Split = "train" if stage == "fit" else "test"
        objects = scanobjectnn_objects(
            self.root, split, self.variant, self.background, self.drop_background_points, seed=self.seed
        )
        return {split: objects}
