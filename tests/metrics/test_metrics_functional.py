from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from lcreg.checks import ShapeError
from lcreg.metrics.functional import (
    euler_errors_deg,
    registration_recall,
    rotation_error_deg,
    translation_error,
    translation_errors,
)


def random_pairs(num: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    gen = np.random.default_rng(seed)
    pred, gt = np.tile(np.eye(4), (2, num, 1, 1))
    gt[:, :3, :3] = Rotation.from_euler("zyx", gen.uniform(0, math.radians(45), (num, 3))).as_matrix()
    perturbation = Rotation.from_rotvec(gen.normal(size=(num, 3)))
    pred[:, :3, :3] = (Rotation.from_matrix(gt[:, :3, :3]) * perturbation).as_matrix()
    gt[:, :3, 3] = gen.uniform(-0.5, 0.5, (num, 3))
    pred[:, :3, 3] = gt[:, :3, 3] + 0.1 * gen.normal(size=(num, 3))
    return pred, gt


def test_rotation_error_matches_scipy(dtype: torch.dtype) -> None:
    pred, gt = random_pairs(50)
    got = rotation_error_deg(torch.tensor(pred, dtype=dtype), torch.tensor(gt, dtype=dtype))
    assert got.shape == (50,) and got.dtype == dtype
    rel = Rotation.from_matrix(pred[:, :3, :3]).inv() * Rotation.from_matrix(gt[:, :3, :3])
    np.testing.assert_allclose(got.double().numpy(), np.degrees(rel.magnitude()), atol=1e-3)
    trace = np.einsum("bji,bji->b", pred[:, :3, :3], gt[:, :3, :3])
    arccos = np.degrees(np.arccos(np.clip((trace - 1) / 2, -1, 1)))
    np.testing.assert_allclose(got.double().numpy(), arccos, atol=1e-3)


@pytest.mark.parametrize("angle_deg", [0.0, 1e-3, 0.5, 90.0, 179.9, 180.0])
def test_rotation_error_exact_angles(dtype: torch.dtype, angle_deg: float) -> None:
    gt = torch.eye(4, dtype=dtype).expand(2, 4, 4).clone()
    axis = np.array([[1.0, 2.0, 2.0], [0.0, 0.0, 1.0]]) / np.array([[3.0], [1.0]])
    pred = gt.clone()
    pred[:, :3, :3] = torch.tensor(Rotation.from_rotvec(axis * math.radians(angle_deg)).as_matrix(), dtype=dtype)
    got = rotation_error_deg(pred, gt)
    # atan2 keeps float32 accurate to ~1e-5 degrees even at 1e-3 degrees, where arccos would be ~0.02 off.
    torch.testing.assert_close(got, torch.full((2,), angle_deg, dtype=dtype), atol=1e-4, rtol=1e-6)
    torch.testing.assert_close(rotation_error_deg(gt, pred), got)  # symmetric


def test_translation_errors_match_numpy(dtype: torch.dtype) -> None:
    pred, gt = random_pairs(20, seed=1)
    p, g = torch.tensor(pred, dtype=dtype), torch.tensor(gt, dtype=dtype)
    diff = pred[:, :3, 3] - gt[:, :3, 3]
    np.testing.assert_allclose(translation_errors(p, g).double().numpy(), diff, atol=1e-6)
    np.testing.assert_allclose(translation_error(p, g).double().numpy(), np.linalg.norm(diff, axis=1), atol=1e-6)


def test_euler_errors_match_scipy(dtype: torch.dtype) -> None:
    pred, gt = random_pairs(30, seed=2)
    got = euler_errors_deg(torch.tensor(pred, dtype=dtype), torch.tensor(gt, dtype=dtype))
    assert got.shape == (30, 3)
    expected = np.degrees(
        Rotation.from_matrix(pred[:, :3, :3]).as_euler("zyx") - Rotation.from_matrix(gt[:, :3, :3]).as_euler("zyx")
    )
    np.testing.assert_allclose(got.double().numpy(), expected, atol=1e-3)


def test_euler_errors_are_not_wrapped() -> None:
    gt = torch.eye(4, dtype=torch.float64)[None].repeat(2, 1, 1)
    pred = gt.clone()
    # z = 179 deg vs z = -179 deg: DCP reports 358, not the wrapped 2.
    gt[0, :3, :3] = torch.tensor(Rotation.from_euler("zyx", [-179, 0, 0], degrees=True).as_matrix())
    pred[0, :3, :3] = torch.tensor(Rotation.from_euler("zyx", [179, 0, 0], degrees=True).as_matrix())
    torch.testing.assert_close(euler_errors_deg(pred, gt)[0], torch.tensor([358.0, 0.0, 0.0], dtype=torch.float64))
    torch.testing.assert_close(euler_errors_deg(pred, gt)[1], torch.zeros(3, dtype=torch.float64))


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_nonfinite_prediction_gives_nan_errors_for_that_pair_only(bad: float) -> None:
    pred_np, gt_np = random_pairs(3, seed=3)
    pred, gt = torch.tensor(pred_np), torch.tensor(gt_np)
    pred[1, 0, 0] = bad
    for fn in (rotation_error_deg, translation_error, translation_errors, euler_errors_deg):
        err = fn(pred, gt)
        assert torch.isnan(err[1]).all(), fn.__name__
        assert torch.isfinite(err[[0, 2]]).all(), fn.__name__


def test_registration_recall() -> None:
    rot = torch.tensor([0.5, 1.9, 2.0, 0.1, float("nan"), 0.1])
    trans = torch.tensor([0.001, 0.009, 0.001, 0.02, 0.0, float("nan")])
    # Successes: pairs 0 and 1 only (2.0 is not < 2.0, 0.02 >= 0.01, NaN fails).
    torch.testing.assert_close(registration_recall(rot, trans, 2.0, 0.01), torch.tensor(2 / 6))
    torch.testing.assert_close(registration_recall(rot, trans, 5.0, 0.05), torch.tensor(4 / 6))
    assert registration_recall(rot.double(), trans.double(), 2.0, 0.01).dtype == torch.float64
    assert torch.isnan(registration_recall(torch.zeros(0), torch.zeros(0), 2.0, 0.01))


def test_errors() -> None:
    eye = torch.eye(4).expand(2, 4, 4)
    with pytest.raises(ShapeError, match="transform_gt"):
        rotation_error_deg(eye, torch.eye(4).expand(3, 4, 4))
    with pytest.raises(ShapeError, match="transform_pred"):
        translation_error(torch.eye(3).expand(2, 3, 3), eye)
    with pytest.raises(TypeError, match="transform_pred"):
        euler_errors_deg(eye.long(), eye)
    with pytest.raises(TypeError, match="transform_gt"):
        translation_errors(eye, eye.double())
    with pytest.raises(ShapeError, match="trans_err"):
        registration_recall(torch.zeros(3), torch.zeros(4), 2.0, 0.01)
