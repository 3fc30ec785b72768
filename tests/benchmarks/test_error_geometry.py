"""``benchmarks/error_geometry.py``: do test errors lie along motions the object's surface hardly shows?"""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest
import torch
from test_smoke import load  # type: ignore[import-not-found]

from lcreg.data.datamodule import SyntheticDataModule
from lcreg.geometry import se3, so3
from lcreg.geometry.normals import estimate_normals
from lcreg.geometry.surface import random_motions_like, surface_residual

error_geometry = load("error_geometry")
INIT = {"num_train": 2, "num_val": 2, "num_test": 8, "num_points": 128, "batch_size": 4, "seed": 3}


def _args(**kwargs: object) -> argparse.Namespace:
    return error_geometry.parse(["--draws", "24", *(a for k, v in kwargs.items() for a in (f"--{k}", str(v)))])


def _random_errors(gt: torch.Tensor, seed: int) -> torch.Tensor:
    """Each truth moved by 10° about a random axis and 0.02 in a random direction."""
    size = se3.make_transform(
        torch.tensor([[0.9848, -0.1736, 0.0], [0.1736, 0.9848, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)[None],
        torch.tensor([[0.02, 0.0, 0.0]], dtype=torch.float64),
    )
    motions = random_motions_like(size, len(gt), torch.Generator().manual_seed(seed))[0]
    return se3.compose(gt, motions)


def _easiest_errors(gt: torch.Tensor) -> torch.Tensor:
    """Each truth moved by the motion of 10° and 0.02 that the pair's object shows least, of 64 drawn."""
    dm = SyntheticDataModule(**INIT)
    dm.setup("test")
    preds = []
    for k in range(len(gt)):
        source = dm.test_set[k]["points_src"].double()[None].expand(64, -1, -1)
        surface = dm.test_set.object_points(k)[None]
        normals = estimate_normals(surface, k=16)
        draws = se3.inverse(gt[k : k + 1]) @ _random_errors(gt[k : k + 1].expand(64, 4, 4), k)  # (64, 4, 4)
        residuals = surface_residual(source, draws, surface.expand(64, -1, -1), normals.expand(64, -1, -1))
        preds.append(gt[k] @ draws[int(residuals.argmin())])
    return torch.stack(preds)


def _cells(text: str, group: str) -> list[str]:
    (line,) = [line for line in text.splitlines() if line.startswith(f"| {group} |")]
    return [cell.strip() for cell in line.strip("|").split("|")]


def test_random_errors_score_about_one_and_the_easiest_errors_well_below(tmp_path: Path) -> None:
    gt = error_geometry.synthetic_truths(INIT)
    random_run = error_geometry.write_run(tmp_path / "random", INIT, _random_errors(gt, 99), gt)
    easy_run = error_geometry.write_run(tmp_path / "easy", INIT, _easiest_errors(gt), gt)
    random_pairs, failed = error_geometry.score_run(random_run, _args())
    easy_pairs, _ = error_geometry.score_run(easy_run, _args())
    assert failed == 0 and len(random_pairs) == len(easy_pairs) == 8
    assert all(p.rre_deg == pytest.approx(10.0, abs=0.05) for p in random_pairs + easy_pairs)
    random_ratio = error_geometry.summary(random_pairs, 5.0)["ratio"]
    easy_ratio = error_geometry.summary(easy_pairs, 5.0)["ratio"]
    assert 0.6 < random_ratio < 1.6
    assert easy_ratio < 0.75 * random_ratio
    assert all(p.freedom <= 1.0 for p in easy_pairs)


def test_seeds_give_mean_and_std_and_a_failed_pair_is_counted_not_scored(tmp_path: Path) -> None:
    gt = error_geometry.synthetic_truths(INIT)
    pred = _random_errors(gt, 5)
    pred[3] = float("nan")
    runs = [error_geometry.write_run(tmp_path / f"s{k}", INIT, pred, gt) for k in range(2)]
    text, seeds = error_geometry.report(runs, _args())
    assert "failed pairs left out, per run: 1, 1)" in text
    assert len(seeds[0]) == 7 and _cells(text, "all pairs")[1] == "7"
    pairs_csv = tmp_path / "pairs.csv"
    error_geometry.write_pairs(pairs_csv, runs, seeds)
    assert len(pairs_csv.read_text().splitlines()) == 1 + 14


def test_runs_of_other_pairs_noisy_pairs_and_missing_files_are_refused(tmp_path: Path) -> None:
    gt = error_geometry.synthetic_truths(INIT)
    pred = _random_errors(gt, 1)
    other = error_geometry.write_run(tmp_path / "other", {**INIT, "seed": 4}, pred, gt)
    with pytest.raises(error_geometry.ErrorGeometryError, match="not the config's pair"):
        error_geometry.score_run(other, _args())
    noisy = error_geometry.write_run(tmp_path / "noisy", {**INIT, "noise_sigma": 0.01}, pred, gt)
    with pytest.raises(error_geometry.ErrorGeometryError, match="off its object"):
        error_geometry.score_run(noisy, _args())
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "config.yaml").write_text((other / "config.yaml").read_text())
    with pytest.raises(error_geometry.ErrorGeometryError, match=r"test_transforms\.npz"):
        error_geometry.score_run(tmp_path / "empty", _args())
    with pytest.raises(error_geometry.ErrorGeometryError, match=r"config\.yaml"):
        error_geometry.score_run(tmp_path / "nothing", _args())


def test_the_plot_is_a_png_of_every_scored_pair(tmp_path: Path) -> None:
    png = tmp_path / "geometry.png"
    error_geometry.main(["--smoke", "--out", str(tmp_path / "report.md"), "--plot", str(png)])
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000


def test_the_rotation_part_scores_as_the_whole_error_when_the_error_does_not_shift(tmp_path: Path) -> None:
    gt = error_geometry.synthetic_truths(INIT)
    turn = se3.make_transform(so3.exp(torch.tensor([[0.0, 0.0, 0.2]], dtype=torch.float64)), torch.zeros(1, 3))
    turns = random_motions_like(turn, len(gt), torch.Generator().manual_seed(2))[0]  # 0.2 rad, random axes
    run = error_geometry.write_run(tmp_path / "turns", INIT, se3.compose(gt, turns), gt)
    pairs, _ = error_geometry.score_run(run, _args())
    assert all(p.turn_ratio == p.ratio and p.turn_residual == p.residual for p in pairs)
    shifted, _ = error_geometry.score_run(
        error_geometry.write_run(tmp_path / "shifts", INIT, _random_errors(gt, 4), gt), _args()
    )
    assert all(p.turn_ratio != p.ratio for p in shifted)
