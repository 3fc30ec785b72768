"""``lcreg fit --validate_first``: the starting weights are validated and stay a candidate of the selection."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest
import torch

from lcreg.cli import main

from _cli_runs import TINY_DVDS, config_args  # type: ignore[import-not-found]

pytestmark = pytest.mark.usefixtures("isolated_cli")

FROZEN = "--model.init_args.optimizer.init_args.lr=0.0"  # training changes no weight: no validation can beat step 0


def _fit(tmp_path: Path, *extra: str) -> Path:
    """``lcreg fit --config configs/dvds.yaml`` (the main job, which sets ``validate_first``) on a tiny budget."""
    outputs = [f"--trainer.logger.init_args.save_dir={tmp_path}", f"--trainer.default_root_dir={tmp_path}"]
    main(["fit", *config_args("dvds.yaml"), *TINY_DVDS, *outputs, *extra])
    return max((tmp_path / "lcreg").glob("version_*"))


def _selected(run: Path) -> Path:
    """The best checkpoint the run recorded in its ``last.ckpt`` (what ``--ckpt_path best`` tests)."""
    state = torch.load(run / "checkpoints" / "last.ckpt", weights_only=True)["callbacks"]
    (best,) = [v["best_model_path"] for k, v in state.items() if k.startswith("ModelCheckpoint")]
    return Path(best)


def _validated_steps(run: Path) -> list[int]:
    """The steps of the validation rows of the run's ``metrics.csv``."""
    rows = csv.DictReader((run / "metrics.csv").open(encoding="utf-8"))
    return [int(r["step"]) for r in rows if r.get("val/rre_mean_deg")]


def test_a_run_that_never_beats_its_starting_weights_selects_them(tmp_path: Path) -> None:
    run = _fit(tmp_path, FROZEN, "--trainer.max_epochs=2")
    assert _validated_steps(run) == [0, 1, 3]  # the untrained weights first, then after each epoch
    best = _selected(run)
    assert best.is_file() and torch.load(best, weights_only=True)["global_step"] == 0
    assert sorted(p.name for p in (run / "checkpoints").glob("*.ckpt")) == sorted(["last.ckpt", best.name])


def test_without_validate_first_the_selection_holds_trained_checkpoints_only(tmp_path: Path) -> None:
    run = _fit(tmp_path, FROZEN, "--validate_first=false")
    assert _validated_steps(run) == [1]
    assert torch.load(_selected(run), weights_only=True)["global_step"] == 2


def test_a_resumed_run_does_not_validate_its_starting_weights_again(tmp_path: Path) -> None:
    run = _fit(tmp_path)
    assert _validated_steps(run) == [0, 1]
    resumed = _fit(tmp_path, "--trainer.max_epochs=2", "--ckpt_path=last")
    assert resumed == run and _validated_steps(run) == [3]  # the new segment; the first is metrics.segment1.csv
    assert torch.load(_selected(run), weights_only=True)["global_step"] in (0, 2, 4)


def test_validating_first_leaves_the_training_as_it_would_be_without(tmp_path: Path) -> None:
    # Before: the validation drew from the global RNG (its data loader's seed), so the same seed trained other weights.
    first = _fit(tmp_path / "first")
    plain = _fit(tmp_path / "plain", "--validate_first=false")
    trained = [torch.load(run / "checkpoints" / "last.ckpt", weights_only=True)["state_dict"] for run in (first, plain)]
    assert trained[0].keys() == trained[1].keys()
    for key, value in trained[0].items():
        torch.testing.assert_close(trained[1][key], value, rtol=0, atol=0, msg=key)
