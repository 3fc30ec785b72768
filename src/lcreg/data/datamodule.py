"""Pair datasets and Lightning DataModules for object registration (ModelNet40 and the embedded synthetic shapes).

* :class:`PairDataset` turns objects into pairs with :func:`lcreg.data.pairs.make_pair`. Deterministic datasets
  (validation, test) seed a fresh generator with ``seed + index``, so the same pairs come out on every run, in every
  worker and every epoch. Training items are ``(index, seed)`` keys from :class:`lcreg.data.sampling.EpochSampler`
  (order and seeds fixed by a base seed and the epoch), so training pairs change every epoch yet a resumed run sees
  the same stream; a plain training index draws its seed from the global torch RNG.
* the loaders batch pairs with :func:`lcreg.data.collate.collate_pairs` (a :class:`lcreg.types.RegistrationBatch`).
* :class:`PairDataModule` holds the protocol options (the LightningCLI keys under ``data.init_args``), carves the
  validation objects out of the training pool with a seeded permutation (never out of the test set) and builds the
  loaders; subclasses only say which objects make up the pools. Its ``state_dict`` (saved in every checkpoint) is
  the training stream's position, so ``lcreg fit --ckpt_path last`` continues mid-epoch with the same batches.
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
import torch
from lightning.pytorch import LightningDataModule
from torch.utils.data import DataLoader, Dataset

from lcreg.checks import (
    DatasetLayoutError,
    ShapeError,
    check_count_or_fraction,
    dataset_root,
    resolve_count,
)
from lcreg.data.collate import collate_pairs
from lcreg.data.modelnet40 import EXPECTED_LAYOUT, load_shape_names, modelnet40_objects
from lcreg.data.pairs import ObjectSet, PairProtocol, PartialMode, make_pair, normalize_object
from lcreg.data.sampling import ResumableLoader, ResumableTrainingOrder
from lcreg.data.synthetic import PRIMITIVES, synthetic_shapes

__all__ = [
    "ModelNet40DataModule",
    "PairDataModule",
    "PairDataset",
    "SyntheticDataModule",
]

_SEED_HIGH = 2**62
SYNTHETIC_TEST_SEED_OFFSET = 1_000_003
"""The synthetic test shapes use ``shape_seed + SYNTHETIC_TEST_SEED_OFFSET``, so they differ from the train shapes."""
TRAIN_SUBSET_SEED_OFFSET = 2_000_003
"""The ``train_objects`` subset is drawn with ``seed + TRAIN_SUBSET_SEED_OFFSET``, a stream apart from the carve-out."""


class PairDataset(Dataset[dict[str, torch.Tensor]]):
    """Registration pairs drawn from a fixed set of objects.

    Args:
        points: Object points ``(S, P, 3)`` (NumPy array or tensor, kept on the CPU).
        normals: Object normals ``(S, P, 3)`` or ``None``.
        protocol: How pairs are made.
        deterministic: If ``True`` (validation/test), item ``i`` always uses ``torch.Generator().manual_seed(seed +
            i)``; if ``False`` (training), every call draws a fresh seed from the global torch RNG. A key ``(i, s)``
            (:class:`~lcreg.data.sampling.EpochSampler`) uses seed ``s`` in both cases.
        seed: Base seed of deterministic items.
        pairs_per_object: Pairs drawn from every object (``>= 1``): the dataset has ``S * pairs_per_object`` items,
            item ``i`` is a pair of object ``i % S`` (with its own generator, ``seed + i`` when deterministic).
            More pairs per object make a small validation split steadier without taking objects from training.
        labels: Optional class label of every object ``(S,)`` (:meth:`object_labels`; not part of the items).

    Raises:
        ShapeError: If ``points``/``normals`` are not ``(S, P, 3)`` with the same shape.
        ValueError: If ``pairs_per_object`` is not an integer ``>= 1``.

    Example:
        >>> points = torch.rand(4, 2048, 3)
        >>> ds = PairDataset(points, None, PairProtocol(), deterministic=True, seed=0)
        >>> sorted(ds[0])
        ['angles_zyx', 'index', 'points_ref', 'points_src', 'transform_ref_src']
    """

    def __init__(
        self,
        points: np.ndarray | torch.Tensor,
        normals: np.ndarray | torch.Tensor | None,
        protocol: PairProtocol,
        deterministic: bool = False,
        seed: int = 0,
        pairs_per_object: int = 1,
        labels: np.ndarray | torch.Tensor | None = None,
    ) -> None:
        self.points = torch.as_tensor(points)
        self.normals = None if normals is None else torch.as_tensor(normals)
        self.labels = None if labels is None else torch.as_tensor(labels, dtype=torch.int64)
        if self.points.ndim != 3 or self.points.shape[-1] != 3:
            raise ShapeError("points", ("S", "P", 3), self.points.shape)
        if self.normals is not None and self.normals.shape != self.points.shape:
            raise ShapeError("normals", tuple(self.points.shape), self.normals.shape)
        if self.labels is not None and self.labels.shape != self.points.shape[:1]:
            raise ShapeError("labels", tuple(self.points.shape[:1]), self.labels.shape)
        self.protocol = protocol
        self.deterministic = deterministic
        self.seed = int(seed)
        self.pairs_per_object = _check_pairs_per_object(pairs_per_object)

    @classmethod
    def from_objects(
        cls,
        objects: ObjectSet,
        protocol: PairProtocol,
        deterministic: bool = False,
        seed: int = 0,
        pairs_per_object: int = 1,
    ) -> PairDataset:
        """Build a dataset from an :class:`~lcreg.data.pairs.ObjectSet` (its labels included)."""
        return cls(objects.points, objects.normals, protocol, deterministic, seed, pairs_per_object, objects.labels)

    def object_labels(self, index: torch.Tensor) -> torch.Tensor | None:
        """Class label of the object of each pair ``index (K,)``: ``labels[index % S]`` ``(K,)``, or ``None``."""
        return None if self.labels is None else self.labels[index.cpu().long() % self.num_objects]

    def object_points(self, index: int) -> torch.Tensor:
        """The whole object of pair ``index`` ``(P, 3)``, in the frame of the pair's clean source points.

        Every point of a clean source is a row of it (before noise and crop, :func:`~lcreg.data.pairs.make_pair`); it
        is the surface a source's points lie on, e.g. to ask how far an estimate moves them off it
        (:func:`lcreg.geometry.surface.surface_residual`).
        """
        if not -len(self) <= index < len(self):
            raise IndexError(f"index {index} is out of range for a dataset of {len(self)} pairs")
        points = self.points[index % len(self) % self.num_objects].to(torch.float64)
        return normalize_object(points) if self.protocol.normalize else points

    @property
    def num_objects(self) -> int:
        """Objects ``S`` the pairs are drawn from."""
        return int(self.points.shape[0])

    def __len__(self) -> int:
        return self.num_objects * self.pairs_per_object

    def generator(self, index: int) -> torch.Generator:
        """The CPU generator of item ``index`` (fixed when deterministic, fresh from the global RNG otherwise)."""
        if self.deterministic:
            return torch.Generator().manual_seed(self.seed + index)
        return torch.Generator().manual_seed(int(torch.randint(0, _SEED_HIGH, (1,)).item()))

    def __getitem__(self, key: int | tuple[int, int]) -> dict[str, torch.Tensor]:
        """Pair ``key`` (an index, or ``(index, seed)``).

        Returns:
            The keys of :func:`~lcreg.data.pairs.make_pair` plus ``index`` (int64 scalar, the pair's index ``i``;
            its object is ``i % S``).
        """
        return self._pair(key)

    def item_with_indices(self, key: int | tuple[int, int]) -> dict[str, torch.Tensor]:
        """Pair ``key`` as ``self[key]`` (the same pair when deterministic) with the object row of every point.

        Returns:
            ``self[key]``'s keys plus ``point_index_src`` and ``point_index_ref`` ``(K,)`` int64
            (:func:`~lcreg.data.pairs.make_pair`; :func:`~lcreg.data.pairs.true_correspondences` matches them).
        """
        return self._pair(key, with_indices=True)

    def _pair(self, key: int | tuple[int, int], with_indices: bool = False) -> dict[str, torch.Tensor]:
        index, seed = key if isinstance(key, tuple) else (key, None)
        if not -len(self) <= index < len(self):
            raise IndexError(f"index {index} is out of range for a dataset of {len(self)} pairs")
        index = index % len(self)
        item = index % self.num_objects
        normals = None if self.normals is None else self.normals[item]
        generator = self.generator(index) if seed is None else torch.Generator().manual_seed(seed)
        pair = make_pair(self.points[item], normals, self.protocol, generator, with_indices)
        pair["index"] = torch.tensor(index, dtype=torch.int64)
        return pair


def _check_pairs_per_object(value: Any, name: str = "pairs_per_object", minimum: int = 1) -> int:
    """``value`` as an int ``>= minimum`` (bools and non-integers refused with a ``ValueError`` naming ``name``)."""
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ValueError(f"`{name}` must be an integer >= {minimum}, got {value!r}")
    return value


def _check_train_objects(value: Any) -> int | float | None:
    """``train_objects``: ``None``, an int count ``>= 1`` or a float fraction in ``(0, 1)`` (else a ``ValueError``).

    A whole float above 1 is the count it spells: under LightningCLI, jsonargparse parses this ``int | float | None``
    argument float first (typing hands it back as ``Optional[Union[float, int]]``), so a count from a config or the
    command line arrives as a float, and a fraction cannot exceed 1. For the same reason 1.0 (one object, or all of
    them) is refused as ambiguous: ``None`` keeps all.
    """
    if isinstance(value, float) and value == 1.0:
        raise ValueError(
            "`train_objects` 1.0 is ambiguous (a config's count 1 arrives as 1.0): give null (None) to keep all the "
            "training objects, or a fraction below 1"
        )
    if isinstance(value, float) and value > 1.0 and value.is_integer():
        value = int(value)
    return None if value is None else check_count_or_fraction(value, "train_objects", wrong_type=ValueError)


def _rank_within_label(labels: np.ndarray) -> np.ndarray:
    """For each position, how many earlier positions hold the same label (0 for a label's first occurrence)."""
    ranks = np.zeros(len(labels), dtype=np.int64)
    seen: dict[int, int] = {}
    for i, label in enumerate(labels.tolist()):
        ranks[i] = seen.get(label, 0)
        seen[label] = ranks[i] + 1
    return ranks


class PairDataModule(ResumableTrainingOrder, LightningDataModule):
    """Base DataModule: pair protocol options, validation carving and loaders.

    Subclasses implement :meth:`_load_objects`. Validation and test pairs are deterministic per index (generator
    seeded with ``seed + index``); training pairs change every epoch.

    Args:
        num_points: Points sampled per cloud (``N``).
        batch_size: Pairs per batch (all loaders).
        num_workers: DataLoader workers (persistent when > 0).
        max_angle_deg: Each Euler angle ``U[0, max_angle_deg]`` degrees.
        max_translation: Each translation component ``U[-max_translation, max_translation]``.
        noise_sigma: Gaussian noise std added independently to both clouds (0 = clean).
        noise_clip: Noise clip ``±noise_clip``.
        partial: ``"none"``, ``"prnet"`` (shared far anchor) or ``"viewpoint"`` crops.
        partial_keep: Points kept per cloud by a crop: a count or a fraction of ``num_points``.
        independent_sampling: Source and reference are independent samplings of the object.
        normalize: Scale every object into the unit sphere before sampling.
        val_fraction: Fraction of the training pool held out for validation (seeded, ignored by subclasses that
            define their own validation objects).
        val_pairs_per_object: Validation pairs drawn from every validation object (each with its own fixed
            motion and samplings). 1 is one pair per object; more make checkpoint selection and early stopping
            steadier on a small split (``modelnet40_mini``: 78 objects) without taking objects from training.
        train_objects: Train on a seeded subset of the training objects (after the validation objects are carved
            out): an int count or a float fraction below 1 of them (rounded, at least one); a whole float above 1
            is a count (a config's count reaches here as a float), 1.0 is refused. ``None`` (default) keeps all.
            Validation and test objects do not change, and for one ``seed`` a smaller subset lies inside a larger
            one, so runs at several sizes measure how the error scales with the training data.
        train_class_cap: Keep at most this many training objects of each class label (the first ones of the same
            seeded order as ``train_objects``, which then takes a prefix of what is kept: the cap evens out the
            whole kept set, not each prefix of it). ``None`` (default): no cap. A
            cap at the size of the smaller classes gives a training set whose classes are more even than the
            dataset's (``modelnet40_mini``: 80 % airplanes) at a size that a ``train_objects`` count can match.
        seed: Seed of the validation carve-out and base seed of the deterministic val/test pairs.

    Raises:
        ValueError: On invalid protocol options or ``val_fraction``/``batch_size``/``num_workers``/
            ``train_objects`` (in :meth:`setup` also a ``train_objects`` count above the training objects).
        DatasetLayoutError: In :meth:`setup`, when a split it builds has no objects.
    """

    def __init__(
        self,
        num_points: int = 1024,
        batch_size: int = 32,
        num_workers: int = 0,
        max_angle_deg: float = 45.0,
        max_translation: float = 0.5,
        noise_sigma: float = 0.0,
        noise_clip: float = 0.05,
        partial: PartialMode = "none",
        partial_keep: int | float = 768,
        independent_sampling: bool = True,
        normalize: bool = True,
        val_fraction: float = 0.1,
        val_pairs_per_object: int = 1,
        train_objects: int | float | None = None,
        train_class_cap: int | None = None,
        seed: int = 1234,
    ) -> None:
        super().__init__()
        self.save_hyperparameters()
        self.val_pairs_per_object = _check_pairs_per_object(val_pairs_per_object, "val_pairs_per_object")
        self.train_objects = _check_train_objects(train_objects)
        self.train_class_cap = (
            None if train_class_cap is None else _check_pairs_per_object(train_class_cap, "train_class_cap")
        )
        _check_pairs_per_object(batch_size, "batch_size")  # '2' and 2.5 too: one line naming the argument
        _check_pairs_per_object(num_workers, "num_workers", minimum=0)
        if not 0.0 <= val_fraction < 1.0:
            raise ValueError(f"`val_fraction` must be in [0, 1), got {val_fraction}")
        self.pair_protocol = PairProtocol(
            num_points=num_points,
            max_angle_deg=max_angle_deg,
            max_translation=max_translation,
            independent_sampling=independent_sampling,
            normalize=normalize,
            noise_sigma=noise_sigma,
            noise_clip=noise_clip,
            partial=partial,
            partial_keep=partial_keep,
        )
        self.batch_size = batch_size
        self.num_workers = num_workers
        self.val_fraction = val_fraction
        self.seed = seed
        self.train_set: PairDataset | None = None
        self.val_set: PairDataset | None = None
        self.test_set: PairDataset | None = None

    def _load_objects(self, stage: Literal["fit", "test"]) -> dict[str, ObjectSet]:
        """Objects of a stage: ``{"train": ..., "val": ... (optional)}`` for ``"fit"``, ``{"test": ...}`` else.

        Without a ``"val"`` entry, validation objects are carved out of ``"train"`` with ``val_fraction``.
        """
        raise NotImplementedError

    def split_train_val(self, objects: ObjectSet) -> tuple[ObjectSet, ObjectSet]:
        """Split a training pool into (train, val) with a permutation seeded by ``seed``.

        The validation size is ``round(val_fraction * S)`` (at least 1 when ``val_fraction > 0`` and ``S > 1``).
        """
        total = len(objects)
        num_val = round(self.val_fraction * total)
        if self.val_fraction > 0 and total > 1:
            num_val = min(max(num_val, 1), total - 1)
        perm = torch.randperm(total, generator=torch.Generator().manual_seed(self.seed)).numpy()
        val_idx, train_idx = np.sort(perm[:num_val]), np.sort(perm[num_val:])
        return objects.subset(train_idx), objects.subset(val_idx)

    def keep_training_objects(self, objects: ObjectSet) -> ObjectSet:
        """The training objects kept by ``train_class_cap`` and then ``train_objects`` (all of them without either).

        Both walk one permutation seeded by ``seed``: the cap keeps the first ``train_class_cap`` objects of each
        label in it, ``train_objects`` the first ``n`` of what is left; the subset keeps the original order, so the
        subsets of one seed are nested.

        Raises:
            ValueError: If a ``train_objects`` count exceeds the training objects (after the cap).
        """
        if self.train_objects is None and self.train_class_cap is None:
            return objects
        generator = torch.Generator().manual_seed(self.seed + TRAIN_SUBSET_SEED_OFFSET)
        order = torch.randperm(len(objects), generator=generator).numpy()
        if self.train_class_cap is not None:
            order = order[_rank_within_label(objects.labels[order]) < self.train_class_cap]
        total = len(order)
        if self.train_objects is None:
            return objects.subset(np.sort(order))
        if isinstance(self.train_objects, int) and self.train_objects > total:
            capped = "" if self.train_class_cap is None else f" kept by `train_class_cap` ({self.train_class_cap})"
            raise ValueError(f"`train_objects` ({self.train_objects}) exceeds the {total} training objects{capped}")
        return objects.subset(np.sort(order[: resolve_count(self.train_objects, total)]))

    def setup(self, stage: str | None = None) -> None:
        """Build the datasets needed by ``stage`` (``fit``/``validate`` need train+val, ``test``/``predict`` test)."""
        if stage in (None, "fit", "validate") and (self.train_set is None or self.val_set is None):
            objects = self._load_objects("fit")
            if "val" in objects:
                train, val = objects["train"], objects["val"]
            else:
                train, val = self.split_train_val(objects["train"])
            train = self.keep_training_objects(train)
            self._check_not_empty(train, "train")
            self._check_not_empty(val, "validation")
            self.train_set = PairDataset.from_objects(train, self.pair_protocol, deterministic=False, seed=self.seed)
            self.val_set = PairDataset.from_objects(
                val, self.pair_protocol, deterministic=True, seed=self.seed, pairs_per_object=self.val_pairs_per_object
            )
        if stage in (None, "test", "predict") and self.test_set is None:
            test = self._load_objects("test")["test"]
            self._check_not_empty(test, "test")
            self.test_set = PairDataset.from_objects(test, self.pair_protocol, deterministic=True, seed=self.seed)

    def _check_not_empty(self, objects: ObjectSet, split: str) -> None:
        """Raise ``DatasetLayoutError`` for a split without objects (training would silently do nothing)."""
        if len(objects) == 0:
            raise DatasetLayoutError(
                f"{type(self).__name__}: the {split} split has no objects (val_fraction={self.val_fraction}; "
                "check the dataset's files, labels and the split options)"
            )

    def class_names(self) -> list[str] | None:
        """Names of the class labels (label = list index), or ``None``; subclasses that know them override this."""
        return None

    def pair_classes(self, split: Literal["val", "test"], index: torch.Tensor) -> list[str] | None:
        """The class of the object of each pair ``index (K,)`` of a set-up split (its name, else its label).

        ``lcreg test`` writes it into ``test_per_pair.csv``, so that failures can be read per class (e.g. objects
        with an axis of symmetry, whose rotation about it is not observable). ``None`` when the split has no labels.
        """
        dataset = self.test_set if split == "test" else self.val_set
        labels = None if dataset is None else dataset.object_labels(index)
        if labels is None:
            return None
        names = self.class_names() or []
        return [names[label] if 0 <= label < len(names) else str(label) for label in labels.tolist()]

    @property
    def points_per_cloud(self) -> int:
        """Points in every cloud this module yields (``num_points``, or the crop's ``partial_keep``)."""
        return self.pair_protocol.num_kept

    def _loader(self, dataset: PairDataset | None, name: str, shuffle: bool) -> DataLoader[Any]:
        """A DataLoader over ``dataset`` with :func:`~lcreg.data.collate.collate_pairs`.

        The shuffled (training) loader follows an :class:`~lcreg.data.sampling.EpochSampler` (resumable) and drops
        the last incomplete batch when there is a full one (as the DCP/PCRNet originals do): a batch of one pair
        breaks batch-wise BatchNorm (FMR-Net's decoder, PCRNet-style MLPs). Validation and test keep every pair.
        Every loader has its own generator, so iterating it never draws from the global RNG.
        """
        if dataset is None:
            raise RuntimeError(f"the {name} set is not built; call `setup()` with the matching stage first")
        sampler = self.training_sampler(len(dataset), pair_seeds=True) if shuffle else None
        return (ResumableLoader if shuffle else DataLoader)(
            dataset,
            batch_size=self.batch_size,
            sampler=sampler,
            drop_last=shuffle and len(dataset) > self.batch_size,
            num_workers=self.num_workers,
            persistent_workers=self.num_workers > 0,
            collate_fn=collate_pairs,
            generator=torch.Generator(),
        )

    def train_dataloader(self) -> DataLoader[Any]:
        """Shuffled training pairs (new pairs every epoch; order and pairs fixed by the seed and the epoch)."""
        return self._loader(self.train_set, "train", shuffle=True)

    def val_dataloader(self) -> DataLoader[Any]:
        """Deterministic validation pairs, in order."""
        return self._loader(self.val_set, "val", shuffle=False)

    def test_dataloader(self) -> DataLoader[Any]:
        """Deterministic test pairs, in order."""
        return self._loader(self.test_set, "test", shuffle=False)

    def predict_dataloader(self) -> DataLoader[Any]:
        """The test pairs (``predict`` registers the test set)."""
        return self._loader(self.test_set, "test", shuffle=False)


class ModelNet40DataModule(PairDataModule):
    """ModelNet40 (official ``modelnet40_ply_hdf5_2048`` layout) under the unseen-objects/-categories protocols.

    Train and validation objects come from the train split of labels 0-19 (validation carved with
    ``val_fraction``); the test set follows ``protocol`` (see :mod:`lcreg.data.modelnet40`).

    Args:
        root: Dataset folder (checked in :meth:`setup`, not here, so configs can be built without the data).
        protocol: ``"unseen_objects"`` or ``"unseen_categories"``.
        unseen_categories_test: ``"all"`` (labels 20-39 of both splits, as PointNetLK Revisited) or
            ``"test_split"`` (labels 20-39 of the test split, as DCP/PRNet).
        **kwargs: Options of :class:`PairDataModule` (``num_points``, ``batch_size``, ...).
    """

    def __init__(
        self,
        root: str,
        protocol: Literal["unseen_objects", "unseen_categories"] = "unseen_objects",
        unseen_categories_test: Literal["test_split", "all"] = "all",
        **kwargs: Any,
    ) -> None:
        if protocol not in ("unseen_objects", "unseen_categories"):
            raise ValueError(f"`protocol` must be 'unseen_objects' or 'unseen_categories', got {protocol!r}")
        if unseen_categories_test not in ("test_split", "all"):
            raise ValueError(f"`unseen_categories_test` must be 'test_split' or 'all', got {unseen_categories_test!r}")
        super().__init__(**kwargs)
        self.root = root
        self.protocol = protocol
        self.unseen_categories_test = unseen_categories_test

    def class_names(self) -> list[str] | None:
        """The names of ``shape_names.txt`` (``None`` when the dataset has no such file)."""
        return load_shape_names(self.root)

    def _load_objects(self, stage: Literal["fit", "test"]) -> dict[str, ObjectSet]:
        dataset_root(self.root, type(self).__name__, EXPECTED_LAYOUT)
        part: Literal["train", "test"] = "train" if stage == "fit" else "test"
        return {part: modelnet40_objects(self.root, self.protocol, part, self.unseen_categories_test)}


class SyntheticDataModule(PairDataModule):
    """Embedded procedural shapes (:func:`lcreg.data.synthetic.synthetic_shapes`): needs no files.

    Train and validation shapes are disjoint slices of one stream (``shape_seed``); test shapes come from another
    seed (``shape_seed + 1_000_003``). ``val_fraction`` is not used (``num_val`` sets the validation size).

    Args:
        num_train: Training shapes.
        num_val: Validation shapes.
        num_test: Test shapes.
        points_per_shape: Points per shape (must be >= ``num_points``).
        shape_seed: Seed of the shapes.
        **kwargs: Options of :class:`PairDataModule` (``num_points``, ``batch_size``, ...).
    """

    def __init__(
        self,
        num_train: int = 512,
        num_val: int = 64,
        num_test: int = 128,
        points_per_shape: int = 2048,
        shape_seed: int = 0,
        **kwargs: Any,
    ) -> None:
        super().__init__(**kwargs)
        for name, value in (("num_train", num_train), ("num_val", num_val), ("num_test", num_test)):
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"`{name}` must be an int >= 1 (an empty split trains or checks nothing), got {value}")
        if points_per_shape < self.pair_protocol.num_points:
            raise ValueError(
                f"`points_per_shape` ({points_per_shape}) must be >= `num_points` ({self.pair_protocol.num_points})"
            )
        self.num_train = num_train
        self.num_val = num_val
        self.num_test = num_test
        self.points_per_shape = points_per_shape
        self.shape_seed = shape_seed

    def class_names(self) -> list[str]:
        """A shape's label is the kind of its first primitive (:data:`~lcreg.data.synthetic.PRIMITIVES`)."""
        return list(PRIMITIVES)

    def _load_objects(self, stage: Literal["fit", "test"]) -> dict[str, ObjectSet]:
        if stage == "fit":
            pool = ObjectSet(*synthetic_shapes(self.num_train + self.num_val, self.points_per_shape, self.shape_seed))
            train_idx = np.arange(self.num_train)
            val_idx = np.arange(self.num_train, self.num_train + self.num_val)
            return {"train": pool.subset(train_idx), "val": pool.subset(val_idx)}
        seed = self.shape_seed + SYNTHETIC_TEST_SEED_OFFSET
        return {"test": ObjectSet(*synthetic_shapes(self.num_test, self.points_per_shape, seed))}
