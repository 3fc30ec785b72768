"""Real-data DVDs training (slow: run with `pytest -m slow`; excluded from the default run and CI)."""

import math

import lightning as L
import pytest

from lcreg.data.datamodule import ModelNet40DataModule
from lcreg.models.dvds import DVDs

from _shared_data import shared_data  # type: ignore[import-not-found]


@pytest.mark.slow
@pytest.mark.data
def test_dvds_trains_on_modelnet40_mini_and_reports_finite_metrics(tmp_path) -> None:  # type: ignore[no-untyped-def]
    root = shared_data("modelnet40_mini")
    L.seed_everything(0)
    dm = ModelNet40DataModule(root=str(root), num_points=512, batch_size=16)
    model = DVDs(batch_norm=False)
    trainer = L.Trainer(
        max_epochs=1,
        limit_train_batches=10,
        accelerator="cpu",
        logger=False,
        default_root_dir=tmp_path,
        enable_progress_bar=False,
        enable_model_summary=False,
    )
    trainer.fit(model, dm)
    metrics = trainer.validate(model, dm, verbose=False)[0]
    assert all(math.isfinite(v) for v in metrics.values())
    assert metrics["val/rre_median_deg"] < 10.0  # 78 validation pairs, rotations up to 45 degrees per axis
