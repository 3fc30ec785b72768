"""Benchmark pairs: deterministic ModelNet40 or embedded synthetic pairs, and the synthetic data of smoke runs."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import fields, replace
from typing import TYPE_CHECKING, Any, Literal

from lightning.pytorch import LightningDataModule

from lcreg.experiments.benchmarking.registry import Values
from lcreg.types import RegistrationBatch

if TYPE_CHECKING:
    from lcreg.data.datamodule import PairDataModule

__all__ = [
    "SYNTHETIC_DATA",
    "ClassGroup",
    "class_groups",
    "pair_batches",
    "pair_batches_and_classes",
    "pair_datamodule",
    "split_batches",
    "synthetic_options",
    "synthetic_overrides",
]

SYNTHETIC_DATA = "lcreg.data.datamodule.SyntheticDataModule"
Split = Literal["val", "test"]
Protocol = Literal["unseen_objects", "unseen_categories"]


def synthetic_options(pairs: int = 2, num_points: int = 64, batch_size: int = 2) -> dict[str, Any]:
    """Constructor arguments of a tiny :class:`~lcreg.data.datamodule.SyntheticDataModule` (smoke runs).

    Args:
        pairs: Validation and test pairs.
        num_points: Points per cloud.
        batch_size: Pairs per batch (training uses ``2 * batch_size`` shapes).
    """
    return {
        "num_train": 2 * batch_size,
        "num_val": pairs,
        "num_test": pairs,
        "num_points": num_points,
        "points_per_shape": 2 * num_points,
        "batch_size": batch_size,
        "num_workers": 0,
    }


def synthetic_overrides(pairs: int = 2, num_points: int = 64, batch_size: int = 2) -> Values:
    """Values that replace a config's data block by tiny embedded synthetic pairs (no files needed)."""
    return {"data": {"class_path": SYNTHETIC_DATA, "init_args": synthetic_options(pairs, num_points, batch_size)}}


def split_batches(datamodule: LightningDataModule, split: Split = "test") -> list[RegistrationBatch]:
    """Set ``datamodule`` up for ``split`` and return all its (deterministic) batches."""
    datamodule.setup("fit" if split == "val" else "test")
    loader = datamodule.val_dataloader() if split == "val" else datamodule.test_dataloader()
    return list(loader)


def pair_batches(
    root: str | None,
    split: Split = "test",
    pairs: int | None = None,
    num_points: int = 1024,
    batch_size: int = 16,
    protocol: Protocol = "unseen_objects",
    **options: Any,
) -> tuple[list[RegistrationBatch], str]:
    """Deterministic pairs of ModelNet40 (``root``) or of the embedded synthetic shapes (``root=None``).

    Args:
        root: ModelNet40 folder, or ``None`` for the synthetic shapes.
        split: ``"val"`` (carved out of the training objects) or ``"test"``.
        pairs: Keep the first ``pairs`` pairs (``None``: all; synthetic: 128 test / 64 validation shapes).
        num_points: Points per cloud.
        batch_size: Pairs per batch.
        protocol: ModelNet40 protocol (``"unseen_objects"`` or ``"unseen_categories"``).
        **options: Further pair options of :class:`~lcreg.data.datamodule.PairDataModule` (``noise_sigma``, ``seed``).

    Returns:
        The batches and a description of their source.
    """
    batches, source, _ = pair_batches_and_classes(root, split, pairs, num_points, batch_size, protocol, **options)
    return batches, source


def pair_batches_and_classes(
    root: str | None,
    split: Split = "test",
    pairs: int | None = None,
    num_points: int = 1024,
    batch_size: int = 16,
    protocol: Protocol = "unseen_objects",
    **options: Any,
) -> tuple[list[RegistrationBatch], str, list[str] | None]:
    """:func:`pair_batches` and the class of every pair's object, in pair order (``None`` without labels).

    The class is :meth:`~lcreg.data.datamodule.PairDataModule.pair_classes`'s (its name, else its label), so that
    failures can be read per class (e.g. shapes with an axis of symmetry).
    """
    dm, source = pair_datamodule(root, split, pairs, num_points, batch_size, protocol, **options)
    batches = _first_pairs(split_batches(dm, split), pairs)
    return batches, source, _classes(dm, split, batches)


def pair_datamodule(
    root: str | None,
    split: Split = "test",
    pairs: int | None = None,
    num_points: int = 1024,
    batch_size: int = 16,
    protocol: Protocol = "unseen_objects",
    **options: Any,
) -> tuple[PairDataModule, str]:
    """The DataModule (not set up) of :func:`pair_batches`'s pairs, and a description of their source.

    For the pairs' datasets themselves (``dm.test_set`` after ``dm.setup("test")``, e.g. their
    :meth:`~lcreg.data.datamodule.PairDataset.item_with_indices`). Arguments as :func:`pair_batches`; ``pairs``
    sizes the synthetic splits only.
    """
    from lcreg.data.datamodule import ModelNet40DataModule, SyntheticDataModule

    if root is None:
        sizes = synthetic_options(pairs, num_points, batch_size) if pairs else {"num_points": num_points}
        return SyntheticDataModule(**{**sizes, "batch_size": batch_size, **options}), "embedded synthetic shapes"
    dm = ModelNet40DataModule(root, protocol, num_points=num_points, batch_size=batch_size, **options)
    return dm, f"ModelNet40 {root} ({protocol.replace('_', ' ')} {split} pairs)"


def _classes(dm: PairDataModule, split: Split, batches: list[RegistrationBatch]) -> list[str] | None:
    """The class of every pair of ``batches`` (``None`` when the split has no labels or a batch no indices)."""
    classes: list[str] = []
    for batch in batches:
        names = None if batch.index is None else dm.pair_classes(split, batch.index)
        if names is None:
            return None
        classes += names
    return classes


def _first_pairs(batches: Iterable[RegistrationBatch], pairs: int | None) -> list[RegistrationBatch]:
    """The batches holding the first ``pairs`` pairs (the last one cut to size); all of them for ``None``."""
    out: list[RegistrationBatch] = []
    left = pairs
    for batch in batches:
        if left is not None and left <= 0:
            break
        if left is not None and len(batch) > left:
            batch = replace(batch, **{f.name: _head(getattr(batch, f.name), left) for f in fields(batch)})
        out.append(batch)
        left = None if left is None else left - len(batch)
    return out


def _head(value: Any, count: int) -> Any:
    return None if value is None else value[:count]


ClassGroup = tuple[str, frozenset[str]]
"""A group of test pairs by object class: its name and the classes of its pairs."""


def class_groups(classes: Sequence[str], min_pairs: int, without: Sequence[Sequence[str]] = ()) -> list[ClassGroup]:
    """The groups per-class reports split test pairs into, from the class of every pair.

    All pairs; each class with ``min_pairs`` or more pairs, largest first; the other classes pooled
    (``"the other N classes"``); and for each list in ``without``, all pairs but those classes.

    Raises:
        ValueError: A ``without`` list names a class no pair has, or leaves no pair.
    """
    counts: dict[str, int] = {}
    for cls in classes:
        counts[cls] = counts.get(cls, 0) + 1
    every = frozenset(counts)
    large = sorted((c for c, n in counts.items() if n >= min_pairs), key=lambda c: (-counts[c], c))
    found: list[ClassGroup] = [("all pairs", every), *((cls, frozenset([cls])) for cls in large)]
    small = every - set(large)
    if small:
        found.append((f"the other {len(small)} classes", small))
    for excluded in without:
        unknown = sorted(set(excluded) - every)
        if unknown:
            raise ValueError(f"--without {' '.join(excluded)}: no test pair of class {', '.join(unknown)}")
        if set(excluded) >= every:
            raise ValueError(f"--without {' '.join(excluded)}: leaves no test pair")
        found.append((f"all but {', '.join(excluded)}", every - set(excluded)))
    return found
