from __future__ import annotations

import dataclasses
import re
import warnings
from functools import partial
from pathlib import Path

import pytest
import torch
from lightning.pytorch import Callback, Trainer

from _training import fit_batches  # type: ignore[import-not-found]
from lcreg.geometry import se3
from lcreg.models.base import RegistrationModule
from lcreg.types import RegistrationBatch, RegistrationResult


class _Translate(RegistrationModule):
    """Estimates a learned translation; the training pass records that it was used."""

    def __init__(self, **kwargs: object) -> None:
        super().__init__(**kwargs)  # type: ignore[arg-type]
        self.shift = torch.nn.Parameter(torch.zeros(3))
        self.training_passes = 0

    def forward(self, points_src: torch.Tensor, points_ref: torch.Tensor) -> RegistrationResult:
        b = points_src.shape[0]
        transform = se3.make_transform(torch.eye(3).expand(b, 3, 3), self.shift.expand(b, 3))
        return RegistrationResult(transform, torch.ones(b, dtype=torch.bool), torch.ones(b, dtype=torch.int64))

    def training_forward(self, batch: RegistrationBatch) -> RegistrationResult:
        self.training_passes += 1
        return super().training_forward(batch)

    def _compute_loss(self, result: RegistrationResult, batch: RegistrationBatch) -> dict[str, torch.Tensor]:
        gt = self.ground_truth(batch)
        return {"loss": (result.translation - gt[:, :3, 3]).pow(2).mean()}


def _batch(with_gt: bool = True) -> RegistrationBatch:
    src = torch.randn(2, 16, 3, generator=torch.Generator().manual_seed(0))
    gt = se3.make_transform(torch.eye(3).expand(2, 3, 3), torch.tensor([[0.1, 0.2, 0.3]] * 2))
    return RegistrationBatch(src, se3.transform_points(gt, src), gt if with_gt else None)


def test_training_step_uses_training_forward_and_other_stages_do_not() -> None:
    model = _Translate()
    loss = model.training_step(_batch(), 0)
    assert model.training_passes == 1
    torch.testing.assert_close(loss, torch.tensor((0.01 + 0.04 + 0.09) / 3))
    model.eval()
    model.register(_batch().points_src, _batch().points_ref)
    assert model.training_passes == 1


def test_ground_truth_missing_is_a_clear_error() -> None:
    model = _Translate()
    with pytest.raises(ValueError, match="_Translate is trained with a ground-truth pose"):
        model.training_losses(model(_batch().points_src, _batch().points_ref), _batch(with_gt=False))
    assert dataclasses.replace(_batch(), transform_ref_src=None).transform_ref_src is None


def test_plateau_scheduler_is_monitored_on_the_validation_loss() -> None:
    plateau = partial(torch.optim.lr_scheduler.ReduceLROnPlateau, factor=0.5)
    config = _Translate(lr_scheduler=plateau).configure_optimizers()
    assert isinstance(config["lr_scheduler"]["scheduler"], torch.optim.lr_scheduler.ReduceLROnPlateau)
    assert config["lr_scheduler"]["monitor"] == "val/loss"
    step = partial(torch.optim.lr_scheduler.StepLR, step_size=3)
    config = _Translate(lr_scheduler=step).configure_optimizers()
    assert isinstance(config["lr_scheduler"]["scheduler"], torch.optim.lr_scheduler.StepLR)
    assert config["lr_scheduler"]["interval"] == "epoch"
    assert (
        _Translate(lr_scheduler=step, lr_scheduler_interval="step").configure_optimizers()["lr_scheduler"]["interval"]
        == "step"
    )
    assert isinstance(_Translate().configure_optimizers(), torch.optim.Adam)


class _Rates(Callback):
    """The learning rate of every training batch."""

    def __init__(self) -> None:
        self.seen: list[float] = []

    def on_train_batch_start(self, trainer: Trainer, *args: object) -> None:
        self.seen.append(trainer.optimizers[0].param_groups[0]["lr"])


def _fit_two_batch_epochs(model: RegistrationModule, max_steps: int, *callbacks: Callback) -> None:
    """Train ``model`` for ``max_steps`` on epochs of 2 batches."""
    fit_batches(model, [_batch(), _batch()], *callbacks, max_steps=max_steps, max_epochs=-1)


def test_a_step_interval_steps_the_schedule_after_every_optimiser_step() -> None:
    """Milestones in steps do not move with the training set's size (an epoch here is 2 steps)."""
    step = partial(torch.optim.lr_scheduler.StepLR, step_size=3, gamma=0.5)
    rates: dict[str, list[float]] = {}
    for interval in ("epoch", "step"):
        model, recorder = _Translate(lr_scheduler=step, lr_scheduler_interval=interval), _Rates()
        _fit_two_batch_epochs(model, 8, recorder)
        rates[interval] = recorder.seen
    lr = 1e-3  # Adam's default
    assert rates["step"] == [lr] * 3 + [lr / 2] * 3 + [lr / 4] * 2
    assert rates["epoch"] == [lr] * 6 + [lr / 2] * 2  # every 3 epochs of 2 steps


@pytest.mark.parametrize(
    ("milestones", "interval", "beyond"),
    [([2, 4, 10], "epoch", "[4, 10] (epochs)"), ([5, 8, 20], "step", "[8, 20] (steps)")],
)
def test_milestones_beyond_the_run_are_a_warning_naming_them(milestones: list[int], interval: str, beyond: str) -> None:
    """8 steps are 4 epochs of 2: a MultiStepLR milestone at epoch 4 or step 8 would never change the rate."""
    schedule = partial(torch.optim.lr_scheduler.MultiStepLR, milestones=milestones)
    model = _Translate(lr_scheduler=schedule, lr_scheduler_interval=interval)
    message = rf"MultiStepLR's milestones {re.escape(beyond)} lie beyond this run's 8 optimiser steps \(4 epochs of 2"
    with pytest.warns(UserWarning, match=message):
        _fit_two_batch_epochs(model, 8)


def test_milestones_within_the_run_and_other_schedules_give_no_warning() -> None:
    schedules = [
        partial(torch.optim.lr_scheduler.MultiStepLR, milestones=[1, 3]),
        partial(torch.optim.lr_scheduler.StepLR, step_size=3),
        partial(torch.optim.lr_scheduler.ExponentialLR, gamma=0.9),
        None,
    ]
    for schedule in schedules:
        with warnings.catch_warnings():
            warnings.filterwarnings("error", message="lr_scheduler:")
            _fit_two_batch_epochs(_Translate(lr_scheduler=schedule), 8)


def test_a_step_interval_is_refused_for_a_plateau_schedule_and_a_bad_interval() -> None:
    plateau = partial(torch.optim.lr_scheduler.ReduceLROnPlateau, factor=0.5)
    with pytest.raises(ValueError, match="ReduceLROnPlateau steps on the validation loss"):
        _Translate(lr_scheduler=plateau, lr_scheduler_interval="step").configure_optimizers()
    with pytest.raises(ValueError, match="`lr_scheduler_interval` must be 'epoch' or 'step', got 'batch'"):
        _Translate(lr_scheduler_interval="batch")


class _CountingRefiner(RegistrationModule):
    """Moves the estimate by a fixed translation and counts its calls (stands in for ICP)."""

    has_loss = False

    def __init__(self) -> None:
        super().__init__()
        self.calls = 0
        self.offset = se3.make_transform(torch.eye(3)[None], torch.tensor([[0.0, 0.0, 0.5]]))

    def refine(self, points_src: torch.Tensor, points_ref: torch.Tensor, init: torch.Tensor) -> RegistrationResult:
        self.calls += 1
        transform = self.offset.expand_as(init) @ init
        return RegistrationResult.fixed_iterations(transform, num_iters=3, aux={"refined": True})


def test_refiner_runs_after_forward_outside_training_only() -> None:
    refiner = _CountingRefiner()
    model = _Translate(refiner=refiner)
    with torch.no_grad():
        model.shift.copy_(torch.tensor([0.1, 0.0, 0.0]))
    batch = _batch()
    result = model.register(batch.points_src, batch.points_ref)
    expected_coarse = model(batch.points_src, batch.points_ref).transform_ref_src
    torch.testing.assert_close(result.aux["coarse_transform_ref_src"], expected_coarse)
    torch.testing.assert_close(result.translation, torch.tensor([[0.1, 0.0, 0.5]] * 2))
    assert result.num_iters.tolist() == [4, 4] and result.aux["refined"] is True
    model.training_step(batch, 0)  # training never refines
    assert refiner.calls == 1
    model.eval().validation_step(batch, 0)
    model.predict_step(batch, 0)
    assert refiner.calls == 3


def test_refiner_is_a_constructor_argument_neither_a_submodule_nor_saved(tmp_path: Path) -> None:
    from lcreg.baselines.classical import ICP

    keys = set(_Translate().state_dict())
    model = _Translate(refiner=ICP())
    assert set(model.state_dict()) == keys and isinstance(model.refiner, ICP)
    assert all(not isinstance(m, ICP) for m in model.modules())
    with pytest.raises(TypeError, match="refiner"):
        _Translate(refiner=3)
    with pytest.raises(TypeError, match="cannot refine"):
        _Translate(refiner=_Translate()).register(_batch().points_src, _batch().points_ref)
    # Weights of a plain checkpoint load into the configured instance; the refiner stays.
    trained = _Translate()
    with torch.no_grad():
        trained.shift.copy_(torch.tensor([0.3, -0.2, 0.1]))
    model.load_state_dict(trained.state_dict())
    torch.testing.assert_close(model.shift, trained.shift)
    assert isinstance(model.refiner, ICP)


# --- subclassing needs no ritual -----------------------------------------------------------------------------------
class _Host(RegistrationModule):
    """A host as a user writes one: build the layers, nothing else."""

    def __init__(self, width: int = 8, **kwargs: object) -> None:
        from lcreg.nn.pointnet import PointNetEncoder

        super().__init__(**kwargs)  # type: ignore[arg-type]
        self.encoder = PointNetEncoder([width, width], batch_norm=False)


class _WiderHost(_Host):
    def __init__(self, extra: int = 1, **kwargs: object) -> None:
        super().__init__(width=4 * extra, **kwargs)  # type: ignore[arg-type]


def test_hosts_save_their_arguments_and_bind_terms_without_ritual_calls() -> None:
    from lcreg.models.loss_terms import LocalConsistencyLoss

    host = _Host(width=16, loss_terms=[LocalConsistencyLoss()], max_bad_steps=3)
    assert dict(host.hparams) == {"width": 16, "max_bad_steps": 3}  # the components are never hyper-parameters
    assert host.loss_terms[0].local_consistency.metric.weight.shape == (16, 32)  # bound after __init__
    wider = _WiderHost(extra=2, loss_terms=[LocalConsistencyLoss()])
    assert dict(wider.hparams) == {"extra": 2}  # the outermost constructor's arguments: what rebuilds it
    assert wider.loss_terms[0].local_consistency.metric.weight.shape == (8, 16)
    assert type(wider)(**wider.hparams).encoder.feature_dim == 8


def test_assigning_a_component_after_construction_works_or_raises() -> None:
    import lcreg

    from _weights_files import tiny_model  # type: ignore[import-not-found]

    model = tiny_model("dvds")
    model.refiner = lcreg.ICP()  # was filed under _modules and ignored: model.refiner stayed None
    assert isinstance(model.refiner, lcreg.ICP) and "refiner" not in dict(model.named_modules())
    assert not any(key.startswith("refiner") for key in model.state_dict())  # never saved
    model.voxel_grid = lcreg.VoxelGrid()
    assert isinstance(model.voxel_grid, lcreg.VoxelGrid)
    with pytest.raises(TypeError, match="`refiner` must be a RegistrationModule"):
        model.refiner = torch.nn.Linear(2, 2)
    with pytest.raises(TypeError, match="`voxel_grid` must be"):
        model.voxel_grid = "27"
    model.refiner = None
    assert model.refiner is None
