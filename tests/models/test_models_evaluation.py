"""``test_per_pair.csv``: its component columns give the test figures back, for all pairs and for any subset."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from _training import quiet_trainer  # type: ignore[import-not-found]
from lcreg.data.datamodule import SyntheticDataModule
from lcreg.geometry import se3
from lcreg.metrics.functional import rotation_error_deg
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
    trainer = quiet_trainer(tmp_path)
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


def test_the_transforms_file_holds_each_pair_s_estimate_and_truth_in_the_csv_s_order(tmp_path: Path) -> None:
    data = SyntheticDataModule(num_points=32, batch_size=2, num_train=2, num_val=2, num_test=5, points_per_shape=64)
    data.setup("test")
    assert data.test_set is not None
    truths = {k: torch.as_tensor(data.test_set[k]["transform_ref_src"]) for k in range(5)}
    turn = se3.make_transform(
        torch.tensor([[[math.cos(0.1), -math.sin(0.1), 0.0], [math.sin(0.1), math.cos(0.1), 0.0], [0.0, 0.0, 1.0]]]),
        torch.zeros(1, 3),
    )

    class _TruthTurned(_Identity):
        def test_step(self, batch, batch_idx):  # type: ignore[no-untyped-def]
            pred = torch.stack([truths[int(k)] for k in batch.index]) @ turn
            pred[batch.index == 2] = float("nan")
            self.test_pairs.update(transform_pred=pred, transform_gt=batch.transform_ref_src, index=batch.index)

    trainer = quiet_trainer(tmp_path)
    trainer.test(_TruthTurned(), datamodule=data, verbose=False)
    with (tmp_path / "test_per_pair.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    with np.load(tmp_path / "test_transforms.npz") as saved:
        index, pred, gt = saved["index"], saved["transform_pred"], saved["transform_gt"]
    assert index.tolist() == [int(r["index"]) for r in rows] == [0, 1, 2, 3, 4]
    for k, row in enumerate(rows):
        assert np.allclose(gt[k], truths[k].numpy(), atol=1e-7)
        if k == 2:
            assert np.isnan(pred[k]).all() and math.isnan(float(row["rotation_error_deg"]))
            continue
        error = rotation_error_deg(torch.from_numpy(pred[k : k + 1]), torch.from_numpy(gt[k : k + 1]))
        assert error.item() == pytest.approx(float(row["rotation_error_deg"]), abs=1e-4)
        assert error.item() == pytest.approx(math.degrees(0.1), abs=1e-3)
