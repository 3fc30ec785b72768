"""benchmarks/oracle_floor.py: the rigid fit on the exact matches, its numbers, and that its pairs are the runs'."""

from __future__ import annotations

from types import ModuleType

import pytest
import torch
from test_smoke import load  # type: ignore[import-not-found]

from lcreg.experiments.benchmarking import build
from lcreg.experiments.reproduce.budgets import CONVERGE_EPOCHS_OF_8, CONVERGE_SMALL_BATCH, DataChoice, RunBudget

from _shared_data import shared_data  # type: ignore[import-not-found]


@pytest.fixture(scope="module")
def oracle() -> ModuleType:
    return load("oracle_floor")


def test_clean_same_points_are_solved_exactly_and_noise_sets_a_floor(oracle: ModuleType) -> None:
    clean = oracle.oracle_floor(None, oracle.Setting("clean", "", 64, 0.0), points=64)
    assert clean.matches == [64] * clean.pairs and clean.metrics["rre_median_deg"] < 1e-4
    noisy = oracle.oracle_floor(None, oracle.Setting("noisy", "", 64, 0.05), points=64)
    assert 0.1 < noisy.metrics["rre_median_deg"] < 5 and noisy.metrics["rmse_t"] > 1e-4
    cropped = oracle.oracle_floor(None, oracle.Setting("crop", "", 64, 0.0, "prnet", 0.75), points=64)
    assert all(3 <= m < 48 for m in cropped.matches) and cropped.metrics["rre_median_deg"] < 1e-4


def test_noise_floor_matches_the_procrustes_error_theory(oracle: ModuleType) -> None:
    """Twice the points, about 1/sqrt(2) of the rotation error (the fit averages independent noise)."""
    small = oracle.oracle_floor(None, oracle.Setting("n", "", 128, 0.02), points=128)
    large = oracle.oracle_floor(None, oracle.Setting("n", "", 512, 0.02), points=512)
    assert 0.3 < large.metrics["rmse_r_deg"] / small.metrics["rmse_r_deg"] < 0.75


@pytest.mark.parametrize(
    ("index", "data", "budget", "host"),
    [
        (1, DataChoice(None), CONVERGE_SMALL_BATCH, "dcp"),
        (4, DataChoice(None, partial="prnet", partial_keep=0.75), CONVERGE_EPOCHS_OF_8, "idam"),
    ],
    ids=["lc_dcp_prnet_converge", "idam_partial_converge"],
)
def test_its_pairs_are_the_runs_test_pairs(
    oracle: ModuleType, index: int, data: DataChoice, budget: RunBudget, host: str
) -> None:
    root = str(shared_data("modelnet40_mini"))
    data = DataChoice(root, partial=data.partial, partial_keep=data.partial_keep)
    _, runs = build(host, with_data=True, values=data.overrides(budget))
    setting = oracle.SETTINGS[index]
    assert setting.points == budget.points
    ours, _ = oracle.pair_datamodule(root, "test", None, setting.points, **setting.options())
    runs.setup("test")
    ours.setup("test")
    assert len(runs.test_set) == len(ours.test_set) == 164
    for i in (0, 57, 163):
        theirs, mine = runs.test_set[i], ours.test_set.item_with_indices(i)
        assert all(torch.equal(theirs[key], mine[key]) for key in theirs)
