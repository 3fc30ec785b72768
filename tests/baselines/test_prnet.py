from __future__ import annotations

from pathlib import Path

import pytest
import torch
import yaml

from lcreg.baselines.prnet import (
    PRNet,
    TemperatureNet,
    sample_correspondences,
    select_keypoints,
)
from lcreg.geometry import se3
from lcreg.geometry.random_transforms import random_rotation
from lcreg.models.loss_terms import LossTerm
from lcreg.nn.losses import cycle_consistency_mse
from lcreg.types import RegistrationBatch, RegistrationResult

from _host_contract import (  # type: ignore[import-not-found]
    check_bad_inputs,
    check_forward_backward,
    check_local_consistency_gradient,
    check_rotation_equivariance,
    check_training_lowers_loss,
    lc_terms,
    tiny_batch,
)

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
EMB = 32


def _tiny(loss_terms: list[LossTerm] | None = None, **kwargs: object) -> PRNet:
    args: dict[str, object] = {"emb_dims": EMB, "k": 8, "num_heads": 4, "ff_dims": 64, "num_keypoints": 32}
    args.update(kwargs)
    return PRNet(loss_terms=loss_terms or [], **args)  # type: ignore[arg-type]


@pytest.fixture(scope="module")
def batch() -> RegistrationBatch:
    return tiny_batch(batch_size=3, num_points=64)


@pytest.fixture(scope="module")
def trained_forward(batch: RegistrationBatch) -> tuple[PRNet, RegistrationResult]:
    torch.manual_seed(0)
    model = _tiny().train()
    return model, model(batch.points_src, batch.points_ref)


# --- host contract -------------------------------------------------------------------------------------------------
def test_forward_backward(batch: RegistrationBatch) -> None:
    torch.manual_seed(0)
    result = check_forward_backward(_tiny, batch)
    assert (result.num_iters == 3).all() and result.converged.all()


def test_training_lowers_loss(batch: RegistrationBatch) -> None:
    check_training_lowers_loss(lambda: _tiny(num_iterations=2), batch, steps=6)


def test_without_batch_norm_the_trained_network_is_the_evaluated_one(batch: RegistrationBatch) -> None:
    """``batch_norm=False`` drops BatchNorm from the DGCNN and the TemperatureNet: with the deterministic softmax
    sampler a training-mode pass then equals the eval pass (with BatchNorm it does not). In float64: three iterations
    of float32 rounding reach 3e-4."""
    src, ref = batch.points_src.double(), batch.points_ref.double()
    for batch_norm in (True, False):
        torch.manual_seed(0)
        model = _tiny(sampler="softmax", batch_norm=batch_norm).double()
        assert any(isinstance(m, torch.nn.BatchNorm1d) for m in model.modules()) is batch_norm
        with torch.no_grad():
            trained = model.train()(src, ref).transform_ref_src
            evaluated = model.eval()(src, ref).transform_ref_src
        gap = float((trained - evaluated).abs().max())
        assert gap > 1e-2 if batch_norm else gap < 1e-9, (batch_norm, gap)
    check_training_lowers_loss(lambda: _tiny(num_iterations=2, batch_norm=False), batch, steps=6)
    encoder_only = _tiny(batch_norm=False, temperature_batch_norm=True)
    assert not any(isinstance(m, torch.nn.BatchNorm1d) for m in encoder_only.encoder.modules())
    assert any(isinstance(m, torch.nn.BatchNorm1d) for m in encoder_only.temperature_net.modules())


def test_local_consistency_gradient_reaches_the_dgcnn(batch: RegistrationBatch) -> None:
    check_local_consistency_gradient(_tiny, batch)


def test_bad_inputs_raise_typed_errors() -> None:
    check_bad_inputs(_tiny)


def test_min_points_covers_the_knn_graph_and_local_consistency() -> None:
    assert _tiny().min_points == 8
    assert _tiny(lc_terms(num_local_points=16)).min_points == 16


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [({"sampler": "hard"}, "sampler"), ({"num_keypoints": 2}, "num_keypoints"), ({"num_iterations": 0}, "iterations")],
)
def test_bad_arguments(kwargs: dict[str, object], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        _tiny(**kwargs)


# --- keypoints and temperature -------------------------------------------------------------------------------------
@pytest.mark.parametrize("num_keypoints", [5, 40])
def test_keypoints_are_the_largest_embedding_norms(num_keypoints: int) -> None:
    gen = torch.Generator().manual_seed(1)
    points, features = torch.randn(2, 12, 3, generator=gen), torch.randn(2, 12, 6, generator=gen)
    keypoints, keyfeatures, idx = select_keypoints(points, features, num_keypoints)
    k = min(num_keypoints, 12)
    assert keypoints.shape == (2, k, 3) and keyfeatures.shape == (2, k, 6)
    for b in range(2):
        norms = [float(torch.sqrt((features[b, i] ** 2).sum())) for i in range(12)]
        expected = sorted(range(12), key=lambda i: -norms[i])[:k]
        assert idx[b].tolist() == expected
        for j, i in enumerate(expected):
            assert torch.equal(keypoints[b, j], points[b, i]) and torch.equal(keyfeatures[b, j], features[b, i])


@pytest.mark.parametrize(("bias", "expected"), [(1e4, 100.0), (-5.0, 0.01), (3.0, 3.0)])
def test_temperature_is_clamped_to_the_factor_range(bias: float, expected: float) -> None:
    net = TemperatureNet(emb_dims=6, hidden=8, temp_factor=100.0).eval()
    linear = net.out[0]
    assert isinstance(linear, torch.nn.Linear)
    with torch.no_grad():
        linear.weight.zero_()
        linear.bias.fill_(bias)
    feat_src, feat_ref = torch.randn(2, 7, 6), torch.randn(2, 9, 6)
    temperature, disparity = net(feat_src, feat_ref)
    torch.testing.assert_close(temperature, torch.full((2,), expected))
    for b in range(2):
        torch.testing.assert_close(disparity[b], (feat_src[b].sum(0) / 7 - feat_ref[b].sum(0) / 9).abs())
    # Clamped outputs pass no gradient to the bias; an unclamped one passes exactly 1 per pair.
    temperature.sum().backward()
    assert linear.bias.grad is not None
    assert float(linear.bias.grad) == pytest.approx(2.0 if expected == 3.0 else 0.0)


# --- sampler -------------------------------------------------------------------------------------------------------
def test_hard_gumbel_samples_follow_the_softmax_of_the_scores_whatever_the_temperature() -> None:
    scores = torch.tensor([0.5, -1.0, 1.5, 0.0]).expand(1, 20000, 4).contiguous()
    gen = torch.Generator().manual_seed(0)
    sample = sample_correspondences(scores, torch.tensor([7.0]), "gumbel_softmax", generator=gen)
    assert set(sample.unique().tolist()) == {0.0, 1.0} and (sample.sum(-1) == 1).all()
    # Gumbel-max: P(argmax = j) = softmax(scores)_j, independent of tau.
    torch.testing.assert_close(sample.mean(1)[0], torch.softmax(scores[0, 0], -1), atol=0.015, rtol=0)


def test_gumbel_straight_through_gradient_is_that_of_the_relaxed_sample() -> None:
    scores = torch.randn(2, 5, 6, dtype=torch.float64, requires_grad=True)
    temperature = torch.tensor([0.5, 2.0], dtype=torch.float64)
    weights = torch.randn(2, 5, 6, dtype=torch.float64)
    sample = sample_correspondences(scores, temperature, generator=torch.Generator().manual_seed(3))
    (grad,) = torch.autograd.grad((weights * sample).sum(), scores)
    noise = -torch.empty_like(scores).exponential_(generator=torch.Generator().manual_seed(3)).log()
    relaxed = torch.softmax((scores + noise) / temperature[:, None, None], dim=-1)
    (expected,) = torch.autograd.grad((weights * relaxed).sum(), scores)
    torch.testing.assert_close(grad, expected)
    torch.testing.assert_close(sample.detach(), torch.nn.functional.one_hot(relaxed.argmax(-1), 6).double())


def test_softmax_and_deterministic_samplers() -> None:
    scores = torch.randn(2, 4, 5)
    temperature = torch.tensor([0.3, 4.0])
    soft = sample_correspondences(scores, temperature, "softmax")
    for b in range(2):
        torch.testing.assert_close(soft[b], torch.softmax(temperature[b] * scores[b], dim=-1))
    hard = sample_correspondences(scores, temperature, "gumbel_softmax", deterministic=True)
    assert torch.equal(hard.argmax(-1), scores.argmax(-1)) and torch.equal(hard.sum(-1), torch.ones(2, 4))


# --- head, iterations, losses --------------------------------------------------------------------------------------
@pytest.mark.parametrize("sampler", ["gumbel_softmax", "softmax"])
def test_head_is_rotation_equivariant_for_fixed_correspondences(sampler: str) -> None:
    model = _tiny(sampler=sampler).double().train()
    gen = torch.Generator().manual_seed(2)
    points_ref = torch.randn(2, 20, 3, generator=gen, dtype=torch.float64)
    points_src = torch.randn(2, 16, 3, generator=gen, dtype=torch.float64)
    feat_src = torch.randn(2, 16, EMB, generator=gen, dtype=torch.float64)
    feat_ref = torch.randn(2, 20, EMB, generator=gen, dtype=torch.float64)
    temperature = torch.tensor([0.7, 3.0], dtype=torch.float64)

    def estimate(src: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
        torch.manual_seed(5)  # the same Gumbel noise, hence the same correspondences
        return model.head(src, ref, feat_src, feat_ref, temperature)

    # 1e-6: the contract helper draws G in float32 (G^-1 = G^T then holds to ~1e-8); the head itself is exact.
    check_rotation_equivariance(estimate, points_src, points_ref, atol=1e-6)


def test_discounted_loss_equals_the_hand_assembled_sum(
    trained_forward: tuple[PRNet, RegistrationResult], batch: RegistrationBatch
) -> None:
    model, result = trained_forward
    losses = model.training_losses(result, batch)
    gt = batch.transform_ref_src
    assert gt is not None
    aux = result.aux
    eye = torch.eye(3)
    pose = alignment = cycle = 0.0
    for i in range(3):
        cum, ab, ba = aux["transform_cumulative"][:, i], aux["transform_ab"][:, i], aux["transform_ba"][:, i]
        rot_err = torch.einsum("bji,bjk->bik", cum[:, :3, :3], gt[:, :3, :3]) - eye
        pose += 0.9**i * (rot_err.pow(2).mean() + (cum[:, :3, 3] - gt[:, :3, 3]).pow(2).mean())
        alignment += 0.1 * 0.9**i * aux["feature_disparity"][:, i].mean()
        cyc_rot = torch.einsum("bij,bjk->bik", ab[:, :3, :3], ba[:, :3, :3]) - eye
        cyc_t = ab[:, :3, 3] + torch.einsum("bij,bj->bi", ab[:, :3, :3], ba[:, :3, 3])
        cycle += 0.1 * 0.9**i * (cyc_rot.pow(2).mean() + cyc_t.pow(2).mean())
    torch.testing.assert_close(losses["pose"], pose)
    torch.testing.assert_close(losses["feature_alignment"], alignment)
    torch.testing.assert_close(losses["cycle"], cycle)
    torch.testing.assert_close(losses["loss"], pose + alignment + cycle)


def test_cumulative_transform_composes_the_iterations(trained_forward: tuple[PRNet, RegistrationResult]) -> None:
    _, result = trained_forward
    ab, cumulative = result.aux["transform_ab"], result.aux["transform_cumulative"]
    assert ab.shape == (3, 3, 4, 4) and result.aux["temperature"].shape == (3, 3)
    expected = torch.eye(4).expand(3, 4, 4)
    for i in range(3):
        expected = ab[:, i] @ expected  # the latest estimate is applied last
        torch.testing.assert_close(cumulative[:, i], expected)
    torch.testing.assert_close(result.transform_ref_src, expected)
    assert result.transform_ref_src.requires_grad  # not detached between iterations


def test_each_iteration_registers_the_moved_source(batch: RegistrationBatch) -> None:
    torch.manual_seed(0)
    model = _tiny(deterministic_eval=True).eval()
    with torch.no_grad():
        result = model(batch.points_src, batch.points_ref)
        moved = se3.transform_points(result.aux["transform_cumulative"][:, 0], batch.points_src)
        ab, ba, _, _ = model.iteration(moved, batch.points_ref)
    torch.testing.assert_close(ab, result.aux["transform_ab"][:, 1], atol=1e-5, rtol=0)
    torch.testing.assert_close(ba, result.aux["transform_ba"][:, 1], atol=1e-5, rtol=0)


def test_cycle_loss_is_zero_exactly_for_inverse_estimates() -> None:
    gen = torch.Generator().manual_seed(4)
    rot = random_rotation(5, generator=gen, dtype=torch.float64)
    transform_ab = se3.make_transform(rot, torch.randn(5, 3, generator=gen, dtype=torch.float64))
    transform_ba = se3.inverse(transform_ab)
    assert float(cycle_consistency_mse(transform_ab, transform_ba)) < 1e-28
    # Upstream's translation term MSE(t_ab, -t_ba) is not zero for the same exact inverses.
    assert float((transform_ab[:, :3, 3] + transform_ba[:, :3, 3]).pow(2).mean()) > 1e-2
    perturbed = transform_ba.clone()
    perturbed[:, :3, 3] += 0.1
    assert float(cycle_consistency_mse(transform_ab, perturbed)) == pytest.approx(0.01, rel=1e-9)


def test_eval_sampling_is_seeded_or_deterministic(batch: RegistrationBatch) -> None:
    torch.manual_seed(0)
    model = _tiny()
    src, ref = batch.points_src[:2], batch.points_ref[:2]

    def run(seed: int) -> torch.Tensor:
        torch.manual_seed(seed)
        return model.register(src, ref).transform_ref_src

    torch.testing.assert_close(run(1), run(1))  # faithful default: Gumbel at test time, reproducible by seed
    assert not torch.allclose(run(1), run(2))
    model.deterministic_eval = True
    torch.testing.assert_close(run(1), run(2))


def test_configs_carry_the_original_hyperparameters() -> None:
    def load(name: str) -> dict:
        return yaml.safe_load((CONFIGS / name).read_text())

    plain = load("models/prnet.yaml")  # every composition is built in tests/test_method_configs.py
    model = plain["model"]["init_args"]
    assert plain["model"]["class_path"] == "lcreg.baselines.prnet.PRNet"
    assert model["optimizer"]["init_args"] == {"lr": 1e-3, "weight_decay": 1e-4}
    assert model["lr_scheduler"]["init_args"]["milestones"] == [30, 60, 80]
    assert (model["num_keypoints"], model["num_iterations"], model["sampler"]) == (512, 3, "gumbel_softmax")
    assert plain["trainer"]["max_epochs"] == 100  # batch 36: tests/test_method_configs.py::test_original_batch_sizes


def test_training_logs_the_temperature_the_gumbel_sampler_uses(tmp_path: Path) -> None:
    import csv

    from lightning.pytorch import Trainer
    from lightning.pytorch.loggers import CSVLogger

    from lcreg.data.datamodule import SyntheticDataModule

    torch.manual_seed(0)
    data = SyntheticDataModule(num_points=64, batch_size=2, num_train=4, num_val=2, num_test=2, points_per_shape=128)
    trainer = Trainer(
        max_steps=2,
        logger=CSVLogger(tmp_path, name="prnet"),
        log_every_n_steps=1,
        limit_val_batches=0,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        accelerator="cpu",
    )
    trainer.fit(_tiny(), datamodule=data)
    rows = list(csv.DictReader(next(tmp_path.rglob("metrics.csv")).open()))
    logged = [
        (float(r["train/temperature_min"]), float(r["train/temperature_mean"]))
        for r in rows
        if r.get("train/temperature_min")
    ]
    assert len(logged) == 2 and all(0.01 - 1e-6 <= low <= mean <= 100 for low, mean in logged)  # temp_factor 100
