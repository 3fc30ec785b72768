from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from lcreg.data.kitti import KITTIOdometryDataModule, scan_path

from _shared_data import shared_data


@pytest.mark.data
def test_datamodule_standard_pair_keeps_lidar_frames_and_json_ground_truth() -> None:
    import torch

    from lcreg.geometry import se3

    root = shared_data("kitti")
    dm = KITTIOdometryDataModule(str(root), test_split="train")  # the only standard pair with scans: 00/11-0
    dm.setup("test")
    ds = dm.datasets["test"]
    assert [p.name for p in ds.pairs] == ["00/11-0"]
    listed = next(p for p in json.loads((root / "pairs" / "train.json").read_text()) if p["frame0"] == 11)
    item = ds[0]
    torch.testing.assert_close(item["transform_ref_src"], torch.tensor(listed["transform"], dtype=torch.float32))
    full = len(np.fromfile(scan_path(root, 0, 0), dtype=np.float32)) // 4
    assert full > 100_000 and 5_000 < item["points_src"].shape[0] < full / 3  # 0.3 m voxels of a ~122k-point scan
    # The ground truth brings the source scan onto the reference: most points find a neighbour within 0.5 m.
    from scipy.spatial import cKDTree

    mapped = se3.transform_points(item["transform_ref_src"][None], item["points_src"][None])[0].numpy()
    tree = cKDTree(item["points_ref"].numpy())
    aligned, raw_fraction = (
        np.mean(tree.query(mapped)[0] < 0.5),
        np.mean(tree.query(item["points_src"].numpy())[0] < 0.5),
    )
    assert aligned > 0.5 and aligned > 1.5 * raw_fraction, (aligned, raw_fraction)  # measured 0.58 vs 0.36 (ground)
    batch = next(iter(dm.test_dataloader()))
    assert batch.points_src.shape[0] == 1


def test_datamodule_options_are_checked(tmp_path: Path) -> None:

    with pytest.raises(ValueError, match="selection"):
        KITTIOdometryDataModule(str(tmp_path), selection="every")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="min_distance"):
        KITTIOdometryDataModule(str(tmp_path), min_distance=0.0)
    with pytest.raises(ValueError, match="batch_size"):
        KITTIOdometryDataModule(str(tmp_path), batch_size=2)  # every point kept: clouds differ in size
    with pytest.raises(ValueError, match="no train pairs"):
        KITTIOdometryDataModule(str(tmp_path)).setup("fit")
