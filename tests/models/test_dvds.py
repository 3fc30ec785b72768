from __future__ import annotations

import csv
import dataclasses
from pathlib import Path

import lightning as L
import pytest
import torch

from lcreg.checks import NonFiniteError, ShapeError, TooFewPointsError
from lcreg.data.collate import collate_pairs
from lcreg.data.datamodule import PairDataset, SyntheticDataModule
from lcreg.data.pairs import PairProtocol
from lcreg.data.synthetic import synthetic_shapes
from lcreg.geometry import se3
from lcreg.geometry.random_transforms import random_euler_transform
from lcreg.models.base import RegistrationModule
from lcreg.models.dvds import DVDs
from lcreg.models.evaluation import COMPONENT_COLUMNS
from lcreg.models.loss_terms import LocalConsistencyLoss
from lcreg.nn.local_consistency import LocalConsistency
from lcreg.nn.pointnet import PointNetEncoder
from lcreg.types import RegistrationBatch, RegistrationResult

from _host_contract import check_local_consistency_gradient  # type: ignore[import-not-found]

TINY = {
    "encoder_channels": (16, 32),
    "decoder_grid_size": 8,
    "decoder_hidden": (32,),
    "normal_hidden": (16,),
    "diagnostics_every_n_steps": 0,
}


def _lc(weight: float = 1.0, num_local_points: int = 16) -> list[LocalConsistencyLoss]:
    """Paper model D's LC term (as configs/lc.yaml injects it); weight 0 means no LC term at all."""
    return [LocalConsistencyLoss(LocalConsistency(num_local_points=num_local_points), weight)] if weight else []


def _model(seed: int = 0, lc_weight: float = 1.0, **overrides: object) -> DVDs:
    torch.manual_seed(seed)
    return DVDs(**{**TINY, "loss_terms": _lc(lc_weight), **overrides})  # type: ignore[arg-type]


@pytest.fixture(scope="module")
def batch() -> RegistrationBatch:
    points, normals, _ = synthetic_shapes(4, 256, seed=0)
    dataset = PairDataset(points, normals, PairProtocol(num_points=128), deterministic=True, seed=0)
    return collate_pairs([dataset[i] for i in range(4)])


def test_forward_returns_a_registration_result(batch: RegistrationBatch) -> None:
    model = _model().eval()
    result = model(batch.points_src, batch.points_ref)
    assert isinstance(result, RegistrationResult)
    assert result.transform_ref_src.shape == (4, 4, 4)
    assert result.converged.shape == (4,) and result.converged.dtype == torch.bool
    assert result.num_iters.shape == (4,) and result.num_iters.dtype == torch.int64
    assert ((result.num_iters >= 1) & (result.num_iters <= 10)).all()
    assert torch.isfinite(result.transform_ref_src).all()
    rot = result.rotation
    torch.testing.assert_close(rot @ rot.transpose(1, 2), torch.eye(3).expand(4, 3, 3), atol=1e-4, rtol=0)
    assert not result.transform_ref_src.requires_grad


def test_compute_loss_terms_are_finite_and_weighted(batch: RegistrationBatch) -> None:
    model = _model().train()
    result = model(batch.points_src, batch.points_ref)
    assert model.training and model.encoder.training  # the solver restored the mode
    losses = model.training_losses(result, batch)
    assert set(losses) == {"global", "recon", "normal", "lc", "loss"}
    for name, value in losses.items():
        assert value.ndim == 0 and torch.isfinite(value), name
        assert value >= 0, name
    expected = losses["global"] + 0.5 * losses["recon"] + 0.1 * losses["normal"] + 1.0 * losses["lc"]
    torch.testing.assert_close(losses["loss"], expected)
    assert losses["loss"].requires_grad


def test_injected_local_consistency_follows_the_host_contract(batch: RegistrationBatch) -> None:
    check_local_consistency_gradient(lambda terms: _model(loss_terms=terms), batch)


def test_loss_does_not_depend_on_the_ground_truth(batch: RegistrationBatch) -> None:
    model = _model().train()
    result = model(batch.points_src, batch.points_ref)
    random_gt, _ = random_euler_transform(4, generator=torch.Generator().manual_seed(5))
    variants = [
        batch,
        dataclasses.replace(batch, transform_ref_src=random_gt),
        dataclasses.replace(batch, transform_ref_src=None),
    ]
    all_losses = [model.training_losses(result, b) for b in variants]
    for losses in all_losses[1:]:
        assert losses.keys() == all_losses[0].keys()
        for name in losses:
            torch.testing.assert_close(losses[name], all_losses[0][name], atol=0, rtol=0)
    # ... but it does depend on the estimate.
    moved = dataclasses.replace(result, transform_ref_src=random_gt)
    assert not torch.allclose(model.training_losses(moved, batch)["global"], all_losses[0]["global"])


def test_a_few_optimizer_steps_lower_the_loss(batch: RegistrationBatch) -> None:
    model = _model().train()
    optimizer = model.configure_optimizers()
    assert isinstance(optimizer, torch.optim.Adam)
    trained = {id(p) for group in optimizer.param_groups for p in group["params"]}
    assert len(model.loss_terms) == 1
    assert all(id(p) not in trained for p in model.loss_terms.parameters())  # the FC metric stays frozen
    history, recon = [], []
    for _ in range(8):
        losses = model.training_losses(model(batch.points_src, batch.points_ref), batch)
        history.append(float(losses["loss"].detach()))
        recon.append(float(losses["recon"].detach()))
        optimizer.zero_grad()
        losses["loss"].backward()
        optimizer.step()
    # The estimate is re-solved every step, so the loss is noisy: compare the last steps with the first.
    assert sum(history[-3:]) / 3 < 0.9 * history[0], history
    assert recon[-1] < recon[0], recon


@pytest.mark.parametrize(("squared", "decoder"), [(False, "folding"), (True, "folding"), (True, "mlp")])
def test_reconstruction_term_is_the_chamfer_of_both_decodings(
    batch: RegistrationBatch, squared: bool, decoder: str
) -> None:
    """``L_CD`` per cloud against scipy's nearest neighbours: mean distance both ways (the paper), or mean squared
    distance both ways with ``squared_chamfer`` (FMR-Net's reconstruction loss); the two clouds' terms summed. The
    same with FMR-Net's MLP decoder."""
    from scipy.spatial import cKDTree

    model = _model(lc_weight=0.0, squared_chamfer=squared, batch_norm=False, decoder=decoder).train()  # codes alone
    losses = model.training_losses(model(batch.points_src, batch.points_ref), batch)
    expected = 0.0
    with torch.no_grad():
        for cloud in (batch.points_src, batch.points_ref):
            for decoded, points in zip(model.decoder(model.encoder(cloud)).double(), cloud.double(), strict=True):
                a, b = decoded.numpy(), points.numpy()
                d_ab, d_ba = cKDTree(b).query(a)[0], cKDTree(a).query(b)[0]
                power = 2 if squared else 1
                expected += ((d_ab**power).mean() + (d_ba**power).mean()) / len(cloud)
    torch.testing.assert_close(losses["recon"].double(), torch.tensor(expected, dtype=torch.float64), rtol=1e-4, atol=0)


@pytest.mark.parametrize(("batch_norm", "norm_batch"), [(False, "joint"), (True, "per_cloud")])
def test_fmr_nets_objective_and_decoder_on_dvds_is_fmr_net(
    batch: RegistrationBatch, batch_norm: bool, norm_batch: str
) -> None:
    """The goal (c) control ``recon_sq_bn_lr1e-3_mlpdec`` (docs/results/converge): DVDs with FMR-Net's reconstruction
    (squared Chamfer, weight 1, no other term) and decoder, given FMR-Net's weights, has FMR-Net's loss and encoder
    gradients: without BatchNorm whatever ``norm_batch``, with it when each cloud's batch is normalised alone as
    FMR-Net does (``norm_batch="per_cloud"``). The default ``"joint"`` normalises ``[X, Y, W(X)]`` together."""
    from lcreg.baselines.fmr import FMRNet

    widths = {"encoder_channels": (16, 32), "decoder_hidden": (32, 16)}
    torch.manual_seed(0)
    fmr = FMRNet(**widths, decoder_points=64, batch_norm=batch_norm).train()  # type: ignore[arg-type]
    recon_only = {"lambda_global": 0.0, "lambda_normal": 0.0, "lambda_recon": 1.0, "squared_chamfer": True}

    def dvds(norm: str) -> DVDs:
        model = DVDs(
            **widths,  # type: ignore[arg-type]
            **recon_only,  # type: ignore[arg-type]
            batch_norm=batch_norm,
            decoder="mlp",
            decoder_grid_size=8,
            loss_terms=[],
            norm_batch=norm,  # type: ignore[arg-type]
        )
        model.load_state_dict(fmr.state_dict())  # strict: the same modules, names and shapes
        return model.train()

    def loss_and_grads(model: RegistrationModule) -> tuple[torch.Tensor, tuple[torch.Tensor, ...]]:
        loss = model.training_losses(model.training_forward(batch), batch)["loss"]
        return loss, torch.autograd.grad(loss, list(model.encoder.parameters()))

    theirs, ours = loss_and_grads(fmr), loss_and_grads(dvds(norm_batch))
    torch.testing.assert_close(ours[0], theirs[0], rtol=1e-6, atol=0)
    for expected, got in zip(theirs[1], ours[1], strict=True):
        torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-8)
    if batch_norm:  # the joint batch's statistics include W(X): another function
        joint = loss_and_grads(dvds("joint"))[1]
        assert not all(torch.allclose(a, b, rtol=1e-3, atol=1e-6) for a, b in zip(theirs[1], joint, strict=True))
    with pytest.raises(ValueError, match="`norm_batch` must be 'joint' or 'per_cloud'"):
        dvds("separate")


def test_the_decoder_is_foldingnet_or_fmr_nets_mlp(batch: RegistrationBatch) -> None:
    """``decoder="mlp"`` swaps FoldingNet for FMR-Net's decoder (grid_size**2 points, the encoder's BatchNorm); the
    decoder trains only, so neither is in an exported file; anything else is refused, naming the argument."""
    from lcreg.nn.decoders import MLPDecoder
    from lcreg.nn.folding import FoldingDecoder

    assert isinstance(_model().decoder, FoldingDecoder)
    model = _model(decoder="mlp", decoder_hidden=(32, 16)).train()
    assert isinstance(model.decoder, MLPDecoder)
    assert any(isinstance(m, torch.nn.BatchNorm1d) for m in model.decoder.modules())
    code = model.encoder(batch.points_src)
    assert model.decoder(code).shape == (len(batch), TINY["decoder_grid_size"] ** 2, 3)  # type: ignore[operator]
    losses = model.training_losses(model(batch.points_src, batch.points_ref), batch)
    assert torch.isfinite(losses["recon"]) and losses["recon"] > 0
    assert "decoder" in DVDs.training_only_modules  # left out of exported files, whichever it is
    assert _model(decoder="mlp", lambda_recon=0.0).decoder is None
    with pytest.raises(ValueError, match="`decoder` must be 'folding' or 'mlp'"):
        _model(decoder="transformer")


def test_ablation_flags_remove_modules_and_terms(batch: RegistrationBatch) -> None:
    cases = [
        ({"lc_weight": 0.0}, "lc", None),
        ({"lambda_recon": 0.0}, "recon", "decoder"),
        ({"lambda_normal": 0.0}, "normal", "normal_head"),
    ]
    for overrides, term, module in cases:
        model = _model(**overrides).train()  # type: ignore[arg-type]
        assert module is None or getattr(model, module) is None, module
        losses = model.training_losses(model(batch.points_src, batch.points_ref), batch)
        assert term not in losses and "loss" in losses and torch.isfinite(losses["loss"])
    model_a = _model(lc_weight=0.0, lambda_recon=0.0, lambda_normal=0.0).train()
    losses = model_a.training_losses(model_a(batch.points_src, batch.points_ref), batch)
    assert set(losses) == {"global", "loss"}
    torch.testing.assert_close(losses["loss"], losses["global"])
    assert model_a.min_points == 3  # no LC: small clouds are fine
    with pytest.raises(ValueError, match="lambda"):
        _model(lambda_recon=-1.0)
    with pytest.raises(ValueError, match="weight"):
        _model(lc_weight=-1.0)


def test_missing_normals_fall_back_to_pca(batch: RegistrationBatch) -> None:
    model = _model().train()
    result = model(batch.points_src, batch.points_ref)
    no_normals = dataclasses.replace(batch, normals_src=None, normals_ref=None)
    losses = model.training_losses(result, no_normals)
    assert (
        torch.isfinite(losses["normal"]) and 0 <= float(losses["normal"].detach()) <= 2
    )  # |cos| in [0, 1], two clouds
    with_normals = model.training_losses(result, batch)
    assert not torch.allclose(losses["normal"], with_normals["normal"])
    losses["loss"].backward()
    assert model.normal_head is not None
    assert all(p.grad is not None for p in model.normal_head.parameters())
    # PCA normals have no sign: flipping the predicted normals changes the oriented loss only.
    code = model.encoder(batch.points_src).detach()
    with torch.no_grad():
        unoriented = model._normal_loss(batch.points_src, None, code)
        oriented = model._normal_loss(batch.points_src, batch.normals_src, code)
        last = model.normal_head.mlp.rest[-1]
        assert isinstance(last, torch.nn.Linear)
        last.weight.neg_()
        last.bias.neg_()
        torch.testing.assert_close(model._normal_loss(batch.points_src, None, code), unoriented)
        flipped = model._normal_loss(batch.points_src, batch.normals_src, code)
    torch.testing.assert_close(oriented + flipped, torch.tensor(2.0))  # (1 - c) + (1 + c)


@pytest.mark.parametrize(
    ("src", "error", "name"),
    [
        (torch.full((2, 32, 3), float("nan")), NonFiniteError, "points_src"),
        (torch.full((2, 32, 3), float("inf")), NonFiniteError, "points_src"),
        (torch.zeros(2, 0, 3), TooFewPointsError, "points_src"),
        (torch.zeros(2, 32, 2), ShapeError, "points_src"),
        (torch.zeros(32, 3), ShapeError, "points_src"),
        (torch.zeros(2, 32, 3, dtype=torch.int32), TypeError, "points_src"),
        (torch.randn(2, 10, 3), TooFewPointsError, "points_src"),  # < num_local_points
        (torch.randn(3, 32, 3), ShapeError, "points_ref"),  # batch sizes differ
    ],
    ids=["nan", "inf", "empty", "two_columns", "unbatched", "int", "fewer_than_local", "batch_mismatch"],
)
def test_register_rejects_bad_inputs(src: torch.Tensor, error: type[Exception], name: str) -> None:
    model = _model()
    with pytest.raises(error, match=name):
        model.register(src, torch.randn(2, 32, 3))
    if name == "points_src":  # the same defect in the other argument is reported under its name
        with pytest.raises(error, match="points_ref"):
            model.register(torch.randn(2, 32, 3), src)


def test_register_runs_in_eval_mode_and_restores_the_mode(batch: RegistrationBatch) -> None:
    model = _model().train()
    result = model.register(batch.points_src, batch.points_ref)
    assert model.training and result.transform_ref_src.shape == (4, 4, 4)
    model.eval()
    model.register(batch.points_src, batch.points_ref)
    assert not model.training


def test_trainer_fast_dev_run_fit_and_test(tmp_path: Path) -> None:
    L.seed_everything(0)
    model = DVDs(**{**TINY, "diagnostics_every_n_steps": 1, "loss_terms": _lc()})  # type: ignore[arg-type]
    data = SyntheticDataModule(num_points=128, batch_size=2, num_train=4, num_val=2, num_test=2, points_per_shape=256)
    trainer = L.Trainer(
        fast_dev_run=True,
        accelerator="cpu",
        logger=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        default_root_dir=tmp_path,
    )
    trainer.fit(model, datamodule=data)
    logged = trainer.callback_metrics
    for key in ("train/loss", "train/global", "train/lc", "val/loss", "val/rre_mean_deg"):
        assert key in logged and torch.isfinite(logged[key]), key
    assert "train/lc_grad_norm" in logged and float(logged["train/lc_grad_norm"]) > 0
    for key in ("train/j_cond", "train/j_sensitivity", "train/j_dir_rx", "train/j_dir_tz"):  # J conditioning
        assert key in logged and 0 < float(logged[key]) < float("inf"), key
    trainer.test(model, datamodule=data)
    assert "test/rre_mean_deg" in trainer.callback_metrics
    assert "test/loss" not in trainer.callback_metrics  # the training losses are not computed at test time
    rows = list(csv.reader((tmp_path / "test_per_pair.csv").open()))
    assert rows[0] == ["index", "rotation_error_deg", "translation_error", "class", *COMPONENT_COLUMNS]
    assert len(rows) == 3


class MinimalHost(RegistrationModule):
    """A third-party host: an encoder, identity registration and its own loss."""

    def __init__(self, **kwargs: object) -> None:
        super().__init__(**kwargs)  # type: ignore[arg-type]
        self.encoder = PointNetEncoder((16, 32))

    def forward(self, points_src: torch.Tensor, points_ref: torch.Tensor) -> RegistrationResult:
        b = points_src.shape[0]
        return RegistrationResult(
            transform_ref_src=se3.identity(b, dtype=points_src.dtype),
            converged=torch.ones(b, dtype=torch.bool),
            num_iters=torch.ones(b, dtype=torch.int64),
        )

    def _compute_loss(self, result: RegistrationResult, batch: RegistrationBatch) -> dict[str, torch.Tensor]:
        feats = self.encoder(torch.cat([batch.points_src, batch.points_ref]))
        f_src, f_ref = feats.chunk(2)
        return {"host": (f_src - f_ref).norm(dim=-1).mean(), "loss": (f_src - f_ref).norm(dim=-1).mean()}


def test_injected_local_consistency_on_a_minimal_host(batch: RegistrationBatch) -> None:
    torch.manual_seed(0)
    host = MinimalHost(loss_terms=_lc(0.5)).train()
    assert host.loss_terms[0].local_consistency.feature_dim == 32  # bound to the host's width at construction
    assert host.min_points == 16
    losses = host.training_losses(host(batch.points_src, batch.points_ref), batch)
    assert set(losses) == {"host", "lc", "loss"}
    assert losses["lc"] > 0
    torch.testing.assert_close(losses["loss"], losses["host"] + 0.5 * losses["lc"])
    params = list(host.encoder.parameters())
    grads = torch.autograd.grad(losses["lc"], params, allow_unused=True)
    assert sum(float(g.abs().sum()) for g in grads if g is not None) > 0
    off = MinimalHost()
    assert set(off.training_losses(off(batch.points_src, batch.points_ref), batch)) == {"host", "loss"}
    with pytest.raises(ValueError, match="built for 64 features"):
        MinimalHost(loss_terms=[LocalConsistencyLoss(LocalConsistency(feature_dim=64, num_local_points=16))])
