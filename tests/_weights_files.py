"""Shared pieces of the pretrained-weights tests: tiny models, checkpoints like `lcreg fit` writes, exported files.

Every file is created by the test itself in a temporary folder, from a freshly built (seeded) model: no test depends
on weights outside the repository.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from lcreg.baselines.fmr import FMRNet
from lcreg.baselines.pointnetlk import PointNetLK
from lcreg.models.base import RegistrationModule
from lcreg.models.dvds import DVDs
from lcreg.models.loss_terms import LocalConsistencyLoss
from lcreg.nn.local_consistency import LocalConsistency
from lcreg.weights import class_path_of
from lcreg.weights.export import export_weights

TINY_ARGS: dict[str, dict[str, Any]] = {
    "dvds": {"encoder_channels": [16, 32], "decoder_grid_size": 4, "decoder_hidden": [16], "normal_hidden": [8]},
    "pointnetlk": {"encoder_channels": [16, 32], "max_iterations": 3, "eval_iterations": 4},
    "fmr": {"encoder_channels": [16, 32], "decoder_hidden": [16], "decoder_points": 32},
}
CLASSES: dict[str, type[RegistrationModule]] = {"dvds": DVDs, "pointnetlk": PointNetLK, "fmr": FMRNet}


def tiny_model(kind: str, seed: int = 0, lc: bool = True, **overrides: Any) -> RegistrationModule:
    """A seeded tiny model with its training-only modules (DVDs: decoder, normal head; FMR-Net: decoder; LC term)."""
    torch.manual_seed(seed)
    terms = [LocalConsistencyLoss(LocalConsistency(num_local_points=8))] if lc else []
    model = CLASSES[kind](**{**TINY_ARGS[kind], **overrides}, loss_terms=terms)
    with torch.no_grad():  # non-default BatchNorm statistics, so a lost buffer would show
        for module in model.modules():
            if isinstance(module, torch.nn.BatchNorm1d):
                module.running_mean.uniform_(-0.1, 0.1)
                module.running_var.uniform_(0.5, 1.5)
    return model


def lightning_checkpoint(model: RegistrationModule, path: Path, **extra: Any) -> Path:
    """Write what `lcreg fit` writes for ``model``: ``state_dict``, ``hyper_parameters`` with ``_class_path``, ..."""
    content = {
        "epoch": 3,
        "global_step": 120,
        "pytorch-lightning_version": "2.6.6",
        "state_dict": model.state_dict(),
        "hyper_parameters": {"_class_path": class_path_of(model), **model.hparams},
        "datamodule_hyper_parameters": {
            "_class_path": "lcreg.data.datamodule.ModelNet40DataModule",
            "root": "/somewhere/modelnet40_mini",
            "num_points": 512,
        },
        "optimizer_states": [{"state": {}, "param_groups": []}],
        **extra,
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(content, path)
    return path


def exported(model: RegistrationModule, folder: Path, name: str = "tiny", **kwargs: Any) -> Path:
    """``model`` through a checkpoint and :func:`lcreg.weights.export.export_weights` into ``folder/<name>.pt``."""
    checkpoint = lightning_checkpoint(model, folder / "ckpt" / f"{name}.ckpt")
    return export_weights(checkpoint, name, folder, **kwargs)


def rewrite(path: Path, target: Path, **changes: Any) -> Path:
    """A copy of weights file ``path`` at ``target`` with top-level entries replaced (``None`` removes one)."""
    content = torch.load(path, weights_only=True)
    for key, value in changes.items():
        if value is None:
            content.pop(key)
        else:
            content[key] = value
    torch.save(content, target)
    return target
