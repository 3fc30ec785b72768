from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from lcreg.checks import DatasetLayoutError
from lcreg.data.datamodule import ModelNet40DataModule
from lcreg.data.modelnet40 import load_modelnet40_h5, load_shape_names, modelnet40_objects
from lcreg.types import RegistrationBatch

from _shared_data import shared_data


def _write_layout(
    root: Path,
    labels: dict[str, np.ndarray],
    num_points: int = 64,
    normals: bool = True,
    prefix: str = "data/modelnet40_ply_hdf5_2048/",
) -> None:
    """A tiny dataset in the official layout: one h5 per split, list files with upstream-style entries."""
    root.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    for split, lab in labels.items():
        name = f"ply_data_{split}0.h5"
        with h5py.File(root / name, "w") as f:
            f["data"] = rng.normal(size=(len(lab), num_points, 3)).astype(np.float32)
            f["label"] = lab.astype(np.uint8)[:, None]
            if normals:
                f["normal"] = rng.normal(size=(len(lab), num_points, 3)).astype(np.float32)
        (root / f"{split}_files.txt").write_text(f"{prefix}{name}\n")


# ------------------------------------------------------------------------------------------------ written layouts


def test_reads_a_written_layout_resolving_entries_by_basename(tmp_path: Path) -> None:
    labels = {"train": np.array([0, 5, 25, 39, 19]), "test": np.array([1, 30, 2])}
    _write_layout(tmp_path, labels)
    points, normals, lab = load_modelnet40_h5(tmp_path, "train")
    assert points.shape == (5, 64, 3) and points.dtype == np.float32
    assert normals is not None and normals.shape == (5, 64, 3)
    assert lab.dtype == np.int64 and lab.tolist() == [0, 5, 25, 39, 19]
    assert load_shape_names(tmp_path) is None
    assert len(modelnet40_objects(tmp_path, "unseen_objects", "train")) == 3
    assert modelnet40_objects(tmp_path, "unseen_objects", "test").labels.tolist() == [1, 2]
    assert modelnet40_objects(tmp_path, "unseen_categories", "test", "test_split").labels.tolist() == [30]
    assert sorted(modelnet40_objects(tmp_path, "unseen_categories", "test", "all").labels.tolist()) == [25, 30, 39]


def test_missing_normals_give_none(tmp_path: Path) -> None:
    _write_layout(tmp_path, {"train": np.array([0, 1])}, normals=False, prefix="")
    assert load_modelnet40_h5(tmp_path, "train")[1] is None


def test_missing_root_names_the_path(tmp_path: Path) -> None:
    missing = tmp_path / "nowhere"
    with pytest.raises(FileNotFoundError, match=r"nowhere.*train_files\.txt"):
        load_modelnet40_h5(missing, "train")
    _write_layout(tmp_path, {"train": np.array([0])})
    with pytest.raises(FileNotFoundError, match=r"test_files\.txt"):
        load_modelnet40_h5(tmp_path, "test")
    (tmp_path / "test_files.txt").write_text("data/ply_data_test7.h5\n")
    with pytest.raises(FileNotFoundError, match=r"ply_data_test7\.h5"):
        load_modelnet40_h5(tmp_path, "test")
    with pytest.raises(ValueError, match="split"):
        load_modelnet40_h5(tmp_path, "val")  # type: ignore[arg-type]


def test_corrupt_and_malformed_files_name_the_path(tmp_path: Path) -> None:
    (tmp_path / "bad.h5").write_bytes(b"this is not an HDF5 file")
    (tmp_path / "train_files.txt").write_text("bad.h5\n")
    with pytest.raises(DatasetLayoutError, match=r"bad\.h5.*HDF5"):
        load_modelnet40_h5(tmp_path, "train")

    with h5py.File(tmp_path / "nolabel.h5", "w") as f:
        f["data"] = np.zeros((2, 16, 3), np.float32)
    (tmp_path / "train_files.txt").write_text("nolabel.h5\n")
    with pytest.raises(DatasetLayoutError, match=r"nolabel\.h5.*'label'"):
        load_modelnet40_h5(tmp_path, "train")

    with h5py.File(tmp_path / "flat.h5", "w") as f:
        f["data"] = np.zeros((2, 16), np.float32)
        f["label"] = np.zeros((2, 1), np.uint8)
    (tmp_path / "train_files.txt").write_text("flat.h5\n")
    with pytest.raises(DatasetLayoutError, match=r"flat\.h5.*'data'"):
        load_modelnet40_h5(tmp_path, "train")

    with h5py.File(tmp_path / "labels.h5", "w") as f:
        f["data"] = np.zeros((2, 16, 3), np.float32)
        f["label"] = np.zeros((3, 1), np.uint8)
    (tmp_path / "train_files.txt").write_text("labels.h5\n")
    with pytest.raises(DatasetLayoutError, match=r"labels\.h5.*'label'"):
        load_modelnet40_h5(tmp_path, "train")

    (tmp_path / "train_files.txt").write_text("\n")
    with pytest.raises(DatasetLayoutError, match="lists no h5 file"):
        load_modelnet40_h5(tmp_path, "train")


@pytest.mark.parametrize(
    ("kind", "message"),
    [
        ("nan", r"bad\.h5': objects at rows \[1, 3\] of 'data' hold NaN/Inf"),
        ("nan_normal", r"bad\.h5': objects at rows \[2\] of 'normal' hold NaN/Inf"),
        ("identical", r"bad\.h5': objects at rows \[0\] of 'data' have all their points identical"),
        ("too_few", r"bad\.h5': objects hold 2 point\(s\), registration needs at least 3"),
    ],
)
def test_unusable_objects_name_the_file_and_rows(tmp_path: Path, kind: str, message: str) -> None:
    """Before: a later `points` contains ... NaN/Inf (or a degenerate-cloud error) without the file or the row."""
    rng = np.random.default_rng(0)
    points = rng.normal(size=(4, 2 if kind == "too_few" else 16, 3)).astype(np.float32)
    normals = rng.normal(size=points.shape).astype(np.float32)
    if kind == "nan":
        points[1, 3, 0] = np.nan
        points[3, 0, 2] = np.inf
    elif kind == "nan_normal":
        normals[2, 5, 1] = np.nan
    elif kind == "identical":
        points[0] = 0.25
    with h5py.File(tmp_path / "bad.h5", "w") as f:
        f["data"], f["normal"], f["label"] = points, normals, np.zeros((4, 1), np.uint8)
    (tmp_path / "train_files.txt").write_text("bad.h5\n")
    with pytest.raises(DatasetLayoutError, match=message):
        load_modelnet40_h5(tmp_path, "train")


def test_datamodule_checks_root_in_setup_not_init(tmp_path: Path) -> None:
    dm = ModelNet40DataModule(root=str(tmp_path / "absent"), num_points=32)  # building a config needs no data
    with pytest.raises(FileNotFoundError, match="absent"):
        dm.setup("fit")
    with pytest.raises(ValueError, match="protocol"):
        ModelNet40DataModule(root=".", protocol="unseen")  # type: ignore[arg-type]


def test_datamodule_on_a_written_layout(tmp_path: Path) -> None:
    _write_layout(tmp_path, {"train": np.arange(40) % 20, "test": np.arange(10)})
    dm = ModelNet40DataModule(root=str(tmp_path), num_points=32, batch_size=4, val_fraction=0.25)
    dm.setup("fit")
    assert dm.train_set is not None and dm.val_set is not None
    assert (len(dm.train_set), len(dm.val_set)) == (30, 10)
    batch = next(iter(dm.train_dataloader()))
    assert isinstance(batch, RegistrationBatch) and batch.points_src.shape == (4, 32, 3)
    assert batch.normals_src is not None and batch.normals_src.shape == (4, 32, 3)


def test_pair_classes_name_each_pairs_object_by_shape_names(tmp_path: Path) -> None:
    """Pair ``i`` is a pair of object ``i % S``; its class is that object's line of ``shape_names.txt``."""
    test_labels = np.array([4, 1, 7])
    _write_layout(tmp_path, {"train": np.arange(40) % 20, "test": test_labels})
    dm = ModelNet40DataModule(root=str(tmp_path), num_points=32, val_fraction=0.25, val_pairs_per_object=2)
    dm.setup("test")
    assert dm.class_names() is None  # no shape_names.txt: the labels themselves
    assert dm.pair_classes("test", torch.tensor([2, 0])) == ["7", "4"]
    names = [f"class{k}" for k in range(40)]
    (tmp_path / "shape_names.txt").write_text("\n".join(names) + "\n")
    assert dm.pair_classes("test", torch.tensor([0, 1, 2])) == ["class4", "class1", "class7"]
    dm.setup("fit")
    assert dm.val_set is not None and dm.val_set.labels is not None and len(dm.val_set) == 20
    index = torch.arange(20)
    expected = [names[int(dm.val_set.labels[i % 10])] for i in range(20)]
    assert dm.pair_classes("val", index) == expected and expected[:10] == expected[10:]


@pytest.mark.parametrize(
    ("labels", "stage", "match"),
    [
        ({"train": np.array([3, 45, 7]), "test": np.arange(4)}, "fit", "1 label.*outside 0-39"),
        ({"train": np.zeros(0, dtype=int), "test": np.arange(4)}, "fit", "holds no objects"),
        ({"train": np.arange(20, 40), "test": np.arange(4)}, "fit", "train split has no objects"),
        ({"train": np.arange(40) % 20, "test": np.arange(20, 30)}, "test", "test split has no objects"),
    ],
    ids=["label_out_of_range", "zero_objects", "no_seen_category", "no_test_object"],
)
def test_empty_or_mislabelled_data_raises_instead_of_training_on_nothing(
    tmp_path: Path, labels: dict[str, np.ndarray], stage: str, match: str
) -> None:
    # Before (issue 14, defect 9): these gave empty or wrong splits and a run that trained/tested on nothing.
    _write_layout(tmp_path, labels)
    dm = ModelNet40DataModule(root=str(tmp_path), num_points=32, batch_size=4, val_fraction=0.25)
    with pytest.raises(DatasetLayoutError, match=match):
        dm.setup(stage)


def test_val_fraction_zero_is_refused_at_setup(tmp_path: Path) -> None:
    _write_layout(tmp_path, {"train": np.arange(40) % 20, "test": np.arange(10)})
    dm = ModelNet40DataModule(root=str(tmp_path), num_points=32, val_fraction=0.0)
    with pytest.raises(DatasetLayoutError, match=r"validation split has no objects \(val_fraction=0.0"):
        dm.setup("fit")


# ------------------------------------------------------------------------------------------------ real data


def test_shared_data_helper_skips_with_a_reason_when_absent() -> None:
    with pytest.raises(pytest.skip.Exception, match="not found at"):
        shared_data("no_such_dataset")


@pytest.mark.data
def test_real_modelnet40_mini_splits() -> None:
    root = shared_data("modelnet40_mini")
    points, normals, labels = load_modelnet40_h5(root, "train")
    assert points.shape == (849, 2048, 3) and normals is not None and normals.shape == (849, 2048, 3)
    assert labels.shape == (849,) and labels.dtype == np.int64 and labels.max() < 40
    names = load_shape_names(root)
    assert names is not None and len(names) == 40 and names[0] == "airplane"
    np.testing.assert_allclose(np.linalg.norm(normals[:4], axis=-1), 1.0, atol=1e-3)

    assert len(modelnet40_objects(root, "unseen_objects", "train")) == 783
    assert len(modelnet40_objects(root, "unseen_objects", "test")) == 164
    assert len(modelnet40_objects(root, "unseen_categories", "test", "all")) == 80
    assert len(modelnet40_objects(root, "unseen_categories", "test", "test_split")) == 14


@pytest.mark.data
@pytest.mark.parametrize(("protocol", "num_test"), [("unseen_objects", 164), ("unseen_categories", 80)])
def test_real_modelnet40_datamodule(protocol: str, num_test: int) -> None:
    root = shared_data("modelnet40_mini")
    dm = ModelNet40DataModule(root=str(root), protocol=protocol, batch_size=8)  # type: ignore[arg-type]
    dm.setup("fit")
    dm.setup("test")
    assert dm.train_set is not None and dm.val_set is not None and dm.test_set is not None
    assert len(dm.val_set) == round(0.1 * 783) == 78
    assert len(dm.train_set) == 783 - 78
    assert len(dm.test_set) == num_test
    batch = next(iter(dm.test_dataloader()))
    assert batch.points_src.shape == (8, 1024, 3) and batch.points_ref.shape == (8, 1024, 3)
    assert batch.transform_ref_src is not None and batch.transform_ref_src.shape == (8, 4, 4)
    assert batch.normals_ref is not None
    torch.testing.assert_close(batch.normals_ref.norm(dim=-1), torch.ones(8, 1024))
    assert batch.index is not None and batch.index.tolist() == list(range(8))
