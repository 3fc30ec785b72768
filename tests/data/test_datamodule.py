from __future__ import annotations

from pathlib import Path

import lightning as L
import numpy as np
import pytest
import torch
from jsonargparse import ArgumentParser

from lcreg.checks import ShapeError
from lcreg.data.datamodule import (
    TRAIN_SUBSET_SEED_OFFSET,
    ModelNet40DataModule,
    PairDataModule,
    PairDataset,
    SyntheticDataModule,
)
from lcreg.data.pairs import ObjectSet, PairProtocol
from lcreg.data.synthetic import PRIMITIVES, synthetic_shapes
from lcreg.types import RegistrationBatch

PROTOCOL = PairProtocol(num_points=64)


@pytest.fixture(scope="module")
def shapes() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return synthetic_shapes(6, 128, seed=0)


def _small_module(**kwargs: object) -> SyntheticDataModule:
    options: dict = {"num_train": 12, "num_val": 4, "num_test": 6, "points_per_shape": 128, "num_points": 64}
    options.update(batch_size=4)
    options.update(kwargs)
    return SyntheticDataModule(**options)


# ------------------------------------------------------------------------------------------------ PairDataset


def _assert_same(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> None:
    assert a.keys() == b.keys()
    for key in a:
        assert torch.equal(a[key], b[key]), key


def test_deterministic_pairs_repeat_across_calls_and_instances(shapes: tuple) -> None:
    points, normals, _ = shapes
    ds = PairDataset(points, normals, PROTOCOL, deterministic=True, seed=7)
    twin = PairDataset(points.copy(), normals.copy(), PROTOCOL, deterministic=True, seed=7)
    torch.manual_seed(0)
    first = ds[2]
    torch.manual_seed(1)  # the global RNG does not matter
    _assert_same(first, ds[2])
    _assert_same(first, twin[2])
    assert first["index"].item() == 2 and first["index"].dtype == torch.int64
    assert not torch.equal(ds[3]["transform_ref_src"], first["transform_ref_src"])
    other_seed = PairDataset(points, normals, PROTOCOL, deterministic=True, seed=8)
    assert not torch.equal(other_seed[2]["transform_ref_src"], first["transform_ref_src"])
    _assert_same(ds[-1], ds[len(ds) - 1])
    with pytest.raises(IndexError):
        ds[len(ds)]


def test_item_with_indices_is_the_same_pair_with_its_object_rows(shapes: tuple) -> None:
    points, normals, _ = shapes
    ds = PairDataset(points, normals, PROTOCOL, deterministic=True, seed=7, pairs_per_object=2)
    for key in (2, 9, (3, 123)):
        pair, with_rows = ds[key], ds.item_with_indices(key)
        _assert_same(pair, {k: with_rows[k] for k in pair})
        rows = with_rows["point_index_src"]
        item = int(pair["index"]) % ds.num_objects
        assert rows.shape == (64,) and rows.unique().numel() == 64 and int(rows.max()) < points.shape[1]
        centred = torch.as_tensor(points[item]).double() - torch.as_tensor(points[item]).double().mean(0)
        expected = (centred / centred.norm(dim=-1).max())[rows]  # the normalized object's rows
        assert torch.allclose(pair["points_src"].double(), expected, atol=1e-6)
    with pytest.raises(IndexError):
        ds.item_with_indices(len(ds))


def test_object_points_are_the_whole_object_in_the_clean_source_s_frame(shapes: tuple) -> None:
    points, normals, _ = shapes
    partial = PairProtocol(num_points=64, partial="prnet", partial_keep=0.5)
    ds = PairDataset(points, normals, partial, deterministic=True, seed=7, pairs_per_object=2)
    for key in (2, 9):
        pair, whole = ds.item_with_indices(key), ds.object_points(key)
        assert whole.shape == (points.shape[1], 3) and whole.dtype == torch.float64
        assert whole.norm(dim=-1).max().item() == pytest.approx(1.0)
        assert torch.allclose(pair["points_src"].double(), whole[pair["point_index_src"]], atol=1e-6)
    raw = PairDataset(points, normals, PairProtocol(num_points=64, normalize=False), deterministic=True)
    assert torch.allclose(raw.object_points(1), torch.as_tensor(points[1]).double())
    with pytest.raises(IndexError):
        ds.object_points(len(ds))


def test_several_pairs_per_object_keep_the_first_pairs_and_add_new_ones(shapes: tuple) -> None:
    points, normals, _ = shapes
    one = PairDataset(points, normals, PROTOCOL, deterministic=True, seed=7)
    three = PairDataset(points, normals, PROTOCOL, deterministic=True, seed=7, pairs_per_object=3)
    assert (len(one), len(three), three.num_objects) == (6, 18, 6)
    for i in range(len(one)):  # the first S pairs are the one-pair-per-object pairs, unchanged
        _assert_same(one[i], three[i])
    objects = torch.as_tensor(points)
    for i in (0, 6, 12, 17):
        pair = three[i]
        assert pair["index"].item() == i
        # Each cloud is a sampling of object i % S (normalised copies: compare shapes after centring).
        src = pair["points_src"] - pair["points_src"].mean(0)
        dist = torch.cdist(src[None], (objects - objects.mean(1, keepdim=True)))  # (S, N, P) after broadcasting
        nearest = dist.min(-1).values.mean(-1)
        assert int(nearest.argmin()) == i % 6
    assert not torch.equal(three[0]["transform_ref_src"], three[6]["transform_ref_src"])  # new motion per pair
    _assert_same(three[-1], three[17])
    with pytest.raises(IndexError, match="18 pairs"):
        three[18]
    for bad in (0, -1, 2.5, True, "2"):
        with pytest.raises(ValueError, match="pairs_per_object"):
            PairDataset(points, normals, PROTOCOL, pairs_per_object=bad)  # type: ignore[arg-type]


def test_datamodule_draws_several_validation_pairs_per_object() -> None:
    dm = _small_module(val_pairs_per_object=3)
    dm.setup("fit")
    assert dm.val_set is not None and dm.train_set is not None
    assert (len(dm.val_set), dm.val_set.num_objects, len(dm.train_set)) == (12, 4, 12)
    batches = list(dm.val_dataloader())
    assert torch.equal(torch.cat([b.index for b in batches]), torch.arange(12))
    assert dm.hparams["val_pairs_per_object"] == 3
    with pytest.raises(ValueError, match="val_pairs_per_object"):
        _small_module(val_pairs_per_object=0)


def test_training_pairs_vary_but_follow_the_global_seed(shapes: tuple) -> None:
    points, normals, _ = shapes
    ds = PairDataset(points, normals, PROTOCOL, deterministic=False)
    torch.manual_seed(0)
    a, b = ds[0], ds[0]
    assert not torch.equal(a["transform_ref_src"], b["transform_ref_src"])
    torch.manual_seed(0)
    _assert_same(a, ds[0])  # seed_everything makes training reproducible


def test_dataset_validates_shapes() -> None:
    with pytest.raises(ShapeError, match="points"):
        PairDataset(np.zeros((4, 10)), None, PROTOCOL)
    with pytest.raises(ShapeError, match="normals"):
        PairDataset(np.zeros((4, 10, 3)), np.zeros((4, 9, 3)), PROTOCOL)
    with pytest.raises(ShapeError, match="labels"):
        PairDataset(np.zeros((4, 10, 3)), None, PROTOCOL, labels=np.zeros(3))


def test_object_labels_follow_the_pairs_objects(shapes: tuple) -> None:
    points, normals, labels = shapes
    ds = PairDataset.from_objects(ObjectSet(points, normals, labels), PROTOCOL, pairs_per_object=3)
    index = torch.tensor([0, 7, 17, 6])
    assert ds.object_labels(index).tolist() == [labels[0], labels[1], labels[5], labels[0]]
    assert PairDataset(points, normals, PROTOCOL).object_labels(index) is None
    dm = _small_module()
    dm.setup("test")
    assert dm.test_set is not None and dm.test_set.labels is not None
    kinds = dm.pair_classes("test", torch.arange(6))
    assert kinds == [dm.class_names()[int(k)] for k in dm.test_set.labels] and set(kinds) <= set(PRIMITIVES)


# ------------------------------------------------------------------------------------------------ DataModules


def test_synthetic_datamodule_loaders() -> None:
    dm = _small_module(partial="prnet", partial_keep=48)
    dm.setup("fit")
    dm.setup("test")
    assert dm.train_set is not None and dm.val_set is not None and dm.test_set is not None
    assert (len(dm.train_set), len(dm.val_set), len(dm.test_set)) == (12, 4, 6)
    loaders = {
        "train": dm.train_dataloader(),
        "val": dm.val_dataloader(),
        "test": dm.test_dataloader(),
        "predict": dm.predict_dataloader(),
    }
    for name, loader in loaders.items():
        batch = next(iter(loader))
        assert isinstance(batch, RegistrationBatch), name
        assert batch.points_src.shape == (4, 48, 3) and batch.points_ref.shape == (4, 48, 3)
        assert batch.transform_ref_src is not None and batch.transform_ref_src.shape == (4, 4, 4)
        assert batch.normals_src is not None and batch.normals_src.shape == (4, 48, 3)
        assert batch.points_src.dtype == torch.float32
    assert sum(len(b) for b in loaders["test"]) == 6  # evaluation keeps every pair
    assert [len(b) for b in loaders["train"]] == [4, 4, 4]  # 12 pairs: nothing dropped
    dm.batch_size = 5
    assert [len(b) for b in dm.train_dataloader()] == [5, 5]  # the incomplete last batch is dropped (BatchNorm)
    assert [len(b) for b in dm.test_dataloader()] == [5, 1]
    dm.batch_size = 32
    assert [len(b) for b in dm.train_dataloader()] == [12]  # fewer pairs than a batch: keep them
    dm.batch_size = 4
    first_val = [b.points_src for b in dm.val_dataloader()]
    again = [b.points_src for b in dm.val_dataloader()]
    assert all(torch.equal(x, y) for x, y in zip(first_val, again))  # same val pairs every epoch


def test_synthetic_test_shapes_differ_from_train_shapes() -> None:
    dm = _small_module(num_points=128, normalize=False)
    dm.setup(None)
    assert dm.train_set is not None and dm.val_set is not None and dm.test_set is not None
    train = torch.cat([dm.train_set.points, dm.val_set.points]).flatten(1)
    test = dm.test_set.points.flatten(1)
    assert torch.cdist(test, train).min() > 1e-3


def test_val_pairs_identical_with_workers() -> None:
    serial = _small_module()
    serial.setup("fit")
    parallel = _small_module(num_workers=2)
    parallel.setup("fit")
    loader = parallel.val_dataloader()
    assert loader.persistent_workers
    for a, b in zip(serial.val_dataloader(), loader):
        assert torch.equal(a.points_src, b.points_src) and torch.equal(a.points_ref, b.points_ref)


def test_val_carved_from_train_pool_deterministically() -> None:
    dm = ModelNet40DataModule(root=".", val_fraction=0.2, seed=3)
    points, normals, labels = synthetic_shapes(20, 16, seed=0)
    pool = ObjectSet(points, normals, labels)
    train, val = dm.split_train_val(pool)
    _, val2 = dm.split_train_val(pool)
    assert (len(train), len(val)) == (16, 4)
    np.testing.assert_array_equal(val.points, val2.points)
    assert np.isin(val.points[:, 0, 0], train.points[:, 0, 0]).sum() == 0  # disjoint


def test_datamodule_validates_and_records_hyperparameters() -> None:
    dm = _small_module(batch_size=3, noise_sigma=0.01)
    assert dm.hparams["batch_size"] == 3 and dm.hparams["num_train"] == 12 and dm.hparams["noise_sigma"] == 0.01
    assert dm.pair_protocol.noise_sigma == 0.01
    with pytest.raises(ValueError, match="val_fraction"):
        _small_module(val_fraction=1.0)
    with pytest.raises(ValueError, match="points_per_shape"):
        _small_module(num_points=256)
    with pytest.raises(ValueError, match="partial"):
        _small_module(partial="half")
    with pytest.raises(RuntimeError, match="setup"):
        _small_module().train_dataloader()
    with pytest.raises(NotImplementedError):
        PairDataModule().setup("fit")


@pytest.mark.parametrize("cls", [ModelNet40DataModule, SyntheticDataModule])
def test_jsonargparse_exposes_base_and_own_arguments(cls: type) -> None:
    parser = ArgumentParser(exit_on_error=False)
    parser.add_class_arguments(cls, "data")
    dests = {action.dest for action in parser._actions}
    own = "data.root" if cls is ModelNet40DataModule else "data.num_train"
    assert {"data.batch_size", "data.num_points", "data.partial_keep", "data.seed", own} <= dests
    args = ["--data.batch_size=8", "--data.partial=prnet", "--data.partial_keep=700", "--data.train_objects=0.5"]
    if cls is ModelNet40DataModule:
        args.append("--data.root=/somewhere")
    dm = parser.instantiate(parser.parse_args(args)).data
    assert isinstance(dm, cls)
    assert dm.batch_size == 8 and dm.pair_protocol.partial_keep == 700 and dm.pair_protocol.num_kept == 700
    assert dm.hparams["batch_size"] == 8 and dm.train_objects == 0.5


def _training_objects(dm: SyntheticDataModule) -> list[bytes]:
    dm.setup("fit")
    assert dm.train_set is not None
    return [points.numpy().tobytes() for points in dm.train_set.points]


def test_train_objects_trains_on_a_nested_seeded_subset_and_leaves_validation_and_test_alone() -> None:
    full = _small_module()
    every = _training_objects(full)
    half = _training_objects(_small_module(train_objects=0.5))
    quarter = _training_objects(_small_module(train_objects=3))
    assert (len(every), len(half), len(quarter)) == (12, 6, 3)
    assert set(quarter) < set(half) < set(every)  # one permutation per seed: the subsets are nested
    assert [obj for obj in every if obj in half] == half  # in their original order
    assert half == _training_objects(_small_module(train_objects=6))  # a fraction and its count agree
    assert half == _training_objects(_small_module(train_objects=0.5))  # seeded: the same subset every time
    assert half != _training_objects(_small_module(train_objects=0.5, seed=99))
    tiny = _training_objects(_small_module(train_objects=0.01))
    assert tiny == _training_objects(_small_module(train_objects=1)) and len(tiny) == 1  # at least one object
    subset = _small_module(train_objects=0.5)
    subset.setup()
    full.setup()
    assert subset.val_set is not None and full.val_set is not None and subset.test_set is not None
    assert torch.equal(subset.val_set.points, full.val_set.points)
    assert full.test_set is not None and torch.equal(subset.test_set.points, full.test_set.points)
    assert len(subset.train_dataloader()) == 6 // 4  # the loader trains on the subset (drop_last)


@pytest.mark.parametrize("value", [0, -2, 0.0, 1.0, 1.5, -0.5, True, "3"])
def test_train_objects_refuses_what_is_not_a_count_or_a_fraction(value: object) -> None:
    with pytest.raises(ValueError, match="`train_objects`"):
        _small_module(train_objects=value)


def test_train_objects_above_the_training_objects_is_an_error_naming_both() -> None:
    with pytest.raises(ValueError, match=r"`train_objects` \(13\) exceeds the 12 training objects"):
        _small_module(train_objects=13).setup("fit")


def _labelled_pool(labels: list[int]) -> ObjectSet:
    points = np.arange(len(labels), dtype=np.float32)[:, None, None] * np.ones((1, 4, 3), dtype=np.float32)
    return ObjectSet(points, None, np.asarray(labels, dtype=np.int64))


def test_train_class_cap_keeps_the_first_objects_of_each_label_in_the_seeded_order() -> None:
    labels = [0] * 6 + [1] * 3 + [2]
    pool = _labelled_pool(labels)
    kept = ModelNet40DataModule(root=".", train_class_cap=2, seed=5).keep_training_objects(pool)
    order = torch.randperm(10, generator=torch.Generator().manual_seed(5 + TRAIN_SUBSET_SEED_OFFSET)).tolist()
    expected = sorted([i for i in order if labels[i] == 0][:2] + [i for i in order if labels[i] == 1][:2] + [9])
    assert kept.points[:, 0, 0].astype(int).tolist() == expected  # original order, at most 2 per label
    assert sorted(kept.labels.tolist()) == [0, 0, 1, 1, 2]
    alone = ModelNet40DataModule(root=".", train_objects=4, seed=5).keep_training_objects(pool)
    assert alone.points[:, 0, 0].astype(int).tolist() == sorted(order[:4])  # without a cap: train_objects as before
    both = ModelNet40DataModule(root=".", train_class_cap=2, train_objects=3, seed=5).keep_training_objects(pool)
    assert set(both.points[:, 0, 0].astype(int).tolist()) < set(expected)  # drawn from what the cap kept
    with pytest.raises(ValueError, match=r"`train_objects` \(6\) exceeds the 5 training objects kept by"):
        ModelNet40DataModule(root=".", train_class_cap=2, train_objects=6).keep_training_objects(pool)


@pytest.mark.parametrize("value", [0, -1, 2.5, True, "3"])
def test_train_class_cap_refuses_what_is_not_a_count(value: object) -> None:
    with pytest.raises(ValueError, match="`train_class_cap` must be an integer >= 1"):
        ModelNet40DataModule(root=".", train_class_cap=value)  # type: ignore[arg-type]


class _TranslationModel(L.LightningModule):
    """Fits one translation to the pairs: just enough to drive the loaders through a Trainer."""

    def __init__(self) -> None:
        super().__init__()
        self.translation = torch.nn.Parameter(torch.zeros(3))

    def _loss(self, batch: RegistrationBatch) -> torch.Tensor:
        residual = batch.points_ref.mean(1) - batch.points_src.mean(1) - self.translation
        return residual.square().mean()

    def training_step(self, batch: RegistrationBatch, batch_idx: int) -> torch.Tensor:
        return self._loss(batch)

    def validation_step(self, batch: RegistrationBatch, batch_idx: int) -> None:
        self.log("val/loss", self._loss(batch), batch_size=len(batch))

    def test_step(self, batch: RegistrationBatch, batch_idx: int) -> None:
        self.log("test/loss", self._loss(batch), batch_size=len(batch))

    def configure_optimizers(self) -> torch.optim.Optimizer:
        return torch.optim.SGD(self.parameters(), lr=0.1)


def test_trainer_fast_dev_run() -> None:
    dm = _small_module()
    trainer = L.Trainer(fast_dev_run=True, accelerator="cpu", logger=False, enable_progress_bar=False)
    trainer.fit(_TranslationModel(), datamodule=dm)
    trainer.test(_TranslationModel(), datamodule=dm, verbose=False)


@pytest.mark.parametrize("name", ["num_train", "num_val", "num_test"])
def test_synthetic_split_sizes_must_be_positive(name: str) -> None:
    # Before (issue 14, defect 9): num_val=0 built an empty validation set and training ran without validation.
    with pytest.raises(ValueError, match=f"`{name}` must be an int >= 1"):
        SyntheticDataModule(**{name: 0})


def test_clouds_smaller_than_local_consistency_fail_before_the_first_step(tmp_path: Path) -> None:
    # Before (issue 14, defect 9): num_points below LC's num_local_points failed inside the first training step.
    from lightning.pytorch import Trainer

    from lcreg.checks import TooFewPointsError
    from lcreg.models.dvds import DVDs
    from lcreg.models.loss_terms import LocalConsistencyLoss

    model = DVDs(loss_terms=[LocalConsistencyLoss()])
    dm = SyntheticDataModule(num_train=4, num_val=2, num_test=2, points_per_shape=64, num_points=32, batch_size=2)
    trainer = Trainer(
        max_steps=1, logger=False, enable_checkpointing=False, enable_progress_bar=False, default_root_dir=tmp_path
    )
    before = [p.detach().clone() for p in model.parameters()]
    with pytest.raises(TooFewPointsError, match=r"clouds of 32 points.*at least 64.*'lc' 64"):
        trainer.fit(model, datamodule=dm)
    assert trainer.global_step == 0
    assert all(torch.equal(a, b) for a, b in zip(before, model.parameters()))


@pytest.mark.parametrize(
    ("option", "value"), [("batch_size", "2"), ("batch_size", 2.5), ("batch_size", 0), ("num_workers", -1)]
)
def test_loader_sizes_of_the_wrong_type_are_named(option: str, value: object) -> None:
    from lcreg.data.datamodule import SyntheticDataModule

    with pytest.raises(ValueError, match=f"`{option}` must be an integer"):  # was a TypeError from deep inside
        SyntheticDataModule(**{option: value})
