"""Scene registration pairs (3DMatch / 7-Scenes fragments, KITTI scans): a pair list, a dataset and a DataModule base.

A scene dataset is a list of :class:`ScenePair` (two files and the ground truth that maps the source file's points
into the reference file's frame). :class:`ScenePairDataset` turns pair ``i`` into a registration pair, the same
way on every call (generator seeded with ``seed + i``):

1. read both files (:func:`lcreg.data.io.read_points`) and voxel-downsample them (``voxel_size``, optional;
   :func:`lcreg.data.io.voxel_downsample`, Open3D's grid);
2. sample ``num_points`` points per cloud without replacement (``None`` keeps every point; a cloud with fewer points
   is padded by repeating random points, which changes neither a max-pooled descriptor nor a nearest neighbour);
3. optionally map the source into the reference frame with the ground truth (``align``) and shift both clouds so
   that the reference centroid is the origin (``center``);
4. apply the extra random transform ``P`` of the object protocol to the reference (each Euler angle
   ``U[0, max_angle_deg]``, each translation component ``U[-max_translation, max_translation]``; 0 and 0 disable it).

With ``A`` the transform applied to the source, ``B`` the one applied to the reference and ``M`` the file ground
truth, the pair's ground truth is ``B M A^-1`` (``P`` when ``align``). Coordinates stay in the files' units
(metres); only rigid transforms are applied, so the points keep their original relative positions.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np
import torch
from lightning.pytorch import LightningDataModule
from torch.utils.data import DataLoader, Dataset

from lcreg.data.collate import collate_pairs
from lcreg.data.io import read_points, voxel_downsample
from lcreg.data.pairs import PairProtocol
from lcreg.data.sampling import ResumableLoader, ResumableTrainingOrder
from lcreg.geometry import se3
from lcreg.geometry.random_transforms import random_euler_transform

__all__ = ["ScenePair", "ScenePairDataModule", "ScenePairDataset"]

Split = Literal["train", "val", "test"]


@dataclass(frozen=True)
class ScenePair:
    """Two point-cloud files and the ground truth between them.

    Attributes:
        path_src: Source cloud file (any format of :func:`lcreg.data.io.read_points`).
        path_ref: Reference cloud file.
        transform_ref_src: ``(4, 4)`` float64 ``[R t; 0 1]`` mapping source points into the reference frame.
        name: Short identifier, e.g. ``"7-scenes-redkitchen/0-1"`` or ``"00/11-0"``.
        overlap: Overlap ratio in ``[0, 1]`` when the dataset provides one.
    """

    path_src: Path
    path_ref: Path
    transform_ref_src: np.ndarray = field(repr=False, compare=False)
    name: str = ""
    overlap: float | None = None


@functools.lru_cache(maxsize=128)
def _load_cloud(path: Path, voxel_size: float | None) -> np.ndarray:
    """Read (and downsample) one cloud once; fragments appear in many pairs."""
    points = read_points(path)
    return points if voxel_size is None else voxel_downsample(points, voxel_size)


def _sample(points: np.ndarray, num_points: int | None, generator: torch.Generator) -> torch.Tensor:
    """``num_points`` rows of ``(N, 3)`` without replacement, padded with random repeats when ``N < num_points``."""
    pts = torch.from_numpy(points).double()
    if num_points is None:
        return pts
    n = pts.shape[0]
    idx = torch.randperm(n, generator=generator)[:num_points]
    if n < num_points:
        idx = torch.cat([idx, torch.randint(n, (num_points - n,), generator=generator)])
    return pts[idx]


class ScenePairDataset(Dataset[dict[str, torch.Tensor]]):
    """Registration pairs from scene files (see the module docstring for the steps); item ``i`` is deterministic.

    Args:
        pairs: The file pairs and their ground truths.
        num_points: Points per cloud (``None``: all points after downsampling; then batches hold one pair).
        voxel_size: Voxel downsampling edge in file units before sampling (``None``: off).
        align: Map the source into the reference frame with the file ground truth first.
        center: Shift both clouds so that the reference centroid is the origin.
        max_angle_deg: Extra random rotation, each Euler angle ``U[0, max_angle_deg]`` (0: none).
        max_translation: Extra random translation, each component ``U[-t, t]`` (0: none).
        seed: Item ``i`` uses ``torch.Generator().manual_seed(seed + i)``.

    Raises:
        ValueError: If ``pairs`` is empty or an option is out of range.
    """

    def __init__(
        self,
        pairs: list[ScenePair],
        num_points: int | None = 2048,
        voxel_size: float | None = None,
        align: bool = True,
        center: bool = True,
        max_angle_deg: float = 45.0,
        max_translation: float = 0.5,
        seed: int = 0,
    ) -> None:
        if not pairs:
            raise ValueError("`pairs` is empty: the dataset has no scene pair")
        if num_points is not None and num_points < 1:
            raise ValueError(f"`num_points` must be >= 1 or None, got {num_points}")
        if voxel_size is not None and not voxel_size > 0:
            raise ValueError(f"`voxel_size` must be > 0 or None, got {voxel_size}")
        PairProtocol(max_angle_deg=max_angle_deg, max_translation=max_translation)  # validates the bounds
        self.pairs = pairs
        self.num_points = num_points
        self.voxel_size = voxel_size
        self.align = align
        self.center = center
        self.max_angle_deg = max_angle_deg
        self.max_translation = max_translation
        self.seed = seed

    def __len__(self) -> int:
        return len(self.pairs)

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        """Pair ``index``: ``points_src (N, 3)``, ``points_ref (M, 3)``, ``transform_ref_src (4, 4)``, ``index``."""
        if not -len(self) <= index < len(self):
            raise IndexError(f"index {index} is out of range for {len(self)} scene pairs")
        index = index % len(self)
        pair = self.pairs[index]
        generator = torch.Generator().manual_seed(self.seed + index)
        src = _sample(_load_cloud(Path(pair.path_src), self.voxel_size), self.num_points, generator)
        ref = _sample(_load_cloud(Path(pair.path_ref), self.voxel_size), self.num_points, generator)
        gt = torch.as_tensor(pair.transform_ref_src, dtype=torch.float64)
        shift = se3.identity(1, dtype=torch.float64)[0]
        if self.center:
            shift[:3, 3] = -ref.mean(0)
        to_src = shift @ gt if self.align else shift  # A
        extra, _ = random_euler_transform(
            1, self.max_angle_deg, self.max_translation, generator=generator, dtype=torch.float64
        )
        to_ref = extra[0] @ shift  # B
        return {
            "points_src": se3.transform_points(to_src[None], src[None])[0].float(),
            "points_ref": se3.transform_points(to_ref[None], ref[None])[0].float(),
            "transform_ref_src": (to_ref @ gt @ se3.inverse(to_src)).float(),
            "index": torch.tensor(index, dtype=torch.int64),
        }


class ScenePairDataModule(ResumableTrainingOrder, LightningDataModule):
    """Base DataModule of scene pairs: subclasses list the pairs of each split in :meth:`pairs`.

    Args:
        num_points: Points per cloud (``None``: all points after downsampling, with ``batch_size`` 1).
        voxel_size: Voxel downsampling edge in file units (``None``: off).
        align: Map the source into the reference frame with the ground truth before the extra transform.
        center: Put the reference centroid at the origin.
        max_angle_deg: Extra rotation bound (degrees, each Euler angle).
        max_translation: Extra translation bound (file units, each component).
        batch_size: Pairs per batch.
        num_workers: DataLoader workers.
        seed: Base seed of the deterministic pairs.

    Raises:
        ValueError: On an invalid option, or ``num_points=None`` with ``batch_size > 1``.
    """

    recall_thresholds: ClassVar[tuple[tuple[float, float], ...]] = ()
    """The benchmark's standard recall, ``(rotation degrees, translation in file units)`` pairs: registration models
    log ``recall_r{deg}_t{trans}`` for each at validation and test (:meth:`lcreg.models.base.RegistrationModule.setup`)
    unless their own ``recall_thresholds`` is set. None here; the dataset subclasses set theirs."""

    def __init__(
        self,
        num_points: int | None = 2048,
        voxel_size: float | None = None,
        align: bool = True,
        center: bool = True,
        max_angle_deg: float = 45.0,
        max_translation: float = 0.5,
        batch_size: int = 1,
        num_workers: int = 0,
        seed: int = 1234,
    ) -> None:
        super().__init__()
        if batch_size < 1 or num_workers < 0:
            raise ValueError(f"need batch_size >= 1 and num_workers >= 0, got {batch_size} and {num_workers}")
        if num_points is None and batch_size > 1:
            raise ValueError("`num_points=None` keeps every point, so clouds differ in size: use `batch_size: 1`")
        self.options: dict[str, Any] = {
            "num_points": num_points,
            "voxel_size": voxel_size,
            "align": align,
            "center": center,
            "max_angle_deg": max_angle_deg,
            "max_translation": max_translation,
            "seed": seed,
        }
        ScenePairDataset([ScenePair(Path(), Path(), np.eye(4))], **self.options)  # validates the options early
        self.batch_size = batch_size
        self.num_workers = num_workers
        self.datasets: dict[str, ScenePairDataset] = {}

    def pairs(self, split: Split) -> list[ScenePair]:
        """The file pairs of ``split`` (``"train"``, ``"val"`` or ``"test"``)."""
        raise NotImplementedError

    def setup(self, stage: str | None = None) -> None:
        """Build the datasets of ``stage`` (``fit``/``validate``: train and val; ``test``/``predict``: test)."""
        splits: tuple[Split, ...] = ("train", "val") if stage in ("fit", "validate") else ("test",)
        if stage is None:
            splits = ("train", "val", "test")
        for split in splits:
            if split not in self.datasets:
                pairs = self.pairs(split)
                if not pairs:
                    raise ValueError(
                        f"{type(self).__name__} has no {split} pairs: its {split} split is not configured or is empty"
                    )
                self.datasets[split] = ScenePairDataset(pairs, **self.options)

    def _loader(self, split: Split, shuffle: bool = False) -> DataLoader[Any]:
        if split not in self.datasets:
            raise RuntimeError(f"the {split} set is not built; call `setup()` with the matching stage first")
        dataset = self.datasets[split]
        sampler = self.training_sampler(len(dataset), pair_seeds=False) if shuffle else None  # resumable order
        return (ResumableLoader if shuffle else DataLoader)(
            dataset,
            batch_size=self.batch_size,
            sampler=sampler,
            num_workers=self.num_workers,
            persistent_workers=self.num_workers > 0,
            collate_fn=collate_pairs,
            generator=torch.Generator(),  # iterating never draws from the global RNG
        )

    def train_dataloader(self) -> DataLoader[Any]:
        """Training pairs, shuffled (models here are trained on objects; scenes are for evaluation)."""
        return self._loader("train", shuffle=True)

    def val_dataloader(self) -> DataLoader[Any]:
        """Deterministic validation pairs, in order."""
        return self._loader("val")

    def test_dataloader(self) -> DataLoader[Any]:
        """Deterministic test pairs, in order."""
        return self._loader("test")

    def predict_dataloader(self) -> DataLoader[Any]:
        """The test pairs."""
        return self._loader("test")
