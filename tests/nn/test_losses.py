from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from lcreg.geometry import se3, so3
from lcreg.nn.losses import lk_pose_loss, rotation_translation_mse, transform_mse, weighted_pose_loss


def _transforms(b: int, seed: int) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    rot = so3.exp(torch.randn(b, 3, generator=gen, dtype=torch.float64))
    return se3.make_transform(rot, torch.randn(b, 3, generator=gen, dtype=torch.float64))


def test_rotation_translation_mse_matches_hand_computation() -> None:
    pred, gt = _transforms(4, seed=0), _transforms(4, seed=1)
    p, g = pred.numpy(), gt.numpy()
    rot = sum(((p[i, :3, :3].T @ g[i, :3, :3] - np.eye(3)) ** 2).sum() for i in range(4)) / 36
    trans = sum(((p[i, :3, 3] - g[i, :3, 3]) ** 2).sum() for i in range(4)) / 12
    assert float(rotation_translation_mse(pred, gt)) == pytest.approx(rot + trans, rel=1e-12)


def test_rotation_part_is_a_function_of_the_relative_angle() -> None:
    """``||R^T R_gt - I||_F^2 = 4 (1 - cos theta)``, so the 9-element mean is ``4 (1 - cos theta) / 9``."""
    angle = 0.7
    axis = torch.tensor([[1.0, 2.0, -0.5]], dtype=torch.float64)
    rot = so3.exp(angle * axis / axis.norm())
    zero = torch.zeros(1, 3, dtype=torch.float64)
    gt = _transforms(1, seed=2)
    pred = se3.make_transform(gt[:, :3, :3] @ rot, gt[:, :3, 3] + torch.tensor([[0.3, 0.0, 0.0]], dtype=torch.float64))
    expected = 4 * (1 - math.cos(angle)) / 9 + 0.09 / 3
    assert float(rotation_translation_mse(pred, gt)) == pytest.approx(expected, rel=1e-12)
    same = se3.make_transform(rot, zero)
    assert float(rotation_translation_mse(same, same)) == pytest.approx(0.0, abs=1e-25)


def test_rotation_translation_mse_vanishes_only_at_the_ground_truth() -> None:
    gt = _transforms(3, seed=3)
    assert float(rotation_translation_mse(gt, gt.clone())) == pytest.approx(0.0, abs=1e-25)
    pred = gt.clone().requires_grad_(True)
    loss = rotation_translation_mse(pred, gt)
    (grad,) = torch.autograd.grad(loss, pred)
    torch.testing.assert_close(grad, torch.zeros_like(grad), atol=1e-12, rtol=0)  # a minimum
    assert float(rotation_translation_mse(_transforms(3, seed=4), gt)) > 1e-3


def test_transform_mse_matches_hand_computation() -> None:
    a, b = _transforms(3, seed=5), _transforms(3, seed=6)
    an, bn = a.numpy(), b.numpy()
    expected = np.mean([(an[i] @ bn[i] - np.eye(4)) ** 2 for i in range(3)])
    assert float(transform_mse(a, b)) == pytest.approx(expected, rel=1e-12)
    assert float(transform_mse(a, se3.inverse(a))) == pytest.approx(0.0, abs=1e-25)
    assert float(transform_mse(a, a)) > 1e-3


def test_losses_are_differentiable() -> None:
    xi = torch.randn(2, 6, generator=torch.Generator().manual_seed(7), dtype=torch.float64, requires_grad=True)
    gt = _transforms(2, seed=8)
    assert torch.autograd.gradcheck(lambda x: rotation_translation_mse(se3.exp(x), gt), (xi,))
    assert torch.autograd.gradcheck(lambda x: transform_mse(se3.exp(x), se3.inverse(gt)), (xi,))
    assert torch.autograd.gradcheck(lambda x: weighted_pose_loss(se3.exp(x), gt, 25.0), (xi,))


def test_weighted_pose_loss_against_numpy_and_lk_pose_loss() -> None:
    pred, gt = _transforms(4, seed=9), _transforms(4, seed=10)
    errors = [p @ np.linalg.inv(g) for p, g in zip(pred.numpy(), gt.numpy())]
    rot = np.mean([((e[:3, :3] - np.eye(3)) ** 2).sum() for e in errors])
    trans = np.mean([(e[:3, 3] ** 2).sum() for e in errors])
    for weight in (0.0, 1.0, 25.0):
        assert float(weighted_pose_loss(pred, gt, weight)) == pytest.approx(rot + weight * trans, rel=1e-12)
    assert float(weighted_pose_loss(pred, gt)) == pytest.approx(float(lk_pose_loss(pred, gt)), rel=1e-12)
    assert float(weighted_pose_loss(gt, gt.clone(), 25.0)) == pytest.approx(0.0, abs=1e-25)


def test_weighted_pose_loss_weighs_the_recall_thresholds_alike_near_25() -> None:
    """A 2 deg rotation error and a 0.01 translation error cost the same at ``w = 2 theta^2 / 0.01^2 = 24.4``."""
    gt = _transforms(1, seed=11)
    zero = torch.zeros(1, 3, dtype=torch.float64)
    turned = se3.make_transform(so3.exp(torch.tensor([[0.0, 0.0, math.radians(2.0)]], dtype=torch.float64)), zero)
    shifted = se3.make_transform(torch.eye(3, dtype=torch.float64)[None], zero + torch.tensor([0.01, 0.0, 0.0]))
    weight = 4 * (1 - math.cos(math.radians(2.0))) / 0.01**2
    assert 24.0 < weight < 25.0
    rot_cost = float(weighted_pose_loss(se3.compose(turned, gt), gt, weight))
    trans_cost = float(weighted_pose_loss(se3.compose(shifted, gt), gt, weight))
    assert rot_cost == pytest.approx(trans_cost, rel=1e-6)  # 1 - cos: cancellation at 2 deg
