"""Batching of registration pairs: :func:`collate_pairs`, the ``collate_fn`` of every DataLoader of :mod:`lcreg.data`.

Items are dicts as :class:`~lcreg.data.datamodule.PairDataset` and :class:`~lcreg.data.scenes.ScenePairDataset`
return them; the batch is a :class:`~lcreg.types.RegistrationBatch`. This module imports torch only (no Lightning).
"""

from __future__ import annotations

import torch

from lcreg.checks import ShapeError
from lcreg.types import RegistrationBatch

__all__ = ["BATCH_KEYS", "collate_pairs"]

BATCH_KEYS = ("points_src", "points_ref", "transform_ref_src", "normals_src", "normals_ref", "index")
"""Item keys that are stacked into the batch; any other key (e.g. ``angles_zyx``) is dropped."""


def _stack(items: list[dict[str, torch.Tensor]], key: str) -> torch.Tensor | None:
    """``key`` of every item stacked along a new first dimension, or ``None`` when no item has it."""
    present = [key in item for item in items]
    if not any(present):
        return None
    if not all(present):
        raise ValueError(f"`{key}` is present in {sum(present)} of {len(items)} items; a batch needs all or none")
    values = [item[key] for item in items]
    for i, value in enumerate(values):
        if value.shape != values[0].shape:
            # Every pair of a batch must have the same size (fixed num_points and partial_keep).
            raise ShapeError(f"items[{i}]['{key}']", tuple(values[0].shape), value.shape)
    return torch.stack(values)


def collate_pairs(items: list[dict[str, torch.Tensor]]) -> RegistrationBatch:
    """Stack pair dicts (from :class:`~lcreg.data.datamodule.PairDataset` or a scene dataset) into a batch.

    Args:
        items: Dicts with ``points_src (N, 3)``, ``points_ref (M, 3)`` and optionally ``transform_ref_src (4, 4)``,
            ``normals_src``/``normals_ref`` and ``index``; other keys (``angles_zyx``) are dropped.

    Returns:
        A :class:`~lcreg.types.RegistrationBatch` with ``points_src (B, N, 3)``, ``points_ref (B, M, 3)``,
        ``transform_ref_src (B, 4, 4)`` (or ``None``), normals ``(B, N, 3)``/``(B, M, 3)`` (or ``None``) and
        ``index (B,)``.

    Raises:
        ValueError: If ``items`` is empty, some items have a key that others lack, or the points are missing.
        ShapeError: If the clouds of the batch do not all have the same size.
    """
    if not items:
        raise ValueError("`items` must not be empty")
    stacked = {key: _stack(items, key) for key in BATCH_KEYS}
    points_src, points_ref = stacked["points_src"], stacked["points_ref"]
    if points_src is None or points_ref is None:
        raise ValueError("every item needs `points_src` and `points_ref`")
    return RegistrationBatch(
        points_src=points_src,
        points_ref=points_ref,
        transform_ref_src=stacked["transform_ref_src"],
        normals_src=stacked["normals_src"],
        normals_ref=stacked["normals_ref"],
        index=stacked["index"],
    )
