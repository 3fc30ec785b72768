"""Transform files round-trip in every format; the moved source is a PLY any reader reads; nothing half-written."""

from __future__ import annotations

import json

import numpy as np
import pytest

from lcreg.data.io import read_points
from lcreg.registration.outputs import TransformFileError, read_transform, write_ply, write_transform


@pytest.mark.parametrize("suffix", [".txt", ".json", ".npy"])
def test_transform_round_trip(tmp_path, suffix):
    transform = np.eye(4)
    transform[:3, 3] = [1.5, -2.25, 1e-7]
    transform[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    path = write_transform(tmp_path / f"T{suffix}", transform, {"fitness": 0.5})
    np.testing.assert_allclose(read_transform(path), transform, rtol=1e-9, atol=1e-15)
    if suffix == ".json":
        assert json.loads(path.read_text())["fitness"] == 0.5
    assert [p.name for p in tmp_path.iterdir()] == [path.name]  # no temporary file left


def test_ply_is_read_back_exactly(tmp_path, pair):
    path = write_ply(tmp_path / "aligned.ply", pair[0])
    np.testing.assert_array_equal(read_points(path), pair[0].astype(np.float32))
    import open3d as o3d

    np.testing.assert_allclose(np.asarray(o3d.io.read_point_cloud(str(path)).points), pair[0], atol=1e-6)


def test_refusals_write_nothing(tmp_path):
    with pytest.raises(ValueError, match=r"--out.*extension"):
        write_transform(tmp_path / "T.csv", np.eye(4))
    with pytest.raises(FileNotFoundError, match="does not exist"):
        write_transform(tmp_path / "no" / "T.txt", np.eye(4))
    with pytest.raises(ValueError, match="--save-aligned"):
        write_ply(tmp_path / "a.xyz", np.zeros((3, 3)))
    assert list(tmp_path.iterdir()) == []
    bad = tmp_path / "bad.txt"
    bad.write_text("1 2 3\n")
    with pytest.raises(TransformFileError, match=r"bad.txt"):
        read_transform(bad)
    with pytest.raises(FileNotFoundError, match=r"nope.npy"):
        read_transform(tmp_path / "nope.npy")


def test_written_files_follow_the_umask_like_open(tmp_path):
    import os

    import numpy as np

    from lcreg.registration.outputs import write_transform

    previous = os.umask(0o022)
    try:
        path = write_transform(tmp_path / "T.txt", np.eye(4))
        reference = tmp_path / "plain.txt"
        reference.write_text("x")
        assert (path.stat().st_mode & 0o777) == (reference.stat().st_mode & 0o777) == 0o644  # was 0o600
    finally:
        os.umask(previous)
