from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from lcreg.data.scenes import ScenePair, ScenePairDataModule, ScenePairDataset
from lcreg.data.threedmatch import SevenScenesDataModule
from lcreg.geometry import se3

from _shared_data import shared_data


def _rigid(seed: int, angle_deg: float = 30.0, shift: float = 2.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    out = np.eye(4)
    out[:3, :3] = Rotation.from_rotvec(rng.normal(size=3) / np.sqrt(3) * np.deg2rad(angle_deg)).as_matrix()
    out[:3, 3] = rng.uniform(-shift, shift, size=3)
    return out


def _write_pair(tmp_path: Path, n: int = 300) -> ScenePair:
    """A 'scene' S; the reference file holds S, the source file holds M^-1 S (same order), GT = M."""
    rng = np.random.default_rng(0)
    scene = rng.uniform([0, 0, 0], [4, 3, 2.5], size=(n, 3))
    gt = _rigid(1)
    src = (scene - gt[:3, 3]) @ gt[:3, :3]  # M^-1 S
    np.save(tmp_path / "src.npy", src.astype(np.float32))
    np.save(tmp_path / "ref.npy", scene.astype(np.float32))
    return ScenePair(tmp_path / "src.npy", tmp_path / "ref.npy", gt, name="toy/0-1")


@pytest.mark.parametrize(("align", "center", "angle"), [(True, True, 45.0), (False, True, 45.0), (False, False, 0.0)])
def test_ground_truth_maps_every_source_point_onto_its_reference_point(
    tmp_path: Path, align: bool, center: bool, angle: float
) -> None:
    # num_points=None keeps the file order, so source point k and reference point k are the same scene point.
    pair = _write_pair(tmp_path)
    ds = ScenePairDataset(
        [pair], num_points=None, align=align, center=center, max_angle_deg=angle, max_translation=0.5 * bool(angle)
    )
    item = ds[0]
    mapped = se3.transform_points(item["transform_ref_src"][None].double(), item["points_src"][None].double())[0]
    torch.testing.assert_close(mapped, item["points_ref"].double(), atol=2e-5, rtol=0)
    if center:
        assert item["points_ref"].double().mean(0).norm() > 0  # displaced by the extra transform
    if not (align or center or angle):
        torch.testing.assert_close(item["transform_ref_src"].double(), torch.from_numpy(pair.transform_ref_src))


def test_aligned_pairs_have_the_protocol_displacement(tmp_path: Path) -> None:
    pair = _write_pair(tmp_path)
    ds = ScenePairDataset([pair] * 20, num_points=64, max_angle_deg=45.0, max_translation=0.5, seed=7)
    for i in range(len(ds)):
        gt = ds[i]["transform_ref_src"].double().numpy()
        angles = Rotation.from_matrix(gt[:3, :3]).as_euler("zyx", degrees=True)
        assert (angles > -1e-3).all() and (angles < 45 + 1e-3).all()
        assert np.abs(gt[:3, 3]).max() <= 0.5 + 1e-6


def test_items_are_deterministic_and_sampling_pads_small_clouds(tmp_path: Path) -> None:
    pair = _write_pair(tmp_path, n=100)
    ds = ScenePairDataset([pair, pair], num_points=150, seed=3)
    a, b = ds[1], ds[1]
    for key in a:
        torch.testing.assert_close(a[key], b[key], atol=0, rtol=0)
    assert not torch.equal(ds[0]["transform_ref_src"], a["transform_ref_src"])
    assert a["points_src"].shape == (150, 3)
    # Padding repeats points of the cloud: exactly 100 distinct rows.
    assert len(torch.unique(a["points_ref"], dim=0)) == 100


def test_bad_options_raise_named_errors(tmp_path: Path) -> None:
    pair = _write_pair(tmp_path)
    with pytest.raises(ValueError, match="pairs"):
        ScenePairDataset([])
    with pytest.raises(ValueError, match="num_points"):
        ScenePairDataset([pair], num_points=0)
    with pytest.raises(ValueError, match="voxel_size"):
        ScenePairDataset([pair], voxel_size=-1.0)
    with pytest.raises(ValueError, match="max_angle_deg"):
        ScenePairDataset([pair], max_angle_deg=-5.0)
    with pytest.raises(ValueError, match="batch_size"):
        ScenePairDataModule(num_points=None, batch_size=4)
    missing = ScenePair(tmp_path / "nope.ply", pair.path_ref, np.eye(4))
    with pytest.raises(FileNotFoundError, match=r"nope\.ply"):
        ScenePairDataset([missing])[0]


def test_seven_scenes_without_a_split_or_root_says_so(tmp_path: Path) -> None:
    dm = SevenScenesDataModule(str(tmp_path / "absent"))
    with pytest.raises(FileNotFoundError, match="absent"):
        dm.setup("test")
    with pytest.raises(ValueError, match="no train pairs"):
        SevenScenesDataModule(str(tmp_path)).setup("fit")


@pytest.mark.data
def test_seven_scenes_redkitchen_pairs_are_aligned_by_their_ground_truth() -> None:
    dm = SevenScenesDataModule(str(shared_data("3dmatch")), batch_size=4)
    dm.setup("test")
    ds = dm.datasets["test"]
    assert len(ds) == 52  # redkitchen pairs with more than 70 % overlap
    batch = next(iter(dm.test_dataloader()))
    assert batch.points_src.shape == (4, 2048, 3) and batch.transform_ref_src is not None
    mapped = se3.transform_points(batch.transform_ref_src, batch.points_src)
    for i in range(4):
        tree = cKDTree(batch.points_ref[i].numpy())
        aligned = np.median(tree.query(mapped[i].numpy())[0])
        raw = np.median(tree.query(batch.points_src[i].numpy())[0])
        assert aligned < 0.06 < raw, (aligned, raw)  # ~4 cm between two 2048-point samplings of a fragment


@pytest.mark.data
def test_seven_scenes_module_takes_any_3dmatch_scene() -> None:
    root = str(shared_data("3dmatch"))
    every = SevenScenesDataModule(root, test_scenes=None).pairs("test")
    assert len(every) == 197  # the eight 3DMatch test scenes, overlap > 0.7
    sun3d = SevenScenesDataModule(root, test_scenes=["sun3d-hotel_umd-maryland_hotel3"])
    sun3d.setup("test")
    assert len(sun3d.datasets["test"]) == 4 and sun3d.datasets["test"][0]["points_src"].shape == (2048, 3)
