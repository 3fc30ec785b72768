"""Object datasets and registration pairs.

* :mod:`lcreg.data.pairs`: the one pair protocol (:class:`PairProtocol`, :func:`make_pair`), shared by every dataset;
* :mod:`lcreg.data.synthetic`: embedded procedural shapes with analytic normals (no files);
* :mod:`lcreg.data.modelnet40`: the official ModelNet40 HDF5 layout and its unseen-objects/-categories protocols;
* :mod:`lcreg.data.datamodule`: :class:`PairDataset`, :func:`collate_pairs` and the Lightning DataModules.

Names are re-exported lazily, so ``import lcreg.data.pairs`` does not import Lightning.
"""

from __future__ import annotations

import importlib
from typing import Any

__all__ = [
    "DatasetLayoutError",
    "ModelNet40DataModule",
    "ObjectSet",
    "PairDataModule",
    "PairDataset",
    "PairProtocol",
    "SyntheticDataModule",
    "collate_pairs",
    "load_modelnet40_h5",
    "make_pair",
    "modelnet40_objects",
    "synthetic_shapes",
]

_SOURCES = {
    "DatasetLayoutError": "modelnet40",
    "ModelNet40DataModule": "datamodule",
    "ObjectSet": "pairs",
    "PairDataModule": "datamodule",
    "PairDataset": "datamodule",
    "PairProtocol": "pairs",
    "SyntheticDataModule": "datamodule",
    "collate_pairs": "datamodule",
    "load_modelnet40_h5": "modelnet40",
    "make_pair": "pairs",
    "modelnet40_objects": "modelnet40",
    "synthetic_shapes": "synthetic",
}


def __getattr__(name: str) -> Any:
    """Import the submodule that defines ``name`` on first access."""
    if name in _SOURCES:
        return getattr(importlib.import_module(f"{__name__}.{_SOURCES[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *__all__])
