"""The one loss protocol: injected LossTerms on every model, LC among them, and the mixin for outside modules."""

from __future__ import annotations

import pytest
import torch
from lightning.pytorch import LightningModule

from lcreg.baselines.classical import ICP
from lcreg.baselines.dcp import DCP
from lcreg.data.datamodule import PairDataset, collate_pairs
from lcreg.data.pairs import PairProtocol
from lcreg.data.synthetic import synthetic_shapes
from lcreg.models.base import RegistrationModule
from lcreg.models.loss_terms import LocalConsistencyLoss, LossTerm
from lcreg.models.mixins import LocalConsistencyMixin
from lcreg.nn.local_consistency import LocalConsistency
from lcreg.nn.pointnet import PointNetEncoder
from lcreg.types import RegistrationBatch, RegistrationResult


@pytest.fixture(scope="module")
def batch() -> RegistrationBatch:
    points, normals, _ = synthetic_shapes(2, 256, seed=0)
    dataset = PairDataset(points, normals, PairProtocol(num_points=96), deterministic=True, seed=0)
    return collate_pairs([dataset[i] for i in range(2)])


def _tiny_dcp(**kwargs: object) -> DCP:
    torch.manual_seed(0)
    return DCP(emb_dims=32, k=8, heads=2, ff_dims=32, edge_channels=(16, 16, 16, 16), **kwargs)  # type: ignore[arg-type]


class _ScaleTerm(LossTerm):
    """A user-defined term: the mean squared translation of the estimate."""

    def forward(self, model: RegistrationModule, result: RegistrationResult, batch: RegistrationBatch) -> torch.Tensor:
        return result.translation.pow(2).sum(-1).mean()


def test_injected_terms_are_weighted_logged_by_name_and_composable(batch: RegistrationBatch) -> None:
    lc = LocalConsistencyLoss(LocalConsistency(num_local_points=16), weight=0.5)
    model = _tiny_dcp(loss_terms=[lc, _ScaleTerm(weight=2.0, name="scale")]).train()
    assert lc.local_consistency.feature_dim == 32 and model.min_points == 16
    losses = model.training_losses(model.training_forward(batch), batch)
    assert set(losses) == {"pose", "lc", "scale", "loss"}
    torch.testing.assert_close(losses["loss"], losses["pose"] + 0.5 * losses["lc"] + 2.0 * losses["scale"])
    logged: dict[str, torch.Tensor] = {}
    model.log = lambda name, value, **_: logged.__setitem__(name, value)  # type: ignore[method-assign]
    model.training_step(batch, 0)
    assert {"train/pose", "train/lc", "train/scale", "train/loss"} <= set(logged)


def test_compute_loss_is_gone_so_no_caller_can_leave_a_term_out(batch: RegistrationBatch) -> None:
    # Regression: benchmarks called `compute_loss`, which silently left the LC term out of the pilot's training.
    model = _tiny_dcp(loss_terms=[LocalConsistencyLoss(LocalConsistency(num_local_points=16))])
    assert not hasattr(model, "compute_loss")
    assert "lc" in model.training_losses(model.training_forward(batch), batch)


def test_bad_terms_fail_at_construction() -> None:
    with pytest.raises(TypeError, match="LossTerm"):
        _tiny_dcp(loss_terms=[torch.nn.Linear(2, 2)])
    with pytest.raises(ValueError, match="distinct names"):
        _tiny_dcp(loss_terms=[_ScaleTerm(name="a"), _ScaleTerm(name="a")])
    with pytest.raises(ValueError, match="built for 64 features, the encoder has 32"):
        _tiny_dcp(loss_terms=[LocalConsistencyLoss(LocalConsistency(feature_dim=64))])
    with pytest.raises(ValueError, match="weight"):
        _ScaleTerm(weight=-1.0)
    with pytest.raises(ValueError, match="name"):
        _ScaleTerm(name="loss")


def test_components_are_not_hyperparameters() -> None:
    model = _tiny_dcp(loss_terms=[LocalConsistencyLoss()], refiner=ICP(), lr_scheduler=None)
    assert {"emb_dims", "k"} <= set(model.hparams)
    assert not {"loss_terms", "refiner", "optimizer", "lr_scheduler"} & set(model.hparams)


# --- the mixin, for LightningModules written outside lcreg -------------------------------------------------------
class _UserNet(LightningModule):
    def __init__(self) -> None:
        super().__init__()
        self.encoder = PointNetEncoder((16, 32))

    def training_step(self, batch: RegistrationBatch, batch_idx: int) -> torch.Tensor:
        return self.encoder(batch.points_src).pow(2).mean()


def _with_lc(cls: type) -> LightningModule:
    torch.manual_seed(0)
    net = cls()
    net.attach_local_consistency(LocalConsistency(num_local_points=16), 0.5)
    net.log = lambda *args, **kwargs: None  # no trainer attached
    return net


class _MixinFirst(LocalConsistencyMixin, _UserNet):
    pass


class _MixinSecond(_UserNet, LocalConsistencyMixin):
    pass


class _SubclassCallingSuper(_MixinSecond):
    def training_step(self, batch: RegistrationBatch, batch_idx: int) -> torch.Tensor:
        return super().training_step(batch, batch_idx)


@pytest.mark.parametrize("cls", [_MixinFirst, _MixinSecond, _SubclassCallingSuper])
def test_mixin_adds_lc_once_in_any_base_order(cls: type, batch: RegistrationBatch) -> None:
    # Regression: with the mixin second, LC was attached and never added to the loss.
    net = _with_lc(cls)
    plain = net.encoder(batch.points_src).pow(2).mean()
    lc = net.local_consistency_loss(batch)
    torch.testing.assert_close(net.training_step(batch, 0), plain + 0.5 * lc)


def test_mixin_refuses_lcreg_models_at_class_creation() -> None:
    with pytest.raises(TypeError, match="injected loss term"):

        class _Wrong(RegistrationModule, LocalConsistencyMixin):  # the order that silently dropped LC
            pass


def test_self_motion_pairs_are_two_samplings_related_by_the_generated_motion() -> None:
    from lcreg.geometry import se3
    from lcreg.models.loss_terms import SelfMotionLoss

    points, _, _ = synthetic_shapes(3, 200, seed=1)
    clouds = torch.tensor(points, dtype=torch.float64)
    term = SelfMotionLoss(sample_fraction=0.5, max_angle_deg=30.0, max_translation=0.2)
    torch.manual_seed(0)
    src, ref, motion = term.make_pairs(clouds)
    assert src.shape == ref.shape == (3, 100, 3) and motion.shape == (3, 4, 4)
    back = se3.transform_points(se3.inverse(motion), ref)
    for cloud, a, b in zip(clouds, src, back, strict=True):
        # both samplings are subsets of the cloud without repeats, and differ from each other
        da, db = torch.cdist(a, cloud).min(1).values, torch.cdist(b, cloud).min(1).values
        assert float(da.max()) < 1e-6 and float(db.max()) < 1e-6
        assert len(torch.unique(a, dim=0)) == 100 and not torch.equal(a, b)
    angles = torch.rad2deg(torch.arccos(((motion[:, :3, :3].diagonal(dim1=1, dim2=2).sum(-1) - 1) / 2).clamp(-1, 1)))
    assert float(angles.max()) <= 30.0 * 3**0.5 and float(motion[:, :3, 3].abs().max()) <= 0.2


def test_self_motion_trains_through_the_solve_without_the_dataset_pose(batch: RegistrationBatch) -> None:
    import dataclasses

    from lcreg.models.dvds import DVDs
    from lcreg.models.loss_terms import SelfMotionLoss

    torch.manual_seed(0)
    model = DVDs(
        encoder_channels=(16, 32),
        lambda_recon=0,
        lambda_normal=0,
        lambda_global=0,
        loss_terms=[SelfMotionLoss(weight=2.0)],
        diagnostics_every_n_steps=0,
    ).train()
    unlabeled = dataclasses.replace(batch, transform_ref_src=None)
    losses = model.training_losses(model.training_forward(unlabeled), unlabeled)
    assert set(losses) == {"global", "self_motion", "loss"}
    torch.testing.assert_close(losses["loss"], 2.0 * losses["self_motion"])  # lambda_global = 0
    assert float(losses["self_motion"]) > 0
    losses["loss"].backward()
    grad = sum(float(p.grad.abs().sum()) for p in model.encoder.parameters() if p.grad is not None)
    assert grad > 0  # through the differentiable solve, although DVDs' own solve holds the estimate fixed
    assert not model.solver.differentiable


def test_self_motion_translation_weight_scales_only_the_translation_error(batch: RegistrationBatch) -> None:
    """The term is ``||R_e - I||^2 + w ||t_e||^2`` of the host's estimate against the generated motion."""
    from lcreg.geometry import se3
    from lcreg.models.dvds import DVDs
    from lcreg.models.loss_terms import SelfMotionLoss

    torch.manual_seed(0)
    model = DVDs(encoder_channels=(16, 32), lambda_recon=0, lambda_normal=0, diagnostics_every_n_steps=0).eval()
    values = {}
    for weight in (1.0, 25.0):
        torch.manual_seed(1)  # the same pairs and motions for both weights
        term = SelfMotionLoss(translation_weight=weight)
        values[weight] = float(term(model, model(batch.points_src, batch.points_ref), batch))
    torch.manual_seed(1)
    src, ref, motion = SelfMotionLoss().make_pairs(batch.points_src)
    rot, trans = se3.split(se3.compose(model.differentiable_forward(src, ref).transform_ref_src, se3.inverse(motion)))
    rot_part = float((rot - torch.eye(3)).pow(2).sum((1, 2)).mean())
    trans_part = float(trans.pow(2).sum(-1).mean())
    assert values[1.0] == pytest.approx(rot_part + trans_part, rel=1e-4)
    assert values[25.0] == pytest.approx(rot_part + 25.0 * trans_part, rel=1e-4)
    assert trans_part > 1e-4 * rot_part  # the weight is seen


@pytest.mark.parametrize(
    "kwargs",
    [{"sample_fraction": 0.0}, {"sample_fraction": 1.5}, {"noise_std": -1.0}, {"translation_weight": -1.0}],
)
def test_self_motion_rejects_bad_settings(kwargs: dict[str, float]) -> None:
    from lcreg.models.loss_terms import SelfMotionLoss

    with pytest.raises(ValueError, match=next(iter(kwargs))):
        SelfMotionLoss(**kwargs)


def test_stationarity_term_is_the_pose_loss_of_one_update_from_the_generated_motion(batch: RegistrationBatch) -> None:
    """``SelfMotionStationarityLoss``: the same pairs as ``SelfMotionLoss``, scored after one ``step_from`` update
    started at the generated motion (0 where it is a fixed point: one sampling); it trains the encoder without the
    dataset pose, and a host without an IC-LK solve is refused when bound."""
    import dataclasses

    from lcreg.models.dvds import DVDs
    from lcreg.models.loss_terms import SelfMotionLoss, SelfMotionStationarityLoss
    from lcreg.nn.losses import weighted_pose_loss

    torch.manual_seed(0)
    term = SelfMotionStationarityLoss(weight=3.0, translation_weight=100.0)
    model = DVDs(encoder_channels=(16, 32), lambda_recon=0, lambda_normal=0, lambda_global=0, loss_terms=[term]).train()
    unlabeled = dataclasses.replace(batch, transform_ref_src=None)
    torch.manual_seed(1)
    losses = model.training_losses(model.training_forward(unlabeled), unlabeled)
    assert set(losses) == {"global", "self_motion_stationarity", "loss"}
    torch.testing.assert_close(losses["loss"], 3.0 * losses["self_motion_stationarity"])
    torch.manual_seed(1)
    src, ref, motion = SelfMotionLoss().make_pairs(batch.points_src)  # the pairs the term drew
    expected = weighted_pose_loss(model.step_from(src, ref, motion), motion, 100.0)
    torch.testing.assert_close(losses["self_motion_stationarity"], expected)
    assert float(expected) > 0  # two samplings: the motion is not a fixed point
    losses["loss"].backward()
    assert sum(float(p.grad.abs().sum()) for p in model.encoder.parameters() if p.grad is not None) > 0
    torch.manual_seed(2)
    one_sampling = SelfMotionStationarityLoss(sample_fraction=1.0)(model, None, batch)  # type: ignore[arg-type]
    assert float(one_sampling) < 1e-8
    with pytest.raises(TypeError, match="step_from"):
        _tiny_dcp(loss_terms=[SelfMotionStationarityLoss()])
