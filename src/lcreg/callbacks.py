"""Lightning callbacks used by the CLI."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from lightning.pytorch import LightningModule, Trainer
from lightning.pytorch.callbacks import BasePredictionWriter
from lightning.pytorch.utilities import rank_zero_info

from lcreg.types import RegistrationResult

__all__ = ["TransformWriter"]


class TransformWriter(BasePredictionWriter):
    """Write ``lcreg predict`` results to ``<log_dir>/predictions.npz``.

    Arrays: ``index (P,)`` (dataset index when the batches carry it, else a running count),
    ``transform_ref_src (P, 4, 4)`` (maps source into reference), ``converged (P,)``, ``num_iters (P,)`` and, when
    the data has a ground truth, ``transform_gt (P, 4, 4)``.

    Args:
        filename: File name inside the logger's directory (or ``default_root_dir`` without a logger).
    """

    def __init__(self, filename: str = "predictions.npz") -> None:
        super().__init__(write_interval="epoch")
        self.filename = filename

    def write_on_epoch_end(
        self,
        trainer: Trainer,
        pl_module: LightningModule,
        predictions: Sequence[Any],
        batch_indices: Sequence[Any],
    ) -> None:
        """Concatenate the per-batch :class:`RegistrationResult` objects and save them."""
        results = [r for r in predictions if isinstance(r, RegistrationResult)]
        if not results:
            return
        out: dict[str, np.ndarray] = {
            "transform_ref_src": torch.cat([r.transform_ref_src for r in results]).cpu().numpy(),
            "converged": torch.cat([r.converged for r in results]).cpu().numpy(),
            "num_iters": torch.cat([r.num_iters for r in results]).cpu().numpy(),
        }
        for key in ("index", "transform_gt"):
            if all(isinstance(r.aux.get(key), torch.Tensor) for r in results):
                out[key] = torch.cat([r.aux[key] for r in results]).cpu().numpy()
        out.setdefault("index", np.arange(len(out["converged"])))
        directory = Path(trainer.log_dir or trainer.default_root_dir)
        directory.mkdir(parents=True, exist_ok=True)
        path = directory / self.filename
        np.savez(path, **out)  # type: ignore[arg-type]  # numpy stubs type **kwds as allow_pickle
        rank_zero_info(f"{len(out['index'])} predictions written to {path}")
