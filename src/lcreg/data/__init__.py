"""Object datasets and registration pairs.

* :mod:`lcreg.data.pairs`: the one pair protocol (:class:`PairProtocol`, :func:`make_pair`), shared by every dataset;
* :mod:`lcreg.data.synthetic`: embedded procedural shapes with analytic normals (no files);
* :mod:`lcreg.data.modelnet40`: the official ModelNet40 HDF5 layout and its unseen-objects/-categories protocols;
* :mod:`lcreg.data.datamodule`: :class:`PairDataset` and the object DataModules;
* :mod:`lcreg.data.collate`: :func:`collate_pairs`, pair dicts into a :class:`~lcreg.types.RegistrationBatch`;
* :mod:`lcreg.data.scanobjectnn`: the official ScanObjectNN h5 layout and its DataModule (object protocol);
* :mod:`lcreg.data.io`: :func:`read_points` for ``.ply``/``.pcd``/``.xyz``/``.npy``/KITTI ``.bin`` files and
  :func:`~lcreg.data.io.voxel_downsample` (Open3D's voxel grid, the one downsampler of point arrays);
* :mod:`lcreg.data.scenes`: scene pairs from files (:class:`ScenePair`, :class:`ScenePairDataset`,
  :class:`ScenePairDataModule`);
* :mod:`lcreg.data.threedmatch`: 3DMatch / 7-Scenes fragment pairs and :class:`SevenScenesDataModule`;
* :mod:`lcreg.data.kitti`: KITTI odometry pairs and :class:`KITTIOdometryDataModule`;
* :mod:`lcreg.data.pairlists`: :func:`read_pair_list` (CSV lists, 3DMatch benchmarks, KITTI json lists) into
  :class:`ListedPair` for registering many pairs.

Names are re-exported lazily, so ``import lcreg.data.pairs`` does not import Lightning. :class:`DatasetLayoutError` is
:class:`lcreg.checks.DatasetLayoutError` (re-exported here as part of the data API).
"""

from __future__ import annotations

import importlib
from typing import Any

__all__ = [
    "DatasetLayoutError",
    "KITTIOdometryDataModule",
    "ListedPair",
    "ModelNet40DataModule",
    "ObjectSet",
    "PairDataModule",
    "PairDataset",
    "PairProtocol",
    "ScanObjectNNDataModule",
    "ScenePair",
    "ScenePairDataModule",
    "ScenePairDataset",
    "SevenScenesDataModule",
    "SyntheticDataModule",
    "collate_pairs",
    "kitti_pairs",
    "load_modelnet40_h5",
    "load_scanobjectnn_h5",
    "make_pair",
    "modelnet40_objects",
    "read_pair_list",
    "read_points",
    "scanobjectnn_objects",
    "synthetic_shapes",
    "threedmatch_pairs",
]

_SOURCES = {
    "DatasetLayoutError": "lcreg.checks",
    "KITTIOdometryDataModule": "kitti",
    "ListedPair": "pairlists",
    "ModelNet40DataModule": "datamodule",
    "ObjectSet": "pairs",
    "PairDataModule": "datamodule",
    "PairDataset": "datamodule",
    "PairProtocol": "pairs",
    "ScanObjectNNDataModule": "scanobjectnn",
    "ScenePair": "scenes",
    "ScenePairDataModule": "scenes",
    "ScenePairDataset": "scenes",
    "SevenScenesDataModule": "threedmatch",
    "SyntheticDataModule": "datamodule",
    "collate_pairs": "collate",
    "kitti_pairs": "kitti",
    "load_modelnet40_h5": "modelnet40",
    "load_scanobjectnn_h5": "scanobjectnn",
    "make_pair": "pairs",
    "modelnet40_objects": "modelnet40",
    "read_pair_list": "pairlists",
    "read_points": "io",
    "scanobjectnn_objects": "scanobjectnn",
    "synthetic_shapes": "synthetic",
    "threedmatch_pairs": "threedmatch",
}


def __getattr__(name: str) -> Any:
    """Import the submodule that defines ``name`` on first access."""
    if name in _SOURCES:
        source = _SOURCES[name]
        return getattr(importlib.import_module(source if "." in source else f"{__name__}.{source}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *__all__])
