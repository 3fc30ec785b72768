"""``lcreg register --pairs`` on the real 3DMatch and KITTI lists of ``../shared/data`` (skipped when absent)."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import torch

from lcreg.cli import main
from lcreg.data.pairlists import read_pair_list
from lcreg.metrics.functional import correspondence_rmse_sq

from _shared_data import shared_data  # type: ignore[import-not-found]

pytestmark = pytest.mark.data


def test_threedmatch_scene_scores_with_the_official_recall(tmp_path, capsys):
    scene = shared_data("3dmatch") / "benchmarks" / "3DMatch" / "7-scenes-redkitchen"
    results = tmp_path / "kitchen.csv"
    main(["register", "--pairs", str(scene), "--method", "fgr+icp", "--limit", "4", "--results", str(results)])
    rows = list(csv.DictReader(results.open()))
    pairs = {p.name: p for p in read_pair_list(scene)[:4]}
    assert [r["name"] for r in rows] == list(pairs)
    for row in rows:
        pair = pairs[row["name"]]
        estimate = np.array([float(row[f"t{i}{j}"]) for i in range(4) for j in range(4)]).reshape(4, 4)
        expected = correspondence_rmse_sq(
            torch.tensor(estimate)[None], torch.tensor(pair.transform_ref_src)[None], torch.tensor(pair.info)[None]
        )
        assert np.isclose(float(row["rmse"]) ** 2, float(expected[0]), rtol=1e-4, atol=1e-10)
        assert row["scored"] == str(int(pair.scored))
    summary = json.loads(results.with_suffix(".summary.json").read_text())
    scored = [r for r in rows if r["scored"] == "1"]
    assert summary["overall"]["scored_pairs"] == len(scored)
    assert summary["overall"]["threedmatch_recall"] == np.mean([float(r["rmse"]) <= 0.2 for r in scored])
    assert summary["thresholds"] == {"rre_deg": 15.0, "rte": 0.3, "rmse": 0.2}
    assert "3DMatch recall" in capsys.readouterr().out


def test_kitti_pair_list_registers_full_scans(tmp_path):
    pairs_json = shared_data("kitti") / "pairs" / "train.json"
    results = tmp_path / "kitti.csv"
    with pytest.warns(UserWarning, match="skipped"):
        main(["register", "--pairs", str(pairs_json), "--results", str(results), "--no-progress"])
    rows = list(csv.DictReader(results.open()))
    assert len(rows) == 1 and rows[0]["name"] == "00/11-0"
    assert float(rows[0]["rre_deg"]) < 5 and float(rows[0]["rte"]) < 2 and rows[0]["success"] == "1"


def test_the_same_scans_in_millimetres_and_metres_give_the_same_transform():
    import lcreg
    from lcreg.data.io import read_points
    from lcreg.metrics.functional import rotation_error_deg

    folder = shared_data("3dmatch") / "fragments" / "7-scenes-redkitchen"
    src, ref = (read_points(folder / f"cloud_bin_{k}.ply").astype(np.float64) for k in (0, 1))
    metres, millimetres = lcreg.register(src, ref), lcreg.register(1000 * src, 1000 * ref)
    in_metres = millimetres.transform.copy()
    in_metres[:3, 3] /= 1000
    rre = float(rotation_error_deg(torch.tensor(in_metres)[None], torch.tensor(metres.transform)[None])[0])
    assert rre < 0.01 and np.abs(in_metres[:3, 3] - metres.transform[:3, 3]).max() < 1e-3  # was 0.43 vs 0.195 deg
    assert np.isclose(millimetres.voxel_size, 1000 * metres.voxel_size, rtol=1e-9)


def _halves_of_a_fragment() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two overlapping parts of a 3DMatch fragment (about 46 % of each in common), the second moved by 20 degrees."""
    from scipy.spatial.transform import Rotation

    from lcreg.data.io import read_points

    points = read_points(shared_data("3dmatch") / "fragments" / "7-scenes-redkitchen" / "cloud_bin_0.ply")
    points = points.astype(np.float64)
    low, high = np.quantile(points[:, 0], [0.35, 0.65])
    gt = np.eye(4)
    gt[:3, :3] = Rotation.from_euler("z", 20, degrees=True).as_matrix()
    gt[:3, 3] = (0.1, -0.05, 0.05)
    second = points[points[:, 0] > low]
    return points[points[:, 0] < high], second @ gt[:3, :3].T + gt[:3, 3], gt


def test_a_learned_object_method_on_partial_scans_warns_or_falls_back():
    import lcreg
    from lcreg.registration import LowFitnessWarning

    src, ref, gt = _halves_of_a_fragment()
    with pytest.warns(LowFitnessWarning, match=r"dvds\+icp: fitness 0\.\d+ is below 0\.5.*ransac\+icp"):
        failed = lcreg.register(src, ref, "dvds+icp")
    assert np.linalg.norm(failed.transform[:3, 3] - gt[:3, 3]) > 0.2  # the object model fails here (about 0.7 m)
    rescued = lcreg.register(src, ref, "dvds+icp", fallback="ransac+icp")
    assert rescued.method == "ransac+icp" and rescued.extra["fallback"]["first"] == "dvds+icp"
    assert np.linalg.norm(rescued.transform[:3, 3] - gt[:3, 3]) < 0.05


def test_the_default_on_the_readme_pair_falls_back_where_kiss_finds_no_solution():
    pytest.importorskip("kiss_matcher")
    import lcreg
    from lcreg.metrics.functional import rotation_error_deg, translation_error

    folder = shared_data("3dmatch") / "fragments" / "7-scenes-redkitchen"
    scene = shared_data("3dmatch") / "benchmarks" / "3DMatch" / "7-scenes-redkitchen"
    gt = next(p for p in read_pair_list(scene) if p.name.endswith("/24-35")).transform_ref_src
    result = lcreg.register(folder / "cloud_bin_35.ply", folder / "cloud_bin_24.ply")
    assert result.extra["fallback"]["no_solution"] and result.method == "ransac+icp"
    pred, truth = torch.tensor(result.transform)[None], torch.tensor(gt)[None]
    assert float(rotation_error_deg(pred, truth)[0]) < 1.0 and float(translation_error(pred, truth)[0]) < 0.06
