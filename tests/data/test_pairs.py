from __future__ import annotations

import math

import pytest
import torch

from lcreg.checks import ShapeError, TooFewPointsError
from lcreg.data import pairs
from lcreg.data.pairs import ANCHOR_DISTANCE, ObjectSet, PairProtocol, make_pair, true_correspondences
from lcreg.geometry.euler import euler_zyx_to_matrix
from lcreg.geometry.se3 import inverse, transform_points


def _object(num: int = 2048, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """An off-centre ellipsoid surface (not in the unit sphere) with its analytic normals."""
    g = torch.Generator().manual_seed(seed)
    u = torch.randn(num, 3, generator=g, dtype=torch.float64)
    u = u / u.norm(dim=-1, keepdim=True)
    axes = torch.tensor([2.0, 1.0, 0.5], dtype=torch.float64)
    points = u * axes + torch.tensor([3.0, -1.0, 0.5], dtype=torch.float64)
    normals = u / axes
    return points.float(), (3.0 * normals).float()  # normals deliberately not unit


def _normalized(points: torch.Tensor) -> torch.Tensor:
    centred = points.double() - points.double().mean(0)
    return centred / centred.norm(dim=-1).max()


def _row_match(a: torch.Tensor, b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Distance from each row of ``a`` to its nearest row of ``b`` and that row's index."""
    d = torch.cdist(a.double(), b.double())
    return d.min(dim=1)


def _ref_in_src_frame(pair: dict[str, torch.Tensor]) -> torch.Tensor:
    """The reference points mapped back by the inverse ground truth ``(K, 3)`` (float64)."""
    transform = pair["transform_ref_src"].double()[None]
    return transform_points(inverse(transform), pair["points_ref"].double()[None])[0]


def _pair(protocol: PairProtocol, seed: int = 0, with_normals: bool = True) -> dict[str, torch.Tensor]:
    points, normals = _object()
    return make_pair(points, normals if with_normals else None, protocol, torch.Generator().manual_seed(seed))


# ------------------------------------------------------------------------------------------------ protocol fields


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"num_points": 0}, "num_points"),
        ({"num_points": 1.5}, "num_points"),
        ({"max_angle_deg": -1.0}, "max_angle_deg"),
        ({"max_angle_deg": 270.0}, "max_angle_deg"),
        ({"max_translation": float("nan")}, "max_translation"),
        ({"noise_sigma": -0.1}, "noise_sigma"),
        ({"noise_clip": -0.1}, "noise_clip"),
        ({"partial": "random"}, "partial"),
        ({"partial": "prnet", "partial_keep": 0}, "partial_keep"),
        ({"partial": "prnet", "partial_keep": 1.5}, "partial_keep"),
        ({"partial": "prnet", "partial_keep": 0.0}, "partial_keep"),
        ({"partial": "prnet", "partial_keep": 2000}, "partial_keep"),
    ],
)
def test_protocol_rejects_bad_fields_naming_them(kwargs: dict, field: str) -> None:
    with pytest.raises(ValueError, match=field):
        PairProtocol(**kwargs)


def test_protocol_partial_keep_type_and_count() -> None:
    with pytest.raises(TypeError, match="partial_keep"):
        PairProtocol(partial_keep="768")  # type: ignore[arg-type]
    assert PairProtocol().num_kept == 1024  # no crop: partial_keep is ignored
    assert PairProtocol(num_points=512).num_kept == 512  # default keep 768 > 512 is fine without a crop
    assert PairProtocol(partial="prnet").num_kept == 768
    assert PairProtocol(partial="viewpoint", partial_keep=0.75).num_kept == 768
    assert PairProtocol(partial="prnet", partial_keep=1.0).num_kept == 1024


# ------------------------------------------------------------------------------------------------ make_pair


def test_output_keys_shapes_dtypes() -> None:
    points, normals = _object()
    pair = make_pair(points.double(), normals.double(), PairProtocol(), torch.Generator().manual_seed(0))
    assert set(pair) == {"points_src", "points_ref", "normals_src", "normals_ref", "transform_ref_src", "angles_zyx"}
    for key in ("points_src", "points_ref", "normals_src", "normals_ref"):
        assert pair[key].shape == (1024, 3)
    assert pair["transform_ref_src"].shape == (4, 4)
    assert pair["angles_zyx"].shape == (3,)
    assert all(t.dtype == torch.float32 and t.device.type == "cpu" for t in pair.values())
    no_normals = _pair(PairProtocol(), with_normals=False)
    assert "normals_src" not in no_normals and "normals_ref" not in no_normals


def test_angles_and_translations_follow_the_protocol() -> None:
    protocol = PairProtocol(num_points=64, max_angle_deg=45.0, max_translation=0.5)
    points, _ = _object(256)
    g = torch.Generator().manual_seed(1)
    pairs_ = [make_pair(points, None, protocol, g) for _ in range(300)]
    angles = torch.stack([p["angles_zyx"] for p in pairs_])
    transforms = torch.stack([p["transform_ref_src"] for p in pairs_])
    assert angles.min() >= 0 and angles.max() <= math.radians(45.0) + 1e-6
    assert angles.max() > math.radians(40.0) and angles.min() < math.radians(5.0)  # the range is covered
    trans = transforms[:, :3, 3]
    assert trans.abs().max() <= 0.5 + 1e-6 and trans.min() < -0.4 and trans.max() > 0.4
    torch.testing.assert_close(euler_zyx_to_matrix(angles.double()).float(), transforms[:, :3, :3], atol=1e-6, rtol=0)
    torch.testing.assert_close(transforms[:, 3], torch.tensor([0.0, 0, 0, 1]).expand(300, 4))


def test_ground_truth_maps_second_sampling_exactly() -> None:
    points, _ = _object()
    obj = _normalized(points)
    pair = _pair(PairProtocol())
    ref_in_src = _ref_in_src_frame(pair)
    dist_ref, idx_ref = _row_match(ref_in_src, obj)
    dist_src, idx_src = _row_match(pair["points_src"], obj)
    assert dist_ref.max() < 1e-5 and dist_src.max() < 1e-6  # every point is an object point (normalized frame)
    assert idx_ref.unique().numel() == 1024 and idx_src.unique().numel() == 1024  # without replacement
    # Independent samplings: a different subset, overlapping about N/P = half.
    common = torch.isin(idx_src, idx_ref).sum().item()
    assert 300 < common < 800


def test_same_points_when_not_independent() -> None:
    points, _ = _object()
    obj = _normalized(points)
    pair = _pair(PairProtocol(independent_sampling=False))
    ref_in_src = _ref_in_src_frame(pair)
    _, idx_ref = _row_match(ref_in_src, obj)
    _, idx_src = _row_match(pair["points_src"], obj)
    assert torch.equal(idx_src.sort().values, idx_ref.sort().values)  # identical sets
    assert not torch.equal(idx_src, idx_ref)  # in another order


def test_normalization_into_unit_sphere_and_off_switch() -> None:
    pair = _pair(PairProtocol(independent_sampling=False))
    assert pair["points_src"].norm(dim=-1).max() <= 1.0 + 1e-6
    points, _ = _object()
    raw = make_pair(points, None, PairProtocol(normalize=False), torch.Generator().manual_seed(0))
    dist, _ = _row_match(raw["points_src"], points)
    assert dist.max() < 1e-6  # raw coordinates kept


def test_normals_follow_the_transform_and_are_unit() -> None:
    points, normals = _object()
    pair = _pair(PairProtocol())
    rot = pair["transform_ref_src"][:3, :3].double()
    for key in ("normals_src", "normals_ref"):
        torch.testing.assert_close(pair[key].norm(dim=-1), torch.ones(1024), atol=1e-6, rtol=0)
    unit = normals.double() / normals.double().norm(dim=-1, keepdim=True)
    _, idx_src = _row_match(pair["points_src"], _normalized(points))
    torch.testing.assert_close(pair["normals_src"].double(), unit[idx_src], atol=1e-6, rtol=0)
    ref_in_src = _ref_in_src_frame(pair)
    _, idx_ref = _row_match(ref_in_src, _normalized(points))
    torch.testing.assert_close(pair["normals_ref"].double(), unit[idx_ref] @ rot.T, atol=1e-6, rtol=0)


def test_noise_is_independent_clipped_and_leaves_the_rest_unchanged() -> None:
    clean = _pair(PairProtocol(), seed=3)
    noisy = _pair(PairProtocol(noise_sigma=0.01, noise_clip=0.05), seed=3)
    torch.testing.assert_close(noisy["transform_ref_src"], clean["transform_ref_src"])
    torch.testing.assert_close(noisy["normals_ref"], clean["normals_ref"])
    noise_src = noisy["points_src"] - clean["points_src"]
    noise_ref = noisy["points_ref"] - clean["points_ref"]
    for noise in (noise_src, noise_ref):
        assert 0.008 < noise.std().item() < 0.012
        assert noise.abs().max() <= 0.05 + 1e-6
    correlation = torch.corrcoef(torch.stack([noise_src.flatten(), noise_ref.flatten()]))[0, 1]
    assert correlation.abs() < 0.1  # independent draws, not one shared noise

    clipped = _pair(PairProtocol(noise_sigma=0.05, noise_clip=0.02), seed=3)
    noise = clipped["points_src"] - clean["points_src"]
    assert noise.abs().max() <= 0.02 + 1e-6
    assert (noise.abs() > 0.02 - 1e-6).float().mean() > 0.5  # most values hit the clip


def test_prnet_crop_shares_the_anchor_and_keeps_nearest(monkeypatch: pytest.MonkeyPatch) -> None:
    anchors: list[torch.Tensor] = []
    original = pairs._crop_to_anchor

    def recording(points: torch.Tensor, anchor: torch.Tensor, keep: int) -> torch.Tensor:
        anchors.append(anchor.clone())
        return original(points, anchor, keep)

    monkeypatch.setattr(pairs, "_crop_to_anchor", recording)
    full = _pair(PairProtocol(partial="prnet", partial_keep=1024), seed=5)
    anchors.clear()
    part = _pair(PairProtocol(partial="prnet", partial_keep=768), seed=5)
    assert len(anchors) == 2 and torch.equal(anchors[0], anchors[1])  # one anchor for source and reference
    torch.testing.assert_close(anchors[0].norm(), torch.tensor(ANCHOR_DISTANCE, dtype=torch.float64))
    for key in ("points_src", "points_ref", "normals_src", "normals_ref"):
        assert part[key].shape == (768, 3)
    torch.testing.assert_close(part["transform_ref_src"], full["transform_ref_src"])
    for key in ("points_src", "points_ref"):
        # Same sampling (same seed, same draws); the kept points are the 768 nearest to the anchor.
        dist = (full[key].double() - anchors[0]).norm(dim=-1)
        nearest = dist.topk(768, largest=False).indices.sort().values
        torch.testing.assert_close(part[key], full[key][nearest])
    # Source and reference keep different regions of the object (partial overlap).
    points, _ = _object()
    _, idx_ref = _row_match(_ref_in_src_frame(part), _normalized(points))
    _, idx_src = _row_match(part["points_src"], _normalized(points))
    assert not torch.equal(idx_src.sort().values, idx_ref.sort().values)


def test_viewpoint_crop_keeps_the_count_with_independent_views(monkeypatch: pytest.MonkeyPatch) -> None:
    views: list[torch.Tensor] = []
    original = pairs._crop_to_view

    def recording(points: torch.Tensor, direction: torch.Tensor, keep: int) -> torch.Tensor:
        views.append(direction.clone())
        return original(points, direction, keep)

    monkeypatch.setattr(pairs, "_crop_to_view", recording)
    part = _pair(PairProtocol(partial="viewpoint", partial_keep=0.5), seed=2)
    assert part["points_src"].shape == (512, 3) and part["points_ref"].shape == (512, 3)
    assert len(views) == 2 and not torch.allclose(views[0], views[1])
    for view in views:
        torch.testing.assert_close(view.norm(), torch.tensor(1.0, dtype=torch.float64))
    # The kept source points are the half most visible towards the view: projections above the rest.
    assert (part["points_src"].double() @ views[0]).min() > -0.5


def test_same_generator_seed_gives_the_same_pair() -> None:
    protocol = PairProtocol(noise_sigma=0.01, partial="prnet")
    a, b = _pair(protocol, seed=11), _pair(protocol, seed=11)
    c = _pair(protocol, seed=12)
    for key in a:
        assert torch.equal(a[key], b[key])
    assert not torch.equal(a["points_src"], c["points_src"])


@pytest.mark.parametrize(
    "protocol",
    [
        PairProtocol(),
        PairProtocol(independent_sampling=False),
        PairProtocol(independent_sampling=False, partial="prnet", partial_keep=0.75),
        PairProtocol(partial="viewpoint", partial_keep=0.5),
    ],
    ids=["independent", "same_points", "prnet_crop", "viewpoint_crop"],
)
def test_indices_name_each_kept_points_object_row_and_change_nothing_else(protocol: PairProtocol) -> None:
    points, normals = _object()
    obj = _normalized(points)
    plain = make_pair(points, normals, protocol, torch.Generator().manual_seed(3))
    pair = make_pair(points, normals, protocol, torch.Generator().manual_seed(3), with_indices=True)
    assert set(pair) - set(plain) == {"point_index_src", "point_index_ref"}
    assert all(torch.equal(plain[key], pair[key]) for key in plain)  # the same draws, the same pair
    assert pair["point_index_src"].dtype == torch.int64 and pair["point_index_src"].shape == (protocol.num_kept,)
    assert torch.allclose(pair["points_src"].double(), obj[pair["point_index_src"]], atol=1e-6)
    assert torch.allclose(_ref_in_src_frame(pair), obj[pair["point_index_ref"]], atol=1e-5)


def test_true_correspondences_against_a_brute_force_loop() -> None:
    protocol = PairProtocol(independent_sampling=False, partial="prnet", partial_keep=0.75, noise_sigma=0.01)
    points, _ = _object()
    pair = make_pair(points, None, protocol, torch.Generator().manual_seed(5), with_indices=True)
    index_src, index_ref = pair["point_index_src"], pair["point_index_ref"]
    rows_src, rows_ref = true_correspondences(index_src, index_ref)
    expected = [(i, j) for i in range(len(index_src)) for j in range(len(index_ref)) if index_src[i] == index_ref[j]]
    assert list(zip(rows_src.tolist(), rows_ref.tolist())) == expected
    assert 0 < len(expected) < protocol.num_kept  # the crops overlap partly
    # The matched points are one object point up to the noise (clipped at 0.05 per coordinate on each cloud).
    gap = (pair["points_src"].double()[rows_src] - _ref_in_src_frame(pair)[rows_ref]).abs().max()
    assert 0 < gap <= 2 * protocol.noise_clip + 1e-5
    empty = true_correspondences(torch.tensor([0, 1]), torch.tensor([2, 3]))
    assert empty[0].numel() == empty[1].numel() == 0


def test_true_correspondences_rejects_bad_indices_naming_them() -> None:
    with pytest.raises(TypeError, match="index_src"):
        true_correspondences(torch.tensor([0.0, 1.0]), torch.tensor([0, 1]))
    with pytest.raises(ShapeError, match="index_ref"):
        true_correspondences(torch.tensor([0, 1]), torch.tensor([[0, 1]]))


def test_input_validation() -> None:
    points, normals = _object(512)
    g = torch.Generator().manual_seed(0)
    with pytest.raises(TooFewPointsError, match="512 points"):
        make_pair(points, None, PairProtocol(num_points=1024), g)
    with pytest.raises(ShapeError, match="points"):
        make_pair(points[None], None, PairProtocol(num_points=64), g)
    with pytest.raises(ShapeError, match="normals"):
        make_pair(points, normals[:100], PairProtocol(num_points=64), g)
    with pytest.raises(TypeError, match="points"):
        make_pair(points.numpy(), None, PairProtocol(num_points=64), g)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="identical"):
        make_pair(torch.ones(128, 3), None, PairProtocol(num_points=64), g)
    bad = points.clone()
    bad[3, 1] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        make_pair(bad, None, PairProtocol(num_points=64), g)


def test_object_set_validates_and_subsets() -> None:
    points = torch.rand(5, 32, 3).numpy()
    labels = torch.arange(5).numpy()
    objects = ObjectSet(points, None, labels)
    assert len(objects.subset(labels >= 2)) == 3
    assert len(ObjectSet.concatenate([objects, objects])) == 10
    with pytest.raises(ShapeError, match="labels"):
        ObjectSet(points, None, labels[:3])
    with pytest.raises(ShapeError, match="normals"):
        ObjectSet(points, points[:, :4], labels)
