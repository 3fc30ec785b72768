from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation
from torchmetrics import MetricCollection

from lcreg.checks import NonFiniteError
from lcreg.geometry.random_transforms import random_euler_transform
from lcreg.metrics.registration import (
    EulerRotationMAE,
    EulerRotationRMSE,
    NumFailed,
    PerPairErrors,
    PoseErrorClippedMean,
    RegistrationRecall,
    RotationErrorClippedMean,
    RotationErrorMean,
    RotationErrorMedian,
    TranslationErrorMean,
    TranslationMAE,
    TranslationRMSE,
    check_recall_thresholds,
    recall_key,
    registration_metrics,
)

KEYS = [
    "rmse_r_deg",
    "mae_r_deg",
    "rmse_t",
    "mae_t",
    "rre_mean_deg",
    "rre_median_deg",
    "rre_clip5_deg",
    "pose_clip_r2_t0p01",
    "rte_mean",
    "recall_r2_t0p01",
    "recall_r5_t0p05",
]


def transform(euler_zyx_deg: list[float], trans: list[float], dtype: torch.dtype = torch.float64) -> torch.Tensor:
    out = torch.eye(4, dtype=dtype)
    out[:3, :3] = torch.tensor(Rotation.from_euler("zyx", euler_zyx_deg, degrees=True).as_matrix(), dtype=dtype)
    out[:3, 3] = torch.tensor(trans, dtype=dtype)
    return out


@pytest.fixture
def hand_made() -> tuple[torch.Tensor, torch.Tensor]:
    """Three pairs with ground truth identity-rotation: Euler errors (10, 0, 0), (0, 0, -20), (0, 0, 0)."""
    gt = torch.stack([transform([0, 0, 0], [0.0, 0.0, 0.0])] * 3)
    pred = torch.stack(
        [
            transform([10, 0, 0], [0.1, 0.0, 0.0]),
            transform([0, 0, -20], [0.0, -0.2, 0.2]),
            transform([0, 0, 0], [0.0, 0.0, 0.005]),
        ]
    )
    return pred, gt


def test_hand_made_values(hand_made: tuple[torch.Tensor, torch.Tensor]) -> None:
    pred, gt = hand_made
    expected = {
        EulerRotationRMSE: math.sqrt((10**2 + 20**2) / 9),
        EulerRotationMAE: (10 + 20) / 9,
        TranslationRMSE: math.sqrt((0.1**2 + 0.2**2 + 0.2**2 + 0.005**2) / 9),
        TranslationMAE: (0.1 + 0.2 + 0.2 + 0.005) / 9,
        RotationErrorMean: (10 + 20 + 0) / 3,
        RotationErrorMedian: 10.0,
        TranslationErrorMean: (0.1 + math.sqrt(0.08) + 0.005) / 3,
        NumFailed: 0.0,
    }
    for cls, value in expected.items():
        metric = cls()
        metric.update(transform_pred=pred, transform_gt=gt)
        assert float(metric.compute()) == pytest.approx(value, rel=1e-9, abs=1e-12), cls.__name__
    recall = RegistrationRecall(rot_thr_deg=2.0, trans_thr=0.01)
    recall.update(pred, gt)
    assert float(recall.compute()) == pytest.approx(1 / 3)
    loose = RegistrationRecall(rot_thr_deg=15.0, trans_thr=0.15)
    loose.update(pred, gt)
    assert float(loose.compute()) == pytest.approx(2 / 3)


def test_median_of_even_count_averages_the_middle_pair() -> None:
    gt = torch.eye(4).expand(4, 4, 4)
    pred = torch.stack([transform([a, 0, 0], [0, 0, 0], torch.float32) for a in (1, 2, 4, 30)])
    metric = RotationErrorMedian()
    metric.update(pred, gt)
    assert float(metric.compute()) == pytest.approx(3.0, abs=1e-4)


def test_failure_policy(hand_made: tuple[torch.Tensor, torch.Tensor]) -> None:
    pred, gt = hand_made
    failed_pred = torch.full((1, 4, 4), float("nan"), dtype=torch.float64)
    failed_gt = transform([5, 5, 5], [0.3, -0.4, 0.0])[None]
    pred, gt = torch.cat([pred, failed_pred]), torch.cat([gt, failed_gt])
    collection = registration_metrics()
    collection.update(transform_pred=pred, transform_gt=gt)
    out = {k: float(v) for k, v in collection.compute().items()}
    # The failed pair: rotation 180 deg, Euler 180 deg per angle, translation ||t_gt|| = 0.5, components |t_gt|.
    assert out["rmse_r_deg"] == pytest.approx(math.sqrt((10**2 + 20**2 + 3 * 180**2) / 12))
    assert out["mae_r_deg"] == pytest.approx((10 + 20 + 3 * 180) / 12)
    assert out["rmse_t"] == pytest.approx(math.sqrt((0.1**2 + 0.08 + 0.005**2 + 0.3**2 + 0.4**2) / 12))
    assert out["mae_t"] == pytest.approx((0.1 + 0.4 + 0.005 + 0.7) / 12)
    assert out["rre_mean_deg"] == pytest.approx((10 + 20 + 180) / 4)
    assert out["rre_median_deg"] == pytest.approx(15.0)
    assert out["rre_clip5_deg"] == pytest.approx((0 + 5 + 5 + 5) / 4)  # the failure counts as the clip, 5 deg
    assert out["pose_clip_r2_t0p01"] == pytest.approx((0.5 + 2.5 + 2.5 + 2.5) / 4)  # the failure counts as the clip
    assert out["rte_mean"] == pytest.approx((0.1 + math.sqrt(0.08) + 0.005 + 0.5) / 4)
    assert out["recall_r2_t0p01"] == pytest.approx(1 / 4)  # the failure counts in the denominator
    assert all(math.isfinite(v) for v in out.values())

    num_failed, per_pair = NumFailed(), PerPairErrors()
    for metric in (num_failed, per_pair):
        metric.update(pred, gt)
    assert float(num_failed.compute()) == 1.0
    rot_err, trans_err, _ = per_pair.compute()
    assert rot_err.shape == trans_err.shape == (4,)
    assert torch.isnan(rot_err[3]) and torch.isnan(trans_err[3]) and torch.isfinite(rot_err[:3]).all()
    euler, components = per_pair.components()  # as the figures count them: the failure at 180 deg, |t_gt|
    assert euler.shape == components.shape == (4, 3)
    torch.testing.assert_close(euler[3], torch.full((3,), 180.0, dtype=euler.dtype))
    torch.testing.assert_close(components[3], torch.tensor([0.3, 0.4, 0.0], dtype=components.dtype))
    assert math.sqrt(float(euler.square().mean())) == pytest.approx(out["rmse_r_deg"])
    assert float(euler.abs().mean()) == pytest.approx(out["mae_r_deg"])
    assert math.sqrt(float(components.square().mean())) == pytest.approx(out["rmse_t"])
    assert float(components.abs().mean()) == pytest.approx(out["mae_t"])


def test_recall_counts_a_failure_even_with_tiny_ground_truth_translation() -> None:
    gt = torch.eye(4)[None]  # the no-motion error of a failure would be 0 here: recall must still fail it
    metric = RegistrationRecall(rot_thr_deg=360.0, trans_thr=1.0)
    metric.update(torch.full((1, 4, 4), float("nan")), gt)
    assert float(metric.compute()) == 0.0


def test_collection_keys_and_two_updates_equal_one(rng: torch.Generator) -> None:
    gt, _ = random_euler_transform(10, generator=rng)
    noise, _ = random_euler_transform(10, max_angle_deg=4.0, max_translation=0.03, generator=rng)
    pred = noise @ gt
    pred[7] = float("nan")
    split = registration_metrics("val/")
    split.update(transform_pred=pred[:6], transform_gt=gt[:6])
    split.update(transform_pred=pred[6:], transform_gt=gt[6:])
    whole = registration_metrics("val/")
    whole.update(transform_pred=pred, transform_gt=gt)
    out_split, out_whole = split.compute(), whole.compute()
    assert sorted(out_split) == sorted(f"val/{k}" for k in KEYS)
    for key in out_whole:
        torch.testing.assert_close(out_split[key], out_whole[key], msg=key)
        assert torch.isfinite(out_whole[key]), key
    assert 0 < float(out_whole["val/recall_r5_t0p05"]) < 1


def test_forward_reset_and_float64(hand_made: tuple[torch.Tensor, torch.Tensor]) -> None:
    pred, gt = hand_made
    metric = RotationErrorMean()
    batch_value = metric(pred, gt)  # forward returns the batch value and accumulates
    assert float(batch_value) == pytest.approx(10.0)
    metric.update(pred[:1], gt[:1])
    assert float(metric.compute()) == pytest.approx(40 / 4)
    metric.reset()
    metric.update(pred[1:2], gt[1:2])
    assert float(metric.compute()) == pytest.approx(20.0)


def test_compute_over_zero_pairs_raises_instead_of_nan() -> None:
    # Before (issue 14, defect 9): every summary metric returned NaN over zero pairs.
    from lcreg.metrics.registration import NoPairsError, PerPairErrors, registration_metrics

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # torchmetrics warns about compute() before update()
        for metric in (EulerRotationRMSE(), RotationErrorMedian(), RegistrationRecall(), TranslationMAE()):
            with pytest.raises(NoPairsError, match=type(metric).__name__):
                metric.compute()
        with pytest.raises(NoPairsError):
            registration_metrics("test/").compute()
        rot, trans, index = PerPairErrors().compute()
        assert rot.numel() == 0 and trans.numel() == 0 and index.numel() == 0


@pytest.mark.parametrize(
    "bad",
    [
        torch.diag(torch.tensor([2.0, 1.0, 1.0, 1.0])),  # scaling
        torch.diag(torch.tensor([-1.0, 1.0, 1.0, 1.0])),  # reflection
        torch.tensor([[1.0, 0.3, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]),  # shear
        torch.tensor([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0.5, 0, 0, 1]]),  # last row
    ],
)
def test_ground_truth_must_be_a_rigid_motion(bad: torch.Tensor) -> None:
    metric = RotationErrorMean()
    good, _ = random_euler_transform(3, generator=torch.Generator().manual_seed(0))
    metric.update(good, good)  # rotations pass (float32 drift is tolerated)
    batch = torch.cat([good, bad[None]])
    with pytest.raises(ValueError, match=r"`transform_gt` must hold rigid motions.*item\(s\) \[3\]"):
        metric.update(batch, batch)


def test_bad_inputs() -> None:
    eye = torch.eye(4)[None]
    metric = RotationErrorMean()
    with pytest.raises(NonFiniteError, match="transform_gt"):
        metric.update(eye, torch.full((1, 4, 4), float("nan")))
    with pytest.raises(ValueError, match="thresholds"):
        RegistrationRecall(rot_thr_deg=0.0)
    with pytest.raises(ValueError, match="thresholds"):
        RegistrationRecall(trans_thr=-1.0)


def test_compute_groups_share_state_without_changing_values(rng: torch.Generator) -> None:
    gt, _ = random_euler_transform(8, generator=rng)
    noise, _ = random_euler_transform(8, max_angle_deg=4.0, max_translation=0.03, generator=rng)
    grouped = registration_metrics()
    separate = MetricCollection(dict(registration_metrics().items(keep_base=True)), compute_groups=False)
    for collection in (grouped, separate):
        for _ in range(2):
            collection.update(transform_pred=noise @ gt, transform_gt=gt)
    assert len(grouped.compute_groups) == 1  # all metrics share one copy of the per-pair errors
    out_grouped, out_separate = grouped.compute(), separate.compute()
    for key in KEYS:
        torch.testing.assert_close(out_grouped[key], out_separate[key], msg=key)


def test_a_pair_seen_twice_counts_once_by_index() -> None:
    # DDP's DistributedSampler pads the evaluation set with repeats (5 pairs on 2 processes: pair 0 twice).
    transforms, _ = random_euler_transform(5, generator=torch.Generator().manual_seed(0))
    preds, _ = random_euler_transform(5, generator=torch.Generator().manual_seed(1))
    single, padded = registration_metrics(), registration_metrics()
    single.update(transform_pred=preds, transform_gt=transforms, index=torch.arange(5))
    rank0, rank1 = torch.tensor([0, 2, 4]), torch.tensor([1, 3, 0])
    for idx in (rank0, rank1):
        padded.update(transform_pred=preds[idx], transform_gt=transforms[idx], index=idx)
    want = {k: float(v) for k, v in single.compute().items()}
    assert {k: float(v) for k, v in padded.compute().items()} == pytest.approx(want, rel=1e-6)
    per_pair = PerPairErrors()
    for idx in (rank0, rank1):
        per_pair.update(transform_pred=preds[idx], transform_gt=transforms[idx], index=idx)
    rot, _, index = per_pair.compute()
    assert index.tolist() == [0, 2, 4, 1, 3] and len(rot) == 5
    one = PerPairErrors()
    one.update(transform_pred=preds[:1], transform_gt=transforms[:1], index=torch.tensor([3]))
    assert one.compute()[0].shape == ()  # torchmetrics squeezes a one-element result ...
    assert [t.shape for t in one.per_pair()] == [(1,), (1,), (1,)]  # ... per_pair keeps (P,)
    unindexed = registration_metrics()
    for idx in (rank0, rank1):
        unindexed.update(transform_pred=preds[idx], transform_gt=transforms[idx])
    assert float(unindexed.compute()["rre_mean_deg"]) != pytest.approx(want["rre_mean_deg"], rel=1e-6)  # 6 pairs


@pytest.mark.parametrize(
    ("rot", "trans", "key"),
    [
        (2.0, 0.01, "recall_r2_t0p01"),
        (5.0, 0.05, "recall_r5_t0p05"),
        (15.0, 0.3, "recall_r15_t0p3"),
        (5, 2, "recall_r5_t2"),
        (2.5, 1e-5, "recall_r2p5_t1e-05"),
    ],
)
def test_recall_key_writes_thresholds_like_the_standard_keys(rot: float, trans: float, key: str) -> None:
    assert recall_key(rot, trans) == key


def test_extra_recall_thresholds_add_keys_equal_to_the_functional_recall(rng: torch.Generator) -> None:
    from lcreg.metrics import functional

    gt, _ = random_euler_transform(64, generator=rng)
    noise, _ = random_euler_transform(64, max_angle_deg=10.0, max_translation=0.1, generator=rng)
    pred = noise @ gt
    collection = registration_metrics("test/", recall_thresholds=[[15, 0.3], (5.0, 0.05), (10.0, 0.25)])
    collection.update(transform_pred=pred, transform_gt=gt)
    out = collection.compute()
    assert sorted(out) == sorted([f"test/{k}" for k in KEYS] + ["test/recall_r15_t0p3", "test/recall_r10_t0p25"])
    rot, trans = functional.rotation_error_deg(pred, gt), functional.translation_error(pred, gt)
    for rot_thr, trans_thr in ((15.0, 0.3), (10.0, 0.25)):  # (5, 0.05) is a standard key: added once
        want = functional.registration_recall(rot, trans, rot_thr, trans_thr)
        assert 0 < float(want) < 1  # a recall that tells the thresholds apart
        torch.testing.assert_close(out[f"test/{recall_key(rot_thr, trans_thr)}"], want.float())


@pytest.mark.parametrize(
    "bad",
    [
        [[15.0]],
        [[15.0, 0.3, 1.0]],
        [[0.0, 0.3]],
        [[15.0, -0.3]],
        [[math.nan, 0.3]],
        [[15.0, math.inf]],
        [[True, 0.3]],
        [["15", 0.3]],
        [15.0, 0.3],
        "15,0.3",
        15.0,
    ],
)
def test_bad_recall_thresholds_are_a_value_error_naming_the_argument(bad: object) -> None:
    with pytest.raises(ValueError, match="`recall_thresholds`"):
        check_recall_thresholds(bad)
    with pytest.raises(ValueError, match="`recall_thresholds`"):
        registration_metrics(recall_thresholds=bad)  # type: ignore[arg-type]


def test_clipped_mean_matches_numpy_and_bounds_one_failure() -> None:
    gen = torch.Generator().manual_seed(0)
    angles = torch.rand(50, 3, generator=gen, dtype=torch.float64) * 8.0  # 0-8 deg per axis: some above the clip
    gt = torch.stack([transform([0, 0, 0], [0, 0, 0]) for _ in range(50)])
    pred = torch.stack([transform(a.tolist(), [0, 0, 0]) for a in angles])
    metric = RotationErrorClippedMean(clip_deg=5.0)
    metric.update(pred, gt)
    rre = np.degrees(Rotation.from_matrix(pred[:, :3, :3].numpy()).magnitude())
    assert float(metric.compute()) == pytest.approx(np.minimum(rre, 5.0).mean(), abs=1e-6)
    assert (rre > 5.0).any() and (rre < 5.0).any()
    # One failed pair moves the clipped mean by at most clip / pairs, the plain mean by far more.
    clipped, plain = RotationErrorClippedMean(clip_deg=5.0), RotationErrorMean()
    failed = torch.cat([pred, torch.full((1, 4, 4), float("nan"), dtype=torch.float64)])
    for metric in (clipped, plain):
        metric.update(failed, torch.cat([gt, gt[:1]]))
    assert float(clipped.compute()) - np.minimum(rre, 5.0).mean() * 50 / 51 == pytest.approx(5.0 / 51, abs=1e-6)
    assert float(plain.compute()) > rre.mean() + 3.0


@pytest.mark.parametrize("clip", [0.0, -1.0, float("nan"), float("inf"), True])
def test_clipped_mean_refuses_a_bad_clip(clip: float) -> None:
    with pytest.raises(ValueError, match="clip_deg"):
        RotationErrorClippedMean(clip_deg=clip)


def test_pose_clipped_mean_matches_numpy_and_is_below_one_exactly_within_the_recall() -> None:
    gen = torch.Generator().manual_seed(1)
    scale = torch.linspace(0.1, 2.5, 60, dtype=torch.float64)[:, None]  # pairs from well within to beyond the clip
    angles = torch.rand(60, 3, generator=gen, dtype=torch.float64) * 2.0 * scale
    trans = (torch.rand(60, 3, generator=gen, dtype=torch.float64) - 0.5) * 0.02 * scale
    gt = torch.stack([transform([0, 0, 0], [0, 0, 0]) for _ in range(60)])
    pred = torch.stack([transform(a.tolist(), t.tolist()) for a, t in zip(angles, trans, strict=True)])
    metric, recall = PoseErrorClippedMean(rot_unit_deg=2.0, trans_unit=0.01, clip=2.5), RegistrationRecall(2.0, 0.01)
    for m in (metric, recall):
        m.update(pred, gt)
    rre = np.degrees(Rotation.from_matrix(pred[:, :3, :3].numpy()).magnitude())
    rte = np.linalg.norm(trans.numpy(), axis=1)
    units = np.maximum(rre / 2.0, rte / 0.01)
    assert float(metric.compute()) == pytest.approx(np.minimum(units, 2.5).mean(), abs=1e-9)
    assert (units > 2.5).any() and (units < 1).any() and ((rte / 0.01 > rre / 2.0) & (units < 2.5)).any()
    assert float(recall.compute()) == pytest.approx((units < 1).mean())


@pytest.mark.parametrize("bad", [{"rot_unit_deg": 0.0}, {"trans_unit": -0.01}, {"clip": float("nan")}, {"clip": True}])
def test_pose_clipped_mean_refuses_bad_units_naming_them(bad: dict[str, float]) -> None:
    with pytest.raises(ValueError, match=f"`{next(iter(bad))}`"):
        PoseErrorClippedMean(**bad)
