"""``test_per_pair.csv``: its component columns give the test figures back, for all pairs and for any subset."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import torch
from lightning.pytorch import Trainer

from lcreg.data.datamodule import SyntheticDataModule
from lcreg.geometry import se3
from lcreg.metrics.registration import registration_metrics
from lcreg.models.base import RegistrationModule
from lcreg.models.evaluation import COMPONENT_COLUMNS
from lcreg.types import RegistrationResult


class _Identity(RegistrationModule):
    """Predicts no motion: every pair's errors are its ground truth's angles and translation."""

    def forward(self, points_src: torch.Tensor, points_ref: torch.Tensor) -> RegistrationResult:
        b = points_src.shape[0]
        transform = se3.identity(b, dtype=points_src.dtype)
        return RegistrationResult(transform, torch.ones(b, dtype=torch.bool), torch.ones(b, dtype=torch.int64))


def _figures(rows: list[dict[str, str]]) -> dict[str, float]:
    euler = [float(r[c]) for r in rows for c in COMPONENT_COLUMNS[:3]]
    trans = [float(r[c]) for r in rows for c in COMPONENT_COLUMNS[3:]]
    return {
        "rmse_r_deg": math.sqrt(sum(v * v for v in euler) / len(euler)),
        "mae_r_deg": sum(abs(v) for v in euler) / len(euler),
        "rmse_t": math.sqrt(sum(v * v for v in trans) / len(trans)),
        "mae_t": sum(abs(v) for v in trans) / len(trans),
    }


def test_the_component_columns_give_the_test_figures_for_all_pairs_and_for_a_subset(tmp_path: Path) -> None:
    data = SyntheticDataModule(num_points=32, batch_size=2, num_train=2, num_val=2, num_test=5, points_per_shape=64)
    trainer = Trainer(
        accelerator="cpu",
        logger=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        default_root_dir=tmp_path,
    )
    trainer.test(_Identity(), datamodule=data, verbose=False)
    with (tmp_path / "test_per_pair.csv").open() as fh:
        reader = csv.DictReader(fh)
        rows = list(reader)
    assert reader.fieldnames == ["index", "rotation_error_deg", "translation_error", "class", *COMPONENT_COLUMNS]
    assert [int(r["index"]) for r in rows] == [0, 1, 2, 3, 4]
    logged = trainer.callback_metrics
    for key, value in _figures(rows).items():
        assert math.isclose(value, float(logged[f"test/{key}"]), rel_tol=1e-5), key

    # A subset (e.g. one class) gets the figures a test of those pairs alone would log.
    assert data.test_set is not None
    gt = torch.stack([torch.as_tensor(data.test_set[k]["transform_ref_src"]) for k in (1, 3)])
    metrics = registration_metrics()
    metrics.update(transform_pred=se3.identity(2, dtype=gt.dtype), transform_gt=gt)
    alone = metrics.compute()
    for key, value in _figures([rows[1], rows[3]]).items():
        assert math.isclose(value, float(alone[key]), rel_tol=1e-5), key
