from __future__ import annotations

import numpy as np
import pytest
import torch

from lcreg.checks import ShapeError
from lcreg.data.collate import collate_pairs
from lcreg.data.datamodule import PairDataset
from lcreg.data.pairs import PairProtocol
from lcreg.data.synthetic import synthetic_shapes
from lcreg.types import RegistrationBatch

PROTOCOL = PairProtocol(num_points=64)


@pytest.fixture(scope="module")
def shapes() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return synthetic_shapes(6, 128, seed=0)


def test_collate_stacks_into_a_registration_batch(shapes: tuple) -> None:
    points, normals, _ = shapes
    ds = PairDataset(points, normals, PROTOCOL, deterministic=True)
    batch = collate_pairs([ds[i] for i in range(3)])
    assert isinstance(batch, RegistrationBatch) and len(batch) == 3
    assert batch.points_src.shape == (3, 64, 3) and batch.points_ref.shape == (3, 64, 3)
    assert batch.transform_ref_src is not None and batch.transform_ref_src.shape == (3, 4, 4)
    assert batch.normals_src is not None and batch.normals_src.shape == (3, 64, 3)
    assert batch.index is not None and batch.index.tolist() == [0, 1, 2]
    torch.testing.assert_close(batch.points_src[1], ds[1]["points_src"])

    no_normals = PairDataset(points, None, PROTOCOL, deterministic=True)
    batch = collate_pairs([no_normals[i] for i in range(2)])
    assert batch.normals_src is None and batch.normals_ref is None


def test_collate_rejects_inconsistent_items(shapes: tuple) -> None:
    points, normals, _ = shapes
    a = PairDataset(points, normals, PROTOCOL, deterministic=True)[0]
    b = PairDataset(points, normals, PairProtocol(num_points=32), deterministic=True)[1]
    with pytest.raises(ShapeError, match=r"items\[1\]\['points_src'\]"):
        collate_pairs([a, b])
    c = PairDataset(points, None, PROTOCOL, deterministic=True)[1]
    with pytest.raises(ValueError, match="normals_src"):
        collate_pairs([a, c])
    with pytest.raises(ValueError, match="empty"):
        collate_pairs([])


def test_collate_drops_other_keys_and_needs_points() -> None:
    item = {"points_src": torch.zeros(5, 3), "points_ref": torch.ones(4, 3), "angles_zyx": torch.zeros(3)}
    batch = collate_pairs([item, item])
    assert batch.points_src.shape == (2, 5, 3) and batch.points_ref.shape == (2, 4, 3)
    assert batch.transform_ref_src is None and batch.index is None
    with pytest.raises(ValueError, match="points_ref"):
        collate_pairs([{"points_src": torch.zeros(5, 3)}])
