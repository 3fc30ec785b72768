from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from lcreg.checks import DatasetLayoutError, NonFiniteError, ShapeError
from lcreg.data.scanobjectnn import (
    SCANOBJECTNN_CLASSES,
    VARIANT_SUFFIXES,
    ScanObjectNNDataModule,
    drop_background,
    load_scanobjectnn_h5,
    scanobjectnn_file,
    scanobjectnn_objects,
)
from lcreg.types import RegistrationBatch

P = 64  # points per object in the written files (2048 in the official ones)


def _write_file(path: Path, num_objects: int, seed: int, background: bool = True, mask: bool = True) -> dict:
    """One h5 file of the official layout: data (S, P, 3) float32, label (S,) int, mask (S, P) with -1 = background."""
    rng = np.random.default_rng(seed)
    points = rng.normal(size=(num_objects, P, 3)).astype(np.float32)
    labels = rng.integers(0, len(SCANOBJECTNN_CLASSES), size=num_objects)
    instance = rng.integers(0, 500, size=(num_objects, 1))  # object points carry an instance id (>= 0)
    masks = np.repeat(instance, P, axis=1)
    if background:
        for i in range(num_objects):
            num_bg = int(rng.integers(1, P // 2))  # every object of the bg folder has some background points
            masks[i, rng.choice(P, size=num_bg, replace=False)] = -1
    path.parent.mkdir(parents=True, exist_ok=True)
    with h5py.File(path, "w") as f:
        f["data"] = points
        f["label"] = labels.astype(np.int64)
        if mask:
            f["mask"] = masks
    return {"points": points, "labels": labels, "mask": masks}


def _write_dataset(root: Path, num_train: int = 20, num_test: int = 8) -> dict[tuple[str, bool, str], dict]:
    """``<root>/h5_files/{main_split,main_split_nobg}`` with variants OBJ and PB_T50_RS; returns the written arrays."""
    written = {}
    for i, (background, folder) in enumerate(((True, "main_split"), (False, "main_split_nobg"))):
        for j, variant in enumerate(("OBJ", "PB_T50_RS")):
            suffix = VARIANT_SUFFIXES[variant]
            for k, (split, prefix, num) in enumerate((("train", "training", num_train), ("test", "test", num_test))):
                path = root / "h5_files" / folder / f"{prefix}_objectdataset{suffix}.h5"
                written[split, background, variant] = _write_file(
                    path, num, seed=100 * i + 10 * j + k, background=background
                )
    return written


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    root = tmp_path_factory.mktemp("ScanObjectNN")
    return root, _write_dataset(root)


# ------------------------------------------------------------------------------------------------ reader


def test_class_names_follow_the_official_label_order() -> None:
    # hkust-vgd/scanobjectnn training_data/README.md FAQ 4: bag 0, bin 1, ..., toilet 14 (not alphabetical).
    assert len(SCANOBJECTNN_CLASSES) == 15 and len(set(SCANOBJECTNN_CLASSES)) == 15
    assert SCANOBJECTNN_CLASSES.index("bag") == 0 and SCANOBJECTNN_CLASSES.index("table") == 9
    assert SCANOBJECTNN_CLASSES.index("bed") == 10 and SCANOBJECTNN_CLASSES.index("toilet") == 14


@pytest.mark.parametrize("split", ["train", "test"])
@pytest.mark.parametrize("variant", ["OBJ", "PB_T50_RS"])
@pytest.mark.parametrize("background", [True, False])
def test_objects_read_back_exactly(dataset: tuple[Path, dict], split: str, variant: str, background: bool) -> None:
    root, written = dataset
    ref = written[split, background, variant]
    objs = scanobjectnn_objects(root, split, variant, background=background)  # type: ignore[arg-type]
    assert objs.points.dtype == np.float32 and objs.points.shape == ref["points"].shape
    assert objs.normals is None
    assert objs.labels.dtype == np.int64
    np.testing.assert_array_equal(objs.points, ref["points"])
    np.testing.assert_array_equal(objs.labels, ref["labels"])


def test_root_may_be_the_dataset_the_h5_files_or_the_split_folder(dataset: tuple[Path, dict]) -> None:
    root, _ = dataset
    expected = root / "h5_files" / "main_split_nobg" / "test_objectdataset_augmentedrot_scale75.h5"
    for given in (root, root / "h5_files", root / "h5_files" / "main_split_nobg"):
        assert scanobjectnn_file(given, "test", "PB_T50_RS", background=False) == expected
    with pytest.raises(FileNotFoundError, match=r"'main_split'.*background=True"):
        scanobjectnn_file(root / "h5_files" / "main_split_nobg", "test", "OBJ", background=True)


def test_background_flag_picks_the_background_free_folder(dataset: tuple[Path, dict]) -> None:
    root, written = dataset
    with_bg = scanobjectnn_objects(root, "train", "OBJ", background=True)
    no_bg = scanobjectnn_objects(root, "train", "OBJ", background=False)
    np.testing.assert_array_equal(no_bg.points, written["train", False, "OBJ"]["points"])
    assert not np.array_equal(with_bg.points, no_bg.points)
    _, _, mask = load_scanobjectnn_h5(scanobjectnn_file(root, "train", "OBJ", background=False))
    assert mask is not None and (mask != -1).all()


def test_drop_background_points_keeps_only_and_all_object_points(dataset: tuple[Path, dict]) -> None:
    root, written = dataset
    ref = written["test", True, "PB_T50_RS"]
    objs = scanobjectnn_objects(root, "test", "PB_T50_RS", background=True, drop_background_points=True, seed=3)
    assert objs.points.shape == ref["points"].shape
    np.testing.assert_array_equal(objs.labels, ref["labels"])
    for i in range(len(objs)):
        fg = ref["points"][i][ref["mask"][i] != -1]
        bg = ref["points"][i][ref["mask"][i] == -1]
        assert 0 < len(fg) < P and len(bg) > 0
        dist_fg = np.linalg.norm(objs.points[i][:, None] - fg[None], axis=-1)
        assert (dist_fg.min(axis=1) == 0).all(), "every returned point is an object point of that object"
        assert (dist_fg.min(axis=0) == 0).all(), "every object point is kept"
        np.testing.assert_array_equal(objs.points[i][: len(fg)], fg)  # object points first, in file order
    again = scanobjectnn_objects(root, "test", "PB_T50_RS", background=True, drop_background_points=True, seed=3)
    np.testing.assert_array_equal(again.points, objs.points)  # deterministic for a seed
    other = scanobjectnn_objects(root, "test", "PB_T50_RS", background=True, drop_background_points=True, seed=4)
    assert not np.array_equal(other.points, objs.points)


def test_drop_background_is_per_object_and_checks_its_inputs() -> None:
    rng = np.random.default_rng(0)
    points = rng.normal(size=(3, 10, 3)).astype(np.float32)
    mask = np.zeros((3, 10), dtype=np.int64)
    mask[:, :4] = -1
    full = drop_background(points, mask, seed=1)
    np.testing.assert_array_equal(drop_background(points[:2], mask[:2], seed=1), full[:2])  # per-object draws
    np.testing.assert_array_equal(full[:, :6], points[:, 4:])  # object points first, then repeats of them
    assert full.shape == points.shape
    for i in range(3):  # the 4 refills are rows of the 6 object points
        assert (np.abs(full[i, 6:, None] - points[i, None, 4:]).sum(-1).min(-1) == 0).all()
    mask[2] = -1
    with pytest.raises(DatasetLayoutError, match=r"'f\.h5'.*object 2 has no object point"):
        drop_background(points, mask, source="f.h5")
    with pytest.raises(ShapeError, match="mask"):
        drop_background(points, mask[:, :5])


def test_nobg_file_without_mask_counts_as_background_free(tmp_path: Path) -> None:
    ref = _write_file(tmp_path / "main_split_nobg" / "test_objectdataset.h5", 4, seed=0, background=False, mask=False)
    objs = scanobjectnn_objects(tmp_path, "test", background=False, drop_background_points=True)
    np.testing.assert_array_equal(objs.points, ref["points"])
    _write_file(tmp_path / "main_split" / "test_objectdataset.h5", 4, seed=0, mask=False)
    assert len(scanobjectnn_objects(tmp_path, "test")) == 4  # a mask is only needed to drop the background
    with pytest.raises(DatasetLayoutError, match=r"test_objectdataset\.h5.*'mask'"):
        scanobjectnn_objects(tmp_path, "test", background=True, drop_background_points=True)


# ------------------------------------------------------------------------------------------------ errors


def test_missing_root_and_missing_file_name_the_path(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match=r"nowhere.*'main_split'.*h5_files"):
        scanobjectnn_objects(tmp_path / "nowhere", "train")
    _write_file(tmp_path / "h5_files" / "main_split" / "training_objectdataset.h5", 2, seed=0)
    with pytest.raises(FileNotFoundError, match=r"test_objectdataset_augmentedrot\.h5.*does not exist"):
        scanobjectnn_objects(tmp_path, "test", "PB_T50_R")
    with pytest.raises(FileNotFoundError, match=r"'main_split_nobg'"):
        scanobjectnn_objects(tmp_path, "train", background=False)
    with pytest.raises(FileNotFoundError, match=r"absent\.h5"):
        load_scanobjectnn_h5(tmp_path / "absent.h5")
    with pytest.raises(ValueError, match="split"):
        scanobjectnn_objects(tmp_path, "val")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="variant"):
        scanobjectnn_objects(tmp_path, "train", "PB_T50")  # type: ignore[arg-type]


def _write_raw(path: Path, **arrays: np.ndarray) -> Path:
    with h5py.File(path, "w") as f:
        for key, value in arrays.items():
            f[key] = value
    return path


def test_corrupt_or_malformed_files_raise_layout_errors_naming_the_file(tmp_path: Path) -> None:
    pts, lab, msk = np.zeros((2, 8, 3), np.float32), np.array([0, 1]), np.zeros((2, 8), np.int64)
    corrupt = tmp_path / "corrupt.h5"
    corrupt.write_bytes(np.random.default_rng(0).bytes(4096))
    with pytest.raises(DatasetLayoutError, match=r"corrupt\.h5.*not a readable HDF5"):
        load_scanobjectnn_h5(corrupt)
    cases = {
        r"nolabel\.h5.*no key\(s\) \['label'\]": _write_raw(tmp_path / "nolabel.h5", data=pts, mask=msk),
        r"nodata\.h5.*no key\(s\) \['data'\]": _write_raw(tmp_path / "nodata.h5", label=lab),
        r"flat\.h5.*'data' has shape \(2, 8\)": _write_raw(tmp_path / "flat.h5", data=pts[..., 0], label=lab),
        r"count\.h5.*'label' has shape \(3,\)": _write_raw(tmp_path / "count.h5", data=pts, label=np.arange(3)),
        r"range\.h5.*'label'\[1\] = 15": _write_raw(tmp_path / "range.h5", data=pts, label=np.array([0, 15])),
        r"frac\.h5.*'label'\[0\]": _write_raw(tmp_path / "frac.h5", data=pts, label=np.array([0.5, 1.0])),
        r"mask\.h5.*'mask' has shape \(2, 7\)": _write_raw(tmp_path / "mask.h5", data=pts, label=lab, mask=msk[:, :7]),
    }
    for pattern, path in cases.items():
        with pytest.raises(DatasetLayoutError, match=pattern):
            load_scanobjectnn_h5(path)
    ok = _write_raw(tmp_path / "ok.h5", data=pts.astype(np.float64), label=lab[:, None].astype(np.uint8), mask=msk)
    points, labels, mask = load_scanobjectnn_h5(ok)
    assert points.dtype == np.float32 and labels.tolist() == [0, 1] and mask is not None and mask.shape == (2, 8)


def test_nan_points_raise_non_finite_error_naming_the_file(tmp_path: Path) -> None:
    path = tmp_path / "h5_files" / "main_split" / "test_objectdataset.h5"
    _write_file(path, 3, seed=0)
    with h5py.File(path, "r+") as f:
        data = f["data"][...]
        data[2, 5, 1] = np.nan
        f["data"][...] = data
    with pytest.raises(NonFiniteError, match=r"test_objectdataset\.h5.*object 2"):
        scanobjectnn_objects(tmp_path, "test")


# ------------------------------------------------------------------------------------------------ DataModule


def test_datamodule_checks_root_in_setup_not_init(tmp_path: Path) -> None:
    dm = ScanObjectNNDataModule(root=str(tmp_path / "absent"), variant="PB_T50_RS", num_points=16)
    with pytest.raises(FileNotFoundError, match="absent"):
        dm.setup("fit")
    with pytest.raises(ValueError, match="variant"):
        ScanObjectNNDataModule(root=".", variant="hardest")  # type: ignore[arg-type]
    defaults = ScanObjectNNDataModule(root=".").pair_protocol
    assert (defaults.num_points, defaults.max_angle_deg, defaults.max_translation) == (1024, 45.0, 0.5)
    assert defaults.normalize


def _module(root: Path, **kwargs: object) -> ScanObjectNNDataModule:
    options: dict = {"num_points": 32, "batch_size": 4, "val_fraction": 0.25, "seed": 7, **kwargs}
    return ScanObjectNNDataModule(root=str(root), variant="PB_T50_RS", **options)


def test_datamodule_splits_and_deterministic_pairs(dataset: tuple[Path, dict]) -> None:
    root, written = dataset
    first, second = _module(root), _module(root)
    for dm in (first, second):
        dm.setup("fit")
        dm.setup("test")
    assert first.train_set is not None and first.val_set is not None and first.test_set is not None
    assert (len(first.train_set), len(first.val_set), len(first.test_set)) == (15, 5, 8)
    # Train + val are the training file's objects, test the test file's.
    train_val = torch.cat([first.train_set.points, first.val_set.points])
    assert sorted(map(tuple, train_val[:, 0].tolist())) == sorted(
        map(tuple, written["train", True, "PB_T50_RS"]["points"][:, 0].tolist())
    )
    np.testing.assert_array_equal(first.test_set.points.numpy(), written["test", True, "PB_T50_RS"]["points"])
    for name in ("val_dataloader", "test_dataloader"):
        a, b = list(getattr(first, name)()), list(getattr(second, name)())
        assert len(a) == len(b) == 2
        for x, y in zip(a, b):
            assert torch.equal(x.points_src, y.points_src) and torch.equal(x.points_ref, y.points_ref)
            assert x.transform_ref_src is not None and y.transform_ref_src is not None
            assert torch.equal(x.transform_ref_src, y.transform_ref_src)
    batch = next(iter(first.train_dataloader()))
    assert isinstance(batch, RegistrationBatch)
    assert batch.points_src.shape == (4, 32, 3) and batch.points_ref.shape == (4, 32, 3)
    assert batch.transform_ref_src is not None and batch.transform_ref_src.shape == (4, 4, 4)
    assert batch.normals_src is None
    last = list(first.test_dataloader())[-1]
    assert last.points_src.shape == (4, 32, 3) and last.index is not None and last.index.tolist() == [4, 5, 6, 7]


def test_ground_truth_maps_source_to_reference_within_the_protocol(dataset: tuple[Path, dict]) -> None:
    root, _ = dataset
    dm = _module(root, independent_sampling=False, drop_background_points=True)
    dm.setup("test")
    assert dm.test_set is not None
    for i in range(len(dm.test_set)):
        pair = dm.test_set[i]
        angles = pair["angles_zyx"].double()
        assert (angles >= 0).all() and (angles <= np.radians(45.0) + 1e-6).all()
        transform = pair["transform_ref_src"].double()
        rot, t = transform[:3, :3], transform[:3, 3]
        assert t.abs().max() <= 0.5 + 1e-6
        np.testing.assert_allclose(transform[3].numpy(), [0, 0, 0, 1])
        np.testing.assert_allclose(rot.numpy(), Rotation.from_euler("zyx", angles.numpy()).as_matrix(), atol=1e-6)
        # Same points in another order (independent_sampling=False): R src + t is the reference as a set.
        mapped = pair["points_src"].double() @ rot.T + t
        dist = torch.cdist(mapped, pair["points_ref"].double())
        assert dist.min(dim=1).values.max() < 1e-5 and dist.min(dim=0).values.max() < 1e-5
        assert pair["points_src"].norm(dim=-1).max() <= 1 + 1e-6  # normalized into the unit sphere
