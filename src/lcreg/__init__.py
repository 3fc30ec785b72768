"""lcreg: deep point-cloud registration (DVDs, local consistency, baselines) on PyTorch Lightning.

``import lcreg`` and ``from lcreg import LocalConsistency`` stay light: they import torch only; Lightning-based
classes are loaded on first access. ``lcreg.pretrained("dvds-modelnet40")`` builds a model with the weights shipped
in the package (:mod:`lcreg.weights`; ``lcreg.pretrained_names()`` lists the names).
"""

from __future__ import annotations

from importlib import import_module
from typing import Any

from lcreg.methods import class_names

__version__ = "0.1.0"

_LAZY = {
    **class_names(),  # every method's class (lcreg.methods: the one table of methods)
    "LocalConsistency": "lcreg.nn.local_consistency",
    "PointNetEncoder": "lcreg.nn.pointnet",
    "InverseCompositionalLK": "lcreg.nn.lk",
    "VoxelGrid": "lcreg.nn.voxel_lk",
    "RegistrationResult": "lcreg.types",
    "RegistrationBatch": "lcreg.types",
    "RegistrationModule": "lcreg.models.base",
    "LocalConsistencyMixin": "lcreg.models.mixins",
    "LossTerm": "lcreg.models.loss_terms",
    "LocalConsistencyLoss": "lcreg.models.loss_terms",
    "LucasKanadeModule": "lcreg.models.lucas_kanade",
    "ModelNet40DataModule": "lcreg.data.datamodule",
    "SyntheticDataModule": "lcreg.data.datamodule",
    "PairDataModule": "lcreg.data.datamodule",
    "ScanObjectNNDataModule": "lcreg.data.scanobjectnn",
    "SevenScenesDataModule": "lcreg.data.threedmatch",
    "KITTIOdometryDataModule": "lcreg.data.kitti",
    "read_points": "lcreg.data.io",
    "pretrained": "lcreg.weights",
    "pretrained_names": "lcreg.weights",
    "register": "lcreg.registration.api",
    "export_registrar": "lcreg.deploy",
    "Registration": "lcreg.registration.api",
}

__all__ = [*_LAZY, "__version__"]


def __getattr__(name: str) -> Any:
    """Import public classes on first access (keeps ``import lcreg`` free of Lightning/Open3D)."""
    if name in _LAZY:
        value = getattr(import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'lcreg' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(__all__)
