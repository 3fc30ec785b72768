"""The LK base shared by DVDs, PointNetLK and FMR-Net: one encoder class, one solver, one forward."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from lcreg.baselines.fmr import FMRNet
from lcreg.baselines.pointnetlk import PointNetLK
from lcreg.geometry import se3
from lcreg.geometry.random_transforms import random_euler_transform
from lcreg.models.dvds import DVDs
from lcreg.models.lucas_kanade import LucasKanadeModule, lk_pose_loss
from lcreg.nn.lk import InverseCompositionalLK
from lcreg.nn.pointnet import PointNetEncoder

from _host_contract import tiny_batch  # type: ignore[import-not-found]
from _weights_files import exported, lightning_checkpoint, tiny_model  # type: ignore[import-not-found]

SMALL = {"encoder_channels": (16, 32)}


@pytest.mark.parametrize(
    "model",
    [
        DVDs(**SMALL, lambda_recon=0, lambda_normal=0),  # type: ignore[arg-type]
        PointNetLK(**SMALL),  # type: ignore[arg-type]
        FMRNet(**SMALL, decoder_hidden=(16,), decoder_points=32),  # type: ignore[arg-type]
    ],
    ids=["dvds", "pointnetlk", "fmr"],
)
def test_lk_models_share_the_encoder_solver_and_forward(model: LucasKanadeModule) -> None:
    assert isinstance(model, LucasKanadeModule)
    assert type(model.encoder) is PointNetEncoder and type(model.solver) is InverseCompositionalLK
    assert type(model).forward is LucasKanadeModule.forward
    batch = tiny_batch(batch_size=2, num_points=48)
    model.eval()
    with torch.no_grad():
        expected = model.solver(model.encoder, batch.points_src, batch.points_ref, model.eval_iterations)
        got = model(batch.points_src, batch.points_ref)
    torch.testing.assert_close(got.transform_ref_src, expected.transform_ref_src)


def test_solver_reports_the_last_residual_and_honours_an_iteration_override() -> None:
    torch.manual_seed(0)
    encoder = PointNetEncoder((16, 32), batch_norm=False).eval()
    solver = InverseCompositionalLK(max_iterations=5, tolerance=0.0)
    batch = tiny_batch(batch_size=2, num_points=48)
    src, ref = batch.points_src, batch.points_ref
    one = solver(encoder, src, ref, max_iterations=1)
    assert one.num_iters.tolist() == [1, 1]
    expected = encoder(src - src.mean(1, keepdim=True)) - encoder(ref - ref.mean(1, keepdim=True))
    torch.testing.assert_close(one.aux["residual"], expected)  # before the only update
    assert solver(encoder, src, ref).num_iters.tolist() == [5, 5]
    with pytest.raises(ValueError, match="max_iterations"):
        solver(encoder, src, ref, max_iterations=0)


def test_lk_pose_loss_is_the_mean_squared_frobenius_norm() -> None:
    gen = torch.Generator().manual_seed(0)
    est, _ = random_euler_transform(4, generator=gen, dtype=torch.float64)
    gt, _ = random_euler_transform(4, generator=gen, dtype=torch.float64)
    expected = np.mean([np.sum((e @ np.linalg.inv(g) - np.eye(4)) ** 2) for e, g in zip(est.numpy(), gt.numpy())])
    np.testing.assert_allclose(float(lk_pose_loss(est, gt)), expected, rtol=1e-10)
    assert float(lk_pose_loss(gt, gt)) < 1e-20
    assert float(lk_pose_loss(se3.identity(1, dtype=torch.float64), se3.identity(1, dtype=torch.float64))) == 0.0


def test_norm_statistics_are_only_updated_in_training() -> None:
    model = PointNetLK(**SMALL)  # type: ignore[arg-type]
    norm = model.encoder.norms[0]
    assert isinstance(norm, torch.nn.BatchNorm1d) and norm.running_mean is not None
    batch = tiny_batch(batch_size=2, num_points=48)
    before = norm.running_mean.clone()
    model.eval().update_norm_statistics(batch)
    assert torch.equal(before, norm.running_mean)
    model.train().update_norm_statistics(batch)
    assert not torch.equal(before, norm.running_mean)


def test_voxel_grid_is_used_outside_training_only_and_not_saved() -> None:
    from lcreg.nn.voxel_lk import VoxelGrid, voxel_lk

    batch = tiny_batch(batch_size=2, num_points=64)
    keys = set(PointNetLK(**SMALL, eval_iterations=4).state_dict())  # type: ignore[arg-type]
    grid = VoxelGrid(grid=2, points_per_voxel=16, min_points=4)
    model = PointNetLK(**SMALL, eval_iterations=4, voxel_grid=grid)  # type: ignore[arg-type]
    assert model.voxel_grid is grid and set(model.state_dict()) == keys and "voxel_grid" not in model.hparams
    model.eval()
    with torch.no_grad():
        got = model(batch.points_src, batch.points_ref)
        expected = voxel_lk(model.solver, model.encoder, grid, batch.points_src, batch.points_ref, 4)
    torch.testing.assert_close(got.transform_ref_src, expected.transform_ref_src)
    assert "num_voxels" in got.aux
    model.train()
    assert "num_voxels" not in model(batch.points_src, batch.points_ref).aux  # training: the plain solver
    assert PointNetLK(**SMALL).voxel_grid is None  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="VoxelGrid"):
        PointNetLK(**SMALL, voxel_grid=3)  # type: ignore[arg-type]


@pytest.mark.parametrize("cls", [DVDs, PointNetLK], ids=["dvds", "pointnetlk"])
def test_eval_starts_are_used_outside_training_only_and_saved(cls: type[LucasKanadeModule]) -> None:
    from lcreg.nn.lk import axis_rotation_starts

    batch = tiny_batch(batch_size=2, num_points=64)
    extra = {"lambda_recon": 0, "lambda_normal": 0} if cls is DVDs else {}
    model = cls(**SMALL, eval_iterations=3, eval_start_angles_deg=[60], **extra)  # type: ignore[arg-type]
    assert model.eval_start_angles_deg == (60.0,) and list(model.hparams["eval_start_angles_deg"]) == [60]
    model.eval()
    with torch.no_grad():
        got = model(batch.points_src, batch.points_ref)
        starts = axis_rotation_starts([60.0], batch.points_src.dtype)
        expected = model.solver(model.encoder, batch.points_src, batch.points_ref, max_iterations=3, starts=starts)
    torch.testing.assert_close(got.transform_ref_src, expected.transform_ref_src)
    assert got.aux["start"].shape == (2,)
    model.eval_start_margin = 0.999  # no start is that much better: the identity's answer
    with torch.no_grad():
        kept = model(batch.points_src, batch.points_ref)
    assert (kept.aux["start"] == 0).all()
    assert cls(**SMALL, eval_start_margin=0.2, **extra).hparams["eval_start_margin"] == 0.2  # type: ignore[arg-type]
    model.train()
    assert "start" not in model(batch.points_src, batch.points_ref).aux  # training: the identity start alone
    assert "start" not in cls(**SMALL, **extra).eval()(batch.points_src, batch.points_ref).aux  # type: ignore[arg-type]


def test_eval_starts_are_checked() -> None:
    from lcreg.nn.voxel_lk import VoxelGrid

    with pytest.raises(ValueError, match="eval_start_angles_deg"):
        PointNetLK(**SMALL, eval_start_angles_deg=[float("nan")])  # type: ignore[arg-type]
    for bad in (-0.5, 1.0):
        with pytest.raises(ValueError, match="eval_start_margin"):
            PointNetLK(**SMALL, eval_start_margin=bad)  # type: ignore[arg-type]
    model = PointNetLK(**SMALL, eval_start_angles_deg=[60], voxel_grid=VoxelGrid(grid=2))  # type: ignore[arg-type]
    batch = tiny_batch(batch_size=1, num_points=64)
    with pytest.raises(ValueError, match="not with `voxel_grid`"):
        model.eval()(batch.points_src, batch.points_ref)


# --- encoder_from: training starts from another IC-LK model's encoder ---------------------------------------------
def _encoder_state(model: LucasKanadeModule) -> dict[str, torch.Tensor]:
    return {k: v.clone() for k, v in model.encoder.state_dict().items()}


def _fit_steps(model: LucasKanadeModule, steps: int, root: Path, ckpt_path: str | None = None) -> Path:
    """``steps`` training steps on one tiny batch (lr 0: parameters move only if something loads them); the last
    checkpoint's path."""
    from lightning.pytorch import Trainer
    from lightning.pytorch.callbacks import ModelCheckpoint

    batch = tiny_batch(batch_size=2, num_points=48)
    loader = torch.utils.data.DataLoader([batch] * steps, batch_size=None, collate_fn=lambda b: b)
    checkpoints = ModelCheckpoint(dirpath=root, save_last=True)
    trainer = Trainer(
        max_steps=steps, logger=False, enable_progress_bar=False, enable_model_summary=False, callbacks=[checkpoints]
    )
    trainer.fit(model, train_dataloaders=loader, ckpt_path=ckpt_path)
    return root / "last.ckpt"


@pytest.mark.parametrize("source_kind", ["fmr", "dvds"])
@pytest.mark.parametrize("suffix", [".pt", ".ckpt"])
def test_encoder_from_loads_another_models_encoder_at_the_first_setup(
    tmp_path: Path, source_kind: str, suffix: str
) -> None:
    source = tiny_model(source_kind, seed=3, lc=False)
    path = (
        exported(source, tmp_path, name="source")
        if suffix == ".pt"
        else lightning_checkpoint(source, tmp_path / "source.ckpt")
    )
    model = PointNetLK(encoder_channels=[16, 32], encoder_from=str(path))
    before = {k: v.clone() for k, v in model.state_dict().items()}
    model.setup("validate")  # a step-0 validation already sees the starting encoder
    expected = _encoder_state(source)
    got = _encoder_state(model)
    assert got.keys() == expected.keys() and all(torch.equal(got[k], expected[k]) for k in got)  # BN buffers too
    assert not torch.equal(got["linears.0.weight"], before["encoder.linears.0.weight"])
    assert all(torch.equal(v, before[k]) for k, v in model.state_dict().items() if not k.startswith("encoder."))
    with torch.no_grad():
        model.encoder.linears[0].weight.add_(1.0)  # trained since: a later setup (fit after validate) keeps it
    trained = _encoder_state(model)
    model.setup("fit")
    assert all(torch.equal(v, trained[k]) for k, v in _encoder_state(model).items())
    assert PointNetLK.inference_hparams["encoder_from"] is None  # the export leaves the path out


def test_weights_loaded_before_the_first_setup_win_over_encoder_from(tmp_path: Path) -> None:
    path = exported(tiny_model("fmr", seed=3, lc=False), tmp_path, name="source")
    own = tiny_model("pointnetlk", seed=5, lc=False, eval_iterations=None, max_iterations=10)
    model = PointNetLK(encoder_channels=[16, 32], encoder_from=str(path))
    model.load_state_dict(own.state_dict())  # what --weights does before Lightning sets the model up
    model.setup("fit")
    assert all(torch.equal(v, own.state_dict()[k]) for k, v in model.state_dict().items())


def test_encoder_from_refuses_missing_files_and_other_encoders(tmp_path: Path) -> None:
    from lcreg.checkpoints import CheckpointMismatchError, CheckpointNotFoundError

    missing = PointNetLK(encoder_channels=[16, 32], encoder_from=str(tmp_path / "nothing.pt"))
    with pytest.raises(CheckpointNotFoundError, match=r"nothing\.pt.*no such file \(the model's `encoder_from`\)"):
        missing.setup("fit")
    wider = exported(tiny_model("fmr", lc=False, encoder_channels=[16, 64]), tmp_path, name="wider")
    model = PointNetLK(encoder_channels=[16, 32], encoder_from=str(wider))
    with pytest.raises(CheckpointMismatchError, match=r"wider.*`encoder` does not fit.*shapes"):
        model.setup("fit")


def test_encoder_from_starts_a_fit_and_a_resumed_fit_keeps_its_checkpoint(tmp_path: Path) -> None:
    first = exported(tiny_model("fmr", seed=1, lc=False), tmp_path, name="first")
    model = PointNetLK(encoder_channels=[16, 32], encoder_from=str(first), optimizer=_zero_lr_adam)
    last = _fit_steps(model, 1, tmp_path / "run")
    params = dict(model.encoder.named_parameters())
    source = dict(tiny_model("fmr", seed=1, lc=False).encoder.named_parameters())
    assert all(torch.equal(params[k], source[k]) for k in params)  # lr 0: the loaded encoder trained
    # the file now holds another encoder: a resumed fit restores its checkpoint over what setup loads
    exported(tiny_model("fmr", seed=2, lc=False), tmp_path, name="first", overwrite=True)
    resumed = PointNetLK(encoder_channels=[16, 32], encoder_from=str(first), optimizer=_zero_lr_adam)
    _fit_steps(resumed, 2, tmp_path / "run", ckpt_path=str(last))
    again = dict(resumed.encoder.named_parameters())
    assert all(torch.equal(again[k], params[k]) for k in again)


def _zero_lr_adam(params: Any) -> torch.optim.Optimizer:
    return torch.optim.Adam(params, lr=0.0)
