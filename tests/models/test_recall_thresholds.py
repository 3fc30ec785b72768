"""The recalls a model logs at validation and test: its ``recall_thresholds``, else its DataModule's (the scene
benchmarks' recall in metres), besides the two standard ones."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from lightning.pytorch import Trainer
from lightning.pytorch.callbacks import Callback

from _training import quiet_trainer  # type: ignore[import-not-found]
from lcreg.data.datamodule import SyntheticDataModule
from lcreg.data.kitti import KITTIOdometryDataModule
from lcreg.data.scenes import ScenePair, ScenePairDataModule, Split
from lcreg.data.threedmatch import SevenScenesDataModule
from lcreg.metrics import functional
from lcreg.models.base import RegistrationModule
from lcreg.types import RegistrationResult

STANDARD = {"recall_r2_t0p01", "recall_r5_t0p05"}


class _Identity(RegistrationModule):
    """Predicts no motion: its errors are those of the ground truth itself, spread across the thresholds."""

    has_loss = False

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)

    def forward(self, points_src: torch.Tensor, points_ref: torch.Tensor) -> RegistrationResult:
        eye = torch.eye(4, dtype=points_src.dtype, device=points_src.device)
        return RegistrationResult.fixed_iterations(eye.expand(len(points_src), 4, 4).clone())


class _ToyScenes(SevenScenesDataModule):
    """7-Scenes' DataModule (and its recall) over a few copies of one small scene pair written by the test."""

    def __init__(self, folder: Path, **kwargs: Any) -> None:
        super().__init__(root=str(folder), max_angle_deg=20.0, max_translation=0.3, num_points=64, **kwargs)
        scene = np.random.default_rng(0).uniform([0, 0, 0], [4, 3, 2.5], size=(200, 3)).astype(np.float32)
        np.save(folder / "scene.npy", scene)
        self.pair = ScenePair(folder / "scene.npy", folder / "scene.npy", np.eye(4), name="toy/0-0")

    def pairs(self, split: Split) -> list[ScenePair]:
        return [self.pair] * 16


def _recall_keys(results: dict[str, float], stage: str = "test") -> set[str]:
    return {k.removeprefix(f"{stage}/") for k in results if k.startswith(f"{stage}/recall_")}


def _expected(data: ScenePairDataModule, split: str, rot_thr: float, trans_thr: float) -> float:
    """The recall of the identity on ``split``, from the per-pair errors of :mod:`lcreg.metrics.functional`."""
    gt = torch.stack([item["transform_ref_src"] for item in data.datasets[split]])
    pred = torch.eye(4).expand_as(gt)
    rot, trans = functional.rotation_error_deg(pred, gt), functional.translation_error(pred, gt)
    return float(functional.registration_recall(rot, trans, rot_thr, trans_thr))


def test_user_thresholds_add_val_and_test_keys_equal_to_the_functional_recall(tmp_path: Path) -> None:
    data = _ToyScenes(tmp_path)
    model = _Identity(recall_thresholds=[[15, 0.3], [22, 0.35]])
    val = quiet_trainer(tmp_path).validate(model, datamodule=data, verbose=False)[0]
    test = quiet_trainer(tmp_path).test(model, datamodule=data, verbose=False)[0]
    for stage, results in (("val", val), ("test", test)):
        assert _recall_keys(results, stage) == STANDARD | {"recall_r15_t0p3", "recall_r22_t0p35"}
        for rot_thr, trans_thr, key in ((15.0, 0.3, "recall_r15_t0p3"), (22.0, 0.35, "recall_r22_t0p35")):
            want = _expected(data, stage, rot_thr, trans_thr)  # the split of the stage
            assert 0 < want < 1  # the thresholds matter on these pairs
            assert results[f"{stage}/{key}"] == pytest.approx(want, abs=1e-6), key


def test_the_datamodule_recall_applies_when_the_model_sets_none(tmp_path: Path) -> None:
    assert SevenScenesDataModule.recall_thresholds == ((15.0, 0.3),)
    assert KITTIOdometryDataModule.recall_thresholds == ((5.0, 2.0),)
    assert not hasattr(SyntheticDataModule, "recall_thresholds")  # object data: only the standard recalls
    data, model = _ToyScenes(tmp_path), _Identity()
    test = quiet_trainer(tmp_path).test(model, datamodule=data, verbose=False)[0]
    assert _recall_keys(test) == STANDARD | {"recall_r15_t0p3"}
    assert test["test/recall_r15_t0p3"] == pytest.approx(_expected(data, "test", 15.0, 0.3), abs=1e-6)
    assert "recall_thresholds" not in model.hparams and model.recall_thresholds is None
    # The same model on object data afterwards: the scene recall is gone again.
    objects = SyntheticDataModule(num_train=2, num_val=2, num_test=2, points_per_shape=64, num_points=32)
    assert _recall_keys(quiet_trainer(tmp_path).test(model, datamodule=objects, verbose=False)[0]) == STANDARD


def test_the_model_setting_overrides_the_datamodule(tmp_path: Path) -> None:
    test = quiet_trainer(tmp_path).test(_Identity(recall_thresholds=[[5, 2]]), datamodule=_ToyScenes(tmp_path))[0]
    assert _recall_keys(test) == STANDARD | {"recall_r5_t2"}


def test_the_summary_line_names_the_extra_recall(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.INFO):
        quiet_trainer(tmp_path).test(_Identity(), datamodule=_ToyScenes(tmp_path), verbose=False)
    (line,) = [r.getMessage() for r in caplog.records if r.getMessage().startswith("[test]")]
    assert "recall_r2_t0p01=" in line and "recall_r15_t0p3=" in line


@pytest.mark.parametrize(
    "bad", [[[15.0]], [[15.0, 0.3, 1.0]], [[0.0, 0.3]], [[15.0, -1.0]], [[float("nan"), 0.3]], [[15.0, float("inf")]]]
)
def test_bad_thresholds_are_a_value_error_naming_the_argument(bad: Any) -> None:
    with pytest.raises(ValueError, match="`recall_thresholds`"):
        _Identity(recall_thresholds=bad)


def test_bad_datamodule_thresholds_fail_in_setup_naming_the_datamodule(tmp_path: Path) -> None:
    class _Bad(_ToyScenes):
        recall_thresholds = ((15.0, 0.0),)

    with pytest.raises(ValueError, match=r"`_Bad\.recall_thresholds`"):
        quiet_trainer(tmp_path).test(_Identity(), datamodule=_Bad(tmp_path), verbose=False)


def test_thresholds_are_hyper_parameters_and_checkpoints_without_them_load(tmp_path: Path) -> None:
    from lcreg.baselines.pcrnet import PCRNet

    small = {"encoder_channels": [8, 16], "regressor_hidden": [16]}
    model = PCRNet(**small, recall_thresholds=[[15, 0.3]])
    assert model.hparams["recall_thresholds"] == [[15, 0.3]] and model.recall_thresholds == ((15.0, 0.3),)
    assert set(model.state_dict()) == set(PCRNet(**small).state_dict())  # metrics hold no saved state
    trainer = quiet_trainer(tmp_path)
    trainer.strategy.connect(model)
    trainer.save_checkpoint(tmp_path / "new.ckpt")
    assert PCRNet.load_from_checkpoint(tmp_path / "new.ckpt").recall_thresholds == ((15.0, 0.3),)
    old = torch.load(tmp_path / "new.ckpt", weights_only=True)
    del old["hyper_parameters"]["recall_thresholds"]  # a checkpoint written before the argument existed
    torch.save(old, tmp_path / "old.ckpt")
    loaded = PCRNet.load_from_checkpoint(tmp_path / "old.ckpt")
    assert loaded.recall_thresholds is None and "test/recall_r15_t0p3" not in loaded.test_metrics.keys()


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_metrics_added_in_setup_run_on_the_model_device(tmp_path: Path) -> None:
    devices: list[str] = []

    class _Devices(Callback):
        def on_test_batch_end(self, trainer: Trainer, pl_module: Any, *args: Any) -> None:
            devices.append(pl_module.test_metrics["recall_r15_t0p3"].device.type)

    data, model = _ToyScenes(tmp_path), _Identity()
    trainer = Trainer(
        accelerator="gpu",
        devices=1,
        logger=False,
        enable_checkpointing=False,
        callbacks=[_Devices()],
        default_root_dir=tmp_path,
    )
    test = trainer.test(model, datamodule=data, verbose=False)[0]
    assert devices and set(devices) == {"cuda"}
    assert test["test/recall_r15_t0p3"] == pytest.approx(_expected(data, "test", 15.0, 0.3), abs=1e-6)
