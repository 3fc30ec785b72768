"""Lightning DataModule of KITTI odometry pairs: :class:`KITTIOdometryDataModule` (evaluation of registration models).

Pairs come from :func:`~lcreg.data.kitti.pairs.kitti_pairs`; loading, voxel downsampling and batching are those of
:class:`~lcreg.data.scenes.ScenePairDataModule`.
"""

from __future__ import annotations

from typing import ClassVar

from lcreg.data.kitti.pairs import kitti_pairs
from lcreg.data.kitti.selection import Selection, Split
from lcreg.data.scenes import ScenePair, ScenePairDataModule
from lcreg.data.scenes import Split as SceneSplit

__all__ = ["KITTIOdometryDataModule"]


class KITTIOdometryDataModule(ScenePairDataModule):
    """KITTI odometry LiDAR pairs (pairs at least 10 m apart, ICP-refined ground truth), for evaluation.

    Defaults follow the FCGF/GeoTransformer protocol that the DVDs paper uses: the standard test split (sequences
    8-10), the real relative pose as the only displacement (no extra random transform, no alignment, original LiDAR
    frames), and 0.3 m voxel downsampling with every remaining point kept (so batches hold one pair). Where scans
    of the split are missing the pairs are dropped; with none left, :func:`kitti_pairs` says which files it needs.

    Args:
        root: KITTI odometry folder (checked in :meth:`setup`).
        test_split: Standard split used as the test set (``"test"``: sequences 8-10).
        val_split: Split used for validation (``None``: none).
        train_split: Split used for training (``None``: none; models here train on objects).
        selection: ``"standard"`` (the FCGF chain / json lists) or ``"all"`` (every pair ``min_distance`` apart).
        min_distance: Metres between the frames of a pair.
        test_sequences: Sequences to use instead of the test split's.
        refine: Refine pose-derived ground truth with ICP (json transforms are used as they are).
        max_frames_apart: ``"all"`` only: largest frame gap of a pair.
        num_points: Points per scan (``None``: every point after downsampling).
        voxel_size: Voxel downsampling edge in metres (``None``: full scans).
        align: Map the source into the reference frame with the ground truth first (off: real displacement).
        center: Put the reference centroid at the origin (off: original LiDAR frames).
        max_angle_deg: Extra random rotation bound (0: none).
        max_translation: Extra random translation bound in metres (0: none).
        batch_size: Pairs per batch (1 when every point is kept).
        num_workers: DataLoader workers.
        seed: Base seed of the deterministic pairs.
    """

    recall_thresholds: ClassVar[tuple[tuple[float, float], ...]] = ((5.0, 2.0),)
    """The KITTI recall (DGR, GeoTransformer): RRE < 5 degrees and RTE < 2 m (``recall_r5_t2``)."""

    def __init__(
        self,
        root: str,
        test_split: Split = "test",
        val_split: Split | None = None,
        train_split: Split | None = None,
        selection: Selection = "standard",
        min_distance: float = 10.0,
        test_sequences: list[int] | None = None,
        refine: bool = True,
        max_frames_apart: int | None = None,
        num_points: int | None = None,
        voxel_size: float | None = 0.3,
        align: bool = False,
        center: bool = False,
        max_angle_deg: float = 0.0,
        max_translation: float = 0.0,
        batch_size: int = 1,
        num_workers: int = 0,
        seed: int = 1234,
    ) -> None:
        super().__init__(
            num_points, voxel_size, align, center, max_angle_deg, max_translation, batch_size, num_workers, seed
        )
        if selection not in ("standard", "all"):
            raise ValueError(f"`selection` must be 'standard' or 'all', got {selection!r}")
        if not min_distance > 0:
            raise ValueError(f"`min_distance` must be > 0, got {min_distance}")
        self.root = root
        self.splits: dict[str, Split | None] = {"train": train_split, "val": val_split, "test": test_split}
        self.selection: Selection = selection
        self.min_distance = min_distance
        self.test_sequences = test_sequences
        self.refine = refine
        self.max_frames_apart = max_frames_apart

    def pairs(self, split: SceneSplit) -> list[ScenePair]:
        """The pairs of the standard split configured for ``split`` (none when it is not configured)."""
        source = self.splits[split]
        if source is None:
            return []
        sequences = self.test_sequences if split == "test" else None
        return kitti_pairs(
            self.root,
            source,
            self.selection,
            self.min_distance,
            sequences,
            self.refine,
            max_frames_apart=self.max_frames_apart,
        )
