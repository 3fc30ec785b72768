"""The official 3DMatch recall: correspondence_rmse_sq against scipy and real correspondences, threedmatch_recall."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from lcreg.checks import ShapeError
from lcreg.data.io import read_points
from lcreg.data.pairlists import read_gt_info
from lcreg.data.threedmatch import fragment_path, read_gt_log
from lcreg.metrics.functional import correspondence_rmse_sq, threedmatch_recall

from _shared_data import shared_data  # type: ignore[import-not-found]


def _rigid(rotvec: np.ndarray, trans: np.ndarray) -> np.ndarray:
    matrix = np.eye(4)
    matrix[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    matrix[:3, 3] = trans
    return matrix


def _random_info(gen: np.random.Generator, num: int) -> np.ndarray:
    """Covariances shaped like gt.info: sum over points p of [I, -[p]x]^T [I, -[p]x] (coupled blocks)."""
    points = gen.normal(loc=[0.0, 0.0, 2.0], scale=0.7, size=(num, 200, 3))
    return np.stack([_point_info(p) for p in points])


def _point_info(points: np.ndarray) -> np.ndarray:
    skew = np.zeros((len(points), 3, 3))
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -points[:, 2], points[:, 1], -points[:, 0]
    skew -= skew.transpose(0, 2, 1)
    jac = np.concatenate([np.broadcast_to(np.eye(3), skew.shape), -skew], axis=2)  # (N, 3, 6)
    return np.einsum("nki,nkj->ij", jac, jac)


def _reference(pred: np.ndarray, gt: np.ndarray, info: np.ndarray) -> float:
    """The official formula with scipy (quaternions scalar-LAST there) and a general matrix inverse."""
    error = np.linalg.inv(gt) @ pred
    quat = Rotation.from_matrix(error[:3, :3]).as_quat()  # (x, y, z, w)
    quat = -quat if quat[3] < 0 else quat
    e = np.concatenate([error[:3, 3], quat[:3]])
    return float(e @ info @ e / info[0, 0])


def _random_case(num: int, seed: int, max_angle: float = math.pi) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    gen = np.random.default_rng(seed)
    gt = np.stack([_rigid(Rotation.random(random_state=seed + k).as_rotvec(), gen.normal(size=3)) for k in range(num)])
    axes = gen.normal(size=(num, 3))
    angles = gen.uniform(0, max_angle, num)
    pred = np.stack(
        [g @ _rigid(a / np.linalg.norm(a) * t, 0.2 * gen.normal(size=3)) for g, a, t in zip(gt, axes, angles)]
    )
    return pred, gt, _random_info(gen, num)


def test_matches_scipy_reference(dtype: torch.dtype) -> None:
    pred, gt, info = _random_case(40, seed=0)
    got = correspondence_rmse_sq(*(torch.tensor(a, dtype=dtype) for a in (pred, gt, info)))
    assert got.shape == (40,) and got.dtype == dtype
    expected = [_reference(p, g, i) for p, g, i in zip(pred, gt, info)]
    rtol = 1e-9 if dtype == torch.float64 else 1e-3
    np.testing.assert_allclose(got.double().numpy(), expected, rtol=rtol, atol=rtol * 1e-2)


@pytest.mark.parametrize("angle_deg", [0.0, 1e-4, 30.0, 120.0, 179.0, 179.999])
def test_all_angles_match_reference(angle_deg: float) -> None:
    gen = np.random.default_rng(1)
    axes = gen.normal(size=(8, 3))
    gt = np.stack([_rigid(np.zeros(3), np.zeros(3))] * 8)
    pred = np.stack([_rigid(a / np.linalg.norm(a) * math.radians(angle_deg), np.zeros(3)) for a in axes])
    info = _random_info(gen, 8)
    got = correspondence_rmse_sq(torch.tensor(pred), torch.tensor(gt), torch.tensor(info))
    expected = [_reference(p, g, i) for p, g, i in zip(pred, gt, info)]
    np.testing.assert_allclose(got.numpy(), expected, rtol=1e-8, atol=1e-15)


def test_identity_estimate_gives_zero(dtype: torch.dtype) -> None:
    _, gt, info = _random_case(5, seed=2)
    gt_t = torch.tensor(gt, dtype=dtype)
    got = correspondence_rmse_sq(gt_t, gt_t, torch.tensor(info, dtype=dtype))
    torch.testing.assert_close(got, torch.zeros(5, dtype=dtype), atol=1e-9 if dtype == torch.float64 else 1e-5, rtol=0)


def test_translation_error_is_exact() -> None:
    """E = [I, d]: p = d^T info[:3, :3] d / info[0, 0] = |d|^2 when info[:3, :3] = n I (as in every gt.info)."""
    gen = np.random.default_rng(3)
    gt = _rigid(gen.normal(size=3), gen.normal(size=3))
    offset = np.array([0.03, -0.04, 0.12])
    pred = gt @ _rigid(np.zeros(3), offset)
    got = correspondence_rmse_sq(*(torch.tensor(a)[None] for a in (pred, gt, _random_info(gen, 1)[0])))
    torch.testing.assert_close(got, torch.tensor([offset @ offset], dtype=torch.float64))


def test_equals_mean_displacement_of_the_linear_model() -> None:
    """With info = sum [I, -[p]x]^T [I, -[p]x], p = mean ||t_E + q.xyz x p||^2 (how gt.info is built, see below)."""
    gen = np.random.default_rng(4)
    points = gen.normal(loc=[0.2, -0.1, 1.5], scale=0.8, size=(500, 3))
    gt = _rigid(gen.normal(size=3), gen.normal(size=3))
    pred = gt @ _rigid(np.array([0.05, -0.02, 0.03]), np.array([0.01, 0.02, -0.05]))
    error = np.linalg.inv(gt) @ pred
    quat = Rotation.from_matrix(error[:3, :3]).as_quat()[:3]
    expected = np.mean(np.sum((error[:3, 3] + np.cross(quat, points)) ** 2, axis=1))
    got = correspondence_rmse_sq(*(torch.tensor(a)[None] for a in (pred, gt, _point_info(points))))
    torch.testing.assert_close(got, torch.tensor([expected], dtype=torch.float64))


def test_quaternion_sign_w_nonnegative_matters() -> None:
    """-q is the same rotation, but info couples t and q, so only the w >= 0 quaternion gives the official value."""
    gen = np.random.default_rng(5)
    gt = np.eye(4)
    pred = _rigid(np.array([0.0, 0.0, math.radians(150)]), np.array([0.3, 0.1, 0.0]))
    info = _random_info(gen, 1)[0]
    got = float(correspondence_rmse_sq(*(torch.tensor(a)[None] for a in (pred, gt, info)))[0])
    quat = Rotation.from_matrix(pred[:3, :3]).as_quat()
    assert quat[3] > 0
    flipped = np.concatenate([pred[:3, 3], -quat[:3]])
    assert got == pytest.approx(_reference(pred, gt, info), rel=1e-10)
    assert got != pytest.approx(float(flipped @ info @ flipped / info[0, 0]), rel=1e-3)
    decoupled = info.copy()
    decoupled[:3, 3:] = decoupled[3:, :3] = 0.0  # without the coupling the sign cancels in the quadratic form
    got_decoupled = correspondence_rmse_sq(*(torch.tensor(a)[None] for a in (pred, gt, decoupled)))
    assert float(got_decoupled[0]) == pytest.approx(float(flipped @ decoupled @ flipped / decoupled[0, 0]))


def test_batched_equals_per_item_loop(dtype: torch.dtype) -> None:
    pred, gt, info = (torch.tensor(a, dtype=dtype) for a in _random_case(12, seed=6))
    batched = correspondence_rmse_sq(pred, gt, info)
    looped = torch.cat([correspondence_rmse_sq(pred[k : k + 1], gt[k : k + 1], info[k : k + 1]) for k in range(12)])
    torch.testing.assert_close(batched, looped)


def test_info_dtype_is_cast_and_nonfinite_estimate_is_nan() -> None:
    pred, gt, info = _random_case(3, seed=7)
    pred_t = torch.tensor(pred, dtype=torch.float32)
    pred_t[1, 0, 0] = float("nan")
    got = correspondence_rmse_sq(pred_t, torch.tensor(gt, dtype=torch.float32), torch.tensor(info))
    assert got.dtype == torch.float32
    assert torch.isnan(got[1]) and torch.isfinite(got[[0, 2]]).all()


def test_rmse_input_errors() -> None:
    eye = torch.eye(4, dtype=torch.float64).expand(2, 4, 4)
    info = torch.eye(6, dtype=torch.float64).expand(2, 6, 6)
    with pytest.raises(ShapeError, match="`info` must have shape"):
        correspondence_rmse_sq(eye, eye, info[:1])
    with pytest.raises(ShapeError, match="`transform_gt`"):
        correspondence_rmse_sq(eye, eye[:, :3], info)
    with pytest.raises(TypeError, match="`info`"):
        correspondence_rmse_sq(eye, eye, info.numpy())  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"positive \[0, 0\].*\[1\]"):
        correspondence_rmse_sq(eye, eye, torch.stack([info[0], torch.zeros(6, 6, dtype=torch.float64)]))


# ----------------------------------------------------------------------------------------------------- recall


def test_recall_threshold_is_inclusive_and_nan_is_a_miss() -> None:
    rmse_sq = torch.tensor([0.0, 0.04, 0.0401, float("nan"), 1.0], dtype=torch.float64)
    scored = torch.tensor([True, True, True, True, False])
    assert float(threedmatch_recall(rmse_sq, scored)) == pytest.approx(0.5)
    assert float(threedmatch_recall(rmse_sq, torch.ones(5, dtype=torch.bool), threshold=1.0)) == pytest.approx(0.8)


def test_recall_ignores_unscored_pairs_and_is_nan_without_any() -> None:
    rmse_sq = torch.tensor([0.0, 9.0, 9.0])
    assert float(threedmatch_recall(rmse_sq, torch.tensor([True, False, False]))) == 1.0
    result = threedmatch_recall(rmse_sq, torch.zeros(3, dtype=torch.bool))
    assert result.dtype == torch.float32 and torch.isnan(result)


def test_recall_input_errors() -> None:
    rmse_sq = torch.zeros(3)
    with pytest.raises(ShapeError, match="`scored`"):
        threedmatch_recall(rmse_sq, torch.ones(2, dtype=torch.bool))
    with pytest.raises(TypeError, match="`scored` must be a bool"):
        threedmatch_recall(rmse_sq, torch.ones(3))
    with pytest.raises(TypeError, match="`rmse_sq`"):
        threedmatch_recall(torch.zeros(3, dtype=torch.int64), torch.ones(3, dtype=torch.bool))
    for bad in (0.0, -0.2, math.nan, math.inf):
        with pytest.raises(ValueError, match="threshold"):
            threedmatch_recall(rmse_sq, torch.ones(3, dtype=torch.bool), threshold=bad)


# ----------------------------------------------------------------------------------------------------- real data

_SCENE = "7-scenes-redkitchen"


def _real_pair(i: int, j: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Fragments i (reference) and j (source) of the 7-Scenes scene, the gt.log matrix and the gt.info block."""
    root = shared_data("3dmatch")
    scene_dir = root / "benchmarks" / "3DMatch" / _SCENE
    gt = read_gt_log(scene_dir / "gt.log").transforms[(i, j)]
    info = read_gt_info(scene_dir / "gt.info")[(i, j)]
    points_ref = read_points(fragment_path(root, _SCENE, i)).astype(np.float64)
    points_src = read_points(fragment_path(root, _SCENE, j)).astype(np.float64)
    return points_ref, points_src, gt, info


def _overlap_mask(points_ref: np.ndarray, points_src: np.ndarray, gt: np.ndarray, radius: float) -> np.ndarray:
    """Source points with a reference point within ``radius`` under the ground truth (the true correspondences)."""
    dist, _ = cKDTree(points_ref).query(points_src @ gt[:3, :3].T + gt[:3, 3], distance_upper_bound=radius)
    return np.isfinite(dist)


@pytest.mark.data
@pytest.mark.parametrize(("i", "j"), [(0, 2), (5, 9), (10, 14)])
def test_real_pairs_agree_with_exact_correspondence_rmse(i: int, j: int) -> None:
    """Exact squared RMSE of the source points that have a reference point within 3 cm, for perturbed estimates.

    Translation errors: equal (gt.info's translation block is n I). Rotation errors: same order of magnitude but
    lower (the covariance approximation weighs the half-angle q.xyz; measured 0.2-1.1 times the exact value).
    """
    points_ref, points_src, gt, info = _real_pair(i, j)
    corr = points_src[_overlap_mask(points_ref, points_src, gt, radius=0.03)]
    assert len(corr) > 1000
    gen = np.random.default_rng(10 * i + j)
    for kind in ("translation", "rotation", "both"):
        for size in (0.02, 0.05, 0.1):
            rotvec = gen.normal(size=3) * size / 2 if kind != "translation" else np.zeros(3)
            trans = gen.normal(size=3) * size / math.sqrt(3) if kind != "rotation" else np.zeros(3)
            delta = _rigid(rotvec, trans)  # the error E = T_gt^-1 T_pred, in the source frame
            exact = np.mean(np.sum((corr @ delta[:3, :3].T + delta[:3, 3] - corr) ** 2, axis=1))
            approx = float(correspondence_rmse_sq(*(torch.tensor(a)[None] for a in (gt @ delta, gt, info)))[0])
            if kind == "translation":
                assert approx == pytest.approx(exact, rel=1e-6)
            else:
                assert 0.1 * exact < approx < 2.0 * exact, (kind, size, approx, exact)


@pytest.mark.data
def test_real_info_is_the_point_covariance_in_the_reference_frame() -> None:
    """gt.info / n is close to the mean of [I, -[p]x]^T [I, -[p]x] over overlap points p in fragment i's frame."""
    points_ref, points_src, gt, info = _real_pair(0, 12)
    mapped = points_src @ gt[:3, :3].T + gt[:3, 3]
    corr = mapped[_overlap_mask(points_ref, points_src, gt, radius=0.03)]
    ours = _point_info(corr) / len(corr)
    official = info / info[0, 0]
    assert np.abs(ours - official).max() < 0.1 * np.abs(official).max()
    # An exact RMSE for e = [t, q.xyz] would need [I, -2[p]x] (q.xyz is half the rotation vector): a rotation block
    # 4 times larger. gt.info does not hold that one.
    rot_official, rot_ours = official[3:, 3:], ours[3:, 3:]
    assert np.abs(rot_official - rot_ours).max() < 0.25 * np.abs(rot_official - 4 * rot_ours).max()
